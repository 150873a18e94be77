// Torch binding of the CUDA projection (projection_cuda.cu): checks and allocates, then one kernel
// each way on the current stream. The camera is 25 host floats (projection.py's packed _view, then
// the camera centre): kernel arguments, so no device copy and no synchronisation. Built by
// smgs/raster/projection_cuda.py.
#include <ATen/ATen.h>
#include <torch/csrc/utils/pybind.h>

#include <c10/cuda/CUDAGuard.h>
#include <c10/cuda/CUDAStream.h>

#include <cstring>
#include <vector>

#include "projection_cuda.h"

namespace smgs {
namespace cuda {

namespace {

void check(int err, const char* what) {
  TORCH_CHECK(err == 0, "smgs cuda projection: ", what, " failed: ", projection_error_string(err));
}

void check_rows(const at::Tensor& t, int64_t n, int64_t k, const char* name) {
  TORCH_CHECK(t.is_cuda() && t.scalar_type() == at::kFloat && t.is_contiguous() && t.dim() == 2 && t.size(0) == n &&
                  t.size(1) == k,
              "smgs cuda projection: ", name, " must be a contiguous float32 CUDA tensor [", n, ", ", k, "]");
}

// A gradient whose rows may be strided (a column block of a packed buffer) but whose entries within
// a row are contiguous.
void check_grad(const at::Tensor& t, int64_t n, int64_t k, const char* name) {
  const bool shape = (k == 1 && t.dim() == 1 && t.size(0) == n) || (t.dim() == 2 && t.size(0) == n && t.size(1) == k);
  TORCH_CHECK(t.is_cuda() && t.scalar_type() == at::kFloat && shape && (t.dim() == 1 || k == 1 || t.stride(1) == 1),
              "smgs cuda projection: the gradient of ", name, " must be float32 CUDA [", n, ", ", k,
              "] with contiguous rows");
}

ProjIn make_in(const at::Tensor& means3d, const at::Tensor& quats, const at::Tensor& scales, const at::Tensor& sh,
               const std::vector<double>& cam, double near_plane, double eps2d, double ext, int64_t degree, bool clamp) {
  const int64_t n = means3d.size(0);
  TORCH_CHECK(n < INT32_MAX, "smgs cuda projection: fewer than 2^31 Gaussians");
  check_rows(means3d, n, 3, "means3d");
  check_rows(quats, n, 4, "quats");
  check_rows(scales, n, 3, "scales");
  TORCH_CHECK(cam.size() == 25, "smgs cuda projection: the camera is 25 floats (rw, tw, f, c, lo, hi, size, centre)");
  ProjIn in{};
  in.means3d = means3d.data_ptr<float>();
  in.quats = quats.data_ptr<float>();
  in.scales = scales.data_ptr<float>();
  in.n = int(n);
  if (sh.numel()) {
    TORCH_CHECK(degree >= 0 && degree <= 3, "smgs cuda projection: sh degree must be 0..3, got ", degree);
    TORCH_CHECK(sh.is_cuda() && sh.scalar_type() == at::kFloat && sh.is_contiguous() && sh.dim() == 3 &&
                    sh.size(0) == n && sh.size(1) >= (degree + 1) * (degree + 1) &&
                    sh.size(1) <= proj::kMaxShBases,
                "smgs cuda projection: sh must be a contiguous float32 CUDA tensor [", n, ", ", (degree + 1) * (degree + 1),
                "..", proj::kMaxShBases, ", C]");
    in.sh = sh.data_ptr<float>();
    in.nbases = int(sh.size(1));
    in.nch = int(sh.size(2));
    in.degree = int(degree);
  }
  in.clamp = clamp;
  in.near = float(near_plane);
  in.eps2d = float(eps2d);
  in.ext = float(ext);
  float f[25];
  for (int k = 0; k < 25; ++k) f[k] = float(cam[k]);
  std::memcpy(&in.cam, f, sizeof in.cam);
  std::memcpy(in.center, f + 22, sizeof in.center);
  return in;
}

// The input checks the forward kernel makes (ProjChecks): the per-Gaussian `rows` ([N] or [N, w],
// +inf allowed where pos_inf_ok), the background, and `bad`, zeroed here on the stream.
void add_checks(ProjIn& in, const std::vector<at::Tensor>& rows, const std::vector<int64_t>& pos_inf_ok,
                const at::Tensor& background, at::Tensor& bad) {
  TORCH_CHECK(rows.size() <= size_t(kMaxRowChecks) && pos_inf_ok.size() == rows.size(),
              "smgs cuda projection: at most ", kMaxRowChecks, " checked inputs, one pos_inf_ok each");
  for (size_t c = 0; c < rows.size(); ++c) {
    const at::Tensor& t = rows[c];
    const int64_t w = t.dim() == 1 ? 1 : t.size(1);
    check_rows(t.dim() == 1 ? t.view({-1, 1}) : t, in.n, w, "a checked input");
    in.chk.rows[c] = RowCheck{t.data_ptr<float>(), int(w), pos_inf_ok[c] != 0};
  }
  in.chk.nrows = int(rows.size());
  if (background.numel()) {
    TORCH_CHECK(background.is_cuda() && background.scalar_type() == at::kFloat && background.is_contiguous(),
                "smgs cuda projection: background must be a contiguous float32 CUDA tensor");
    in.chk.bg = background.data_ptr<float>();
    in.chk.nbg = int(background.numel());
  }
  bad.zero_();
  in.chk.bad = bad.data_ptr<int32_t>();
}

}  // namespace

// Returns [means2d [N,2], conics [N,3], depths [N], radii [N,2], colours [N,C], bad [1]].
// colours is empty without sh; bad (int32, non-zero where an input failed the kernel's checks, whose
// rows are culled) is empty without check_inputs.
std::vector<at::Tensor> project_forward_torch(at::Tensor means3d, at::Tensor quats, at::Tensor scales, at::Tensor sh,
                                              std::vector<double> camera, double near_plane, double eps2d,
                                              double sigma_extent, int64_t sh_degree, bool clamp, bool check_inputs,
                                              std::vector<at::Tensor> checked_rows,
                                              std::vector<int64_t> checked_pos_inf_ok, at::Tensor background) {
  ProjIn in = make_in(means3d, quats, scales, sh, camera, near_plane, eps2d, sigma_extent, sh_degree, clamp);
  const c10::cuda::CUDAGuard guard(means3d.device());
  const int64_t n = in.n;
  auto f32 = means3d.options();
  at::Tensor means2d = at::empty({n, 2}, f32), conics = at::empty({n, 3}, f32), depths = at::empty({n}, f32),
             radii = at::empty({n, 2}, f32), colors = at::empty({in.sh ? n : 0, in.sh ? in.nch : 0}, f32),
             bad = at::empty({check_inputs ? 1 : 0}, means3d.options().dtype(at::kInt));
  if (check_inputs) add_checks(in, checked_rows, checked_pos_inf_ok, background, bad);
  check(project_forward(in, means2d.data_ptr<float>(), conics.data_ptr<float>(), depths.data_ptr<float>(),
                        radii.data_ptr<float>(), in.sh ? colors.data_ptr<float>() : nullptr,
                        c10::cuda::getCurrentCUDAStream().stream()),
        "forward");
  return {means2d, conics, depths, radii, colors, bad};
}

// Returns [dL/dmeans3d [N,3], dL/dquats [N,4], dL/dscales [N,3], dL/dsh [N,K,C] (empty without sh)].
std::vector<at::Tensor> project_backward_torch(at::Tensor means3d, at::Tensor quats, at::Tensor scales, at::Tensor sh,
                                               std::vector<double> camera, double near_plane, double eps2d,
                                               int64_t sh_degree, bool clamp, at::Tensor radii, at::Tensor g_means2d,
                                               at::Tensor g_conics, at::Tensor g_depths, at::Tensor g_colors) {
  const ProjIn in = make_in(means3d, quats, scales, sh, camera, near_plane, eps2d, 0.0, sh_degree, clamp);
  const c10::cuda::CUDAGuard guard(means3d.device());
  const int64_t n = in.n;
  check_rows(radii, n, 2, "radii");
  check_grad(g_means2d, n, 2, "means2d");
  check_grad(g_conics, n, 3, "conics");
  check_grad(g_depths, n, 1, "depths");
  if (in.sh) check_grad(g_colors, n, in.nch, "colours");
  ProjGrad g{g_means2d.data_ptr<float>(), g_conics.data_ptr<float>(), g_depths.data_ptr<float>(),
             in.sh ? g_colors.data_ptr<float>() : nullptr, g_means2d.stride(0), g_conics.stride(0),
             g_depths.stride(0), in.sh ? g_colors.stride(0) : 0};
  auto f32 = means3d.options();
  at::Tensor g_means = at::empty({n, 3}, f32), g_quats = at::empty({n, 4}, f32), g_scales = at::empty({n, 3}, f32),
             g_sh = in.sh ? at::empty_like(sh) : at::empty({0}, f32);
  check(project_backward(in, radii.data_ptr<float>(), g, g_means.data_ptr<float>(), g_quats.data_ptr<float>(),
                         g_scales.data_ptr<float>(), in.sh ? g_sh.data_ptr<float>() : nullptr,
                         c10::cuda::getCurrentCUDAStream().stream()),
        "backward");
  return {g_means, g_quats, g_scales, g_sh};
}

}  // namespace cuda
}  // namespace smgs

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  namespace py = pybind11;
  m.def("forward", &smgs::cuda::project_forward_torch, "EWA projection and SH colours, every row (culled: zeros)",
        py::arg("means3d"), py::arg("quats"), py::arg("scales"), py::arg("sh"), py::arg("camera"),
        py::arg("near_plane"), py::arg("eps2d"), py::arg("sigma_extent"), py::arg("sh_degree"), py::arg("clamp"),
        py::arg("check_inputs"), py::arg("checked_rows"), py::arg("checked_pos_inf_ok"), py::arg("background"));
  m.def("backward", &smgs::cuda::project_backward_torch, "gradients w.r.t. means3d, quats, scales and sh",
        py::arg("means3d"), py::arg("quats"), py::arg("scales"), py::arg("sh"), py::arg("camera"),
        py::arg("near_plane"), py::arg("eps2d"), py::arg("sh_degree"), py::arg("clamp"), py::arg("radii"),
        py::arg("g_means2d"), py::arg("g_conics"), py::arg("g_depths"), py::arg("g_colors"));
}
