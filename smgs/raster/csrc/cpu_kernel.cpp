// Compiled CPU backend of the smgs renderer: tile binning, depth sort, and compositing forward and
// backward with OpenMP across 16x16 tiles and the 16 pixels of a 4x4 block as SIMD lanes.
//
// Semantics are those of smgs/raster/reference.py; tiling only skips pairs that cannot reach
// (their 3σ box misses the block), so it never changes an image. The per-splat math is in
// splat_math.h, shared with future device backends.
//
// Backward: non-softmax modes and the part of each ray after its first k_max composited splats go
// back to front with the 3DGS trick (T_before = T_after / (1 - a)); the softmax head is recomputed
// per block into per-thread scratch (one entry per list position where some lane composites a
// head splat, so at most 2·16·k_max entries: the state before the step and the step's
// intermediates, which the reverse sweep reads instead of recomputing the step a second time)
// and reversed through the hand-written adjoint. Memory is O(pixels + pairs of tiles) plus that
// per-thread scratch, never pixels × k_max.
#include <torch/extension.h>

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>
#include <vector>

#ifdef _OPENMP
#include <omp.h>
#endif

#if defined(__AVX512F__) && defined(__AVX512DQ__)
#include <immintrin.h>
#define SMGS_AVX512 1
#endif

namespace smgs {

#define SMGS_FI inline __attribute__((always_inline))

// ---- 16-lane SIMD types ------------------------------------------------------------------------
constexpr int kLanes = 16;

#ifdef SMGS_AVX512
struct VM {
  __mmask16 m;
};
struct VF {
  __m512 v;
  VF() = default;
  VF(__m512 x) : v(x) {}
  VF(float x) : v(_mm512_set1_ps(x)) {}
};
SMGS_FI VF operator+(VF a, VF b) { return _mm512_add_ps(a.v, b.v); }
SMGS_FI VF operator-(VF a, VF b) { return _mm512_sub_ps(a.v, b.v); }
SMGS_FI VF operator*(VF a, VF b) { return _mm512_mul_ps(a.v, b.v); }
SMGS_FI VF operator/(VF a, VF b) { return _mm512_div_ps(a.v, b.v); }
SMGS_FI VF operator-(VF a) { return _mm512_castsi512_ps(_mm512_xor_si512(_mm512_castps_si512(a.v), _mm512_set1_epi32(int(0x80000000u)))); }
SMGS_FI VM operator<(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LT_OQ)}; }
SMGS_FI VM operator<=(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LE_OQ)}; }
SMGS_FI VM operator>(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GT_OQ)}; }
SMGS_FI VM operator>=(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GE_OQ)}; }
SMGS_FI VM operator==(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_EQ_OQ)}; }
SMGS_FI VM operator!=(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_NEQ_UQ)}; }
SMGS_FI VM mand(VM a, VM b) { return {__mmask16(a.m & b.m)}; }
SMGS_FI VM mor(VM a, VM b) { return {__mmask16(a.m | b.m)}; }
SMGS_FI VM mnot(VM a) { return {__mmask16(~a.m)}; }
SMGS_FI VF sel(VM m, VF a, VF b) { return _mm512_mask_blend_ps(m.m, b.v, a.v); }
// min/max with a constant second argument; a NaN first argument propagates (as torch.clamp)
SMGS_FI VF min_c(VF x, VF c) { return _mm512_min_ps(c.v, x.v); }
SMGS_FI VF max_c(VF x, VF c) { return _mm512_max_ps(c.v, x.v); }
SMGS_FI VF vabs(VF x) { return _mm512_abs_ps(x.v); }
SMGS_FI VF vsqrt(VF x) { return _mm512_sqrt_ps(x.v); }
SMGS_FI VF fmadd(VF a, VF b, VF c) { return _mm512_fmadd_ps(a.v, b.v, c.v); }
// 1/x and √x for the positive normal denominators of the softmax step: rcp14 / rsqrt14 and one
// Newton step (~1 ulp; the divide/sqrt unit is otherwise the bottleneck of a softmax step).
SMGS_FI VF vrcp(VF x) {
  const __m512 r = _mm512_rcp14_ps(x.v);
  return _mm512_fmadd_ps(r, _mm512_fnmadd_ps(x.v, r, _mm512_set1_ps(1.0f)), r);
}
SMGS_FI VF vsqrt_pos(VF x) {
  const __m512 y = _mm512_rsqrt14_ps(x.v);
  const __m512 g = _mm512_mul_ps(x.v, y), h = _mm512_mul_ps(_mm512_set1_ps(0.5f), y);
  const __m512 g1 = _mm512_fmadd_ps(g, _mm512_fnmadd_ps(g, h, _mm512_set1_ps(0.5f)), g);
  return _mm512_maskz_mov_ps(_mm512_cmp_ps_mask(x.v, _mm512_setzero_ps(), _CMP_GT_OQ), g1);
}
// exp: Cephes expf polynomial (~1 ulp) with scalef for 2^n (exact under/overflow to 0 / inf).
SMGS_FI VF vexp(VF x) {
  __m512 v = _mm512_min_ps(_mm512_set1_ps(88.8f), x.v);
  v = _mm512_max_ps(_mm512_set1_ps(-104.0f), v);
  __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(v, _mm512_set1_ps(1.44269504088896341f)),
                                  _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693359375f), v);
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(-2.12194440e-4f), r);
  // p(r) = c0 + c1 r + ... + c5 r^5 by Estrin's scheme (3 dependent FMAs instead of 5)
  const __m512 r2 = _mm512_mul_ps(r, r);
  const __m512 e01 = _mm512_fmadd_ps(_mm512_set1_ps(1.6666665459e-1f), r, _mm512_set1_ps(5.0000001201e-1f));
  const __m512 e23 = _mm512_fmadd_ps(_mm512_set1_ps(8.3334519073e-3f), r, _mm512_set1_ps(4.1665795894e-2f));
  const __m512 e45 = _mm512_fmadd_ps(_mm512_set1_ps(1.9875691500e-4f), r, _mm512_set1_ps(1.3981999507e-3f));
  const __m512 p = _mm512_fmadd_ps(_mm512_fmadd_ps(e45, r2, e23), r2, e01);
  __m512 y = _mm512_fmadd_ps(p, r2, r);
  y = _mm512_add_ps(y, _mm512_set1_ps(1.0f));
  return _mm512_scalef_ps(y, n);
}
// log: Cephes logf polynomial on the mantissa in [√½, √2) (getexp/getmant handle denormals).
SMGS_FI VF vlog(VF x) {
  __m512 e = _mm512_getexp_ps(x.v);
  __m512 m = _mm512_getmant_ps(x.v, _MM_MANT_NORM_1_2, _MM_MANT_SIGN_src);
  __mmask16 big = _mm512_cmp_ps_mask(m, _mm512_set1_ps(1.41421356237f), _CMP_GT_OQ);
  m = _mm512_mask_mul_ps(m, big, m, _mm512_set1_ps(0.5f));
  e = _mm512_mask_add_ps(e, big, e, _mm512_set1_ps(1.0f));
  __m512 t = _mm512_sub_ps(m, _mm512_set1_ps(1.0f));
  __m512 z = _mm512_mul_ps(t, t);
  __m512 y = _mm512_set1_ps(7.0376836292e-2f);
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(-1.1514610310e-1f));
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(1.1676998740e-1f));
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(-1.2420140846e-1f));
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(1.4249322787e-1f));
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(-1.6668057665e-1f));
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(2.0000714765e-1f));
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(-2.4999993993e-1f));
  y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(3.3333331174e-1f));
  y = _mm512_mul_ps(_mm512_mul_ps(y, t), z);
  y = _mm512_fmadd_ps(e, _mm512_set1_ps(-2.12194440e-4f), y);
  y = _mm512_fmadd_ps(z, _mm512_set1_ps(-0.5f), y);
  __m512 r = _mm512_add_ps(t, y);
  r = _mm512_fmadd_ps(e, _mm512_set1_ps(0.693359375f), r);
  __mmask16 neg = _mm512_cmp_ps_mask(x.v, _mm512_setzero_ps(), _CMP_LT_OQ);
  return _mm512_mask_mov_ps(r, neg, _mm512_set1_ps(std::numeric_limits<float>::quiet_NaN()));
}
SMGS_FI bool any(VM m) { return m.m != 0; }
SMGS_FI bool all(VM m) { return m.m == 0xFFFF; }
SMGS_FI int popcount(VM m) { return __builtin_popcount(unsigned(m.m)); }
SMGS_FI VM mask_from_bits(unsigned b) { return {__mmask16(b)}; }
SMGS_FI unsigned bits(VM m) { return m.m; }
SMGS_FI float hsum(VF x) { return _mm512_reduce_add_ps(x.v); }
SMGS_FI float hmax(VF x) { return _mm512_reduce_max_ps(x.v); }
SMGS_FI VF load(const float* p) { return _mm512_loadu_ps(p); }
SMGS_FI void store(float* p, VF x) { _mm512_storeu_ps(p, x.v); }
#else
// Portable fallback: 16 floats with plain loops (vectorised by the compiler where it can).
struct VM {
  unsigned m;
};
struct VF {
  float v[kLanes];
  VF() = default;
  VF(float x) {
    for (int i = 0; i < kLanes; ++i) v[i] = x;
  }
};
#define SMGS_BIN(op)                                   \
  inline VF operator op(VF a, VF b) {                  \
    VF r;                                              \
    for (int i = 0; i < kLanes; ++i) r.v[i] = a.v[i] op b.v[i]; \
    return r;                                          \
  }
