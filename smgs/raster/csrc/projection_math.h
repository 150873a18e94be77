// Per-Gaussian math of the projection: EWA splatting of one 3D Gaussian to its 2D splat (OpenCV
// pinhole), the view-dependent colour from spherical harmonics, and the hand-written adjoints of
// both. The one header the compiled projections include: the CPU pass (projection_cpu.cpp) and the
// CUDA kernels (projection_cuda.cu), as splat_math.h is for compositing. See docs/cuda.md.
//
// The oracle is smgs/raster/projection.py (`_Project`) and smgs/raster/sh.py (`eval_sh`): the same
// formulas in the same order, in float, so results agree with them to rounding (not bitwise:
// PyTorch's addmm/bmm may sum in another order). Built without FMA contraction (-ffp-contract=off on
// the host, --fmad=false on the device) with IEEE division and square root, the CPU and the CUDA
// build of this header give the same bits (tests/test_raster_projection_cuda.py checks it on a GPU).
// The backward recomputes the forward intermediates from the inputs (the same inline functions, so
// the same bits) instead of storing them.
#pragma once

#if !defined(SMGS_HD)
#if defined(__CUDACC__)
#define SMGS_HD __host__ __device__ __attribute__((always_inline))
#elif defined(__GNUC__)
#define SMGS_HD __attribute__((always_inline))
#else
#define SMGS_HD
#endif
#endif

#include <math.h>

