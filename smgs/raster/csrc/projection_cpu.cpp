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
// inputs (the same inline function, so the same bits) instead of storing them.
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

namespace {

// The camera quantities of projection.py's _view (defined there once), as the flat float32 [22]
// it packs: rw [3, 3] row-major, tw [3], then f, c, lo, hi, size [2 each].
struct Cam {
  float rw[3][3], tw[3], f[2], c[2], lo[2], hi[2], size[2];
};
static_assert(sizeof(Cam) == 22 * sizeof(float), "Cam is 22 packed floats");

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

// torch.minimum(torch.maximum(r, lo), hi), NaN propagating as there.
inline float clampf(float r, float lo, float hi) { return r < lo ? lo : (r > hi ? hi : r); }

// The forward intermediates of one Gaussian (the tensors _Project saves for backward).
struct Splat {
  float z, r[2], u[2], ab[2], D[2][3], T[2][3], q[4], qn, R[3][3], TR[2][3], P[2][3];
  float sxx, syy, sxy, det_raw, det;
};

// False if the Gaussian is not in front of the near plane (then only z is set).
inline bool project_one(const Cam& cam, const float* m, const float* quat, const float* s, float near,
                        float eps2d, Splat& o) {
  float pc[3];
  for (int j = 0; j < 3; ++j) pc[j] = cam.tw[j] + (m[0] * cam.rw[j][0] + m[1] * cam.rw[j][1] + m[2] * cam.rw[j][2]);
  o.z = pc[2];
  if (!(o.z > near)) return false;
  for (int a = 0; a < 2; ++a) {
    o.r[a] = pc[a] / o.z;
    o.u[a] = clampf(o.r[a], cam.lo[a], cam.hi[a]);
    o.ab[a] = cam.f[a] / o.z;
    for (int k = 0; k < 3; ++k) {
      o.D[a][k] = cam.rw[a][k] - o.u[a] * cam.rw[2][k];
      o.T[a][k] = o.D[a][k] * o.ab[a];
    }
  }
  o.qn = std::sqrt(((quat[0] * quat[0] + quat[1] * quat[1]) + quat[2] * quat[2]) + quat[3] * quat[3]);
  for (int k = 0; k < 4; ++k) o.q[k] = quat[k] / o.qn;
  const float w = o.q[0], x = o.q[1], y = o.q[2], z = o.q[3];
  // quat_to_rotmat / _rot_linear: const + Σ ±2·q_a·q_b (the factor 2 is exact, so 2·(p ± p') is the
  // same number as ±2p ± 2p').
  o.R[0][0] = 1.f - 2.f * (y * y + z * z);
  o.R[0][1] = 2.f * (x * y - w * z);
  o.R[0][2] = 2.f * (x * z + w * y);
  o.R[1][0] = 2.f * (x * y + w * z);
  o.R[1][1] = 1.f - 2.f * (x * x + z * z);
  o.R[1][2] = 2.f * (y * z - w * x);
  o.R[2][0] = 2.f * (x * z - w * y);
  o.R[2][1] = 2.f * (y * z + w * x);
  o.R[2][2] = 1.f - 2.f * (x * x + y * y);
  for (int a = 0; a < 2; ++a)
    for (int k = 0; k < 3; ++k) {
      o.TR[a][k] = (o.T[a][0] * o.R[0][k] + o.T[a][1] * o.R[1][k]) + o.T[a][2] * o.R[2][k];
      o.P[a][k] = o.TR[a][k] * s[k];
    }
  const float cxx = (o.P[0][0] * o.P[0][0] + o.P[0][1] * o.P[0][1]) + o.P[0][2] * o.P[0][2];
  const float cyy = (o.P[1][0] * o.P[1][0] + o.P[1][1] * o.P[1][1]) + o.P[1][2] * o.P[1][2];
  o.sxy = (o.P[0][0] * o.P[1][0] + o.P[0][1] * o.P[1][1]) + o.P[0][2] * o.P[1][2];
  o.sxx = cxx + eps2d;
  o.syy = cyy + eps2d;
  o.det_raw = o.sxx * o.syy - o.sxy * o.sxy;
  o.det = o.det_raw < 1e-12f ? 1e-12f : o.det_raw;   // clamp_min (NaN stays NaN)
  return true;
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
        Splat o;
        keep[i] = 0;
        if (!project_one(cam, M3 + 3 * i, Q + 4 * i, S + 3 * i, near, eps, o)) continue;
        float* out = buf.get() + kW * i;
        bool on = true;
        for (int a = 0; a < 2; ++a) {
          const float m2 = cam.c[a] + cam.f[a] * o.r[a];
          const float rad = ext * std::sqrt(a == 0 ? o.sxx : o.syy);
          on = on && (m2 + rad > 0.f) && (m2 - rad < cam.size[a]);
          out[a] = m2;
          out[6 + a] = rad;
        }
        if (!on) continue;
        out[2] = o.syy / o.det;
        out[3] = -o.sxy / o.det;
        out[4] = o.sxx / o.det;
        out[5] = o.z;
        keep[i] = 1;
        ++kept;
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
      Splat o;
      project_one(cam, M3 + 3 * i, Q + 4 * i, S + 3 * i, near, eps, o);
      // conic = (syy, −sxy, sxx) / det, det = max(sxx·syy − sxy², 1e-12) (clamp: torch's mask)
      const float inv = 1.f / o.det;
      const float ga = GC[3 * j], gb = GC[3 * j + 1], gc = GC[3 * j + 2];
      const float g_det =
          -((ga * o.syy - gb * o.sxy) + gc * o.sxx) * inv * inv * (o.det_raw >= 1e-12f ? 1.f : 0.f);
      const float g_sxx = gc * inv + g_det * o.syy;
      const float g_syy = ga * inv + g_det * o.sxx;
      const float g_sxy = -gb * inv - 2.f * o.sxy * g_det;
      // Σ2D = P Pᵀ, sxy read from the upper triangle: dL/dP = (G + Gᵀ)·P; P = TR·diag(s)
      const float G[2][2] = {{2.f * g_sxx, g_sxy}, {g_sxy, 2.f * g_syy}};
      float g_P[2][3], g_TR[2][3];
      for (int a = 0; a < 2; ++a)
        for (int k = 0; k < 3; ++k) {
          g_P[a][k] = G[a][0] * o.P[0][k] + G[a][1] * o.P[1][k];
          g_TR[a][k] = g_P[a][k] * S[3 * i + k];
        }
      for (int k = 0; k < 3; ++k) OS[3 * i + k] = g_P[0][k] * o.TR[0][k] + g_P[1][k] * o.TR[1][k];
      float g_T[2][3], g_R[3][3];
      for (int a = 0; a < 2; ++a)
        for (int k = 0; k < 3; ++k)
          g_T[a][k] = (g_TR[a][0] * o.R[k][0] + g_TR[a][1] * o.R[k][1]) + g_TR[a][2] * o.R[k][2];
      for (int j2 = 0; j2 < 3; ++j2)
        for (int k = 0; k < 3; ++k) g_R[j2][k] = o.T[0][j2] * g_TR[0][k] + o.T[1][j2] * g_TR[1][k];
      // T = diag(ab)·D, D = Rw[:2] − u ⊗ Rw[2]; ab = f / z. u = clamp(r) passes the gradient inside
      // the limits, bounds included (torch.clamp); means2d = f·r + c; r = p_xy / z; depth = z
      float g_ab[2], g_r[2];
      for (int a = 0; a < 2; ++a) {
        g_ab[a] = (g_T[a][0] * o.D[a][0] + g_T[a][1] * o.D[a][1]) + g_T[a][2] * o.D[a][2];
        const float g_u =
            -((g_T[a][0] * cam.rw[2][0] + g_T[a][1] * cam.rw[2][1]) + g_T[a][2] * cam.rw[2][2]) * o.ab[a];
        const float pass = (o.r[a] >= cam.lo[a]) && (o.r[a] <= cam.hi[a]) ? 1.f : 0.f;
        g_r[a] = g_u * pass + GM[2 * j + a] * cam.f[a];
      }
      const float g_z = GD[j] - ((g_r[0] * o.r[0] + g_r[1] * o.r[1]) + (g_ab[0] * o.ab[0] + g_ab[1] * o.ab[1])) / o.z;
      const float v[3] = {g_r[0] / o.z, g_r[1] / o.z, g_z};
      for (int k = 0; k < 3; ++k)
        OM[3 * i + k] = (v[0] * cam.rw[0][k] + v[1] * cam.rw[1][k]) + v[2] * cam.rw[2][k];
      // vec(R) = vec(q qᵀ)·L + c (L of _rot_linear: the upper entries q_a·q_b, a <= b, of each term);
      // g_qq = L·vec(g_R), then g_q = (g_qq + g_qqᵀ)·q. Index 0..3 = w, x, y, z.
      const float* gr = &g_R[0][0];
      float Sq[4][4] = {};
      Sq[0][1] = Sq[1][0] = -2.f * gr[5] + 2.f * gr[7];   // w·x
      Sq[0][2] = Sq[2][0] = 2.f * gr[2] + -2.f * gr[6];   // w·y
      Sq[0][3] = Sq[3][0] = -2.f * gr[1] + 2.f * gr[3];   // w·z
      Sq[1][2] = Sq[2][1] = 2.f * gr[1] + 2.f * gr[3];    // x·y
      Sq[1][3] = Sq[3][1] = 2.f * gr[2] + 2.f * gr[6];    // x·z
      Sq[2][3] = Sq[3][2] = 2.f * gr[5] + 2.f * gr[7];    // y·z
      Sq[1][1] = 2.f * (-2.f * gr[4] + -2.f * gr[8]);     // x·x (diagonal: g_qq + g_qqᵀ doubles it)
      Sq[2][2] = 2.f * (-2.f * gr[0] + -2.f * gr[8]);     // y·y
      Sq[3][3] = 2.f * (-2.f * gr[0] + -2.f * gr[4]);     // z·z
      float g_q[4];
      for (int a = 0; a < 4; ++a)
        g_q[a] = ((Sq[a][0] * o.q[0] + Sq[a][1] * o.q[1]) + Sq[a][2] * o.q[2]) + Sq[a][3] * o.q[3];
      const float dot = ((o.q[0] * g_q[0] + o.q[1] * g_q[1]) + o.q[2] * g_q[2]) + o.q[3] * g_q[3];
      for (int a = 0; a < 4; ++a) OQ[4 * i + a] = (g_q[a] - o.q[a] * dot) / o.qn;
    }
  });
  return {g_means, g_quats, g_scales};
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
  m.def("camera", &camera, "the camera quantities as forward reads them, flat (rw, tw, f, c, lo, hi, size)");
}
