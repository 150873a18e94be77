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
//
// The view-dependent colours (spherical harmonics, sh.py's eval_sh, + 0.5 and the clamp) are part of
// the same pass where asked for: evaluated for the kept Gaussians only, straight into the compacted
// rows, from the trainer's two coefficient tensors read in place, and their adjoint in the same
// backward loop (the mean's gradient through the view direction added to the projection's). In
// PyTorch each coefficient's read was a select whose backward zero-filled a whole [N, 16, 3] tensor.
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
  TORCH_CHECK(view.scalar_type() == at::kFloat && view.device().is_cpu() && (view.numel() == 22 || view.numel() == 25),
              "projection_cpu: the camera must be _view's quantities as float32 CPU [22] (or [25] with the centre)");
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

// A gradient the loss may not have reached (an empty tensor: autograd made none, so it is zero): its
// rows, or null.
const float* grad_rows(const at::Tensor& t, int64_t n, int64_t k, const char* name, at::Tensor& keep) {
  if (t.numel() == 0 && n != 0) return nullptr;
  keep = rows(t.reshape({n, k}), n, k, name);
  return keep.data_ptr<float>();
}

constexpr int64_t kBlock = 256;       // Gaussians per compaction block (fixed: no thread dependence)
constexpr int64_t kGrainBlocks = 8;   // parallel only from 2048 Gaussians up (~0.1 ms of work on one
                                      // thread, far above an OpenMP fork/join)
constexpr int64_t kGrain = kBlock * kGrainBlocks;

// The colour stage's inputs as the projection reads them: the SH coefficients as the trainer keeps
// them, in two parts read in place (no concatenation per step): sh0 [N, 1, C] (coefficient 0, 3DGS's
// features_dc) and rest [N, K - 1, C] (features_rest); or as one tensor sh0 [N, K, C] with rest empty.
// Row i's coefficient 0 is at sh0 + i·s0, its others at rest + i·sr (each row's own [·, C] contiguous).
// The degree, the clamp and the camera centre (the view's floats 22..24). `on` is false where no
// colours are asked for (sh0 empty and not [N, K, C]).
struct ShParts {
  bool on = false, one = false;   // one: a single [N, K, C] tensor
  at::Tensor sh0, rest;
  int64_t K = 0, C = 0, s0 = 0, sr = 0;
  int degree = 0;
  bool clamp = true;
  float center[3] = {0.f, 0.f, 0.f};
  const float* p0() const { return sh0.data_ptr<float>(); }
  const float* pr() const { return one ? sh0.data_ptr<float>() + C : rest.data_ptr<float>(); }
};

void check_coefs(const at::Tensor& t, int64_t n, int64_t k_min, int64_t C, const char* what) {
  TORCH_CHECK(t.scalar_type() == at::kFloat && t.device().is_cpu() && t.dim() == 3 && t.size(0) == n &&
                  t.size(1) >= k_min && (C < 0 || t.size(2) == C),
              "projection_cpu: ", what, " must be float32 CPU [", n, ", >= ", k_min, ", C]");
}

ShParts sh_parts(const at::Tensor& sh0, const at::Tensor& rest, int64_t degree, bool clamp, const at::Tensor& view,
                 int64_t n) {
  ShParts p;
  if (sh0.dim() != 3) return p;   // no colour stage
  TORCH_CHECK(degree >= 0 && degree <= 3, "projection_cpu: sh degree must be 0..3, got ", degree);
  const int64_t nb = (degree + 1) * (degree + 1);
  p.one = rest.dim() != 3;
  check_coefs(sh0, n, p.one ? nb : 1, -1, "the SH coefficients (sh0)");
  TORCH_CHECK(p.one || sh0.size(1) == 1, "projection_cpu: sh0 must be [N, 1, C] beside the rest of the coefficients");
  p.C = sh0.size(2);
  if (!p.one) check_coefs(rest, n, nb - 1, p.C, "the rest of the SH coefficients");
  TORCH_CHECK(view.numel() == 25, "projection_cpu: colours from SH need the camera centre (a view of [25] floats)");
  p.on = true;
  p.sh0 = sh0.contiguous();
  p.rest = p.one ? rest : rest.contiguous();
  p.K = p.one ? sh0.size(1) : 1 + rest.size(1);
  p.s0 = p.one ? p.K * p.C : p.C;
  p.sr = p.one ? p.K * p.C : (p.K - 1) * p.C;
  p.degree = int(degree);
  p.clamp = clamp;
  std::memcpy(p.center, view.contiguous().data_ptr<float>() + 22, sizeof p.center);
  return p;
}

}  // namespace