SMGS_BIN(+)
SMGS_BIN(-)
SMGS_BIN(*)
SMGS_BIN(/)
#undef SMGS_BIN
#define SMGS_CMP(op)                                                         \
  inline VM operator op(VF a, VF b) {                                        \
    unsigned m = 0;                                                          \
    for (int i = 0; i < kLanes; ++i) m |= unsigned(a.v[i] op b.v[i]) << i;   \
    return {m};                                                              \
  }
SMGS_CMP(<)
SMGS_CMP(<=)
SMGS_CMP(>)
SMGS_CMP(>=)
SMGS_CMP(==)
SMGS_CMP(!=)
#undef SMGS_CMP
#define SMGS_MAP(name, expr)                                      \
  inline VF name(VF a) {                                          \
    VF r;                                                         \
    for (int i = 0; i < kLanes; ++i) { float x = a.v[i]; r.v[i] = (expr); } \
    return r;                                                     \
  }
SMGS_MAP(operator-, -x)
SMGS_MAP(vabs, std::fabs(x))
SMGS_MAP(vsqrt, std::sqrt(x))
SMGS_MAP(vexp, std::exp(x))
SMGS_MAP(vlog, std::log(x))
SMGS_MAP(vrcp, 1.0f / x)
SMGS_MAP(vsqrt_pos, std::sqrt(x))
#undef SMGS_MAP
SMGS_FI VM mand(VM a, VM b) { return {a.m & b.m}; }
SMGS_FI VM mor(VM a, VM b) { return {a.m | b.m}; }
SMGS_FI VM mnot(VM a) { return {~a.m & 0xFFFFu}; }
SMGS_FI VF sel(VM m, VF a, VF b) {
  VF r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = ((m.m >> i) & 1u) ? a.v[i] : b.v[i];
  return r;
}
SMGS_FI VF min_c(VF x, VF c) {
  VF r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = c.v[i] < x.v[i] ? c.v[i] : x.v[i];
  return r;
}
SMGS_FI VF max_c(VF x, VF c) {
  VF r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = c.v[i] > x.v[i] ? c.v[i] : x.v[i];
  return r;
}
SMGS_FI bool any(VM m) { return (m.m & 0xFFFFu) != 0; }
SMGS_FI bool all(VM m) { return (m.m & 0xFFFFu) == 0xFFFFu; }
SMGS_FI int popcount(VM m) { return __builtin_popcount(m.m & 0xFFFFu); }
SMGS_FI VM mask_from_bits(unsigned b) { return {b & 0xFFFFu}; }
SMGS_FI unsigned bits(VM m) { return m.m & 0xFFFFu; }
SMGS_FI float hsum(VF x) {
  float s = 0.f;
  for (int i = 0; i < kLanes; ++i) s += x.v[i];
  return s;
}
SMGS_FI float hmax(VF x) {
  float s = x.v[0];
  for (int i = 1; i < kLanes; ++i) s = std::max(s, x.v[i]);
  return s;
}
SMGS_FI VF load(const float* p) {
  VF r;
  std::memcpy(r.v, p, sizeof(r.v));
  return r;
}
SMGS_FI void store(float* p, VF x) { std::memcpy(p, x.v, sizeof(x.v)); }
#endif

}  // namespace smgs

#include "splat_math.h"

