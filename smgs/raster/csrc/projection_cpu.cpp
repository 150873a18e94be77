// EWA projection of 3D Gaussians to 2D splats (OpenCV pinhole), forward and hand-written backward,
// one compiled pass each way for float32 CPU tensors.
//
// Why compiled: in PyTorch the projection is ~40 forward and ~50 backward tensor ops, and their
// per-op overhead dominates both at a few Gaussians (a 4-Gaussian training step) and at 10K
// (small [N, 2, 3] batched products). Here it is a plain loop over the Gaussians.
//
// The oracle is smgs/raster/projection.py (`_Project`, which stays the fallback for other dtypes and
// devices): the same formulas in the same order, in float, so results agree to rounding (not
// bitwise: PyTorch's addmm/bmm may sum in another order). Culling: the near plane (z > near), then
// the 3σ box on the image; ids are the survivors in input order. Each Gaussian's math depends on
// nothing but its own inputs and the survivors are compacted in fixed blocks, so results do not
// depend on the number of threads. The backward recomputes the forward intermediates from the
// inputs (the same inline function, so the same bits) instead of storing them. The per-Gaussian
// math, forward and backward, is projection_math.h, which the CUDA projection includes too; this file
// adds only the loops, the compaction and the tensors.
// The ATen and pybind11 headers these bindings use, not <torch/extension.h>: a third of the build time.
#include <ATen/core/Tensor.h>
#include <ATen/ops/empty.h>
#include <ATen/ops/full.h>
#include <ATen/ops/zeros.h>
#include <ATen/ops/zeros_like.h>
#include <torch/csrc/utils/pybind.h>

#include <ATen/Parallel.h>

#include <cmath>
#include <cstdint>
#include <cstring>
#include <memory>
#include <vector>

#include "projection_math.h"

namespace {

using smgs::proj::Cam;

Cam unpack_cam(const at::Tensor& view) {
  TORCH_CHECK(view.scalar_type() == at::kFloat && view.device().is_cpu() && view.numel() == 22,
              "projection_cpu: the camera must be _view's quantities as float32 CPU [22]");
  Cam cam;
  std::memcpy(&cam, view.contiguous().data_ptr<float>(), sizeof cam);
  return cam;
}

at::Tensor rows(const at::Tensor& t, int64_t n, int64_t k, const char* name) {
  TORCH_CHECK(t.scalar_type() == at::kFloat && t.device().is_cpu() && t.dim() == 2 && t.size(0) == n &&
                  t.size(1) == k,
              "projection_cpu: ", name, " must be float32 CPU [", n, ", ", k, "]");
  return t.contiguous();
}

constexpr int64_t kBlock = 256;       // Gaussians per compaction block (fixed: no thread dependence)
constexpr int64_t kGrainBlocks = 8;   // parallel only from 2048 Gaussians up (~0.1 ms of work on one
                                      // thread, far above an OpenMP fork/join)
constexpr int64_t kGrain = kBlock * kGrainBlocks;

}  // namespace