// Returns {ids int64 [M], means2d [M, 2], conics [M, 3], depths [M], radii [M, 2], colours [M, C]} of the M
// Gaussians in front of the near plane whose 3σ box meets the image, in input order. The colours are
// sh.py's eval_sh + 0.5 along the view directions (clamped at 0 where `clamp`: rasterize's colours) of
// the SH coefficients sh0, rest at `degree` (sh_parts); an empty tensor where sh0 is empty.
std::vector<at::Tensor> forward(const at::Tensor& means3d_, const at::Tensor& quats_, const at::Tensor& scales_,
                                const at::Tensor& view, double near_plane, double eps2d, double sigma_extent,
                                const at::Tensor& sh0_, const at::Tensor& rest_, int64_t degree, bool clamp) {
  const int64_t n = means3d_.size(0);
  const at::Tensor means3d = rows(means3d_, n, 3, "means3d"), quats = rows(quats_, n, 4, "quats"),
                   scales = rows(scales_, n, 3, "scales");
  const Cam cam = unpack_cam(view);
  const ShParts sh = sh_parts(sh0_, rest_, degree, clamp, view, n);
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

  // Pass 2: compact the survivors, block by block, with their colours.
  const auto fopt = means3d.options();
  at::Tensor ids = at::empty({m}, fopt.dtype(at::kLong)), means2d = at::empty({m, 2}, fopt),
             conics = at::empty({m, 3}, fopt), depths = at::empty({m}, fopt), radii = at::empty({m, 2}, fopt),
             colours = at::empty({sh.on ? m : 0, sh.C}, fopt);
  int64_t* I = ids.data_ptr<int64_t>();
  float *O2 = means2d.data_ptr<float>(), *OC = conics.data_ptr<float>(), *OD = depths.data_ptr<float>(),
        *OR = radii.data_ptr<float>(), *OK = sh.on ? colours.data_ptr<float>() : nullptr;
  const float *SH0 = sh.on ? sh.p0() : nullptr, *SHR = sh.on ? sh.pr() : nullptr;
  const int64_t C = sh.C;
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
        if (OK && C == 3)   // RGB: the three channels' sums side by side (the same bits)
          smgs::proj::sh_colour_parts<3>(sh.degree, SH0 + i * sh.s0, SHR + i * sh.sr, 3, M3 + 3 * i, sh.center,
                                         sh.clamp, OK + j * C);
        else if (OK)
          smgs::proj::sh_colour_parts(sh.degree, SH0 + i * sh.s0, SHR + i * sh.sr, int(C), M3 + 3 * i, sh.center,
                                      sh.clamp, OK + j * C);
        ++j;
      }
    }
  });
  return {ids, means2d, conics, depths, radii, colours};
}