namespace smgs {

// ---- scene preparation: visibility, 3σ boxes, depth order, tile lists ------------------------------

// Packed per-splat row (depth order): parameters, then colours, then regularised values.
enum { P_MX = 0, P_MY, P_CA, P_CB, P_CC, P_O, P_D, P_AL, P_BE, P_GA, P_COL };

struct Scene {
  int W = 0, H = 0, nch = 0, R = 0, S = 0, M = 0;
  int tiles_x = 0, tiles_y = 0;
  int kmax = 0;
  bool solved = true;
  float reg_scale = 1.f;
  const float* pk = nullptr;       // [M, S]
  const int32_t* box = nullptr;    // [M, 4] inclusive pixel ranges x0, x1, y0, y1
  const int32_t* toff = nullptr;   // [tiles + 1]
  const int32_t* tlist = nullptr;  // [L] rows of pk, ascending = depth order
  const float* bg = nullptr;       // [nch] or null
  int nthreads = 1;
};

// Pixel range of a splat whose float32 q can be <= 4.5. The float evaluation of
// q = ½(a·dx² + c·dy²) + b·dx·dy has |error| <= γ6·(½(a·dx² + c·dy²) + |b·dx·dy|) (six roundings,
// dx and dy each rounded once), and that sum is <= κ·q with κ = 1 + 2|b|/λmin for a positive-definite
// conic, so q_float <= 4.5 implies q <= 4.5 / (1 - γ6·κ). The box of that ellipse (Σ = conic⁻¹,
// half extents sqrt(2·Qmax·Σxx), sqrt(2·Qmax·Σyy)) is computed in double, with margin. Where no
// such bound exists (non-finite or non-PD conic, κ too large) the splat covers the whole image,
// which is always correct.
static bool splat_box(float mx, float my, float ca, float cb, float cc, int W, int H, int32_t* out) {
  int x0 = 0, x1 = W - 1, y0 = 0, y1 = H - 1;
  bool finite = std::isfinite(mx) && std::isfinite(my) && std::isfinite(ca) && std::isfinite(cb) &&
                std::isfinite(cc);
  double a = ca, b = cb, c = cc;
  double det = a * c - b * b;
  if (finite && a > 0 && c > 0 && det > 0) {
    double lmax = 0.5 * (a + c) + std::sqrt(0.25 * (a - c) * (a - c) + b * b);
    double lmin = det / lmax;
    double kappa = 1.0 + 2.0 * std::fabs(b) / lmin;
    double g = 16.0 * 5.9604644775390625e-8 * kappa;  // 2·γ6 with u = 2^-24
    if (g < 0.5) {
      double qmax = 4.5 / (1.0 - g);
      double rx = std::sqrt(2.0 * qmax * c / det), ry = std::sqrt(2.0 * qmax * a / det);
      double sx = 1e-6 * (1.0 + std::fabs(mx) + rx), sy = 1e-6 * (1.0 + std::fabs(my) + ry);
      // pixel i has its centre at i + 0.5
      double fx0 = std::ceil(mx - rx - sx - 0.5), fx1 = std::floor(mx + rx + sx - 0.5);
      double fy0 = std::ceil(my - ry - sy - 0.5), fy1 = std::floor(my + ry + sy - 0.5);
      if (fx1 < 0 || fy1 < 0 || fx0 > W - 1 || fy0 > H - 1 || fx0 > fx1 || fy0 > fy1) return false;
      x0 = int(std::max(fx0, 0.0));
      x1 = int(std::min(fx1, double(W - 1)));
      y0 = int(std::max(fy0, 0.0));
      y1 = int(std::min(fy1, double(H - 1)));
    }
  }
  out[0] = x0;
  out[1] = x1;
  out[2] = y0;
  out[3] = y1;
  return true;
}

// Sort key of a depth: float bits mapped so unsigned order = numeric order, -0 = +0, NaN last
// (as torch.sort); the index in the low `ib` bits makes the order stable.
static inline uint64_t depth_key(float d, uint32_t i, int ib) {
  uint32_t u;
  if (std::isnan(d)) {
    u = 0xFFFFFFFFu;
  } else {
    if (d == 0.f) d = 0.f;
    std::memcpy(&u, &d, 4);
    u = (u & 0x80000000u) ? ~u : (u | 0x80000000u);
  }
  return (uint64_t(u) << ib) | i;
}

// LSD radix sort of 64-bit keys (11-bit digits over the 32 + index_bits meaningful bits); O(n).
static void radix_sort(std::vector<uint64_t>& keys, int index_bits) {
  const int total = 32 + index_bits;
  std::vector<uint64_t> tmp(keys.size());
  std::vector<uint32_t> hist(2048);
  for (int shift = 0; shift < total; shift += 11) {
    std::fill(hist.begin(), hist.end(), 0u);
    for (uint64_t k : keys) hist[(k >> shift) & 2047]++;
    uint32_t sum = 0;
    for (auto& h : hist) {
      uint32_t c = h;
      h = sum;
      sum += c;
    }
    for (uint64_t k : keys) tmp[hist[(k >> shift) & 2047]++] = k;
    keys.swap(tmp);
  }
}

struct Prepared {
  torch::Tensor ids, pk, box, toff, tlist, soff, spos;  // soff/spos: each splat's tile-list entries
};

static Prepared prepare(const torch::Tensor& means2d, const torch::Tensor& conics, const torch::Tensor& opac,
                        const torch::Tensor& colors, const torch::Tensor& depths, const torch::Tensor& alpha,
                        const torch::Tensor& beta, const torch::Tensor& gamma, const torch::Tensor& regv,
                        int W, int H, int nthreads) {
  const int64_t N = means2d.size(0);
  const int nch = int(colors.size(1));
  const int R = regv.numel() ? int(regv.size(1)) : 0;
  const int S = P_COL + nch + R;
  const float* m2 = means2d.data_ptr<float>();
  const float* cn = conics.data_ptr<float>();
  const float* op = opac.data_ptr<float>();
  const float* dp = depths.data_ptr<float>();
  std::vector<int32_t> box(size_t(4) * N);
  std::vector<char> vis(N);
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t i = 0; i < N; ++i) {
    // a <= o·1, so o < 1/255 never reaches (NaN never reaches either)
    vis[i] = (op[i] >= kAlphaMin) &&
             splat_box(m2[2 * i], m2[2 * i + 1], cn[3 * i], cn[3 * i + 1], cn[3 * i + 2], W, H, &box[4 * i]);
  }
  int ib = 1;
  while ((int64_t(1) << ib) < N) ++ib;
  std::vector<uint64_t> keys;
  keys.reserve(N);
  for (int64_t i = 0; i < N; ++i)
    if (vis[i]) keys.push_back(depth_key(dp[i], uint32_t(i), ib));
  radix_sort(keys, ib);
  const uint64_t imask = (uint64_t(1) << ib) - 1;
  const int64_t M = int64_t(keys.size());
  auto i32 = torch::TensorOptions().dtype(torch::kInt32);
  Prepared P;
  P.ids = torch::empty({M}, i32);
  P.pk = torch::empty({M, S}, torch::TensorOptions().dtype(torch::kFloat32));
  P.box = torch::empty({M, 4}, i32);
  int32_t* ids = P.ids.data_ptr<int32_t>();
  float* pk = P.pk.data_ptr<float>();
  int32_t* bx = P.box.data_ptr<int32_t>();
  const float* col = colors.data_ptr<float>();
  const float* al = alpha.numel() ? alpha.data_ptr<float>() : nullptr;
  const float* be = beta.numel() ? beta.data_ptr<float>() : nullptr;
  const float* ga = gamma.numel() ? gamma.data_ptr<float>() : nullptr;
  const float* rv = R ? regv.data_ptr<float>() : nullptr;
#pragma omp parallel for num_threads(nthreads) schedule(static)
  for (int64_t j = 0; j < M; ++j) {
    int64_t i = int64_t(keys[j] & imask);
    ids[j] = int32_t(i);
    float* r = pk + j * S;
    r[P_MX] = m2[2 * i];
    r[P_MY] = m2[2 * i + 1];
    r[P_CA] = cn[3 * i];
    r[P_CB] = cn[3 * i + 1];
    r[P_CC] = cn[3 * i + 2];
    r[P_O] = op[i];
    r[P_D] = dp[i];
    r[P_AL] = al ? al[i] : 1.f;
    r[P_BE] = be ? be[i] : 0.f;
    r[P_GA] = ga ? ga[i] : 0.f;
    for (int c = 0; c < nch; ++c) r[P_COL + c] = col[i * nch + c];
    for (int c = 0; c < R; ++c) r[P_COL + nch + c] = rv[i * R + c];
    for (int c = 0; c < 4; ++c) bx[4 * j + c] = box[4 * i + c];
  }
  const int tx = (W + kTileSize - 1) / kTileSize, ty = (H + kTileSize - 1) / kTileSize;
  P.toff = torch::zeros({int64_t(tx) * ty + 1}, i32);
  int32_t* toff = P.toff.data_ptr<int32_t>();
  int64_t L = 0;
  for (int64_t j = 0; j < M; ++j) {
    const int32_t* b = bx + 4 * j;
    for (int y = b[2] / kTileSize; y <= b[3] / kTileSize; ++y)
      for (int x = b[0] / kTileSize; x <= b[1] / kTileSize; ++x) toff[y * tx + x + 1]++;
  }
  for (int t = 0; t < tx * ty; ++t) toff[t + 1] += toff[t];
  L = toff[tx * ty];
  P.tlist = torch::empty({L}, i32);
  P.soff = torch::empty({M + 1}, i32);
  P.spos = torch::empty({L}, i32);
  int32_t* tl = P.tlist.data_ptr<int32_t>();
  int32_t* soff = P.soff.data_ptr<int32_t>();
  int32_t* spos = P.spos.data_ptr<int32_t>();
  std::vector<int32_t> fill(toff, toff + tx * ty);
  int32_t k = 0;
  for (int64_t j = 0; j < M; ++j) {  // in depth order, so every tile list is depth-ordered
    const int32_t* b = bx + 4 * j;
    soff[j] = k;
    for (int y = b[2] / kTileSize; y <= b[3] / kTileSize; ++y)
      for (int x = b[0] / kTileSize; x <= b[1] / kTileSize; ++x) {
        spos[k++] = fill[y * tx + x];
        tl[fill[y * tx + x]++] = int32_t(j);
      }
  }
  soff[M] = k;
  return P;
}

// ---- blocks ------------------------------------------------------------------------------------------
// A tile of 16x16 pixels is processed as 8 blocks of 8x4 pixels; a block is kNV = 2 vectors of 4x4
// pixels, processed in lockstep over the block's splats: two independent dependency chains per
// splat (the softmax step's chain through the running means is ~200 cycles long, so the loop is
// latency-bound and the second vector comes almost free).
constexpr int kNV = 2;
constexpr int kBW = 4 * kNV;                     // block width in pixels
constexpr int kBX = kTileSize / kBW;             // blocks per tile row
constexpr int kNB = kBX * (kTileSize / 4);       // blocks per tile

// One tile's splats: their packed rows copied into a contiguous per-thread buffer (in tile-list,
// i.e. depth, order; one loop of independent loads instead of a dependent miss per first touch),
// and split into the tile's blocks (a splat goes to the blocks its 3σ box touches).
// Block-list items are positions in the tile list.
struct BlockLists {
  std::vector<float> rows;  // [n, Sp]
  std::vector<int32_t> items;
  int n = 0, Sp = 0;
  int count[kNB];
  const int32_t* list(int b) const { return items.data() + size_t(b) * n; }
};

static inline int padded(int S) { return (S + 15) & ~15; }  // rows on 64-byte boundaries

static void build_block_lists(const Scene& sc, int t, BlockLists& bl) {
  const int off = sc.toff[t];
  const int n = sc.toff[t + 1] - off;
  const int S = sc.S, Sp = padded(S);
  bl.n = n;
  bl.Sp = Sp;
  if (bl.items.size() < size_t(kNB) * n) bl.items.resize(size_t(kNB) * n);
  if (bl.rows.size() < size_t(Sp) * n) bl.rows.resize(size_t(Sp) * n);
  std::fill(bl.count, bl.count + kNB, 0);
  const int tx0 = (t % sc.tiles_x) * kTileSize, ty0 = (t / sc.tiles_x) * kTileSize;
  int32_t* it = bl.items.data();
  float* rows = bl.rows.data();
  const int32_t* tl = sc.tlist + off;
  for (int i = 0; i < n; ++i) std::memcpy(rows + size_t(i) * Sp, sc.pk + size_t(tl[i]) * S, sizeof(float) * S);
  for (int i = 0; i < n; ++i) {
    const int32_t* b = sc.box + 4 * size_t(tl[i]);
    const int bx0 = std::max(b[0] - tx0, 0) / kBW, bx1 = std::min(b[1] - tx0, kTileSize - 1) / kBW;
    const int by0 = std::max(b[2] - ty0, 0) >> 2, by1 = std::min(b[3] - ty0, kTileSize - 1) >> 2;
    for (int by = by0; by <= by1; ++by)
      for (int bx = bx0; bx <= bx1; ++bx) {
        const int k = by * kBX + bx;
        it[size_t(k) * n + bl.count[k]++] = i;
      }
  }
}

