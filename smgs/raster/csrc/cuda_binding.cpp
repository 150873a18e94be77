// Torch binding of the CUDA backend: allocates tensors, runs the binning pipeline and the compositing
// launchers of cuda_kernel.cu (declared in cuda_kernel.h, which has no torch or CUDA types) on the
// current stream, and splits the packed gradients back into per-input tensors. Built with
// smgs/raster/cuda.py (torch.utils.cpp_extension.load); the Python side is the autograd Function.
//
// The interface mirrors the CPU extension (cpu_kernel.cpp): the same arguments in the same order,
// optional inputs as empty tensors, forward returning [rgb, alpha, depth, reg, n_contrib, T_final,
// last, pairs, <state saved for backward>], backward returning the gradients of [means2d, conics,
// opacities, colors, depths, alpha, beta, gamma, reg_values]. The parameter names are part of the
// contract (py::arg below): tests/test_raster_cuda_plumbing.py checks the wrapper against them.
// ATen and torch's pybind11 casters only (not torch/extension.h): half the compile time.
#include <ATen/ATen.h>
#include <torch/csrc/utils/pybind.h>

#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <cstdint>
#include <vector>

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

}  // namespace

// Returns [rgb, alpha, depth, reg, n_contrib, T_final, last, pairs, pk, ranges, tile_list].
std::vector<at::Tensor> forward_torch(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                   at::Tensor colors, at::Tensor depths, at::Tensor alpha,
                                   at::Tensor beta, at::Tensor gamma, at::Tensor background,
                                   at::Tensor reg_values, int64_t width, int64_t height, bool use_gef,
                                   bool use_softmax, int64_t k_max, bool solved, double reg_scale,
                                   bool patch) {
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
  const c10::cuda::CUDAGuard guard(means2d.device());
  void* st = c10::cuda::getCurrentCUDAStream().stream();
  const at::Device dev = means2d.device();
  const int64_t N = means2d.size(0);
  TORCH_CHECK(N < INT32_MAX, "smgs cuda backend: fewer than 2^31 splats");
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

  // binning: boxes and tile counts, prefix sum, (tile, depth) keys, stable radix sort, tile ranges
  at::Tensor pk = at::empty({N, S}, f32), box = at::empty({N, 4}, i32), nt = at::empty({N}, i64),
                dbits = at::empty({N}, i32), offs = at::empty({N}, i64);
  SplatsIn in{means2d.data_ptr<float>(), conics.data_ptr<float>(), opacities.data_ptr<float>(),
              colors.data_ptr<float>(),  depths.data_ptr<float>(), use_gef ? opt_ptr(alpha) : nullptr,
              use_softmax ? opt_ptr(beta) : nullptr, use_softmax ? opt_ptr(gamma) : nullptr,
              opt_ptr(reg_values), int(N), nch, R};
  check(prepare(in, W, H, pk.data_ptr<float>(), box.data_ptr<int32_t>(), nt.data_ptr<int64_t>(),
                reinterpret_cast<uint32_t*>(dbits.data_ptr<int32_t>()), st),
        "prepare");
  at::Tensor tmp = scratch(scan_temp_bytes(int(N)), dev);
  check(scan_tiles(tmp.data_ptr(), size_t(tmp.numel()), nt.data_ptr<int64_t>(), offs.data_ptr<int64_t>(), int(N), st),
        "prefix sum");
  const int64_t count = N ? offs[N - 1].item<int64_t>() : 0;  // synchronises: sizes the tile list
  TORCH_CHECK(count < INT32_MAX, "smgs cuda backend: more than 2^31 (tile, splat) pairs");
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

  // compositing
  at::Tensor rgb = at::empty({H, W, nch}, f32), a = at::empty({H, W}, f32), dep = at::empty({H, W}, f32),
                Tf = at::empty({H, W}, f32), reg = at::empty({H, W, R ? 1 + 2 * R : 0}, f32),
                last = at::empty({H, W}, i32), cnt = at::empty({H, W}, i32), pairs = at::zeros({1}, i64),
                chan = at::empty({int64_t(fwd_chan_floats(nch, W, H))}, f32);
  Scene sc = make_scene(pk, ranges, svals, background, W, H, nch, R, use_gef, use_softmax, k_max, solved, reg_scale,
                        patch);
  FwdOut o{rgb.data_ptr<float>(),
           a.data_ptr<float>(),
           dep.data_ptr<float>(),
           Tf.data_ptr<float>(),
           R ? reg.data_ptr<float>() : nullptr,
           last.data_ptr<int32_t>(),
           cnt.data_ptr<int32_t>(),
           reinterpret_cast<unsigned long long*>(pairs.data_ptr<int64_t>()),
           chan.numel() ? chan.data_ptr<float>() : nullptr};
  check(forward(sc, o, st), "forward compositing");
  return {rgb, a, dep, reg, cnt, Tf, last, pairs, pk, ranges, svals};
}

