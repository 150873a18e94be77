// Torch binding of the opt-in CUDA compositing kernels ("v2", cuda_v2_kernel.cu; docs/cuda.md):
// the default backend's binning (cuda_kernel.cu's prepare, prefix sum, keys, radix sort, ranges),
// then the v2 kernels. The interface is the default binding's (cuda_binding.cpp) plus `radii`: rows
// of the fused projection (smgs/raster/projection_cuda.py) that it culled (radii (0, 0)) get no tile
// (empty `radii`: every row is a splat). One host synchronisation per forward (the pair count the
// tile list needs); the backward synchronises only in softmax modes (the largest per-pixel count
// sizes the head scratch). Built by smgs/raster/cuda_v2.py.
#include <ATen/ATen.h>
#include <torch/csrc/utils/pybind.h>

#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <algorithm>
#include <cstdint>
#include <vector>

#include "cuda_binding_common.h"
#include "cuda_kernel.h"
#include "cuda_pixel.h"
#include "cuda_v2_kernel.h"
#include "splat_math.h"  // kTileSize (host-side here)

namespace smgs {
namespace cuda {

// Returns [rgb, alpha, depth, reg, n_contrib, T_final, last, pairs, pk, ranges, tile_list].
std::vector<at::Tensor> forward_v2(at::Tensor means2d, at::Tensor conics, at::Tensor opacities, at::Tensor colors,
                                   at::Tensor depths, at::Tensor alpha, at::Tensor beta, at::Tensor gamma,
                                   at::Tensor background, at::Tensor reg_values, at::Tensor radii, int64_t width,
                                   int64_t height, bool use_gef, bool use_softmax, int64_t k_max, bool solved,
                                   double reg_scale, bool patch) {
  if (radii.numel()) {
    check_f32(radii, "radii");
    TORCH_CHECK(radii.dim() == 2 && radii.size(0) == means2d.size(0) && radii.size(1) == 2,
                "smgs cuda backend (v2 kernels): radii must be [N, 2] like means2d");
  }
  const c10::cuda::CUDAGuard guard(means2d.device());
  void* st = c10::cuda::getCurrentCUDAStream().stream();
  // rows the fused projection culled (radii (0, 0)) get no tile
  const auto cull = [&](int64_t* ntiles, int n) {
    return radii.numel() ? v2::cull_by_radii(radii.data_ptr<float>(), ntiles, n, st) : 0;
  };
  const Binned b = bin(means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, reg_values, width,
                       height, use_gef, use_softmax, st, cull);
  FwdTensors out(b.W, b.H, b.nch, b.R, means2d.device());
  Scene sc = make_scene(b.pk, b.ranges, b.tile_list, background, b.W, b.H, b.nch, b.R, use_gef, use_softmax, k_max,
                        solved, reg_scale, patch);
  const FwdOut o = out.out(b.R);
  check(v2::forward(sc, o, st), "v2 forward compositing");
  return {out.rgb, out.a, out.dep, out.reg, out.cnt, out.Tf, out.last, out.pairs, b.pk, b.ranges, b.tile_list};
}

// Returns dL/d[means2d, conics, opacities, colors, depths, alpha, beta, gamma, reg_values] over the N
// input splats, as [N, S] packed rows and the column offsets are the caller's (cuda_v2.py slices
// them: views, no copies). head_budget_bytes bounds the softmax head scratch (grid · 256 threads ·
// kmax_eff records); the persistent grid shrinks to fit it.
std::vector<at::Tensor> backward_v2(at::Tensor g_rgb, at::Tensor g_alpha, at::Tensor g_depth, at::Tensor g_reg,
                                    at::Tensor alpha_out, at::Tensor depth_out, at::Tensor T_final, at::Tensor last,
                                    at::Tensor n_contrib, at::Tensor pk, at::Tensor ranges, at::Tensor tile_list,
                                    at::Tensor background, int64_t n, int64_t n_channels, int64_t n_reg, int64_t width,
                                    int64_t height, bool use_gef, bool use_softmax, int64_t k_max, bool solved,
                                    double reg_scale, int64_t head_budget_bytes, bool patch) {
  const BwdIn in = bwd_in(g_rgb, g_alpha, g_depth, g_reg, alpha_out, depth_out, T_final, last, n_contrib, int(n_reg));
  const c10::cuda::CUDAGuard guard(pk.device());
  void* st = c10::cuda::getCurrentCUDAStream().stream();
  const at::Device dev = pk.device();
  const int W = int(width), H = int(height), nch = int(n_channels), R = int(n_reg);
  auto f32 = at::TensorOptions().dtype(at::kFloat).device(dev);
  Scene sc = make_scene(pk, ranges, tile_list, background, W, H, nch, R, use_gef, use_softmax, k_max, solved,
                        reg_scale, patch);
  at::Tensor grad = at::zeros({n, sc.S}, f32);
  at::Tensor counter = at::zeros({1}, at::TensorOptions().dtype(at::kInt).device(dev));
  int kmax_eff = 0;
  if (use_softmax && k_max > 0 && n_contrib.numel()) {
    // the head needs only as many records as the most crowded pixel composited (synchronises; in
    // patch scope a pixel's head steps are at most min(k_max, its count) too)
    const int64_t most = n_contrib.max().item<int64_t>();
    kmax_eff = int(std::min<int64_t>(k_max, most));
  }
  int per_sm = 0;
  const int grid = v2::backward_grid(sc, kmax_eff, head_budget_bytes, &per_sm);
  const int64_t head_floats = int64_t(grid) * 256 * kmax_eff * int64_t(v2::head_record_floats(nch));
  at::Tensor head = at::empty({head_floats}, f32);   // at::empty: 16-byte aligned (float4 records)
  at::Tensor chan = at::empty({int64_t(bwd_chan_floats(nch, W, H))}, f32);
  v2::BwdWork work{grad.data_ptr<float>(), head_floats ? head.data_ptr<float>() : nullptr, kmax_eff, grid,
                   counter.data_ptr<int32_t>(), chan.numel() ? chan.data_ptr<float>() : nullptr};
  if (n) check(v2::backward(sc, in, work, st), "v2 backward compositing");
  return {grad};
}

// sort="per_pixel" and the leading-splat map (cuda_pixel.cu, the twin of the CPU backend's
// forward_pixel): coefs [N, 9] the peak-depth coefficients (smgs/raster/ray_depth.py), intr
// (fx, fy, cx, cy) host floats, window 1..32 (1: the global order), lead_alpha < 0: no map.
// leaders [H, W, 2]: each pixel's first two composited splats with a >= lead_alpha (input indices,
// -1 where fewer; empty without the map).
// Returns [rgb, alpha, depth, n_contrib, T_final, pairs, leaders, list_end, pk, ranges, tile_list, box].
std::vector<at::Tensor> forward_pixel_v2(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                         at::Tensor colors, at::Tensor depths, at::Tensor alpha, at::Tensor beta,
                                         at::Tensor gamma, at::Tensor background, at::Tensor coefs,
                                         std::vector<double> intr, int64_t width, int64_t height, bool use_gef,
                                         bool use_softmax, int64_t k_max, bool solved, int64_t window,
                                         double lead_alpha, bool patch) {
  const int64_t N = means2d.size(0);
  check_f32(coefs, "coefs");
  TORCH_CHECK(coefs.dim() == 2 && coefs.size(0) == N && coefs.size(1) == 9, "coefs must be [N, 9]");
  TORCH_CHECK(intr.size() == 4, "intrinsics must be (fx, fy, cx, cy)");
  TORCH_CHECK(window >= 1 && window <= pixel::kMaxWindow, "smgs cuda backend (v2 kernels): the window must be 1..",
              pixel::kMaxWindow, " splats, got ", window, " (the cpu backend takes any)");
  const c10::cuda::CUDAGuard guard(means2d.device());
  void* st = c10::cuda::getCurrentCUDAStream().stream();
  const at::Tensor none = at::empty({0}, means2d.options());
  const Binned b = bin(means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, none, width, height,
                       use_gef, use_softmax, st, KeepAll{});
  const int W = b.W, H = b.H, nch = b.nch;
  auto f32 = means2d.options();
  auto i32 = f32.dtype(at::kInt);
  at::Tensor rgb = at::empty({H, W, nch}, f32), a = at::empty({H, W}, f32), dep = at::empty({H, W}, f32),
             Tf = at::empty({H, W}, f32), cnt = at::empty({H, W}, i32), lend = at::empty({H, W}, i32),
             pairs = at::zeros({1}, f32.dtype(at::kLong)), chan = at::empty({int64_t(fwd_chan_floats(nch, W, H))}, f32);
  const bool lead = lead_alpha >= 0.0;
  at::Tensor leaders = at::empty({lead ? H : 0, lead ? W : 0, 2}, i32);
  Scene sc = make_scene(b.pk, b.ranges, b.tile_list, background, W, H, nch, 0, use_gef, use_softmax, k_max, solved, 1.0,
                        patch);
  FwdOut o{rgb.data_ptr<float>(), a.data_ptr<float>(), dep.data_ptr<float>(), Tf.data_ptr<float>(), nullptr,
           nullptr, cnt.data_ptr<int32_t>(), reinterpret_cast<unsigned long long*>(pairs.data_ptr<int64_t>()),
           chan.numel() ? chan.data_ptr<float>() : nullptr};
  const pixel::PixelIn pin{b.box.data_ptr<int32_t>(), coefs.data_ptr<float>(), float(intr[0]), float(intr[1]),
                           float(intr[2]), float(intr[3]), int(window)};
  const pixel::PixelOut po{lead ? leaders.data_ptr<int32_t>() : nullptr, float(lead_alpha), lend.data_ptr<int32_t>()};
  check(pixel::forward(sc, pin, o, po, st), "per-pixel forward");
  return {rgb, a, dep, cnt, Tf, pairs, leaders, lend, b.pk, b.ranges, b.tile_list, b.box};
}

// Backward of forward_pixel_v2: each pixel's walk again, then the adjoint back to front. Returns
// [the gradients as packed [N, S] rows] (split by the caller as backward_v2's). The step records
// take grid · 256 · (largest per-pixel count) · 32-48 B, at most scratch_budget_bytes (the
// persistent grid shrinks to fit); reading the largest count synchronises.
std::vector<at::Tensor> backward_pixel_v2(at::Tensor g_rgb, at::Tensor g_alpha, at::Tensor g_depth, at::Tensor alpha_out,
                                          at::Tensor depth_out, at::Tensor n_contrib, at::Tensor pk, at::Tensor ranges,
                                          at::Tensor tile_list, at::Tensor box, at::Tensor coefs,
                                          std::vector<double> intr, at::Tensor background, int64_t n,
                                          int64_t n_channels, int64_t width, int64_t height, bool use_gef,
                                          bool use_softmax, int64_t k_max, bool solved, int64_t window, bool patch,
                                          int64_t scratch_budget_bytes) {
  check_f32(g_rgb, "grad rgb");
  check_f32(g_alpha, "grad alpha");
  check_f32(g_depth, "grad depth");
  TORCH_CHECK(intr.size() == 4, "intrinsics must be (fx, fy, cx, cy)");
  const c10::cuda::CUDAGuard guard(pk.device());
  void* st = c10::cuda::getCurrentCUDAStream().stream();
  const int W = int(width), H = int(height), nch = int(n_channels);
  auto f32 = pk.options();
  Scene sc = make_scene(pk, ranges, tile_list, background, W, H, nch, 0, use_gef, use_softmax, k_max, solved, 1.0,
                        patch);
  at::Tensor grad = at::zeros({n, sc.S}, f32);
  at::Tensor counter = at::zeros({1}, f32.dtype(at::kInt));
  const int max_cnt = n_contrib.numel() ? int(n_contrib.max().item<int64_t>()) : 0;   // synchronises
  if (n == 0 || max_cnt == 0) return {grad};
  const int grid = pixel::backward_grid(sc, max_cnt, scratch_budget_bytes);
  at::Tensor steps =
      at::empty({int64_t(grid) * 256 * max_cnt * int64_t(pixel::step_record_floats(nch, use_softmax))}, f32);
  at::Tensor chan = at::empty({int64_t(bwd_chan_floats(nch, W, H))}, f32);
  BwdIn in{g_rgb.data_ptr<float>(), g_alpha.data_ptr<float>(), g_depth.data_ptr<float>(), nullptr,
           alpha_out.data_ptr<float>(), depth_out.data_ptr<float>(), nullptr, nullptr, n_contrib.data_ptr<int32_t>()};
  const pixel::PixelIn pin{box.data_ptr<int32_t>(), coefs.data_ptr<float>(), float(intr[0]), float(intr[1]),
                           float(intr[2]), float(intr[3]), int(window)};
  pixel::PixelBwdWork work{grad.data_ptr<float>(), steps.data_ptr<float>(), max_cnt, grid, counter.data_ptr<int32_t>(),
                           chan.numel() ? chan.data_ptr<float>() : nullptr};
  check(pixel::backward(sc, pin, in, work, st), "per-pixel backward");
  return {grad};
}

// {grid, blocks per multiprocessor, head scratch bytes} the backward would use: for the GPU check's
// report (no launch).
std::vector<int64_t> backward_plan(int64_t n_channels, int64_t width, int64_t height, bool use_gef, bool use_softmax,
                                   int64_t kmax_eff, int64_t head_budget_bytes) {
  Scene sc{};
  sc.nch = int(n_channels);
  sc.S = P_COL + sc.nch;
  sc.W = int(width);
  sc.H = int(height);
  sc.tiles_x = (sc.W + kTileSize - 1) / kTileSize;
  sc.tiles_y = (sc.H + kTileSize - 1) / kTileSize;
  sc.gef = use_gef;
  sc.soft = use_softmax;
  int per_sm = 0;
  const int k = use_softmax ? int(kmax_eff) : 0;
  const int grid = v2::backward_grid(sc, k, head_budget_bytes, &per_sm);
  return {grid, per_sm, int64_t(grid) * 256 * k * int64_t(v2::head_record_floats(sc.nch)) * 4};
}

}  // namespace cuda
}  // namespace smgs

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  namespace py = pybind11;
  using namespace smgs::cuda;
  m.def("forward", &smgs::cuda::forward_v2, "smgs CUDA splat compositing (v2 kernels), forward", py::arg("means2d"),
        py::arg("conics"), py::arg("opacities"), py::arg("colors"), py::arg("depths"), py::arg("alpha"),
        py::arg("beta"), py::arg("gamma"), py::arg("background"), py::arg("reg_values"), py::arg("radii"),
        py::arg("width"), py::arg("height"), py::arg("use_gef"), py::arg("use_softmax"), py::arg("k_max"),
        py::arg("solved"), py::arg("reg_scale"), py::arg("patch"));
  m.def("backward", &smgs::cuda::backward_v2, "smgs CUDA splat compositing (v2 kernels), backward",
        py::arg("g_rgb"), py::arg("g_alpha"), py::arg("g_depth"), py::arg("g_reg"), py::arg("alpha_out"),
        py::arg("depth_out"), py::arg("T_final"), py::arg("last"), py::arg("n_contrib"), py::arg("pk"),
        py::arg("ranges"), py::arg("tile_list"), py::arg("background"), py::arg("n"), py::arg("n_channels"),
        py::arg("n_reg"), py::arg("width"), py::arg("height"), py::arg("use_gef"), py::arg("use_softmax"),
        py::arg("k_max"), py::arg("solved"), py::arg("reg_scale"), py::arg("head_budget_bytes"), py::arg("patch"));
  m.def("backward_plan", &smgs::cuda::backward_plan, "grid, blocks per SM and head bytes of the v2 backward",
        py::arg("n_channels"), py::arg("width"), py::arg("height"), py::arg("use_gef"), py::arg("use_softmax"),
        py::arg("kmax_eff"), py::arg("head_budget_bytes"));
  m.def("forward_pixel", &smgs::cuda::forward_pixel_v2, "per-pixel order (re-sorting window), forward",
        py::arg("means2d"), py::arg("conics"), py::arg("opacities"), py::arg("colors"), py::arg("depths"),
        py::arg("alpha"), py::arg("beta"), py::arg("gamma"), py::arg("background"), py::arg("coefs"), py::arg("intr"),
        py::arg("width"), py::arg("height"), py::arg("use_gef"), py::arg("use_softmax"), py::arg("k_max"),
        py::arg("solved"), py::arg("window"), py::arg("lead_alpha"), py::arg("patch"));
  m.def("backward_pixel", &smgs::cuda::backward_pixel_v2, "per-pixel order (re-sorting window), backward",
        py::arg("g_rgb"), py::arg("g_alpha"), py::arg("g_depth"), py::arg("alpha_out"), py::arg("depth_out"),
        py::arg("n_contrib"), py::arg("pk"), py::arg("ranges"), py::arg("tile_list"), py::arg("box"),
        py::arg("coefs"), py::arg("intr"), py::arg("background"), py::arg("n"), py::arg("n_channels"),
        py::arg("width"), py::arg("height"), py::arg("use_gef"), py::arg("use_softmax"), py::arg("k_max"),
        py::arg("solved"), py::arg("window"), py::arg("patch"), py::arg("scratch_budget_bytes"));
  m.def("max_window", []() { return pixel::kMaxWindow; }, "the longest re-sorting window of the kernels");
  m.def("layout", []() {
    using namespace smgs;   // packed_row.h
    return std::vector<int>{P_MX, P_MY, P_CA, P_CC, P_O, P_D, P_AL, P_BE, P_GA, P_COL};
  },
        "columns of the packed rows: mx, my, conic a, conic c, opacity, depth, alpha, beta, gamma, first colour");
  m.def("constants", []() {
    std::vector<double> v(10);
    smgs::cuda::constants(v.data());
    return v;
  }, "numeric conventions as compiled");
}
