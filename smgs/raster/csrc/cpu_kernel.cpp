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
// head splat, so at most 16·k_max entries) and reversed through the hand-written adjoint.
// Memory is O(pixels + pairs of tiles), never pixels × k_max.
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
inline VF operator+(VF a, VF b) { return _mm512_add_ps(a.v, b.v); }
inline VF operator-(VF a, VF b) { return _mm512_sub_ps(a.v, b.v); }
inline VF operator*(VF a, VF b) { return _mm512_mul_ps(a.v, b.v); }
inline VF operator/(VF a, VF b) { return _mm512_div_ps(a.v, b.v); }
inline VF operator-(VF a) { return _mm512_castsi512_ps(_mm512_xor_si512(_mm512_castps_si512(a.v), _mm512_set1_epi32(int(0x80000000u)))); }
inline VM operator<(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LT_OQ)}; }
inline VM operator<=(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_LE_OQ)}; }
inline VM operator>(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GT_OQ)}; }
inline VM operator>=(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_GE_OQ)}; }
inline VM operator==(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_EQ_OQ)}; }
inline VM operator!=(VF a, VF b) { return {_mm512_cmp_ps_mask(a.v, b.v, _CMP_NEQ_UQ)}; }
inline VM mand(VM a, VM b) { return {__mmask16(a.m & b.m)}; }
inline VM mor(VM a, VM b) { return {__mmask16(a.m | b.m)}; }
inline VM mnot(VM a) { return {__mmask16(~a.m)}; }
inline VF sel(VM m, VF a, VF b) { return _mm512_mask_blend_ps(m.m, b.v, a.v); }
// min/max with a constant second argument; a NaN first argument propagates (as torch.clamp)
inline VF min_c(VF x, VF c) { return _mm512_min_ps(c.v, x.v); }
inline VF max_c(VF x, VF c) { return _mm512_max_ps(c.v, x.v); }
inline VF vabs(VF x) { return _mm512_abs_ps(x.v); }
inline VF vsqrt(VF x) { return _mm512_sqrt_ps(x.v); }
inline VF fmadd(VF a, VF b, VF c) { return _mm512_fmadd_ps(a.v, b.v, c.v); }
// exp: Cephes expf polynomial (~1 ulp) with scalef for 2^n (exact under/overflow to 0 / inf).
inline VF vexp(VF x) {
  __m512 v = _mm512_min_ps(_mm512_set1_ps(88.8f), x.v);
  v = _mm512_max_ps(_mm512_set1_ps(-104.0f), v);
  __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(v, _mm512_set1_ps(1.44269504088896341f)),
                                  _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(0.693359375f), v);
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(-2.12194440e-4f), r);
  __m512 p = _mm512_set1_ps(1.9875691500e-4f);
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.3981999507e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(8.3334519073e-3f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(4.1665795894e-2f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(1.6666665459e-1f));
  p = _mm512_fmadd_ps(p, r, _mm512_set1_ps(5.0000001201e-1f));
  __m512 y = _mm512_fmadd_ps(p, _mm512_mul_ps(r, r), r);
  y = _mm512_add_ps(y, _mm512_set1_ps(1.0f));
  return _mm512_scalef_ps(y, n);
}
// log: Cephes logf polynomial on the mantissa in [√½, √2) (getexp/getmant handle denormals).
inline VF vlog(VF x) {
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
inline bool any(VM m) { return m.m != 0; }
inline bool all(VM m) { return m.m == 0xFFFF; }
inline int popcount(VM m) { return __builtin_popcount(unsigned(m.m)); }
inline VM mask_from_bits(unsigned b) { return {__mmask16(b)}; }
inline unsigned bits(VM m) { return m.m; }
inline float hsum(VF x) { return _mm512_reduce_add_ps(x.v); }
inline float hmax(VF x) { return _mm512_reduce_max_ps(x.v); }
inline VF load(const float* p) { return _mm512_loadu_ps(p); }
inline void store(float* p, VF x) { _mm512_storeu_ps(p, x.v); }
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
#undef SMGS_MAP
inline VM mand(VM a, VM b) { return {a.m & b.m}; }
inline VM mor(VM a, VM b) { return {a.m | b.m}; }
inline VM mnot(VM a) { return {~a.m & 0xFFFFu}; }
inline VF sel(VM m, VF a, VF b) {
  VF r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = ((m.m >> i) & 1u) ? a.v[i] : b.v[i];
  return r;
}
inline VF min_c(VF x, VF c) {
  VF r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = c.v[i] < x.v[i] ? c.v[i] : x.v[i];
  return r;
}
inline VF max_c(VF x, VF c) {
  VF r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = c.v[i] > x.v[i] ? c.v[i] : x.v[i];
  return r;
}
inline bool any(VM m) { return (m.m & 0xFFFFu) != 0; }
inline bool all(VM m) { return (m.m & 0xFFFFu) == 0xFFFFu; }
inline int popcount(VM m) { return __builtin_popcount(m.m & 0xFFFFu); }
inline VM mask_from_bits(unsigned b) { return {b & 0xFFFFu}; }
inline unsigned bits(VM m) { return m.m & 0xFFFFu; }
inline float hsum(VF x) {
  float s = 0.f;
  for (int i = 0; i < kLanes; ++i) s += x.v[i];
  return s;
}
inline float hmax(VF x) {
  float s = x.v[0];
  for (int i = 1; i < kLanes; ++i) s = std::max(s, x.v[i]);
  return s;
}
inline VF load(const float* p) {
  VF r;
  std::memcpy(r.v, p, sizeof(r.v));
  return r;
}
inline void store(float* p, VF x) { std::memcpy(p, x.v, sizeof(x.v)); }
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

// Splats of one tile split into its 16 blocks of 4x4 pixels (a splat goes to the blocks its box
// touches), each list still in depth order. Items are positions in the tile list.
struct BlockLists {
  std::vector<int32_t> items;
  int n = 0;
  int count[16];
  const int32_t* list(int b) const { return items.data() + size_t(b) * n; }
};

static void build_block_lists(const Scene& sc, int t, BlockLists& bl) {
  const int off = sc.toff[t];
  const int n = sc.toff[t + 1] - off;
  bl.n = n;
  if (bl.items.size() < size_t(16) * n) bl.items.resize(size_t(16) * n);
  std::fill(bl.count, bl.count + 16, 0);
  const int tx0 = (t % sc.tiles_x) * kTileSize, ty0 = (t / sc.tiles_x) * kTileSize;
  int32_t* it = bl.items.data();
  for (int i = 0; i < n; ++i) {
    const int j = sc.tlist[off + i];
    const int32_t* b = sc.box + 4 * size_t(j);
    const int bx0 = std::max(b[0] - tx0, 0) >> 2, bx1 = std::min(b[1] - tx0, kTileSize - 1) >> 2;
    const int by0 = std::max(b[2] - ty0, 0) >> 2, by1 = std::min(b[3] - ty0, kTileSize - 1) >> 2;
    for (int by = by0; by <= by1; ++by)
      for (int bx = bx0; bx <= bx1; ++bx) {
        const int k = by * 4 + bx;
        it[size_t(k) * n + bl.count[k]++] = i;
      }
  }
}

// Pixel lanes of a 4x4 block at (x0, y0): lane l is pixel (x0 + l%4, y0 + l/4).
struct Lanes {
  VF px, py;
  VM valid;
  int idx[kLanes];  // pixel index or -1
  Lanes(int x0, int y0, int W, int H) {
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
  VF v[NCT + 1];
  VF* p(Scratch&, int, int) { return v; }
};
template <>
struct Chan<0> {
  VF* p(Scratch& s, int slot, int n) { return s.get(slot, n); }
};

// ---- forward ---------------------------------------------------------------------------------------
template <bool GEF, bool SOFT, int NCT>
static int64_t fwd_block(const Scene& sc, const int32_t* tl, const int32_t* lst, int n, int x0, int y0,
                         const FwdOut& o, Scratch& scr) {
  const int nch = NCT ? NCT : sc.nch;
  const int R = sc.R;
  const Lanes L(x0, y0, sc.W, sc.H);
  Chan<NCT> cs;
  VF* C = cs.p(scr, 0, nch + 1);
  VF* RG = scr.get(1, 1 + 2 * R);  // reg sums: Σw, Σw·v_r, Σw·v_r²
  for (int c = 0; c < nch + 1; ++c) C[c] = VF(0.f);
  if (R)
    for (int c = 0; c < 1 + 2 * R; ++c) RG[c] = VF(0.f);
  VF T(1.f), A(0.f), dp(0.f), pp(0.f), cnt(0.f), last(0.f), dfront(0.f);
  VM done = mnot(L.valid);
  const VF kmaxf(float(sc.kmax));
  const bool need_head = SOFT || R > 0;
  int64_t pairs = 0;
  for (int i = 0; i < n; ++i) {
    const float* s = sc.pk + size_t(tl[lst[i]]) * sc.S;
    const VM act = mnot(done);
    pairs += popcount(act);
    const Quad<VF> k = splat_quad(L.px, L.py, s[P_MX], s[P_MY], s[P_CA], s[P_CB], s[P_CC]);
    const VM inq = mand(act, k.q <= VF(kQMax));
    if (!any(inq)) continue;
    const Absorb<VF> ab = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]);
    VM reach = mand(inq, ab.a >= VF(kAlphaMin));
    if (!any(reach)) continue;
    const VF T0 = T * (VF(1.f) - ab.a);
    const VM stop = mand(reach, T0 < VF(kTMin));  // 3DGS: not composited, the pixel is done
    done = mor(done, stop);
    reach = mand(reach, mnot(stop));
    if (any(reach)) {
      const float d = s[P_D];
      const float* col = s + P_COL;
      VM head = need_head ? mand(reach, cnt < kmaxf) : reach;
      if (SOFT) {
        const VM soft = mand(head, A > VF(0.f));
        const VF p = -k.q;
        Coef<VF> cf = vanilla_coef(T, A, ab.a);
        if (any(soft)) {
          const SoftFwd<VF> f = softmax_fwd(T, A, dp, pp, ab.a, p, d, s[P_BE], s[P_GA], sc.solved);
          cf.Tn = sel(soft, f.T0, cf.Tn);
          cf.An = sel(soft, f.U, cf.An);
          cf.r = sel(soft, f.r, cf.r);
          cf.aT = sel(soft, f.aT, cf.aT);
          cf.wk = sel(soft, f.wk, cf.wk);
        }
        for (int c = 0; c < nch; ++c) C[c] = sel(reach, C[c] * cf.r + VF(col[c]) * cf.aT, C[c]);
        C[nch] = sel(reach, C[nch] * cf.r + VF(d) * cf.aT, C[nch]);
        dp = sel(head, dp + (VF(d) - dp) * cf.wk, dp);
        pp = sel(head, pp + (p - pp) * cf.wk, pp);
        T = sel(reach, cf.Tn, T);
        A = sel(reach, cf.An, A);
      } else {
        const VF aT = ab.a * T;
        for (int c = 0; c < nch; ++c) C[c] = sel(reach, C[c] + VF(col[c]) * aT, C[c]);
        C[nch] = sel(reach, C[nch] + VF(d) * aT, C[nch]);
        A = sel(reach, A + aT, A);
        T = sel(reach, T0, T);
      }
      if (R) {  // variance regulariser sums over the first k_max composited splats
        const VM first = mand(head, cnt == VF(0.f));
        dfront = sel(first, VF(d), dfront);
        VF w = VF(1.f) / (VF(1.f) + (VF(d) - dfront) / VF(sc.reg_scale));
        w = sel(head, w, VF(0.f));
        RG[0] = RG[0] + w;
        for (int r = 0; r < R; ++r) {
          const VF v(s[P_COL + nch + r]);
          RG[1 + r] = RG[1 + r] + w * v;
          RG[1 + R + r] = RG[1 + R + r] + w * v * v;
        }
      }
      cnt = sel(reach, cnt + VF(1.f), cnt);
      last = sel(reach, VF(float(i + 1)), last);
    }
    if (all(done)) break;
  }
  // outputs
  for (int c = 0; c < nch; ++c) {
    VF v = C[c];
    if (sc.bg) v = v + T * VF(sc.bg[c]);
    L.scatter(o.rgb, nch, c, v);
  }
  const VM pos = A > VF(0.f);
  L.scatter(o.alpha, 1, 0, A);
  L.scatter(o.depth, 1, 0, sel(pos, C[nch] / sel(pos, A, VF(1.f)), VF(0.f)));
  L.scatter(o.Tf, 1, 0, T);
  if (R)
    for (int c = 0; c < 1 + 2 * R; ++c) L.scatter(o.reg, 1 + 2 * R, c, RG[c]);
  alignas(64) float tls[kLanes], tc[kLanes];
  store(tls, last);
  store(tc, cnt);
  for (int l = 0; l < kLanes; ++l)
    if (L.idx[l] >= 0) {
      o.last[L.idx[l]] = int32_t(tls[l]);
      o.cnt[L.idx[l]] = int32_t(tc[l]);
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
      for (int b = 0; b < 16; ++b) {
        const int x0 = tx0 + (b & 3) * 4, y0 = ty0 + (b >> 2) * 4;
        if (x0 >= sc.W || y0 >= sc.H) continue;
        pairs += fwd_block<GEF, SOFT, NCT>(sc, sc.tlist + sc.toff[t], bl.list(b), bl.count[b], x0, y0, o, scr);
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

// Per-thread scratch for the recomputed softmax heads of one block.
struct HeadScratch {
  std::vector<VF> st;  // per entry: T, A, d_past, p_past, C[nc]
  std::vector<int32_t> pos;
  std::vector<uint32_t> mask;
};

template <bool GEF, bool SOFT, int NCT>
// G: gradient rows of this tile's list entries (pk layout), summed over the tile's blocks.
static void bwd_block(const Scene& sc, const int32_t* tl, const int32_t* lst, int n, int x0, int y0,
                      const BwdIn& in, float* G, Scratch& scr, HeadScratch& hs) {
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.R;
  const int S = sc.S;  // gradient rows have the pk layout
  const Lanes L(x0, y0, sc.W, sc.H);
  Chan<NCT> cs1, cs2;
  VF* gC = cs1.p(scr, 0, nc);   // adjoint of the colour state (depth is channel nch)
  VF* C1 = cs2.p(scr, 1, nc);   // phase 1 colour state
  VF* gR = scr.get(2, 2 * R);   // dL/d reg sums Σw·v_r and Σw·v_r²

  // dL/d outputs -> dL/d final state
  const VF Aout = L.gather(in.alpha, 1, 0, 0.f);
  const VF dout = L.gather(in.depth, 1, 0, 0.f);
  const VF g_alpha = L.gather(in.g_alpha, 1, 0, 0.f);
  const VF g_depth = L.gather(in.g_depth, 1, 0, 0.f);
  VF gT(0.f);
  for (int c = 0; c < nch; ++c) {
    gC[c] = L.gather(in.g_rgb, nch, c, 0.f);
    if (sc.bg) gT = gT + gC[c] * VF(sc.bg[c]);
  }
  const VM posA = Aout > VF(0.f);
  const VF Asafe = sel(posA, Aout, VF(1.f));
  gC[nch] = sel(posA, g_depth / Asafe, VF(0.f));            // depth = C_d / A
  VF gA = g_alpha - sel(posA, g_depth * dout / Asafe, VF(0.f));
  VF T = L.gather(in.Tf, 1, 0, 1.f);
  alignas(64) float lastf[kLanes];
  int imax = 0;
  for (int l = 0; l < kLanes; ++l) {
    const int v = L.idx[l] >= 0 ? in.last[L.idx[l]] : 0;
    lastf[l] = float(v);
    imax = std::max(imax, v);
  }
  if (imax == 0) return;
  const VF last = load(lastf);
  const VF kmaxf(float(sc.kmax));

  // Phase 1: recompute each lane's head (its first k_max composited splats) front to back, saving
  // the state before every head step (softmax modes) and taking the regulariser's gradients.
  int ne = 0;
  if ((SOFT || R) && sc.kmax > 0) {
    VF T1(1.f), A1(0.f), dp1(0.f), pp1(0.f), cnt1(0.f), dfront(0.f);
    for (int c = 0; c < nc; ++c) C1[c] = VF(0.f);
    if (R)
      for (int r = 0; r < 2 * R; ++r) gR[r] = L.gather(in.g_reg, 1 + 2 * R, 1 + r, 0.f);
    const size_t esz = size_t(4 + nc);
    for (int i = 0; i < imax; ++i) {
      const VM hv = mand(VF(float(i)) < last, cnt1 < kmaxf);
      if (!any(hv)) break;
      const int j = lst[i];
      const float* s = sc.pk + size_t(tl[j]) * S;
      const Quad<VF> k = splat_quad(L.px, L.py, s[P_MX], s[P_MY], s[P_CA], s[P_CB], s[P_CC]);
      const VM inq = mand(hv, k.q <= VF(kQMax));
      if (!any(inq)) continue;
      const Absorb<VF> ab = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]);
      const VM reach = mand(inq, ab.a >= VF(kAlphaMin));  // before `last`: composited, never stopped
      if (!any(reach)) continue;
      const float d = s[P_D];
      if (SOFT) {
        if (hs.pos.size() <= size_t(ne)) {
          hs.pos.resize(ne + 64);
          hs.mask.resize(ne + 64);
          hs.st.resize((ne + 64) * esz);
        }
        VF* e = hs.st.data() + ne * esz;
        e[0] = T1;
        e[1] = A1;
        e[2] = dp1;
        e[3] = pp1;
        for (int c = 0; c < nc; ++c) e[4 + c] = C1[c];
        hs.pos[ne] = i;
        hs.mask[ne] = bits(reach);
        ++ne;
        const VM soft = mand(reach, A1 > VF(0.f));
        const VF p = -k.q;
        Coef<VF> cf = vanilla_coef(T1, A1, ab.a);
        if (any(soft)) {
          const SoftFwd<VF> f = softmax_fwd(T1, A1, dp1, pp1, ab.a, p, d, s[P_BE], s[P_GA], sc.solved);
          cf.Tn = sel(soft, f.T0, cf.Tn);
          cf.An = sel(soft, f.U, cf.An);
          cf.r = sel(soft, f.r, cf.r);
          cf.aT = sel(soft, f.aT, cf.aT);
          cf.wk = sel(soft, f.wk, cf.wk);
        }
        const float* col = s + P_COL;
        for (int c = 0; c < nch; ++c) C1[c] = sel(reach, C1[c] * cf.r + VF(col[c]) * cf.aT, C1[c]);
        C1[nch] = sel(reach, C1[nch] * cf.r + VF(d) * cf.aT, C1[nch]);
        dp1 = sel(reach, dp1 + (VF(d) - dp1) * cf.wk, dp1);
        pp1 = sel(reach, pp1 + (p - pp1) * cf.wk, pp1);
        T1 = sel(reach, cf.Tn, T1);
        A1 = sel(reach, cf.An, A1);
      }
      if (R) {
        const VM first = mand(reach, cnt1 == VF(0.f));
        dfront = sel(first, VF(d), dfront);
        const VF w = VF(1.f) / (VF(1.f) + (VF(d) - dfront) / VF(sc.reg_scale));
        float* g = G + size_t(j) * S + P_COL + nch;
        for (int r = 0; r < R; ++r) {
          const VF v(s[P_COL + nch + r]);
          // reg = Σ w·[1, v, v·v]: d/dv = w·g1 + 2·w·v·g2 (the weights carry no gradient)
          g[r] += hsum(sel(reach, w * gR[r] + VF(2.f) * w * v * gR[R + r], VF(0.f)));
        }
      }
      cnt1 = sel(reach, cnt1 + VF(1.f), cnt1);
    }
  }

  // Phase 2: back to front over every composited splat.
  VF gdp(0.f), gpp(0.f);  // adjoints of the running means, non-zero only inside a lane's head
  int e = ne - 1;
  const size_t esz = size_t(4 + nc);
  for (int i = imax - 1; i >= 0; --i) {
    const VM valid = VF(float(i)) < last;
    const int j = lst[i];
    const float* s = sc.pk + size_t(tl[j]) * S;
    const Quad<VF> k = splat_quad(L.px, L.py, s[P_MX], s[P_MY], s[P_CA], s[P_CB], s[P_CC]);
    const VM inq = mand(valid, k.q <= VF(kQMax));
    if (!any(inq)) continue;
    const Absorb<VF> ab = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]);
    const VM reach = mand(inq, ab.a >= VF(kAlphaMin));
    if (!any(reach)) continue;
    const float d = s[P_D];
    const float* col = s + P_COL;
    const VF a = ab.a;
    const VF p = -k.q;
    // state before the step: the 3DGS inverse for tail lanes, the saved state for head lanes
    VF Tpre = T / (VF(1.f) - a);
    VF Apre(0.f), dpre(0.f), ppre(0.f);
    VM hm = mask_from_bits(0);
    const VF* ent = nullptr;
    if (SOFT && e >= 0 && hs.pos[e] == i) {
      hm = mask_from_bits(hs.mask[e]);
      ent = hs.st.data() + size_t(e) * esz;
      Tpre = sel(hm, ent[0], Tpre);
      Apre = sel(hm, ent[1], Apre);
      dpre = sel(hm, ent[2], dpre);
      ppre = sel(hm, ent[3], ppre);
      --e;
    }
    VF g_a, g_p(0.f), g_d(0.f), g_be(0.f), g_ga(0.f);
    VF gTn, gAn;
    if (SOFT) {
      const VM soft = mand(hm, Apre > VF(0.f));
      Coef<VF> cf = vanilla_coef(Tpre, Apre, a);
      SoftFwd<VF> f;
      const bool anysoft = any(soft);
      if (anysoft) {
        f = softmax_fwd(Tpre, Apre, dpre, ppre, a, p, d, s[P_BE], s[P_GA], sc.solved);
        cf.r = sel(soft, f.r, cf.r);
        cf.aT = sel(soft, f.aT, cf.aT);
        cf.wk = sel(soft, f.wk, cf.wk);
      }
      // adjoint of C' = C·r + c·aT (depth is channel nch)
      VF g_r(0.f), g_aT(0.f);
      for (int c = 0; c < nc; ++c) {
        const float cv = c < nch ? col[c] : d;
        g_aT = g_aT + gC[c] * VF(cv);
      }
      float* g = G + size_t(j) * S;
      for (int c = 0; c < nch; ++c) g[P_COL + c] += hsum(sel(reach, gC[c] * cf.aT, VF(0.f)));
      g_d = gC[nch] * cf.aT;
      if (anysoft) {
        for (int c = 0; c < nc; ++c) {
          g_r = g_r + gC[c] * ent[4 + c];
          gC[c] = sel(soft, gC[c] * cf.r, gC[c]);
        }
      }
      // adjoint of the running means d' = d + (d_k - d)·wk, p' likewise (head lanes only)
      const VF g_wk = sel(hm, gdp * (VF(d) - dpre) + gpp * (p - ppre), VF(0.f));
      g_d = g_d + sel(hm, gdp * cf.wk, VF(0.f));
      g_p = sel(hm, gpp * cf.wk, VF(0.f));
      gdp = sel(hm, gdp - gdp * cf.wk, gdp);
      gpp = sel(hm, gpp - gpp * cf.wk, gpp);
      VF gTv, gAv, gav;
      vanilla_coef_bwd(Tpre, Apre, a, gT, gA, g_aT, g_wk, gTv, gAv, gav);
      gTn = gTv;
      gAn = gAv;
      g_a = gav;
      if (anysoft) {
        const SoftGrad<VF> sg = softmax_bwd(f, Tpre, Apre, dpre, ppre, a, p, s[P_BE], s[P_GA], sc.solved, gT, gA,
                                            g_r, g_aT, g_wk);
        gTn = sel(soft, sg.T, gTn);
        gAn = sel(soft, sg.A, gAn);
        g_a = sel(soft, sg.a, g_a);
        g_p = g_p + sel(soft, sg.p, VF(0.f));
        g_d = g_d + sel(soft, sg.d, VF(0.f));
        gdp = gdp + sel(soft, sg.dp, VF(0.f));
        gpp = gpp + sel(soft, sg.pp, VF(0.f));
        g_be = sel(soft, sg.beta, VF(0.f));
        g_ga = sel(soft, sg.gamma, VF(0.f));
      }
    } else {
      // 3DGS: C' = C + c·aT, A' = A + aT, T' = T(1-a)
      const VF aT = a * Tpre;
      VF g_aT = gA;
      for (int c = 0; c < nch; ++c) g_aT = g_aT + gC[c] * VF(col[c]);
      g_aT = g_aT + gC[nch] * VF(d);
      float* g = G + size_t(j) * S;
      for (int c = 0; c < nch; ++c) g[P_COL + c] += hsum(sel(reach, gC[c] * aT, VF(0.f)));
      g_d = gC[nch] * aT;
      g_a = g_aT * Tpre - gT * Tpre;
      gTn = g_aT * a + gT * (VF(1.f) - a);
      gAn = gA;
    }
    gT = sel(reach, gTn, gT);
    gA = sel(reach, gAn, gA);
    T = sel(reach, Tpre, T);
    const KernGrad<VF> kg = splat_kernel_bwd<GEF>(k, ab, s[P_CA], s[P_CB], s[P_CC], s[P_O], s[P_AL], g_a, g_p);
    float* g = G + size_t(j) * S;
    const VF zero(0.f);
    g[P_MX] += hsum(sel(reach, kg.mx, zero));
    g[P_MY] += hsum(sel(reach, kg.my, zero));
    g[P_CA] += hsum(sel(reach, kg.ca, zero));
    g[P_CB] += hsum(sel(reach, kg.cb, zero));
    g[P_CC] += hsum(sel(reach, kg.cc, zero));
    g[P_O] += hsum(sel(reach, kg.o, zero));
    g[P_D] += hsum(sel(reach, g_d, zero));
    if (GEF) g[P_AL] += hsum(sel(reach, kg.alpha, zero));
    if (SOFT) {
      g[P_BE] += hsum(sel(reach, g_be, zero));
      g[P_GA] += hsum(sel(reach, g_ga, zero));
    }
  }
}