// Pixel lanes of a 4x4 block at (x0, y0): lane l is pixel (x0 + l%4, y0 + l/4).
struct Lanes {
  VF px, py;
  VM valid;
  int idx[kLanes];  // pixel index or -1
  SMGS_FI void init(int x0, int y0, int W, int H) {
    alignas(64) float fx[kLanes], fy[kLanes];
    unsigned v = 0;
    for (int l = 0; l < kLanes; ++l) {
      const int x = x0 + (l & 3), y = y0 + (l >> 2);
      fx[l] = float(x) + kPixelCenter;
      fy[l] = float(y) + kPixelCenter;
      const bool in = x < W && y < H;
      v |= unsigned(in) << l;
      idx[l] = in ? y * W + x : -1;
    }
    px = load(fx);
    py = load(fy);
    valid = mask_from_bits(v);
  }
  // gather a per-pixel array (stride, offset); lanes outside the image read `fill`
  VF gather(const float* p, int stride, int off, float fill) const {
    alignas(64) float t[kLanes];
    for (int l = 0; l < kLanes; ++l) t[l] = idx[l] >= 0 ? p[size_t(idx[l]) * stride + off] : fill;
    return load(t);
  }
  void scatter(float* p, int stride, int off, VF x) const {
    alignas(64) float t[kLanes];
    store(t, x);
    for (int l = 0; l < kLanes; ++l)
      if (idx[l] >= 0) p[size_t(idx[l]) * stride + off] = t[l];
  }
};

struct FwdOut {
  float *rgb, *alpha, *depth, *Tf, *reg;
  int32_t *last, *cnt;
};

// Channel storage: in registers when the channel count is a compile-time constant, else in
// per-thread heap scratch.
struct Scratch {
  std::vector<VF> v[4];
  VF* get(int slot, int n) {
    if (v[slot].size() < size_t(n)) v[slot].resize(n);
    return v[slot].data();
  }
};
template <int NCT>
struct Chan {
  VF v[kNV * (NCT + 1)];
  VF* p(Scratch&, int, int) { return v; }
};
template <>
struct Chan<0> {
  VF* p(Scratch& s, int slot, int n) { return s.get(slot, n); }
};

// Sums of the lanes of 16 vectors, as one vector (lane k = Σ lanes of v[k]): a transposing tree of
// 45 shuffles and adds instead of 16 horizontal reductions.
#ifdef SMGS_AVX512
SMGS_FI VF reduce16(const VF* v) {
  // the tree leaves lane 4j+e holding input 4e+j: feed it transposed so the result is in order
  constexpr int tr[16] = {0, 4, 8, 12, 1, 5, 9, 13, 2, 6, 10, 14, 3, 7, 11, 15};
  __m512 w[8];
  for (int i = 0; i < 8; ++i) {
    const __m512 a = v[tr[2 * i]].v, b = v[tr[2 * i + 1]].v;
    w[i] = _mm512_add_ps(_mm512_shuffle_f32x4(a, b, 0x44), _mm512_shuffle_f32x4(a, b, 0xEE));
  }
  __m512 x[4];
  for (int i = 0; i < 4; ++i)
    x[i] = _mm512_add_ps(_mm512_shuffle_f32x4(w[2 * i], w[2 * i + 1], 0x88),
                         _mm512_shuffle_f32x4(w[2 * i], w[2 * i + 1], 0xDD));
  const __m512 s0 = _mm512_add_ps(_mm512_unpacklo_ps(x[0], x[1]), _mm512_unpackhi_ps(x[0], x[1]));
  const __m512 s1 = _mm512_add_ps(_mm512_unpacklo_ps(x[2], x[3]), _mm512_unpackhi_ps(x[2], x[3]));
  const __m512d d0 = _mm512_castps_pd(s0), d1 = _mm512_castps_pd(s1);
  return _mm512_add_ps(_mm512_castpd_ps(_mm512_unpacklo_pd(d0, d1)), _mm512_castpd_ps(_mm512_unpackhi_pd(d0, d1)));
}
#else
SMGS_FI VF reduce16(const VF* v) {
  alignas(64) float r[kLanes];
  for (int k = 0; k < kLanes; ++k) r[k] = hsum(v[k]);
  return load(r);
}
#endif

// vanilla_coef for the softmax modes' non-softmax lanes: there wk only matters in a lane's head, and
// a head lane takes the vanilla step only at A = 0, where wk = aT / (0 + aT) = 1 exactly; so no
// division.
SMGS_FI Coef<VF> head_coef(VF T, VF A, VF a) {
  Coef<VF> c;
  c.aT = a * T;
  c.An = A + c.aT;
  c.wk = VF(1.f);
  c.Tn = T * (VF(1.f) - a);
  c.r = VF(1.f);
  return c;
}