// Gradients {means3d [N, 3], quats [N, 4], scales [N, 3], sh0 [N, 1, C], rest [N, K - 1, C]} from those of
// the forward's means2d [M, 2], conics [M, 3], depths [M] and colours [M, C] (rows of `ids`, increasing);
// an empty gradient is one the loss did not reach (zero). Zero for the culled Gaussians, each row
// written once (no zero-fill first); the SH gradients are empty tensors where sh0 is. Transcribes
// _Project.backward and the adjoint of the colours line by line; a Gaussian's mean gets both (the
// colours' through the view direction).
std::vector<at::Tensor> backward(const at::Tensor& means3d_, const at::Tensor& quats_, const at::Tensor& scales_,
                                 const at::Tensor& view, double near_plane, double eps2d, const at::Tensor& ids_,
                                 const at::Tensor& g_m2d_, const at::Tensor& g_con_, const at::Tensor& g_depth_,
                                 const at::Tensor& sh0_, const at::Tensor& rest_, int64_t degree, bool clamp,
                                 const at::Tensor& g_col_) {
  const int64_t n = means3d_.size(0);
  const at::Tensor means3d = rows(means3d_, n, 3, "means3d"), quats = rows(quats_, n, 4, "quats"),
                   scales = rows(scales_, n, 3, "scales");
  const Cam cam = unpack_cam(view);
  const ShParts sh = sh_parts(sh0_, rest_, degree, clamp, view, n);
  TORCH_CHECK(ids_.scalar_type() == at::kLong && ids_.dim() == 1, "projection_cpu: ids must be int64 [M]");
  const at::Tensor ids = ids_.contiguous();
  const int64_t m = ids.size(0);
  at::Tensor hold[4];
  static const float kZero[3] = {0.f, 0.f, 0.f};
  const float* GM = grad_rows(g_m2d_, m, 2, "grad of means2d", hold[0]);
  const float* GC = grad_rows(g_con_, m, 3, "grad of conics", hold[1]);
  const float* GD = grad_rows(g_depth_, m, 1, "grad of depths", hold[2]);
  const float* GK = sh.on ? grad_rows(g_col_, m, sh.C, "grad of colours", hold[3]) : nullptr;
  const float* M3 = means3d.data_ptr<float>();
  const float* Q = quats.data_ptr<float>();
  const float* S = scales.data_ptr<float>();
  const int64_t* I = ids.data_ptr<int64_t>();
  const float near = float(near_plane), eps = float(eps2d);
  const auto fopt = means3d.options();
  at::Tensor g_means = at::empty({n, 3}, fopt), g_quats = at::empty({n, 4}, fopt), g_scales = at::empty({n, 3}, fopt),
             g_sh0 = sh.on ? at::empty({n, sh.one ? sh.K : 1, sh.C}, fopt) : at::empty({0}, fopt),
             g_rest = sh.on && !sh.one ? at::empty({n, sh.K - 1, sh.C}, fopt) : at::empty({0}, fopt);
  float *OM = g_means.data_ptr<float>(), *OQ = g_quats.data_ptr<float>(), *OS = g_scales.data_ptr<float>();
  // the SH gradients in the inputs' layout: one [N, K, C] tensor, or the two parts (row strides s0, sr)
  float* OS0 = sh.on ? g_sh0.data_ptr<float>() : nullptr;
  float* OSR = !sh.on ? nullptr : sh.one ? OS0 + sh.C : g_rest.data_ptr<float>();
  const float *SH0 = sh.on ? sh.p0() : nullptr, *SHR = sh.on ? sh.pr() : nullptr;
  const int64_t C = sh.C, s0 = sh.s0, sr = sh.sr, R = (sh.K - 1) * sh.C;

  for (int64_t j = 0; j < m; ++j)
    TORCH_CHECK(I[j] >= 0 && I[j] < n && (j == 0 || I[j] > I[j - 1]),
                "projection_cpu: ids must be increasing indices of the Gaussians (the forward's)");
  // Rows [i0, i1) of the SH gradients, zero (one block where the coefficients are one tensor).
  auto zero_sh = [&](int64_t i0, int64_t i1) {
    if (!sh.on || i1 <= i0) return;
    std::memset(OS0 + s0 * i0, 0, sizeof(float) * s0 * (i1 - i0));
    if (!sh.one && R) std::memset(OSR + sr * i0, 0, sizeof(float) * sr * (i1 - i0));
  };
  // The rows [i0, i1) that no kept Gaussian has: zero.
  auto zero_rows = [&](int64_t i0, int64_t i1) {
    if (i1 <= i0) return;
    std::memset(OM + 3 * i0, 0, sizeof(float) * 3 * (i1 - i0));
    std::memset(OQ + 4 * i0, 0, sizeof(float) * 4 * (i1 - i0));
    std::memset(OS + 3 * i0, 0, sizeof(float) * 3 * (i1 - i0));
    zero_sh(i0, i1);
  };
  at::parallel_for(0, m, kGrain, [&](int64_t j0, int64_t j1) {
    for (int64_t j = j0; j < j1; ++j) {
      const int64_t i = I[j];
      zero_rows(j == 0 ? 0 : I[j - 1] + 1, i);   // the culled rows before this one
      smgs::proj::project_bwd(cam, M3 + 3 * i, Q + 4 * i, S + 3 * i, near, eps, GM ? GM + 2 * j : kZero,
                              GC ? GC + 3 * j : kZero, GD ? GD[j] : 0.f, OM + 3 * i, OQ + 4 * i, OS + 3 * i);
      if (GK && C == 3)
        smgs::proj::sh_colour_parts_bwd<3>(sh.degree, int(sh.K), SH0 + i * s0, SHR + i * sr, 3, M3 + 3 * i,
                                           sh.center, sh.clamp, GK + j * C, OS0 + i * s0, OSR + i * sr, OM + 3 * i);
      else if (GK)
        smgs::proj::sh_colour_parts_bwd(sh.degree, int(sh.K), SH0 + i * s0, SHR + i * sr, int(C), M3 + 3 * i,
                                        sh.center, sh.clamp, GK + j * C, OS0 + i * s0, OSR + i * sr, OM + 3 * i);
      else
        zero_sh(i, i + 1);
    }
  });
  zero_rows(m == 0 ? 0 : I[m - 1] + 1, n);   // the culled rows after the last kept one
  return {g_means, g_quats, g_scales, g_sh0, g_rest};
}

