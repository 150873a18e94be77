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

#include "cuda_binding_common.h"
#include "cuda_kernel.h"

namespace smgs {
namespace cuda {

// Returns [rgb, alpha, depth, reg, n_contrib, T_final, last, pairs, pk, ranges, tile_list].
std::vector<at::Tensor> forward_torch(at::Tensor means2d, at::Tensor conics, at::Tensor opacities,
                                   at::Tensor colors, at::Tensor depths, at::Tensor alpha,
                                   at::Tensor beta, at::Tensor gamma, at::Tensor background,
                                   at::Tensor reg_values, int64_t width, int64_t height, bool use_gef,
                                   bool use_softmax, int64_t k_max, bool solved, double reg_scale,
                                   bool patch) {
  const c10::cuda::CUDAGuard guard(means2d.device());
  void* st = c10::cuda::getCurrentCUDAStream().stream();
  const Binned b = bin(means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, reg_values, width,
                       height, use_gef, use_softmax, st, KeepAll{});
  FwdTensors out(b.W, b.H, b.nch, b.R, means2d.device());
  Scene sc = make_scene(b.pk, b.ranges, b.tile_list, background, b.W, b.H, b.nch, b.R, use_gef, use_softmax, k_max,
                        solved, reg_scale, patch);
  const FwdOut o = out.out(b.R);
  check(forward(sc, o, st), "forward compositing");
  return {out.rgb, out.a, out.dep, out.reg, out.cnt, out.Tf, out.last, out.pairs, b.pk, b.ranges, b.tile_list};
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
  const BwdIn in = bwd_in(g_rgb, g_alpha, g_depth, g_reg, alpha_out, depth_out, T_final, last, n_contrib, int(n_reg));
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