// ---- forward ---------------------------------------------------------------------------------------
template <bool GEF, bool SOFT, int NCT>
static int64_t fwd_block(const Scene& sc, const float* rows, int Sp, const int32_t* lst, int n, int x0, int y0,
                         const FwdOut& o, Scratch& scr) {
  constexpr int NV = kNV;
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.R;
  Lanes L[NV];
  for (int v = 0; v < NV; ++v) L[v].init(x0 + 4 * v, y0, sc.W, sc.H);
  Chan<NCT> cs;
  VF* C = cs.p(scr, 0, NV * nc);           // C[v * nc + c]; depth is channel nch
  VF* RG = scr.get(1, NV * (1 + 2 * R));   // reg sums per vector: Σw, Σw·v_r, Σw·v_r²
  for (int c = 0; c < NV * nc; ++c) C[c] = VF(0.f);
  for (int c = 0; c < NV * (1 + 2 * R); ++c) RG[c] = VF(0.f);
  VF T[NV], A[NV], dp[NV], pp[NV], cnt[NV], last[NV], dfront[NV];
  VM done[NV];
  for (int v = 0; v < NV; ++v) {
    T[v] = VF(1.f);
    A[v] = dp[v] = pp[v] = cnt[v] = last[v] = dfront[v] = VF(0.f);
    done[v] = mnot(L[v].valid);
  }
  const VF kmaxf(float(sc.kmax));
  const bool need_head = SOFT || R > 0;
  int64_t pairs = 0;
  for (int i = 0; i < n; ++i) {
    const float* s = rows + size_t(lst[i]) * Sp;
    // The early-outs test the splat alone, not `done`: a branch on `done` would wait for the
    // previous splat's whole q -> exp -> T chain before it resolves.
    Quad<VF> k[NV];
    VM inq[NV];
    unsigned anyq = 0;
    for (int v = 0; v < NV; ++v) {
      pairs += popcount(mnot(done[v]));
      k[v] = splat_quad(L[v].px, L[v].py, s[P_MX], s[P_MY], s[P_CA], s[P_CB], s[P_CC]);
      inq[v] = k[v].q <= VF(kQMax);
      anyq |= bits(inq[v]);
    }
    if (!anyq) continue;
    Absorb<VF> ab[NV];
    VM reach[NV];
    unsigned anyr = 0;
    for (int v = 0; v < NV; ++v) {
      ab[v] = splat_absorb<GEF>(k[v].q, s[P_O], s[P_AL]);
      reach[v] = mand(inq[v], ab[v].a >= VF(kAlphaMin));
      anyr |= bits(reach[v]);
    }
    if (!anyr) continue;
    const float d = s[P_D];
    const float* col = s + P_COL;
    bool alldone = true;
    for (int v = 0; v < NV; ++v) {
      VF* Cv = C + v * nc;
      reach[v] = mand(reach[v], mnot(done[v]));
      const VF a = ab[v].a;
      const VF T0 = T[v] * (VF(1.f) - a);
      // 3DGS: not composited, the pixel is done. Only where the step is vanilla: inside the softmax
      // head a later splat can take the pixel from those before it (constants.T_MIN).
      VM stop = mand(reach[v], T0 < VF(kTStop));
      if (SOFT) stop = mand(stop, mnot(cnt[v] < kmaxf));
      done[v] = mor(done[v], stop);
      const VM rv = mand(reach[v], mnot(stop));
      const VM head = need_head ? mand(rv, cnt[v] < kmaxf) : rv;
      if (SOFT) {
        const VM soft = mand(head, A[v] > VF(0.f));
        const VF p = -k[v].q;
        Coef<VF> cf = head_coef(T[v], A[v], a);
        if (any(soft)) {
          const SoftFwd<VF> f = softmax_fwd(T[v], A[v], dp[v], pp[v], a, p, d, s[P_BE], s[P_GA], sc.solved);
          cf.Tn = sel(soft, f.T0, cf.Tn);
          cf.An = sel(soft, f.U, cf.An);
          cf.r = sel(soft, f.r, cf.r);
          cf.aT = sel(soft, f.aT, cf.aT);
          cf.wk = sel(soft, f.wk, cf.wk);
        }
        for (int c = 0; c < nch; ++c) Cv[c] = sel(rv, Cv[c] * cf.r + VF(col[c]) * cf.aT, Cv[c]);
        Cv[nch] = sel(rv, Cv[nch] * cf.r + VF(d) * cf.aT, Cv[nch]);
        dp[v] = sel(head, dp[v] + (VF(d) - dp[v]) * cf.wk, dp[v]);
        pp[v] = sel(head, pp[v] + (p - pp[v]) * cf.wk, pp[v]);
        T[v] = sel(rv, cf.Tn, T[v]);
        A[v] = sel(rv, cf.An, A[v]);
      } else {
        const VF aT = a * T[v];
        for (int c = 0; c < nch; ++c) Cv[c] = sel(rv, Cv[c] + VF(col[c]) * aT, Cv[c]);
        Cv[nch] = sel(rv, Cv[nch] + VF(d) * aT, Cv[nch]);
        A[v] = sel(rv, A[v] + aT, A[v]);
        T[v] = sel(rv, T0, T[v]);
      }
      if (R) {  // variance regulariser sums over the first k_max composited splats
        VF* RGv = RG + v * (1 + 2 * R);
        const VM first = mand(head, cnt[v] == VF(0.f));
        dfront[v] = sel(first, VF(d), dfront[v]);
        VF w = VF(1.f) / (VF(1.f) + (VF(d) - dfront[v]) / VF(sc.reg_scale));
        w = sel(head, w, VF(0.f));
        RGv[0] = RGv[0] + w;
        for (int r = 0; r < R; ++r) {
          const VF rvv(s[P_COL + nch + r]);
          RGv[1 + r] = RGv[1 + r] + w * rvv;
          RGv[1 + R + r] = RGv[1 + R + r] + w * rvv * rvv;
        }
      }
      cnt[v] = sel(rv, cnt[v] + VF(1.f), cnt[v]);
      last[v] = sel(rv, VF(float(i + 1)), last[v]);
      alldone = alldone && all(done[v]);
    }
    if (alldone) break;
  }
  // outputs
  for (int v = 0; v < NV; ++v) {
    const VF* Cv = C + v * nc;
    for (int c = 0; c < nch; ++c) {
      VF x = Cv[c];
      if (sc.bg) x = x + T[v] * VF(sc.bg[c]);
      L[v].scatter(o.rgb, nch, c, x);
    }
    const VM pos = A[v] > VF(0.f);
    L[v].scatter(o.alpha, 1, 0, A[v]);
    L[v].scatter(o.depth, 1, 0, sel(pos, Cv[nch] / sel(pos, A[v], VF(1.f)), VF(0.f)));
    L[v].scatter(o.Tf, 1, 0, T[v]);
    if (R)
      for (int c = 0; c < 1 + 2 * R; ++c) L[v].scatter(o.reg, 1 + 2 * R, c, RG[v * (1 + 2 * R) + c]);
    alignas(64) float tls[kLanes], tc[kLanes];
    store(tls, last[v]);
    store(tc, cnt[v]);
    for (int l = 0; l < kLanes; ++l)
      if (L[v].idx[l] >= 0) {
        o.last[L[v].idx[l]] = int32_t(tls[l]);
        o.cnt[L[v].idx[l]] = int32_t(tc[l]);
      }
  }
  return pairs;
}

template <bool GEF, bool SOFT, int NCT>
static int64_t forward_impl(const Scene& sc, const FwdOut& o) {
  const int nt = sc.tiles_x * sc.tiles_y;
  int64_t pairs = 0;
#pragma omp parallel num_threads(sc.nthreads) reduction(+ : pairs)
  {
    BlockLists bl;
    Scratch scr;
#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < nt; ++t) {
      build_block_lists(sc, t, bl);
      const int tx0 = (t % sc.tiles_x) * kTileSize, ty0 = (t / sc.tiles_x) * kTileSize;
      for (int b = 0; b < kNB; ++b) {
        const int x0 = tx0 + (b % kBX) * kBW, y0 = ty0 + (b / kBX) * 4;
        if (x0 >= sc.W || y0 >= sc.H) continue;
        pairs += fwd_block<GEF, SOFT, NCT>(sc, bl.rows.data(), bl.Sp, bl.list(b), bl.count[b], x0, y0, o, scr);
      }
    }
  }
  return pairs;
}

// ---- backward --------------------------------------------------------------------------------------
struct BwdIn {
  const float *g_rgb, *g_alpha, *g_depth, *g_reg;  // g_reg may be null
  const float *alpha, *depth, *Tf;
  const int32_t* last;
};

// Per-thread scratch for the recomputed softmax heads of one block: one entry per list position
// where some lane composites one of its first k_max splats (so at most 2·16·k_max entries).
struct HeadScratch {
  std::vector<VF> st;  // per entry and vector: T, A, d_past, p_past, C[nc]
  std::vector<int32_t> pos;
  std::vector<uint32_t> mask;  // per entry and vector
  std::vector<SoftFwd<VF>> sf;  // per entry and vector: the softmax step, reused by phase 2
};