namespace smgs {
namespace proj {

// The camera quantities of projection.py's _view (defined there once), as the flat float32 [22]
// it packs: rw [3, 3] row-major, tw [3], then f, c, lo, hi, size [2 each].
struct Cam {
  float rw[3][3], tw[3], f[2], c[2], lo[2], hi[2], size[2];
};
static_assert(sizeof(Cam) == 22 * sizeof(float), "Cam is 22 packed floats");

// torch.minimum(torch.maximum(r, lo), hi), NaN propagating as there.
SMGS_HD inline float clampf(float r, float lo, float hi) { return r < lo ? lo : (r > hi ? hi : r); }

// The forward intermediates of one Gaussian (the tensors _Project saves for backward).
struct Splat {
  float z, r[2], u[2], ab[2], D[2][3], T[2][3], q[4], qn, R[3][3], TR[2][3], P[2][3];
  float sxx, syy, sxy, det_raw, det;
};

// Per Gaussian: p = Rw·m + tw; r = p_xy / z; u = clamp(r) (the Jacobian's clamped direction);
// T = J·Rw = diag(f / z)·(Rw[:2] − u ⊗ Rw[2]); P = T·R(q̂)·diag(s); Σ2D = P Pᵀ + eps2d·I.
// False if the Gaussian is not in front of the near plane (then only z is set).
SMGS_HD inline bool project_one(const Cam& cam, const float* m, const float* quat, const float* s, float near,
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
  o.qn = sqrtf(((quat[0] * quat[0] + quat[1] * quat[1]) + quat[2] * quat[2]) + quat[3] * quat[3]);
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

// One Gaussian's splat: means2d = f·r + c [2], conic = (Σyy, −Σxy, Σxx) / max(det, 1e-12) [3],
// depth = z, radii = sigma_extent·√(Σxx, Σyy) [2]. True where it is kept: in front of the near
// plane and its 3σ box meets the image. Where false, only what was computed before the cull is set
// (nothing behind the near plane; means2d and radii off the image).
SMGS_HD inline bool project_fwd(const Cam& cam, const float* m, const float* quat, const float* s, float near,
                                float eps2d, float ext, float* m2d, float* conic, float* depth, float* radii) {
  Splat o;
  if (!project_one(cam, m, quat, s, near, eps2d, o)) return false;
  bool on = true;
  for (int a = 0; a < 2; ++a) {
    const float m2 = cam.c[a] + cam.f[a] * o.r[a];
    const float rad = ext * sqrtf(a == 0 ? o.sxx : o.syy);
    on = on && (m2 + rad > 0.f) && (m2 - rad < cam.size[a]);
    m2d[a] = m2;
    radii[a] = rad;
  }
  if (!on) return false;
  conic[0] = o.syy / o.det;
  conic[1] = -o.sxy / o.det;
  conic[2] = o.sxx / o.det;
  *depth = o.z;
  return true;
}

// Gradients of one kept Gaussian's means3d [3], quats [4], scales [3] from those of its means2d [2],
// conic [3] and depth: _Project.backward line by line.
SMGS_HD inline void project_bwd(const Cam& cam, const float* m, const float* quat, const float* s, float near,
                                float eps2d, const float* gm2d, const float* gcon, float gdepth, float* g_means,
                                float* g_quats, float* g_scales) {
  Splat o;
  project_one(cam, m, quat, s, near, eps2d, o);
  // conic = (syy, −sxy, sxx) / det, det = max(sxx·syy − sxy², 1e-12) (clamp: torch's mask)
  const float inv = 1.f / o.det;
  const float ga = gcon[0], gb = gcon[1], gc = gcon[2];
  const float g_det = -((ga * o.syy - gb * o.sxy) + gc * o.sxx) * inv * inv * (o.det_raw >= 1e-12f ? 1.f : 0.f);
  const float g_sxx = gc * inv + g_det * o.syy;
  const float g_syy = ga * inv + g_det * o.sxx;
  const float g_sxy = -gb * inv - 2.f * o.sxy * g_det;
  // Σ2D = P Pᵀ, sxy read from the upper triangle: dL/dP = (G + Gᵀ)·P; P = TR·diag(s)
  const float G[2][2] = {{2.f * g_sxx, g_sxy}, {g_sxy, 2.f * g_syy}};
  float g_P[2][3], g_TR[2][3];
  for (int a = 0; a < 2; ++a)
    for (int k = 0; k < 3; ++k) {
      g_P[a][k] = G[a][0] * o.P[0][k] + G[a][1] * o.P[1][k];
      g_TR[a][k] = g_P[a][k] * s[k];
    }
  for (int k = 0; k < 3; ++k) g_scales[k] = g_P[0][k] * o.TR[0][k] + g_P[1][k] * o.TR[1][k];
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
    const float g_u = -((g_T[a][0] * cam.rw[2][0] + g_T[a][1] * cam.rw[2][1]) + g_T[a][2] * cam.rw[2][2]) * o.ab[a];
    const float pass = (o.r[a] >= cam.lo[a]) && (o.r[a] <= cam.hi[a]) ? 1.f : 0.f;
    g_r[a] = g_u * pass + gm2d[a] * cam.f[a];
  }
  const float g_z = gdepth - ((g_r[0] * o.r[0] + g_r[1] * o.r[1]) + (g_ab[0] * o.ab[0] + g_ab[1] * o.ab[1])) / o.z;
  const float v[3] = {g_r[0] / o.z, g_r[1] / o.z, g_z};
  for (int k = 0; k < 3; ++k) g_means[k] = (v[0] * cam.rw[0][k] + v[1] * cam.rw[1][k]) + v[2] * cam.rw[2][k];
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
  for (int a = 0; a < 4; ++a) g_q[a] = ((Sq[a][0] * o.q[0] + Sq[a][1] * o.q[1]) + Sq[a][2] * o.q[2]) + Sq[a][3] * o.q[3];
  const float dot = ((o.q[0] * g_q[0] + o.q[1] * g_q[1]) + o.q[2] * g_q[2]) + o.q[3] * g_q[3];
  for (int a = 0; a < 4; ++a) g_quats[a] = (g_q[a] - o.q[a] * dot) / o.qn;
}

// ---- view-dependent colour: real spherical harmonics up to degree 3 (smgs/raster/sh.py) ----------
// The constants of sh.py (3DGS's utils/sh_utils.py), as float32.
constexpr float kC0 = 0.28209479177387814f;
constexpr float kC1 = 0.4886025119029199f;
// (scalars, not arrays: a constexpr array is not visible in device code)
constexpr float kC2_0 = 1.0925484305920792f, kC2_1 = -1.0925484305920792f, kC2_2 = 0.31539156525252005f,
                kC2_3 = -1.0925484305920792f, kC2_4 = 0.5462742152960396f;
constexpr float kC3_0 = -0.5900435899266435f, kC3_1 = 2.890611442640554f, kC3_2 = -0.4570457994644658f,
                kC3_3 = 0.3731763325901154f, kC3_4 = -0.4570457994644658f, kC3_5 = 1.445305721320277f,
                kC3_6 = -0.5900435899266435f;
constexpr int kMaxShBases = 16;

// The basis values b[k] of `degree` along the unit direction (x, y, z): colour = Σ_k b[k]·sh[k].
SMGS_HD inline void sh_basis(int degree, float x, float y, float z, float* b) {
  b[0] = kC0;
  if (degree < 1) return;
  b[1] = -(kC1 * y);
  b[2] = kC1 * z;
  b[3] = -(kC1 * x);
  if (degree < 2) return;
  const float xx = x * x, yy = y * y, zz = z * z, xy = x * y, yz = y * z, xz = x * z;
  b[4] = kC2_0 * xy;
  b[5] = kC2_1 * yz;
  b[6] = kC2_2 * ((2.f * zz - xx) - yy);
  b[7] = kC2_3 * xz;
  b[8] = kC2_4 * (xx - yy);
  if (degree < 3) return;
  b[9] = kC3_0 * y * (3.f * xx - yy);
  b[10] = kC3_1 * xy * z;
  b[11] = kC3_2 * y * ((4.f * zz - xx) - yy);
  b[12] = kC3_3 * z * ((2.f * zz - 3.f * xx) - 3.f * yy);
  b[13] = kC3_4 * x * ((4.f * zz - xx) - yy);
  b[14] = kC3_5 * z * (xx - yy);
  b[15] = kC3_6 * x * (xx - 3.f * yy);
}

// d b[k] / d(x, y, z) contracted with w[k]: returns (Σ w·∂b/∂x, Σ w·∂b/∂y, Σ w·∂b/∂z).
SMGS_HD inline void sh_basis_bwd(int degree, float x, float y, float z, const float* w, float* g) {
  g[0] = g[1] = g[2] = 0.f;
  if (degree < 1) return;
  g[0] = -(kC1 * w[3]);
  g[1] = -(kC1 * w[1]);
  g[2] = kC1 * w[2];
  if (degree < 2) return;
  const float xx = x * x, yy = y * y, zz = z * z;
  g[0] = g[0] + kC2_0 * y * w[4] + kC2_3 * z * w[7] + kC2_2 * (-2.f * x) * w[6] + kC2_4 * (2.f * x) * w[8];
  g[1] = g[1] + kC2_0 * x * w[4] + kC2_1 * z * w[5] + kC2_2 * (-2.f * y) * w[6] + kC2_4 * (-2.f * y) * w[8];
  g[2] = g[2] + kC2_1 * y * w[5] + kC2_3 * x * w[7] + kC2_2 * (4.f * z) * w[6];
  if (degree < 3) return;
  // b9 = C·y(3xx − yy); b10 = C·xyz; b11 = C·y(4zz − xx − yy); b12 = C·z(2zz − 3xx − 3yy);
  // b13 = C·x(4zz − xx − yy); b14 = C·z(xx − yy); b15 = C·x(xx − 3yy)
  g[0] = g[0] + kC3_0 * (6.f * x * y) * w[9] + kC3_1 * (y * z) * w[10] + kC3_2 * (-2.f * x * y) * w[11] +
         kC3_3 * (-6.f * x * z) * w[12] + kC3_4 * ((4.f * zz - 3.f * xx) - yy) * w[13] +
         kC3_5 * (2.f * x * z) * w[14] + kC3_6 * (3.f * xx - 3.f * yy) * w[15];
  g[1] = g[1] + kC3_0 * (3.f * xx - 3.f * yy) * w[9] + kC3_1 * (x * z) * w[10] +
         kC3_2 * ((4.f * zz - xx) - 3.f * yy) * w[11] + kC3_3 * (-6.f * y * z) * w[12] +
         kC3_4 * (-2.f * x * y) * w[13] + kC3_5 * (-2.f * y * z) * w[14] + kC3_6 * (-6.f * x * y) * w[15];
  g[2] = g[2] + kC3_1 * (x * y) * w[10] + kC3_2 * (8.f * y * z) * w[11] +
         kC3_3 * ((6.f * zz - 3.f * xx) - 3.f * yy) * w[12] + kC3_4 * (8.f * x * z) * w[13] +
         kC3_5 * (xx - yy) * w[14];
}

// The unit viewing direction of a Gaussian: (m − centre) / max(|m − centre|, 1e-12), as rasterize().
struct ShDir {
  float v[3], n, d[3];
  bool clamped;   // |v| < 1e-12: the norm was clamped (the direction has no gradient through it)
};

SMGS_HD inline ShDir sh_dir(const float* m, const float* center) {
  ShDir o;
  for (int k = 0; k < 3; ++k) o.v[k] = m[k] - center[k];
  const float n = sqrtf((o.v[0] * o.v[0] + o.v[1] * o.v[1]) + o.v[2] * o.v[2]);
  o.clamped = !(n >= 1e-12f);
  o.n = o.clamped ? 1e-12f : n;
  for (int k = 0; k < 3; ++k) o.d[k] = o.v[k] / o.n;
  return o;
}

// colour[c] = Σ_k b[k]·sh[k, c] + 0.5 for the G channels c0 .. c0 + G − 1 (each summed k = 0, 1, ...:
// G independent chains side by side, the same operations per channel whatever G).
template <int G>
SMGS_HD inline void sh_sum(const float* b, int nb, const float* sh0, const float* rest, int nch, int c0, float* v) {
  for (int g = 0; g < G; ++g) v[g] = b[0] * sh0[c0 + g];
  for (int k = 1; k < nb; ++k)
    for (int g = 0; g < G; ++g) v[g] = v[g] + b[k] * rest[(k - 1) * nch + c0 + g];
  for (int g = 0; g < G; ++g) v[g] = v[g] + 0.5f;
}

// colour[c] = Σ_k b[k]·sh[k, c] + 0.5, clamped at 0 where `clamp`. The coefficients come in two parts,
// as the trainer keeps them (3DGS's features_dc / features_rest): sh0 [C] is coefficient 0 and rest
// [K - 1, C] (row-major) the others, K >= the degree's bases; read in place, nothing concatenated.
// NCH: the channel count where known at compile time (the CPU projection's 3), whose chains of 16
// dependent additions then run side by side (one after another they were most of the colour's time);
// 0: `nch` at run time, a channel at a time. The same bits either way.
template <int NCH = 0>
SMGS_HD inline void sh_colour_parts(int degree, const float* sh0, const float* rest, int nch, const float* m,
                                    const float* center, bool clamp, float* colour) {
  const ShDir dir = sh_dir(m, center);
  float b[kMaxShBases];
  sh_basis(degree, dir.d[0], dir.d[1], dir.d[2], b);
  const int nb = (degree + 1) * (degree + 1);
  constexpr int G = NCH > 0 ? NCH : 1;
  for (int c0 = 0; c0 < (NCH > 0 ? NCH : nch); c0 += G) {
    float v[G];
    sh_sum<G>(b, nb, sh0, rest, nch, c0, v);
    for (int g = 0; g < G; ++g) colour[c0 + g] = clamp ? (v[g] < 0.f ? 0.f : v[g]) : v[g];   // clamp_min(0) (NaN stays NaN)
  }
}

// sh_colour_parts of one [K, C] row-major block sh (coefficient 0 first).
template <int NCH = 0>
SMGS_HD inline void sh_colour(int degree, const float* sh, int nch, const float* m, const float* center, bool clamp,
                              float* colour) {
  sh_colour_parts<NCH>(degree, sh, sh + nch, nch, m, center, clamp, colour);
}

// Adjoint of sh_colour_parts: from dL/dcolour [C] to dL/dsh0 [C] and dL/drest [nbases - 1, C] (written,
// zero beyond the degree's bases) and dL/dm [3] (added to g_means). NCH as sh_colour_parts'.
template <int NCH = 0>
SMGS_HD inline void sh_colour_parts_bwd(int degree, int nbases, const float* sh0, const float* rest, int nch,
                                        const float* m, const float* center, bool clamp, const float* g_colour,
                                        float* g_sh0, float* g_rest, float* g_means) {
  const ShDir dir = sh_dir(m, center);
  float b[kMaxShBases];
  sh_basis(degree, dir.d[0], dir.d[1], dir.d[2], b);
  const int nb = (degree + 1) * (degree + 1);
  float w[kMaxShBases] = {};   // Σ_c dL/dcolour[c]·sh[k, c] (c = 0, 1, ... in order): the basis values' gradient
  constexpr int G = NCH > 0 ? NCH : 1;
  for (int c0 = 0; c0 < (NCH > 0 ? NCH : nch); c0 += G) {
    float gc[G];
    for (int g = 0; g < G; ++g) gc[g] = g_colour[c0 + g];
    if (clamp) {   // clamp_min(0) passes at >= (torch's mask)
      float v[G];
      sh_sum<G>(b, nb, sh0, rest, nch, c0, v);
      for (int g = 0; g < G; ++g) gc[g] = v[g] >= 0.f ? gc[g] : 0.f;
    }
    for (int g = 0; g < G; ++g) {
      g_sh0[c0 + g] = b[0] * gc[g];
      w[0] = w[0] + gc[g] * sh0[c0 + g];
    }
    for (int k = 1; k < nb; ++k)
      for (int g = 0; g < G; ++g) {
        g_rest[(k - 1) * nch + c0 + g] = b[k] * gc[g];
        w[k] = w[k] + gc[g] * rest[(k - 1) * nch + c0 + g];
      }
    for (int k = nb; k < nbases; ++k)
      for (int g = 0; g < G; ++g) g_rest[(k - 1) * nch + c0 + g] = 0.f;
  }
  if (degree < 1) return;
  float gd[3];
  sh_basis_bwd(degree, dir.d[0], dir.d[1], dir.d[2], w, gd);
  if (dir.clamped) {   // d = v / 1e-12: a constant divisor
    for (int k = 0; k < 3; ++k) g_means[k] = g_means[k] + gd[k] / dir.n;
    return;
  }
  // d = v / |v|: dL/dv = (g − d·(d·g)) / |v|
  const float dg = (dir.d[0] * gd[0] + dir.d[1] * gd[1]) + dir.d[2] * gd[2];
  for (int k = 0; k < 3; ++k) g_means[k] = g_means[k] + (gd[k] - dir.d[k] * dg) / dir.n;
}

// sh_colour_parts_bwd of one [nbases, C] row-major block (sh and g_sh, coefficient 0 first).
template <int NCH = 0>
SMGS_HD inline void sh_colour_bwd(int degree, int nbases, const float* sh, int nch, const float* m,
                                  const float* center, bool clamp, const float* g_colour, float* g_sh,
                                  float* g_means) {
  sh_colour_parts_bwd<NCH>(degree, nbases, sh, sh + nch, nch, m, center, clamp, g_colour, g_sh, g_sh + nch, g_means);
}

}  // namespace proj
}  // namespace smgs