// Returns dL/d[means2d, conics, opacities, colors, depths, alpha, beta, gamma, reg_values] over the N
// input splats (zeros for splats that reach no pixel, and for parameters the mode does not use).
// head_budget_bytes bounds the per-thread softmax-head scratch: tiles are processed in chunks so that
// it is never pixels x k_max.
std::vector<at::Tensor> backward_torch(at::Tensor g_rgb, at::Tensor g_alpha, at::Tensor g_depth,
                                    at::Tensor g_reg, at::Tensor alpha_out, at::Tensor depth_out,
                                    at::Tensor T_final, at::Tensor last, at::Tensor n_contrib,
                                    at::Tensor pk, at::Tensor ranges, at::Tensor tile_list,
                                    at::Tensor background, int64_t n, int64_t n_channels, int64_t n_reg,
                                    int64_t width, int64_t height, bool use_gef, bool use_softmax, int64_t k_max,
                                    bool solved, double reg_scale, int64_t head_budget_bytes, bool patch) {
  check_f32(g_rgb, "grad rgb");
  check_f32(g_alpha, "grad alpha");
  check_f32(g_depth, "grad depth");
  if (n_reg) check_f32(g_reg, "grad reg");
  const c10::cuda::CUDAGuard guard(pk.device());
  void* st = c10::cuda::getCurrentCUDAStream().stream();
  const at::Device dev = pk.device();
  const int W = int(width), H = int(height), nch = int(n_channels), R = int(n_reg);
  auto f32 = at::TensorOptions().dtype(at::kFloat).device(dev);
  Scene sc = make_scene(pk, ranges, tile_list, background, W, H, nch, R, use_gef, use_softmax, k_max, solved,
                        reg_scale, patch);
  at::Tensor grad = at::zeros({n, sc.S}, f32);
  // the head scratch needs only as many entries as the most crowded pixel composited (synchronises,
  // so only in the softmax modes, the only ones with a head; in patch scope a pixel's head steps are
  // at most min(k_max, its count) too)
  const int64_t most = use_softmax && n_contrib.numel() ? n_contrib.max().item<int64_t>() : 0;
  const int kmax_eff = use_softmax ? int(std::min<int64_t>(std::max<int64_t>(k_max, 0), most)) : 0;
  const int64_t tiles = int64_t(sc.tiles_x) * sc.tiles_y;
  const int64_t per_slot = int64_t(kmax_eff) * int64_t(head_entry_floats(nch)) * int64_t(sizeof(float));
  int64_t slots = tiles * 256;
  if (per_slot > 0) {
    const int64_t fit = std::max<int64_t>(1, head_budget_bytes / (per_slot * 256));  // whole tiles
    slots = std::min(tiles, fit) * 256;
  }
  at::Tensor head = at::empty({per_slot > 0 ? slots * per_slot / int64_t(sizeof(float)) : 0}, f32);
  at::Tensor chan = at::empty({int64_t(bwd_chan_floats(nch, W, H))}, f32);
  BwdIn in{g_rgb.data_ptr<float>(),       g_alpha.data_ptr<float>(),  g_depth.data_ptr<float>(),
           R ? g_reg.data_ptr<float>() : nullptr, alpha_out.data_ptr<float>(), depth_out.data_ptr<float>(),
           T_final.data_ptr<float>(),     last.data_ptr<int32_t>(),   n_contrib.data_ptr<int32_t>()};
  BwdWork work{grad.data_ptr<float>(), head.numel() ? head.data_ptr<float>() : nullptr, slots, kmax_eff,
               chan.numel() ? chan.data_ptr<float>() : nullptr};
  if (n) check(backward(sc, in, work, st), "backward compositing");
  // per-input views of the packed rows (strided; autograd and the projection's backward read them
  // as they are, so no copy per input)
  auto cols = [&](int c0, int c1) { return grad.slice(1, c0, c1); };
  return {cols(P_MX, P_MY + 1),
          cols(P_CA, P_CC + 1),
          cols(P_O, P_O + 1).reshape({n}),
          cols(P_COL, P_COL + nch),
          cols(P_D, P_D + 1).reshape({n}),
          cols(P_AL, P_AL + 1).reshape({n}),
          cols(P_BE, P_BE + 1).reshape({n}),
          cols(P_GA, P_GA + 1).reshape({n}),
          cols(P_COL + nch, P_COL + nch + R)};
}

std::vector<double> compiled_constants() {
  std::vector<double> v(10);
  constants(v.data());
  return v;
}

}  // namespace cuda
}  // namespace smgs

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  namespace py = pybind11;
  m.def("forward", &smgs::cuda::forward_torch, "smgs CUDA splat compositing, forward", py::arg("means2d"),
        py::arg("conics"), py::arg("opacities"), py::arg("colors"), py::arg("depths"), py::arg("alpha"),
        py::arg("beta"), py::arg("gamma"), py::arg("background"), py::arg("reg_values"), py::arg("width"),
        py::arg("height"), py::arg("use_gef"), py::arg("use_softmax"), py::arg("k_max"), py::arg("solved"),
        py::arg("reg_scale"), py::arg("patch") = false);
  m.def("backward", &smgs::cuda::backward_torch, "smgs CUDA splat compositing, backward", py::arg("g_rgb"),
        py::arg("g_alpha"), py::arg("g_depth"), py::arg("g_reg"), py::arg("alpha_out"), py::arg("depth_out"),
        py::arg("T_final"), py::arg("last"), py::arg("n_contrib"), py::arg("pk"), py::arg("ranges"),
        py::arg("tile_list"), py::arg("background"), py::arg("n"), py::arg("n_channels"), py::arg("n_reg"),
        py::arg("width"), py::arg("height"), py::arg("use_gef"), py::arg("use_softmax"), py::arg("k_max"),
        py::arg("solved"), py::arg("reg_scale"), py::arg("head_budget_bytes"), py::arg("patch") = false);
  m.def("constants", &smgs::cuda::compiled_constants, "numeric conventions as compiled");
}