// G: gradient rows (stride Sp, pk layout) of this tile's list entries, summed over its blocks.
template <bool GEF, bool SOFT, int NCT>
static void bwd_block(const Scene& sc, const float* rows, int Sp, const int32_t* lst, int n, int x0, int y0,
                      const BwdIn& in, float* G, Scratch& scr, HeadScratch& hs) {
  constexpr int NV = kNV;
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.R;
  Lanes L[NV];
  for (int v = 0; v < NV; ++v) L[v].init(x0 + 4 * v, y0, sc.W, sc.H);
  Chan<NCT> cs1, cs2;
  VF* gC = cs1.p(scr, 0, NV * nc);   // adjoint of the colour state (depth is channel nch)
  VF* C1 = cs2.p(scr, 1, NV * nc);   // phase 1 colour state
  VF* gR = scr.get(2, NV * 2 * R);   // dL/d reg sums Σw·v_r and Σw·v_r²
  VF gT[NV], gA[NV], T[NV], last[NV];
  int imax = 0;
  for (int v = 0; v < NV; ++v) {
    // dL/d outputs -> dL/d final state
    const VF Aout = L[v].gather(in.alpha, 1, 0, 0.f);
    const VF dout = L[v].gather(in.depth, 1, 0, 0.f);
    const VF g_alpha = L[v].gather(in.g_alpha, 1, 0, 0.f);
    const VF g_depth = L[v].gather(in.g_depth, 1, 0, 0.f);
    gT[v] = VF(0.f);
    for (int c = 0; c < nch; ++c) {
      gC[v * nc + c] = L[v].gather(in.g_rgb, nch, c, 0.f);
      if (sc.bg) gT[v] = gT[v] + gC[v * nc + c] * VF(sc.bg[c]);   // rgb += T·bg
    }
    const VM posA = Aout > VF(0.f);
    const VF Asafe = sel(posA, Aout, VF(1.f));
    gC[v * nc + nch] = sel(posA, g_depth / Asafe, VF(0.f));            // depth = C_d / A
    gA[v] = g_alpha - sel(posA, g_depth * dout / Asafe, VF(0.f));
    T[v] = L[v].gather(in.Tf, 1, 0, 1.f);
    alignas(64) float lastf[kLanes];
    for (int l = 0; l < kLanes; ++l) {
      const int x = L[v].idx[l] >= 0 ? in.last[L[v].idx[l]] : 0;
      lastf[l] = float(x);
      imax = std::max(imax, x);
    }
    last[v] = load(lastf);
  }
  if (imax == 0) return;
  const VF kmaxf(float(sc.kmax));
  const size_t esz = size_t(4 + nc);  // vectors per entry and block vector

  // Phase 1: recompute each lane's head (its first k_max composited splats) front to back, saving
  // the state before every head step (softmax modes) and taking the regulariser's gradients.
  int ne = 0;
  if ((SOFT || R) && sc.kmax > 0) {
    VF T1[NV], A1[NV], dp1[NV], pp1[NV], cnt1[NV], dfront[NV];
    for (int v = 0; v < NV; ++v) {
      T1[v] = VF(1.f);
      A1[v] = dp1[v] = pp1[v] = cnt1[v] = dfront[v] = VF(0.f);
      for (int c = 0; c < nc; ++c) C1[v * nc + c] = VF(0.f);
      for (int r = 0; r < 2 * R; ++r) gR[v * 2 * R + r] = L[v].gather(in.g_reg, 1 + 2 * R, 1 + r, 0.f);
    }
    for (int i = 0; i < imax; ++i) {
      VM hv[NV];
      unsigned anyh = 0;
      for (int v = 0; v < NV; ++v) {
        hv[v] = mand(VF(float(i)) < last[v], cnt1[v] < kmaxf);
        anyh |= bits(hv[v]);
      }
      if (!anyh) break;
      const int j = lst[i];
      const float* s = rows + size_t(j) * Sp;
      Quad<VF> k[NV];
      VM reach[NV];
      unsigned anyq = 0, anyr = 0;
      for (int v = 0; v < NV; ++v) {
        k[v] = splat_quad(L[v].px, L[v].py, s[P_MX], s[P_MY], s[P_CA], s[P_CB], s[P_CC]);
        reach[v] = mand(hv[v], k[v].q <= VF(kQMax));
        anyq |= bits(reach[v]);
      }
      if (!anyq) continue;
      Absorb<VF> ab[NV];
      for (int v = 0; v < NV; ++v) {
        ab[v] = splat_absorb<GEF>(k[v].q, s[P_O], s[P_AL]);
        reach[v] = mand(reach[v], ab[v].a >= VF(kAlphaMin));  // before `last`: composited, never stopped
        anyr |= bits(reach[v]);
      }
      if (!anyr) continue;
      const float d = s[P_D];
      const float* col = s + P_COL;
      if (SOFT) {
        if (hs.pos.size() <= size_t(ne)) {
          hs.pos.resize(ne + 64);
          hs.mask.resize(NV * (ne + 64));
          hs.st.resize((ne + 64) * NV * esz);
          if (SOFT) hs.sf.resize((ne + 64) * NV);
        }
        hs.pos[ne] = i;
        for (int v = 0; v < NV; ++v) {
          VF* e = hs.st.data() + (size_t(ne) * NV + v) * esz;
          e[0] = T1[v];
          e[1] = A1[v];
          e[2] = dp1[v];
          e[3] = pp1[v];
          for (int c = 0; c < nc; ++c) e[4 + c] = C1[v * nc + c];
          hs.mask[ne * NV + v] = bits(reach[v]);
        }
        ++ne;
        for (int v = 0; v < NV; ++v) {
          const VM rv = reach[v];
          if (!any(rv)) continue;
          const VF a = ab[v].a;
          const VM soft = mand(rv, A1[v] > VF(0.f));
          const VF p = -k[v].q;
          Coef<VF> cf = head_coef(T1[v], A1[v], a);
          if (any(soft)) {
            SoftFwd<VF>& f = hs.sf[size_t(ne - 1) * NV + v];
            f = softmax_fwd(T1[v], A1[v], dp1[v], pp1[v], a, p, d, s[P_BE], s[P_GA], sc.solved);
            cf.Tn = sel(soft, f.T0, cf.Tn);
            cf.An = sel(soft, f.U, cf.An);
            cf.r = sel(soft, f.r, cf.r);
            cf.aT = sel(soft, f.aT, cf.aT);
            cf.wk = sel(soft, f.wk, cf.wk);
          }
          VF* Cv = C1 + v * nc;
          for (int c = 0; c < nch; ++c) Cv[c] = sel(rv, Cv[c] * cf.r + VF(col[c]) * cf.aT, Cv[c]);
          Cv[nch] = sel(rv, Cv[nch] * cf.r + VF(d) * cf.aT, Cv[nch]);
          dp1[v] = sel(rv, dp1[v] + (VF(d) - dp1[v]) * cf.wk, dp1[v]);
          pp1[v] = sel(rv, pp1[v] + (p - pp1[v]) * cf.wk, pp1[v]);
          T1[v] = sel(rv, cf.Tn, T1[v]);
          A1[v] = sel(rv, cf.An, A1[v]);
        }
      }
      if (R) {
        float* g = G + size_t(j) * Sp + P_COL + nch;
        for (int v = 0; v < NV; ++v) {
          const VM first = mand(reach[v], cnt1[v] == VF(0.f));
          dfront[v] = sel(first, VF(d), dfront[v]);
          const VF w = VF(1.f) / (VF(1.f) + (VF(d) - dfront[v]) / VF(sc.reg_scale));
          for (int r = 0; r < R; ++r) {
            const VF rvv(s[P_COL + nch + r]);
            // reg = Σ w·[1, v, v·v]: d/dv = w·g1 + 2·w·v·g2 (the weights carry no gradient)
            g[r] += hsum(sel(reach[v], w * gR[v * 2 * R + r] + VF(2.f) * w * rvv * gR[v * 2 * R + R + r], VF(0.f)));
          }
        }
      }
      for (int v = 0; v < NV; ++v) cnt1[v] = sel(reach[v], cnt1[v] + VF(1.f), cnt1[v]);
    }
  }

  // Phase 2: back to front over every composited splat.
  VF gdp[NV], gpp[NV];  // adjoints of the running means, non-zero only inside a lane's head
  for (int v = 0; v < NV; ++v) gdp[v] = gpp[v] = VF(0.f);
  int e = ne - 1;
  const VF zero(0.f);
  for (int i = imax - 1; i >= 0; --i) {
    const int j = lst[i];
    const float* s = rows + size_t(j) * Sp;
    Quad<VF> k[NV];
    VM reach[NV];
    unsigned anyq = 0, anyr = 0;
    for (int v = 0; v < NV; ++v) {
      k[v] = splat_quad(L[v].px, L[v].py, s[P_MX], s[P_MY], s[P_CA], s[P_CB], s[P_CC]);
      reach[v] = mand(VF(float(i)) < last[v], k[v].q <= VF(kQMax));
      anyq |= bits(reach[v]);
    }
    if (!anyq) continue;
    Absorb<VF> ab[NV];
    for (int v = 0; v < NV; ++v) {
      ab[v] = splat_absorb<GEF>(k[v].q, s[P_O], s[P_AL]);
      reach[v] = mand(reach[v], ab[v].a >= VF(kAlphaMin));
      anyr |= bits(reach[v]);
    }
    if (!anyr) continue;
    const float d = s[P_D];
    const float* col = s + P_COL;
    const VF* ent = nullptr;
    unsigned hmb[NV] = {};
    if (SOFT && e >= 0 && hs.pos[e] == i) {
      ent = hs.st.data() + size_t(e) * NV * esz;
      for (int v = 0; v < NV; ++v) hmb[v] = hs.mask[e * NV + v];
      --e;
    }
    // per-lane gradients of this splat's parameters, in the pk layout (summed over vectors)
    VF gv[16];
    for (int c = 0; c < 16; ++c) gv[c] = zero;
    for (int v = 0; v < NV; ++v) {
      const VM rv = reach[v];
      if (!any(rv)) continue;
      VF* gCv = gC + v * nc;
      const VF a = ab[v].a;
      const VF p = -k[v].q;
      // state before the step: the 3DGS inverse for tail lanes, the saved state for head lanes
      VF Tpre = T[v] / (VF(1.f) - a);
      VF Apre(0.f), dpre(0.f), ppre(0.f);
      const VM hm = mask_from_bits(hmb[v]);
      const VF* ev = ent ? ent + v * esz : nullptr;
      if (SOFT && hmb[v]) {
        Tpre = sel(hm, ev[0], Tpre);
        Apre = sel(hm, ev[1], Apre);
        dpre = sel(hm, ev[2], dpre);
        ppre = sel(hm, ev[3], ppre);
      }
      VF g_a, g_p(0.f), g_d(0.f), g_be(0.f), g_ga(0.f);
      VF gTn, gAn;
      if (SOFT) {
        const VM soft = mand(hm, Apre > VF(0.f));
        Coef<VF> cf = head_coef(Tpre, Apre, a);
        const bool anysoft = any(soft);
        // phase 1's step of this entry and vector (same inputs): not recomputed
        const SoftFwd<VF>* fp = anysoft ? hs.sf.data() + size_t(e + 1) * NV + v : nullptr;
        if (anysoft) {
          cf.r = sel(soft, fp->r, cf.r);
          cf.aT = sel(soft, fp->aT, cf.aT);
          cf.wk = sel(soft, fp->wk, cf.wk);
        }
        // adjoint of C' = C·r + c·aT (depth is channel nch)
        VF g_r(0.f), g_aT(0.f);
        for (int c = 0; c < nch; ++c) g_aT = g_aT + gCv[c] * VF(col[c]);
        g_aT = g_aT + gCv[nch] * VF(d);
        for (int c = 0; c < nch; ++c) {
          const VF x = sel(rv, gCv[c] * cf.aT, zero);
          if (P_COL + c < 16) gv[P_COL + c] = gv[P_COL + c] + x;
          else G[size_t(j) * Sp + P_COL + c] += hsum(x);
        }
        g_d = gCv[nch] * cf.aT;
        if (anysoft) {
          for (int c = 0; c < nc; ++c) {
            g_r = g_r + gCv[c] * ev[4 + c];
            gCv[c] = sel(soft, gCv[c] * cf.r, gCv[c]);
          }
        }
        // adjoint of the running means d' = d + (d_k - d)·wk, p' likewise (head lanes only)
        const VF g_wk = sel(hm, gdp[v] * (VF(d) - dpre) + gpp[v] * (p - ppre), zero);
        g_d = g_d + sel(hm, gdp[v] * cf.wk, zero);
        g_p = sel(hm, gpp[v] * cf.wk, zero);
        gdp[v] = sel(hm, gdp[v] - gdp[v] * cf.wk, gdp[v]);
        gpp[v] = sel(hm, gpp[v] - gpp[v] * cf.wk, gpp[v]);
        VF gTv, gAv, gav;
        vanilla_coef_bwd(Tpre, Apre, a, gT[v], gA[v], g_aT, g_wk, gTv, gAv, gav);
        gTn = gTv;
        gAn = gAv;
        g_a = gav;
        if (anysoft) {
          const SoftGrad<VF> sg = softmax_bwd(*fp, Tpre, Apre, dpre, ppre, a, p, s[P_BE], s[P_GA], sc.solved,
                                              gT[v], gA[v], g_r, g_aT, g_wk);
          gTn = sel(soft, sg.T, gTn);
          gAn = sel(soft, sg.A, gAn);
          g_a = sel(soft, sg.a, g_a);
          g_p = g_p + sel(soft, sg.p, zero);
          g_d = g_d + sel(soft, sg.d, zero);
          gdp[v] = gdp[v] + sel(soft, sg.dp, zero);
          gpp[v] = gpp[v] + sel(soft, sg.pp, zero);
          g_be = sel(soft, sg.beta, zero);
          g_ga = sel(soft, sg.gamma, zero);
        }
      } else {
        // 3DGS: C' = C + c·aT, A' = A + aT, T' = T(1-a)
        const VF aT = a * Tpre;
        VF g_aT = gA[v];
        for (int c = 0; c < nch; ++c) g_aT = g_aT + gCv[c] * VF(col[c]);
        g_aT = g_aT + gCv[nch] * VF(d);
        for (int c = 0; c < nch; ++c) {
          const VF x = sel(rv, gCv[c] * aT, zero);
          if (P_COL + c < 16) gv[P_COL + c] = gv[P_COL + c] + x;
          else G[size_t(j) * Sp + P_COL + c] += hsum(x);
        }
        g_d = gCv[nch] * aT;
        g_a = g_aT * Tpre - gT[v] * Tpre;
        gTn = g_aT * a + gT[v] * (VF(1.f) - a);
        gAn = gA[v];
      }
      gT[v] = sel(rv, gTn, gT[v]);
      gA[v] = sel(rv, gAn, gA[v]);
      T[v] = sel(rv, Tpre, T[v]);
      const KernGrad<VF> kg =
          splat_kernel_bwd<GEF>(k[v], ab[v], s[P_CA], s[P_CB], s[P_CC], s[P_O], s[P_AL], g_a, g_p);
      gv[P_MX] = gv[P_MX] + sel(rv, kg.mx, zero);
      gv[P_MY] = gv[P_MY] + sel(rv, kg.my, zero);
      gv[P_CA] = gv[P_CA] + sel(rv, kg.ca, zero);
      gv[P_CB] = gv[P_CB] + sel(rv, kg.cb, zero);
      gv[P_CC] = gv[P_CC] + sel(rv, kg.cc, zero);
      gv[P_O] = gv[P_O] + sel(rv, kg.o, zero);
      gv[P_D] = gv[P_D] + sel(rv, g_d, zero);
      if (GEF) gv[P_AL] = gv[P_AL] + sel(rv, kg.alpha, zero);
      if (SOFT) {
        gv[P_BE] = gv[P_BE] + sel(rv, g_be, zero);
        gv[P_GA] = gv[P_GA] + sel(rv, g_ga, zero);
      }
    }
    float* g = G + size_t(j) * Sp;
    store(g, load(g) + reduce16(gv));
  }
}

