// What the torch bindings of the CUDA kernels share (cuda_binding.cpp: the default kernels;
// cuda_v2_binding.cpp: the opt-in ones, which take the default binning): argument checks, the
// compositing scene, the binning pipeline and the compositing outputs. Host code over ATen; in an
// anonymous namespace, so each binding keeps its own copy.
#pragma once

#include <ATen/ATen.h>

#include <algorithm>
#include <cstdint>

#include "cuda_kernel.h"
#include "splat_math.h"  // kTileSize (host-side here)

namespace smgs {
namespace cuda {
namespace {

void check(int err, const char* what) {
  TORCH_CHECK(err == 0, "smgs cuda backend: ", what, " failed: ", error_string(err));
}

void check_f32(const at::Tensor& t, const char* name) {
  TORCH_CHECK(t.is_cuda() && t.scalar_type() == at::kFloat && t.is_contiguous(), "smgs cuda backend: ", name,
              " must be a contiguous float32 CUDA tensor");
}

const float* opt_ptr(const at::Tensor& t) { return t.numel() ? t.data_ptr<float>() : nullptr; }

at::Tensor scratch(size_t bytes, const at::Device& dev) {
  return at::empty({int64_t(std::max<size_t>(bytes, 1))}, at::TensorOptions().dtype(at::kByte).device(dev));
}

Scene make_scene(const at::Tensor& pk, const at::Tensor& ranges, const at::Tensor& vals,
                 const at::Tensor& bg, int W, int H, int nch, int R, bool gef, bool soft, int64_t kmax,
                 bool solved, double reg_scale, bool patch) {
  Scene sc{};
  sc.pk = pk.data_ptr<float>();
  sc.S = P_COL + nch + R;
  sc.nch = nch;
  sc.nreg = R;
  sc.ranges = ranges.data_ptr<int32_t>();
  sc.vals = vals.numel() ? vals.data_ptr<int32_t>() : nullptr;
  sc.W = W;
  sc.H = H;
  sc.tiles_x = (W + kTileSize - 1) / kTileSize;
  sc.tiles_y = (H + kTileSize - 1) / kTileSize;
  sc.gef = gef;
  sc.soft = soft;
  sc.solved = solved;
  sc.kmax = int(std::min<int64_t>(kmax, INT32_MAX));
  sc.patch = patch;
  sc.reg_scale = float(reg_scale);
  sc.bg = opt_ptr(bg);
  return sc;
}

// The binned splats: packed rows, pixel boxes, the sorted tile list and each tile's range in it.
struct Binned {
  at::Tensor pk, box, ranges, tile_list;
  int W, H, nch, R;
};

// bin()'s `cull` that leaves every row in.
struct KeepAll {
  int operator()(int64_t*, int) const { return 0; }
};

// The binning pipeline (as 3DGS, cuda_kernel.cu): boxes and tile counts, prefix sum, (tile, depth)
// keys, stable radix sort, tile ranges. `cull` (optional) runs between the tile counts and the prefix
// sum: it may zero counts (int64 [N], on `st`) to leave rows out and returns a launch error or 0. One
// host synchronisation: the pair count, which sizes the tile list.
template <class Cull>
Binned bin(const at::Tensor& means2d, const at::Tensor& conics, const at::Tensor& opacities, const at::Tensor& colors,
           const at::Tensor& depths, const at::Tensor& alpha, const at::Tensor& beta, const at::Tensor& gamma,
           const at::Tensor& background, const at::Tensor& reg_values, int64_t width, int64_t height, bool use_gef,
           bool use_softmax, void* st, Cull&& cull) {
  check_f32(means2d, "means2d");
  check_f32(conics, "conics");
  check_f32(opacities, "opacities");
  check_f32(colors, "colors");
  check_f32(depths, "depths");
  if (use_gef) check_f32(alpha, "alpha");
  if (use_softmax) {
    check_f32(beta, "beta");
    check_f32(gamma, "gamma");
  }
  if (background.numel()) check_f32(background, "background");
  if (reg_values.numel()) check_f32(reg_values, "reg_values");
  const at::Device dev = means2d.device();
  const int64_t N = means2d.size(0);
  // prepare and emit index the [N, 4] boxes with 32-bit 4·i (smgs/raster/cuda.py MAX_SPLATS)
  TORCH_CHECK(N <= (int64_t(1) << 29), "smgs cuda backend: ", N, " splats; the binning takes at most 2^29 per render "
              "(32-bit box indexing): prune the model, or render with backend='cpu'");
  TORCH_CHECK(width > 0 && height > 0 && width * height < INT32_MAX, "smgs cuda backend: bad image size");
  const int W = int(width), H = int(height);
  const int nch = int(colors.size(1));
  const int R = reg_values.numel() ? int(reg_values.size(1)) : 0;
  const int S = P_COL + nch + R;
  TORCH_CHECK(S <= kMaxRow, "smgs cuda backend: at most ", kMaxRow - P_COL, " colour + regularised channels");
  const int tiles_x = (W + kTileSize - 1) / kTileSize, tiles_y = (H + kTileSize - 1) / kTileSize;
  const int ntile = tiles_x * tiles_y;
  auto f32 = at::TensorOptions().dtype(at::kFloat).device(dev);
  auto i32 = at::TensorOptions().dtype(at::kInt).device(dev);
  auto i64 = at::TensorOptions().dtype(at::kLong).device(dev);

  at::Tensor pk = at::empty({N, S}, f32), box = at::empty({N, 4}, i32), nt = at::empty({N}, i64),
             dbits = at::empty({N}, i32), offs = at::empty({N}, i64);
  SplatsIn in{means2d.data_ptr<float>(), conics.data_ptr<float>(), opacities.data_ptr<float>(),
              colors.data_ptr<float>(),  depths.data_ptr<float>(), use_gef ? opt_ptr(alpha) : nullptr,
              use_softmax ? opt_ptr(beta) : nullptr, use_softmax ? opt_ptr(gamma) : nullptr,
              opt_ptr(reg_values), int(N), nch, R};
  check(prepare(in, W, H, pk.data_ptr<float>(), box.data_ptr<int32_t>(), nt.data_ptr<int64_t>(),
                reinterpret_cast<uint32_t*>(dbits.data_ptr<int32_t>()), st),
        "prepare");
  check(cull(nt.data_ptr<int64_t>(), int(N)), "cull");
  at::Tensor tmp = scratch(scan_temp_bytes(int(N)), dev);
  check(scan_tiles(tmp.data_ptr(), size_t(tmp.numel()), nt.data_ptr<int64_t>(), offs.data_ptr<int64_t>(), int(N), st),
        "prefix sum");
  const int64_t count = N ? offs[N - 1].item<int64_t>() : 0;  // synchronises: sizes the tile list
  TORCH_CHECK(count < INT32_MAX, "smgs cuda backend: ", count, " (tile, splat) pairs; the tile list holds fewer "
              "than 2^31 (32-bit positions): render at a smaller image size, or with fewer or smaller splats");
  at::Tensor keys = at::empty({count}, i64), vals = at::empty({count}, i32);
  check(emit_keys(box.data_ptr<int32_t>(), nt.data_ptr<int64_t>(), offs.data_ptr<int64_t>(),
                  reinterpret_cast<const uint32_t*>(dbits.data_ptr<int32_t>()), int(N), tiles_x,
                  reinterpret_cast<uint64_t*>(keys.data_ptr<int64_t>()), vals.data_ptr<int32_t>(), st),
        "emit keys");
  at::Tensor skeys = at::empty({count}, i64), svals = at::empty({count}, i32);
  const int end_bit = sort_key_bits(ntile);
  at::Tensor stmp = scratch(sort_temp_bytes(int(count), end_bit), dev);
  check(sort_keys(stmp.data_ptr(), size_t(stmp.numel()), reinterpret_cast<const uint64_t*>(keys.data_ptr<int64_t>()),
                  reinterpret_cast<uint64_t*>(skeys.data_ptr<int64_t>()), vals.data_ptr<int32_t>(),
                  svals.data_ptr<int32_t>(), int(count), end_bit, st),
        "radix sort");
  at::Tensor ranges = at::empty({ntile, 2}, i32);
  check(tile_ranges(reinterpret_cast<const uint64_t*>(skeys.data_ptr<int64_t>()), int(count), ntile,
                    ranges.data_ptr<int32_t>(), st),
        "tile ranges");
  return {pk, box, ranges, svals, W, H, nch, R};
}

// The outputs of a compositing forward ([rgb, alpha, depth, reg, n_contrib, T_final, last, pairs]
// of the bindings' forward) and the kernels' view of them.
struct FwdTensors {
  at::Tensor rgb, a, dep, Tf, reg, last, cnt, pairs, chan;
  FwdTensors(int W, int H, int nch, int R, const at::Device& dev) {
    auto f32 = at::TensorOptions().dtype(at::kFloat).device(dev);
    auto i32 = at::TensorOptions().dtype(at::kInt).device(dev);
    auto i64 = at::TensorOptions().dtype(at::kLong).device(dev);
    rgb = at::empty({H, W, nch}, f32);
    a = at::empty({H, W}, f32);
    dep = at::empty({H, W}, f32);
    Tf = at::empty({H, W}, f32);
    reg = at::empty({H, W, R ? 1 + 2 * R : 0}, f32);
    last = at::empty({H, W}, i32);
    cnt = at::empty({H, W}, i32);
    pairs = at::zeros({1}, i64);
    chan = at::empty({int64_t(fwd_chan_floats(nch, W, H))}, f32);
  }
  FwdOut out(int R) {
    return FwdOut{rgb.data_ptr<float>(),
                  a.data_ptr<float>(),
                  dep.data_ptr<float>(),
                  Tf.data_ptr<float>(),
                  R ? reg.data_ptr<float>() : nullptr,
                  last.data_ptr<int32_t>(),
                  cnt.data_ptr<int32_t>(),
                  reinterpret_cast<unsigned long long*>(pairs.data_ptr<int64_t>()),
                  chan.numel() ? chan.data_ptr<float>() : nullptr};
  }
};

// The backward's view of the image gradients and of the forward's outputs it reads.
BwdIn bwd_in(const at::Tensor& g_rgb, const at::Tensor& g_alpha, const at::Tensor& g_depth, const at::Tensor& g_reg,
             const at::Tensor& alpha_out, const at::Tensor& depth_out, const at::Tensor& T_final,
             const at::Tensor& last, const at::Tensor& n_contrib, int R) {
  check_f32(g_rgb, "grad rgb");
  check_f32(g_alpha, "grad alpha");
  check_f32(g_depth, "grad depth");
  if (R) check_f32(g_reg, "grad reg");
  return BwdIn{g_rgb.data_ptr<float>(),       g_alpha.data_ptr<float>(),  g_depth.data_ptr<float>(),
               R ? g_reg.data_ptr<float>() : nullptr, alpha_out.data_ptr<float>(), depth_out.data_ptr<float>(),
               T_final.data_ptr<float>(),     last.data_ptr<int32_t>(),   n_contrib.data_ptr<int32_t>()};
}

}  // namespace
}  // namespace cuda
}  // namespace smgs