// Returns {ids int64 [M], means2d [M, 2], conics [M, 3], depths [M], radii [M, 2]} of the M Gaussians
// in front of the near plane whose 3σ box meets the image, in input order.
std::vector<at::Tensor> forward(const at::Tensor& means3d_, const at::Tensor& quats_, const at::Tensor& scales_,
                                const at::Tensor& view, double near_plane, double eps2d, double sigma_extent) {
  const int64_t n = means3d_.size(0);
  const at::Tensor means3d = rows(means3d_, n, 3, "means3d"), quats = rows(quats_, n, 4, "quats"),
                   scales = rows(scales_, n, 3, "scales");
  const Cam cam = unpack_cam(view);
  const float* M3 = means3d.data_ptr<float>();
  const float* Q = quats.data_ptr<float>();
  const float* S = scales.data_ptr<float>();
  const float near = float(near_plane), eps = float(eps2d), ext = float(sigma_extent);

  // Pass 1: every Gaussian's outputs into scratch rows (m2d 2, conic 3, depth 1, radii 2), a keep
  // flag, and the number kept per block.
  constexpr int kW = 8;
  const int64_t nb = (n + kBlock - 1) / kBlock;
  std::unique_ptr<float[]> buf(new float[size_t(std::max<int64_t>(n, 1) * kW)]);
  std::unique_ptr<uint8_t[]> keep(new uint8_t[size_t(std::max<int64_t>(n, 1))]);
  std::vector<int64_t> count(nb + 1, 0);
  at::parallel_for(0, nb, kGrainBlocks, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      int64_t kept = 0;
      for (int64_t i = b * kBlock; i < std::min(n, (b + 1) * kBlock); ++i) {
        float* out = buf.get() + kW * i;
        keep[i] = smgs::proj::project_fwd(cam, M3 + 3 * i, Q + 4 * i, S + 3 * i, near, eps, ext, out, out + 2,
                                          out + 5, out + 6);
        kept += keep[i];
      }
      count[b + 1] = kept;
    }
  });
  for (int64_t b = 0; b < nb; ++b) count[b + 1] += count[b];
  const int64_t m = count[nb];

  // Pass 2: compact the survivors, block by block.
  const auto fopt = means3d.options();
  at::Tensor ids = at::empty({m}, fopt.dtype(at::kLong)), means2d = at::empty({m, 2}, fopt),
             conics = at::empty({m, 3}, fopt), depths = at::empty({m}, fopt), radii = at::empty({m, 2}, fopt);
  int64_t* I = ids.data_ptr<int64_t>();
  float *O2 = means2d.data_ptr<float>(), *OC = conics.data_ptr<float>(), *OD = depths.data_ptr<float>(),
        *OR = radii.data_ptr<float>();
  at::parallel_for(0, nb, kGrainBlocks, [&](int64_t b0, int64_t b1) {
    for (int64_t b = b0; b < b1; ++b) {
      int64_t j = count[b];
      for (int64_t i = b * kBlock; i < std::min(n, (b + 1) * kBlock); ++i) {
        if (!keep[i]) continue;
        const float* in = buf.get() + kW * i;
        I[j] = i;
        O2[2 * j] = in[0];
        O2[2 * j + 1] = in[1];
        OC[3 * j] = in[2];
        OC[3 * j + 1] = in[3];
        OC[3 * j + 2] = in[4];
        OD[j] = in[5];
        OR[2 * j] = in[6];
        OR[2 * j + 1] = in[7];
        ++j;
      }
    }
  });
  return {ids, means2d, conics, depths, radii};
}

// Gradients {means3d [N, 3], quats [N, 4], scales [N, 3]} from those of the forward's means2d [M, 2],
// conics [M, 3], depths [M] (rows of `ids`); zero for the culled Gaussians. Transcribes
// _Project.backward line by line.
std::vector<at::Tensor> backward(const at::Tensor& means3d_, const at::Tensor& quats_, const at::Tensor& scales_,
                                 const at::Tensor& view, double near_plane, double eps2d, const at::Tensor& ids_,
                                 const at::Tensor& g_m2d_, const at::Tensor& g_con_, const at::Tensor& g_depth_) {
  const int64_t n = means3d_.size(0);
  const at::Tensor means3d = rows(means3d_, n, 3, "means3d"), quats = rows(quats_, n, 4, "quats"),
                   scales = rows(scales_, n, 3, "scales");
  const Cam cam = unpack_cam(view);
  TORCH_CHECK(ids_.scalar_type() == at::kLong && ids_.dim() == 1, "projection_cpu: ids must be int64 [M]");
  const at::Tensor ids = ids_.contiguous();
  const int64_t m = ids.size(0);
  const at::Tensor g_m2d = rows(g_m2d_, m, 2, "grad of means2d"), g_con = rows(g_con_, m, 3, "grad of conics"),
                   g_depth = rows(g_depth_.reshape({m, 1}), m, 1, "grad of depths");
  const float* M3 = means3d.data_ptr<float>();
  const float* Q = quats.data_ptr<float>();
  const float* S = scales.data_ptr<float>();
  const int64_t* I = ids.data_ptr<int64_t>();
  const float *GM = g_m2d.data_ptr<float>(), *GC = g_con.data_ptr<float>(), *GD = g_depth.data_ptr<float>();
  const float near = float(near_plane), eps = float(eps2d);
  at::Tensor g_means = at::zeros({n, 3}, means3d.options()), g_quats = at::zeros({n, 4}, means3d.options()),
             g_scales = at::zeros({n, 3}, means3d.options());
  float *OM = g_means.data_ptr<float>(), *OQ = g_quats.data_ptr<float>(), *OS = g_scales.data_ptr<float>();

  for (int64_t j = 0; j < m; ++j) TORCH_CHECK(I[j] >= 0 && I[j] < n, "projection_cpu: id out of range");

  at::parallel_for(0, m, kGrain, [&](int64_t j0, int64_t j1) {
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t i = I[j];
      smgs::proj::project_bwd(cam, M3 + 3 * i, Q + 4 * i, S + 3 * i, near, eps, GM + 2 * j, GC + 3 * j, GD[j],
                              OM + 3 * i, OQ + 4 * i, OS + 3 * i);
    }
  });
  return {g_means, g_quats, g_scales};
}