template <bool GEF, bool SOFT, int NCT>
static void backward_impl(const Scene& sc, const BwdIn& in, float* E) {
  const int nt = sc.tiles_x * sc.tiles_y;
  const int Sp = padded(sc.S);
#pragma omp parallel num_threads(sc.nthreads)
  {
    BlockLists bl;
    Scratch scr;
    HeadScratch hs;
#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < nt; ++t) {
      const int off = sc.toff[t];
      float* G = E + size_t(off) * Sp;
      std::fill(G, G + size_t(sc.toff[t + 1] - off) * Sp, 0.f);
      build_block_lists(sc, t, bl);
      const int tx0 = (t % sc.tiles_x) * kTileSize, ty0 = (t / sc.tiles_x) * kTileSize;
      for (int b = 0; b < kNB; ++b) {
        const int x0 = tx0 + (b % kBX) * kBW, y0 = ty0 + (b / kBX) * 4;
        if (x0 >= sc.W || y0 >= sc.H) continue;
        bwd_block<GEF, SOFT, NCT>(sc, bl.rows.data(), bl.Sp, bl.list(b), bl.count[b], x0, y0, in, G, scr, hs);
      }
    }
  }
}

// ---- dispatch -------------------------------------------------------------------------------------
template <template <bool, bool, int> class F, class... Args>
static auto dispatch(bool gef, bool soft, int nch, Args&&... args) {
  if (nch == 3) {
    if (gef) return soft ? F<true, true, 3>::run(args...) : F<true, false, 3>::run(args...);
    return soft ? F<false, true, 3>::run(args...) : F<false, false, 3>::run(args...);
  }
  if (gef) return soft ? F<true, true, 0>::run(args...) : F<true, false, 0>::run(args...);
  return soft ? F<false, true, 0>::run(args...) : F<false, false, 0>::run(args...);
}

template <bool GEF, bool SOFT, int NCT>
struct FwdF {
  static int64_t run(const Scene& sc, const FwdOut& o) { return forward_impl<GEF, SOFT, NCT>(sc, o); }
};
template <bool GEF, bool SOFT, int NCT>
struct BwdF {
  static int run(const Scene& sc, const BwdIn& in, float* G) {
    backward_impl<GEF, SOFT, NCT>(sc, in, G);
    return 0;
  }
};

static void check_f32(const torch::Tensor& t, const char* name) {
  TORCH_CHECK(t.device().is_cpu() && t.scalar_type() == torch::kFloat32 && t.is_contiguous(), name,
              " must be a contiguous float32 CPU tensor");
}

static Scene make_scene(const torch::Tensor& pk, const torch::Tensor& box, const torch::Tensor& toff,
                        const torch::Tensor& tlist, const torch::Tensor& bg, int W, int H, int nch, int R,
                        int64_t kmax, bool solved, double reg_scale, int nthreads) {
  Scene sc;
  sc.W = W;
  sc.H = H;
  sc.nch = nch;
  sc.R = R;
  sc.S = P_COL + nch + R;
  sc.M = int(pk.size(0));
  sc.tiles_x = (W + kTileSize - 1) / kTileSize;
  sc.tiles_y = (H + kTileSize - 1) / kTileSize;
  sc.kmax = int(std::min<int64_t>(kmax, int64_t(1) << 24));  // float lane counters are exact to 2^24
  sc.solved = solved;
  sc.reg_scale = float(reg_scale);
  sc.pk = pk.data_ptr<float>();
  sc.box = box.data_ptr<int32_t>();
  sc.toff = toff.data_ptr<int32_t>();
  sc.tlist = tlist.data_ptr<int32_t>();
  sc.bg = bg.numel() ? bg.data_ptr<float>() : nullptr;
  sc.nthreads = std::max(1, nthreads);
  return sc;
}