// View-dependent colours [N, C] from SH coefficients sh [N, K, C] at `degree` along the unit
// directions from the camera centre (three host floats) to means3d: sh.py's eval_sh + 0.5, clamped at
// 0 where `clamp` (rasterize's colours), for every Gaussian: the colour stage alone, the CPU twin of the
// CUDA projection's (the same projection_math.h functions; tests/test_raster_projection_cuda.py compares
// them bit for bit). The renderer's CPU path evaluates it inside forward/backward above, for the kept
// Gaussians only.
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

// The renderer's input checks of float32 CPU tensors (smgs/raster/checks.py), in one call: for each
// tensor {its NaN and ±inf values (NaN and −inf where pos_inf_ok: γ may be +inf), its negative values},
// counted exactly, one pass each, on the caller's thread. In PyTorch each tensor was a sum, then a
// stack, a finiteness test and a read; a sum of a large tensor is a parallel region (an OpenMP wake-up
// each, with passive waits), so a 3dgs step's checks cost ~0.5 ms for ~0.6M floats of parameters.
namespace {
// On the bits, integer compares only (so that the loop vectorises), in blocks whose counts fit 32 bits.
template <bool INF_OK>
void count_bad(const float* p, int64_t n, int64_t& bad, int64_t& neg) {
  constexpr int64_t kBlock = int64_t(1) << 20;
  for (int64_t i0 = 0; i0 < n; i0 += kBlock) {
    const int64_t i1 = std::min(n, i0 + kBlock);
    uint32_t b = 0, g = 0;
    for (int64_t i = i0; i < i1; ++i) {
      uint32_t u;
      std::memcpy(&u, p + i, sizeof u);
      const uint32_t mag = u & 0x7fffffffu;   // exponent all ones: inf (mantissa 0) or NaN
      b += INF_OK ? uint32_t(mag > 0x7f800000u) | uint32_t(u == 0xff800000u) : uint32_t(mag >= 0x7f800000u);
      g += uint32_t(u > 0x80000000u) & uint32_t(u <= 0xff800000u);   // < 0 as torch: not -0, not NaN
    }
    bad += b;
    neg += g;
  }
}

// Whether each slice t[i] is contiguous (the rows of a view such as sh_rest[:, :k]).
bool rows_contiguous(const at::Tensor& t) {
  int64_t want = 1;
  for (int64_t d = t.dim() - 1; d >= 1; --d) {
    if (t.size(d) != 1 && t.stride(d) != want) return false;
    want *= t.size(d);
  }
  return true;
}
}  // namespace

std::vector<int64_t> input_checks(const std::vector<at::Tensor>& tensors, const std::vector<bool>& pos_inf_ok) {
  TORCH_CHECK(tensors.size() == pos_inf_ok.size(), "projection_cpu: input_checks needs one pos_inf_ok per tensor");
  std::vector<int64_t> out(2 * tensors.size(), 0);
  for (size_t k = 0; k < tensors.size(); ++k) {
    const at::Tensor& t = tensors[k];
    TORCH_CHECK(t.scalar_type() == at::kFloat && t.device().is_cpu(), "projection_cpu: input_checks takes float32 CPU tensors");
    if (t.numel() == 0) continue;
    const bool by_rows = t.dim() >= 2 && !t.is_contiguous() && rows_contiguous(t);
    const at::Tensor c = by_rows || t.is_contiguous() ? t : t.contiguous();
    const int64_t rows = by_rows ? c.size(0) : 1, len = c.numel() / rows, step = by_rows ? c.stride(0) : 0;
    const float* p = c.data_ptr<float>();
    for (int64_t r = 0; r < rows; ++r) {
      if (pos_inf_ok[k])
        count_bad<true>(p + r * step, len, out[2 * k], out[2 * k + 1]);
      else
        count_bad<false>(p + r * step, len, out[2 * k], out[2 * k + 1]);
    }
  }
  return out;
}

// The camera quantities as forward reads them, flat [22] (the tests check the layout against _view).
at::Tensor camera(const at::Tensor& view) {
  const Cam cam = unpack_cam(view);
  at::Tensor out = at::empty({22}, at::kFloat);
  std::memcpy(out.data_ptr<float>(), &cam, sizeof cam);
  return out;
}

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &forward, "EWA projection with culling: ids, means2d, conics, depths, radii and the colours from SH");
  m.def("backward", &backward, "gradients w.r.t. means3d, quats, scales, sh0, rest (zero for culled Gaussians)");
  m.def("sh_forward", &sh_forward, "colours from SH coefficients along the view directions (+0.5, clamped)");
  m.def("sh_backward", &sh_backward, "gradients w.r.t. means3d (through the directions) and the SH coefficients");
  m.def("input_checks", &input_checks, "the renderer's input checks: NaN/inf and negative values per tensor");
  m.def("camera", &camera, "the camera quantities as forward reads them, flat (rw, tw, f, c, lo, hi, size)");
}