// View-dependent colours [N, C] from SH coefficients sh [N, K, C] at `degree` along the unit
// directions from the camera centre (three host floats) to means3d: sh.py's eval_sh + 0.5, clamped at
// 0 where `clamp` (rasterize's colours). The CPU twin of the CUDA projection's colour stage (the
// same projection_math.h functions); the renderer's CPU path evaluates SH in PyTorch.
namespace {
void check_sh(const at::Tensor& sh, int64_t n, int64_t degree) {
  TORCH_CHECK(degree >= 0 && degree <= 3, "projection_cpu: sh degree must be 0..3, got ", degree);
  TORCH_CHECK(sh.scalar_type() == at::kFloat && sh.device().is_cpu() && sh.dim() == 3 && sh.size(0) == n &&
                  sh.size(1) >= (degree + 1) * (degree + 1),
              "projection_cpu: sh must be float32 CPU [", n, ", >= ", (degree + 1) * (degree + 1), ", C]");
}

// The SH stage's inputs, checked, as both directions read them.
struct ShIn {
  at::Tensor means3d, sh;
  int64_t n, K, C;
  float center[3];
};

ShIn sh_in(const at::Tensor& means3d_, const at::Tensor& sh_, const std::vector<double>& center_, int64_t degree) {
  const int64_t n = means3d_.size(0);
  ShIn in{rows(means3d_, n, 3, "means3d"), {}, n, 0, 0, {}};
  check_sh(sh_, n, degree);
  TORCH_CHECK(center_.size() == 3, "projection_cpu: the camera centre is three floats");
  in.sh = sh_.contiguous();
  in.K = in.sh.size(1);
  in.C = in.sh.size(2);
  for (int k = 0; k < 3; ++k) in.center[k] = float(center_[k]);
  return in;
}
}  // namespace

at::Tensor sh_forward(const at::Tensor& means3d_, const at::Tensor& sh_, const std::vector<double>& center_,
                      int64_t degree, bool clamp) {
  const ShIn in = sh_in(means3d_, sh_, center_, degree);
  const at::Tensor &means3d = in.means3d, &sh = in.sh;
  const int64_t n = in.n, K = in.K, C = in.C;
  const float* center = in.center;
  at::Tensor out = at::empty({n, C}, means3d.options());
  const float *M3 = means3d.data_ptr<float>(), *SH = sh.data_ptr<float>();
  float* O = out.data_ptr<float>();
  at::parallel_for(0, n, kGrain, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i)
      smgs::proj::sh_colour(int(degree), SH + i * K * C, int(C), M3 + 3 * i, center, clamp, O + i * C);
  });
  return out;
}

// {dL/dmeans3d [N, 3] (through the directions), dL/dsh [N, K, C]} from dL/dcolours [N, C].
std::vector<at::Tensor> sh_backward(const at::Tensor& means3d_, const at::Tensor& sh_,
                                    const std::vector<double>& center_, int64_t degree, bool clamp,
                                    const at::Tensor& g_col_) {
  const ShIn in = sh_in(means3d_, sh_, center_, degree);
  const at::Tensor &means3d = in.means3d, &sh = in.sh;
  const int64_t n = in.n, K = in.K, C = in.C;
  const float* center = in.center;
  const at::Tensor g_col = rows(g_col_, n, C, "grad of colours");
  at::Tensor g_means = at::zeros({n, 3}, means3d.options()), g_sh = at::empty({n, K, C}, means3d.options());
  const float *M3 = means3d.data_ptr<float>(), *SH = sh.data_ptr<float>(), *G = g_col.data_ptr<float>();
  float *OM = g_means.data_ptr<float>(), *OS = g_sh.data_ptr<float>();
  at::parallel_for(0, n, kGrain, [&](int64_t i0, int64_t i1) {
    for (int64_t i = i0; i < i1; ++i)
      smgs::proj::sh_colour_bwd(int(degree), int(K), SH + i * K * C, int(C), M3 + 3 * i, center, clamp, G + i * C,
                                OS + i * K * C, OM + 3 * i);
  });
  return {g_means, g_sh};
}

// The camera quantities as forward reads them, flat [22] (the tests check the layout against _view).
at::Tensor camera(const at::Tensor& view) {
  const Cam cam = unpack_cam(view);
  at::Tensor out = at::empty({22}, at::kFloat);
  std::memcpy(out.data_ptr<float>(), &cam, sizeof cam);
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "EWA projection with culling: ids, means2d, conics, depths, radii");
  m.def("backward", &backward, "gradients w.r.t. means3d, quats, scales (zero for culled Gaussians)");
  m.def("sh_forward", &sh_forward, "colours from SH coefficients along the view directions (+0.5, clamped)");
  m.def("sh_backward", &sh_backward, "gradients w.r.t. means3d (through the directions) and the SH coefficients");
  m.def("camera", &camera, "the camera quantities as forward reads them, flat (rw, tw, f, c, lo, hi, size)");
}