// Returns [rgb, alpha, depth, reg, n_contrib, T_final, last, pairs, ids, pk, box, tile_off, tile_list,
// splat_off, splat_pos].
std::vector<torch::Tensor> forward(torch::Tensor means2d, torch::Tensor conics, torch::Tensor opac,
                                   torch::Tensor colors, torch::Tensor depths, torch::Tensor alpha,
                                   torch::Tensor beta, torch::Tensor gamma, torch::Tensor bg, torch::Tensor regv,
                                   int64_t W, int64_t H, bool gef, bool soft, int64_t kmax, bool solved,
                                   double reg_scale, int64_t nthreads) {
  check_f32(means2d, "means2d");
  check_f32(conics, "conics");
  check_f32(opac, "opacities");
  check_f32(colors, "colors");
  check_f32(depths, "depths");
  const int64_t N = means2d.size(0);
  TORCH_CHECK(N < (int64_t(1) << 24), "the cpu backend handles fewer than 2^24 splats");
  if (gef) check_f32(alpha, "alpha");
  if (soft) {
    check_f32(beta, "beta");
    check_f32(gamma, "gamma");
  }
  if (bg.numel()) check_f32(bg, "background");
  if (regv.numel()) check_f32(regv, "reg_values");
  const int nch = int(colors.size(1));
  const int R = regv.numel() ? int(regv.size(1)) : 0;
  Prepared P = prepare(means2d, conics, opac, colors, depths, alpha, beta, gamma, regv, int(W), int(H), int(nthreads));
  Scene sc = make_scene(P.pk, P.box, P.toff, P.tlist, bg, int(W), int(H), nch, R, kmax, solved, reg_scale,
                        int(nthreads));
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  auto i32 = torch::TensorOptions().dtype(torch::kInt32);
  torch::Tensor rgb = torch::empty({H, W, nch}, f32), a = torch::empty({H, W}, f32), dep = torch::empty({H, W}, f32),
                Tf = torch::empty({H, W}, f32), reg = torch::empty({H, W, R ? 1 + 2 * R : 0}, f32),
                last = torch::empty({H, W}, i32), cnt = torch::empty({H, W}, i32);
  FwdOut o{rgb.data_ptr<float>(), a.data_ptr<float>(), dep.data_ptr<float>(), Tf.data_ptr<float>(),
           R ? reg.data_ptr<float>() : nullptr, last.data_ptr<int32_t>(), cnt.data_ptr<int32_t>()};
  int64_t pairs = dispatch<FwdF>(gef, soft, nch, sc, o);
  torch::Tensor tp = torch::full({1}, pairs, torch::TensorOptions().dtype(torch::kInt64));
  return {rgb, a, dep, reg, cnt, Tf, last, tp, P.ids, P.pk, P.box, P.toff, P.tlist, P.soff, P.spos};
}

// Returns dL/d[means2d, conics, opacities, colors, depths, alpha, beta, gamma, reg_values] over the N
// input splats (zeros for splats that reach no pixel).
std::vector<torch::Tensor> backward(torch::Tensor g_rgb, torch::Tensor g_alpha, torch::Tensor g_depth,
                                    torch::Tensor g_reg, torch::Tensor alpha_out, torch::Tensor depth_out,
                                    torch::Tensor Tf, torch::Tensor last, torch::Tensor ids, torch::Tensor pk,
                                    torch::Tensor box, torch::Tensor toff, torch::Tensor tlist, torch::Tensor soff,
                                    torch::Tensor spos, torch::Tensor bg,
                                    int64_t N, int64_t nch, int64_t R, int64_t W, int64_t H, bool gef, bool soft,
                                    int64_t kmax, bool solved, double reg_scale, int64_t nthreads) {
  check_f32(g_rgb, "grad rgb");
  check_f32(g_alpha, "grad alpha");
  check_f32(g_depth, "grad depth");
  if (R) check_f32(g_reg, "grad reg");
  Scene sc = make_scene(pk, box, toff, tlist, bg, int(W), int(H), int(nch), int(R), kmax, solved, reg_scale,
                        int(nthreads));
  const int S = sc.S;
  // one gradient row per tile-list entry (each tile fills its own rows), then per splat the sum
  // over its tiles in a fixed order: gradients do not depend on the number of threads
  const int Sp = padded(S);
  torch::Tensor E = torch::empty({tlist.numel(), Sp}, torch::TensorOptions().dtype(torch::kFloat32));
  BwdIn in{g_rgb.data_ptr<float>(), g_alpha.data_ptr<float>(), g_depth.data_ptr<float>(),
           R ? g_reg.data_ptr<float>() : nullptr, alpha_out.data_ptr<float>(), depth_out.data_ptr<float>(),
           Tf.data_ptr<float>(), last.data_ptr<int32_t>()};
  dispatch<BwdF>(gef, soft, int(nch), sc, in, E.data_ptr<float>());
  auto f32 = torch::TensorOptions().dtype(torch::kFloat32);
  torch::Tensor gm = torch::zeros({N, 2}, f32), gc = torch::zeros({N, 3}, f32), go = torch::zeros({N}, f32),
                gcol = torch::zeros({N, nch}, f32), gd = torch::zeros({N}, f32), gal = torch::zeros({N}, f32),
                gbe = torch::zeros({N}, f32), gga = torch::zeros({N}, f32), grv = torch::zeros({N, R}, f32);
  const float* Ep = E.data_ptr<float>();
  const int32_t* id = ids.data_ptr<int32_t>();
  const int32_t* so = soff.data_ptr<int32_t>();
  const int32_t* sp = spos.data_ptr<int32_t>();
  float *pm = gm.data_ptr<float>(), *pc = gc.data_ptr<float>(), *po = go.data_ptr<float>(),
        *pcol = gcol.data_ptr<float>(), *pd = gd.data_ptr<float>(), *pal = gal.data_ptr<float>(),
        *pbe = gbe.data_ptr<float>(), *pga = gga.data_ptr<float>(), *prv = R ? grv.data_ptr<float>() : nullptr;
  const int M = sc.M;
#pragma omp parallel num_threads(sc.nthreads)
  {
    std::vector<float> r(S);
#pragma omp for schedule(static)
    for (int j = 0; j < M; ++j) {
      std::fill(r.begin(), r.end(), 0.f);
      for (int k = so[j]; k < so[j + 1]; ++k) {
        const float* e = Ep + size_t(sp[k]) * Sp;
        for (int c = 0; c < S; ++c) r[c] += e[c];
      }
      const int64_t i = id[j];  // rows are in depth order; back to input order
      pm[2 * i] = r[P_MX];
      pm[2 * i + 1] = r[P_MY];
      pc[3 * i] = r[P_CA];
      pc[3 * i + 1] = r[P_CB];
      pc[3 * i + 2] = r[P_CC];
      po[i] = r[P_O];
      pd[i] = r[P_D];
      pal[i] = r[P_AL];
      pbe[i] = r[P_BE];
      pga[i] = r[P_GA];
      for (int c = 0; c < nch; ++c) pcol[i * nch + c] = r[P_COL + c];
      for (int c = 0; c < R; ++c) prv[i * R + c] = r[P_COL + nch + c];
    }
  }
  return {gm, gc, go, gcol, gd, gal, gbe, gga, grv};
}

// Constants as compiled, for the test that they mirror smgs/raster/constants.py.
std::vector<double> constants() {
  return {kAlphaMax, kAlphaMin, kTMin, kQMax, kExpArgMax, kDecayArgMax, kPixelCenter, double(kTileSize), kTStop, kTiny};
}

bool simd_avx512() {
#ifdef SMGS_AVX512
  return true;
#else
  return false;
#endif
}

}  // namespace smgs

PYBIND11_MODULE(TORCH_EXTENSION_NAME, m) {
  m.def("forward", &smgs::forward, "smgs CPU splat compositing, forward");
  m.def("backward", &smgs::backward, "smgs CPU splat compositing, backward");
  m.def("constants", &smgs::constants, "numeric conventions as compiled");
  m.def("simd_avx512", &smgs::simd_avx512, "whether the AVX-512 lanes are compiled in");
}