template <bool GEF, bool SOFT, int NCT>
static void backward_impl(const Scene& sc, const BwdIn& in, float* E) {
  const int nt = sc.tiles_x * sc.tiles_y;
#pragma omp parallel num_threads(sc.nthreads)
  {
    BlockLists bl;
    Scratch scr;
    HeadScratch hs;
#pragma omp for schedule(dynamic, 1)
    for (int t = 0; t < nt; ++t) {
      const int off = sc.toff[t];
      float* G = E + size_t(off) * sc.S;
      std::fill(G, G + size_t(sc.toff[t + 1] - off) * sc.S, 0.f);
      build_block_lists(sc, t, bl);
      const int tx0 = (t % sc.tiles_x) * kTileSize, ty0 = (t / sc.tiles_x) * kTileSize;
      for (int b = 0; b < 16; ++b) {
        const int x0 = tx0 + (b & 3) * 4, y0 = ty0 + (b >> 2) * 4;
        if (x0 >= sc.W || y0 >= sc.H) continue;
        bwd_block<GEF, SOFT, NCT>(sc, sc.tlist + off, bl.list(b), bl.count[b], x0, y0, in, G, scr, hs);
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
  torch::Tensor E = torch::empty({tlist.numel(), S}, torch::TensorOptions().dtype(torch::kFloat32));
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
        const float* e = Ep + size_t(sp[k]) * S;
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
  return {kAlphaMax, kAlphaMin, kTMin, kQMax, kExpArgMax, kDecayArgMax, kPixelCenter, double(kTileSize)};
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
