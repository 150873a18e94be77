// 16-lane float SIMD layer of the compiled CPU kernels: VF (16 floats) and VM (16 lane masks) with
// the operations smgs/raster/csrc/splat_math.h asks of a lane type, on one of four paths chosen at
// build time (smgs/raster/cpu.py passes -DSMGS_ISA_<path> with that path's compiler flags):
//
//   avx512  one __m512 per VF, __mmask16 masks; rcp14/rsqrt14, scalef, getexp/getmant
//   avx2    x86-64-v3 (AVX2 + FMA): two 8-float GCC/Clang vectors (two __m256); the few operations
//           the vector extension lacks (fma, sqrt, rcp, masks as bits, reductions) by intrinsics
//   neon    aarch64 Advanced SIMD: four 4-float vectors (float32x4_t); intrinsics likewise
//   scalar  no intrinsics and no ISA flags: four 4-float vectors as the compiler lowers them for the
//           architecture's baseline (SSE2 on x86-64), exact divide and square root
//
// exp and log are one polynomial each (Cephes expf / logf) on every path, never a libm call per lane.
// Measured error against float64 over the ranges the renderer uses (tests/simd_check.cpp, run by
// tests/test_raster_simd.py on every path this host runs, which checks the bounds in brackets):
//   vexp      1.03 ulp [1.5] (x in [-103, 88.7]; below 2^-126 the denormal result is rounded twice;
//                        0 below -104, inf above 88.8, NaN propagates)
//   vlog      0.73 ulp [1.5] (x > 0, denormals included; log 0 = -inf, log inf = inf, log x<0 = NaN)
//   vrcp      0.53 ulp [1] avx512 (rcp14 + one Newton step), 0.50 avx2 (rcp + a second-order
//                        step), 0.5 neon/scalar (a true division); x > 0 normal
//   vsqrt_pos 0.79 ulp [1] avx512 (rsqrt14 + one Newton step, 0 at x = 0); 0.5 elsewhere (sqrt)
//   vsqrt     0.5 ulp [0.5] (correctly rounded) on every path
// The header needs no torch headers: tests cross-compile it (with the kernel core) for aarch64.
#pragma once

#include <cmath>
#include <cstdint>
#include <cstring>
#include <limits>

#if !defined(SMGS_ISA_AVX512) && !defined(SMGS_ISA_AVX2) && !defined(SMGS_ISA_NEON) && !defined(SMGS_ISA_SCALAR)
// No path requested: the best the compiler targets.
#if defined(__AVX512F__) && defined(__AVX512DQ__)
#define SMGS_ISA_AVX512 1
#elif defined(__AVX2__) && defined(__FMA__)
#define SMGS_ISA_AVX2 1
#elif defined(__aarch64__) && defined(__ARM_NEON)
#define SMGS_ISA_NEON 1
#else
#define SMGS_ISA_SCALAR 1
#endif
#endif

#if defined(SMGS_ISA_AVX512)
#if !(defined(__AVX512F__) && defined(__AVX512DQ__))
#error "SMGS_ISA_AVX512 needs -mavx512f -mavx512dq (or -march=native on an AVX-512 CPU)"
#endif
#include <immintrin.h>
#define SMGS_ISA_NAME "avx512"
#elif defined(SMGS_ISA_AVX2)
#if !(defined(__AVX2__) && defined(__FMA__))
#error "SMGS_ISA_AVX2 needs -mavx2 -mfma (x86-64-v3)"
#endif
#include <immintrin.h>
#define SMGS_ISA_NAME "avx2"
#elif defined(SMGS_ISA_NEON)
#if !(defined(__aarch64__) && defined(__ARM_NEON))
#error "SMGS_ISA_NEON needs an aarch64 compiler"
#endif
#include <arm_neon.h>
#define SMGS_ISA_NAME "neon"
#else
#define SMGS_ISA_NAME "scalar"
#endif

namespace smgs {

#define SMGS_FI inline __attribute__((always_inline))

constexpr int kLanes = 16;
constexpr const char* kIsaName = SMGS_ISA_NAME;

// Cephes expf / logf coefficients, shared by every path.
namespace cephes {
constexpr float kLog2e = 1.44269504088896341f, kLn2Hi = 0.693359375f, kLn2Lo = -2.12194440e-4f;
constexpr float kExpHi = 88.8f, kExpLo = -104.0f;
constexpr float kE0 = 5.0000001201e-1f, kE1 = 1.6666665459e-1f, kE2 = 4.1665795894e-2f,
                kE3 = 8.3334519073e-3f, kE4 = 1.3981999507e-3f, kE5 = 1.9875691500e-4f;
constexpr float kL[9] = {7.0376836292e-2f, -1.1514610310e-1f, 1.1676998740e-1f, -1.2420140846e-1f,
                         1.4249322787e-1f, -1.6668057665e-1f, 2.0000714765e-1f, -2.4999993993e-1f,
                         3.3333331174e-1f};
constexpr float kSqrtHalf2 = 1.41421356237f;  // mantissas above √2 are halved: m in [√½, √2)
}  // namespace cephes

#if defined(SMGS_ISA_AVX512)
// ---- avx512 ----------------------------------------------------------------------------------------
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
// Newton step (the divide/sqrt unit is otherwise the bottleneck of a softmax step).
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
// exp: scalef for 2^n (exact under/overflow to 0 / inf).
SMGS_FI VF vexp(VF x) {
  using namespace cephes;
  __m512 v = _mm512_min_ps(_mm512_set1_ps(kExpHi), x.v);
  v = _mm512_max_ps(_mm512_set1_ps(kExpLo), v);
  __m512 n = _mm512_roundscale_ps(_mm512_mul_ps(v, _mm512_set1_ps(kLog2e)), _MM_FROUND_TO_NEAREST_INT | _MM_FROUND_NO_EXC);
  __m512 r = _mm512_fnmadd_ps(n, _mm512_set1_ps(kLn2Hi), v);
  r = _mm512_fnmadd_ps(n, _mm512_set1_ps(kLn2Lo), r);
  // p(r) = c0 + c1 r + ... + c5 r^5 by Estrin's scheme (3 dependent FMAs instead of 5)
  const __m512 r2 = _mm512_mul_ps(r, r);
  const __m512 e01 = _mm512_fmadd_ps(_mm512_set1_ps(kE1), r, _mm512_set1_ps(kE0));
  const __m512 e23 = _mm512_fmadd_ps(_mm512_set1_ps(kE3), r, _mm512_set1_ps(kE2));
  const __m512 e45 = _mm512_fmadd_ps(_mm512_set1_ps(kE5), r, _mm512_set1_ps(kE4));
  const __m512 p = _mm512_fmadd_ps(_mm512_fmadd_ps(e45, r2, e23), r2, e01);
  __m512 y = _mm512_fmadd_ps(p, r2, r);
  y = _mm512_add_ps(y, _mm512_set1_ps(1.0f));
  return _mm512_scalef_ps(y, n);
}
// log: getexp/getmant split the mantissa (denormals included).
SMGS_FI VF vlog(VF x) {
  using namespace cephes;
  __m512 e = _mm512_getexp_ps(x.v);
  __m512 m = _mm512_getmant_ps(x.v, _MM_MANT_NORM_1_2, _MM_MANT_SIGN_src);
  __mmask16 big = _mm512_cmp_ps_mask(m, _mm512_set1_ps(kSqrtHalf2), _CMP_GT_OQ);
  m = _mm512_mask_mul_ps(m, big, m, _mm512_set1_ps(0.5f));
  e = _mm512_mask_add_ps(e, big, e, _mm512_set1_ps(1.0f));
  __m512 t = _mm512_sub_ps(m, _mm512_set1_ps(1.0f));
  __m512 z = _mm512_mul_ps(t, t);
  __m512 y = _mm512_set1_ps(kL[0]);
  for (int i = 1; i < 9; ++i) y = _mm512_fmadd_ps(y, t, _mm512_set1_ps(kL[i]));
  y = _mm512_mul_ps(_mm512_mul_ps(y, t), z);
  y = _mm512_fmadd_ps(e, _mm512_set1_ps(kLn2Lo), y);
  y = _mm512_fmadd_ps(z, _mm512_set1_ps(-0.5f), y);
  __m512 r = _mm512_add_ps(t, y);
  r = _mm512_fmadd_ps(e, _mm512_set1_ps(kLn2Hi), r);
  const float inf = std::numeric_limits<float>::infinity();
  r = _mm512_mask_mov_ps(r, _mm512_cmp_ps_mask(x.v, _mm512_setzero_ps(), _CMP_EQ_OQ), _mm512_set1_ps(-inf));
  r = _mm512_mask_mov_ps(r, _mm512_cmp_ps_mask(x.v, _mm512_set1_ps(inf), _CMP_EQ_OQ), _mm512_set1_ps(inf));
  __mmask16 neg = _mm512_cmp_ps_mask(x.v, _mm512_setzero_ps(), _CMP_LT_OQ);
  return _mm512_mask_mov_ps(r, neg, _mm512_set1_ps(std::numeric_limits<float>::quiet_NaN()));
}
SMGS_FI bool any(VM m) { return m.m != 0; }
SMGS_FI bool all(VM m) { return m.m == 0xFFFF; }
SMGS_FI int popcount(VM m) { return __builtin_popcount(unsigned(m.m)); }
SMGS_FI VM mask_from_bits(unsigned b) { return {__mmask16(b)}; }
SMGS_FI unsigned bits(VM m) { return m.m; }
SMGS_FI float hsum(VF x) { return _mm512_reduce_add_ps(x.v); }
SMGS_FI VF load(const float* p) { return _mm512_loadu_ps(p); }
SMGS_FI void store(float* p, VF x) { _mm512_storeu_ps(p, x.v); }

// Sums of the lanes of 16 vectors, as one vector (lane k = Σ lanes of v[k]): a transposing tree of
// 45 shuffles and adds instead of 16 horizontal reductions.
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
// ---- avx2 / neon / scalar: kK native-width GCC/Clang vectors ------------------------------------
// Each VF is kK registers of the target's width (a single 64-byte vector would be lowered through
// memory where the target has no 64-byte registers: measured 7x slower on avx2).
#if defined(SMGS_ISA_AVX2)
constexpr int kW = 8;  // one __m256
#else
constexpr int kW = 4;  // one float32x4_t (neon), one SSE2 register (scalar on x86-64)
#endif
constexpr int kK = kLanes / kW;
typedef float FN __attribute__((vector_size(4 * kW)));
typedef int32_t IN __attribute__((vector_size(4 * kW)));

struct VM {
  IN m[kK];  // all ones (true) or zero per lane, as vector comparisons give
};
struct VF {
  FN v[kK];
  VF() = default;
  VF(float x) {
    for (int k = 0; k < kK; ++k) v[k] = FN{} + x;
  }
};
#define SMGS_VBIN(op)                                   \
  SMGS_FI VF operator op(VF a, VF b) {                  \
    VF r;                                               \
    for (int k = 0; k < kK; ++k) r.v[k] = a.v[k] op b.v[k]; \
    return r;                                           \
  }
SMGS_VBIN(+)
SMGS_VBIN(-)
SMGS_VBIN(*)
SMGS_VBIN(/)
#undef SMGS_VBIN
#define SMGS_VCMP(op)                                   \
  SMGS_FI VM operator op(VF a, VF b) {                  \
    VM r;                                               \
    for (int k = 0; k < kK; ++k) r.m[k] = a.v[k] op b.v[k]; \
    return r;                                           \
  }
SMGS_VCMP(<)
SMGS_VCMP(<=)
SMGS_VCMP(>)
SMGS_VCMP(>=)
SMGS_VCMP(==)
SMGS_VCMP(!=)
#undef SMGS_VCMP
SMGS_FI VF operator-(VF a) {
  for (int k = 0; k < kK; ++k) a.v[k] = -a.v[k];
  return a;
}
SMGS_FI VM mand(VM a, VM b) {
  for (int k = 0; k < kK; ++k) a.m[k] &= b.m[k];
  return a;
}
SMGS_FI VM mor(VM a, VM b) {
  for (int k = 0; k < kK; ++k) a.m[k] |= b.m[k];
  return a;
}
SMGS_FI VM mnot(VM a) {
  for (int k = 0; k < kK; ++k) a.m[k] = ~a.m[k];
  return a;
}
// a bitwise blend (the lane masks are all ones or zero): what every target lowers well
SMGS_FI FN seln(IN m, FN a, FN b) { return (FN)((m & (IN)a) | (~m & (IN)b)); }
SMGS_FI VF sel(VM m, VF a, VF b) {
  for (int k = 0; k < kK; ++k) a.v[k] = seln(m.m[k], a.v[k], b.v[k]);
  return a;
}
// min/max with a constant second argument; a NaN first argument propagates (as torch.clamp)
SMGS_FI FN minn(FN x, FN c) { return seln(c < x, c, x); }
SMGS_FI FN maxn(FN x, FN c) { return seln(c > x, c, x); }
SMGS_FI VF min_c(VF x, VF c) {
  for (int k = 0; k < kK; ++k) x.v[k] = minn(x.v[k], c.v[k]);
  return x;
}
SMGS_FI VF max_c(VF x, VF c) {
  for (int k = 0; k < kK; ++k) x.v[k] = maxn(x.v[k], c.v[k]);
  return x;
}
SMGS_FI VF vabs(VF x) {
  for (int k = 0; k < kK; ++k) x.v[k] = (FN)((IN)x.v[k] & 0x7FFFFFFF);
  return x;
}
SMGS_FI VF load(const float* p) {
  VF r;
  std::memcpy(&r.v, p, sizeof r.v);
  return r;
}
SMGS_FI void store(float* p, VF x) { std::memcpy(p, &x.v, sizeof x.v); }

// per-register primitives: fused multiply-add, square root, reciprocal, lane bits
#if defined(SMGS_ISA_AVX2)
SMGS_FI FN fman(FN a, FN b, FN c) { return (FN)_mm256_fmadd_ps((__m256)a, (__m256)b, (__m256)c); }
SMGS_FI FN sqrtn(FN x) { return (FN)_mm256_sqrt_ps((__m256)x); }
// rcp_ps has 12 bits: one Newton step leaves ~1.9 ulp, which the deep softmax stacks of the stiff
// battery see; r·(1 + e + e²) with e = 1 - x·r (one FMA more) is good to ~0.5 ulp, as rcp14 + Newton.
SMGS_FI FN rcpn(FN x) {
  const __m256 r = _mm256_rcp_ps((__m256)x);
  const __m256 e = _mm256_fnmadd_ps((__m256)x, r, _mm256_set1_ps(1.0f));
  return (FN)_mm256_fmadd_ps(r, _mm256_fmadd_ps(e, e, e), r);
}
SMGS_FI unsigned bitsn(IN m) { return unsigned(_mm256_movemask_ps((__m256)m)); }
#elif defined(SMGS_ISA_NEON)
SMGS_FI FN fman(FN a, FN b, FN c) { return (FN)vfmaq_f32((float32x4_t)c, (float32x4_t)a, (float32x4_t)b); }
SMGS_FI FN sqrtn(FN x) { return (FN)vsqrtq_f32((float32x4_t)x); }
SMGS_FI FN rcpn(FN x) { return 1.0f / x; }
SMGS_FI unsigned bitsn(IN m) {
  const uint32x4_t w = {1u, 2u, 4u, 8u};
  return vaddvq_u32(vandq_u32((uint32x4_t)m, w));
}
#else  // scalar
SMGS_FI FN fman(FN a, FN b, FN c) { return a * b + c; }  // no FMA in the baseline ISA: two roundings
SMGS_FI FN sqrtn(FN x) {
  for (int i = 0; i < kW; ++i) x[i] = std::sqrt(x[i]);
  return x;
}
SMGS_FI FN rcpn(FN x) { return 1.0f / x; }
SMGS_FI unsigned bitsn(IN m) {
  unsigned r = 0;
  for (int i = 0; i < kW; ++i) r |= unsigned(m[i] & 1) << i;
  return r;
}
#endif

SMGS_FI VF fmadd(VF a, VF b, VF c) {
  for (int k = 0; k < kK; ++k) a.v[k] = fman(a.v[k], b.v[k], c.v[k]);
  return a;
}
SMGS_FI VF vsqrt(VF x) {
  for (int k = 0; k < kK; ++k) x.v[k] = sqrtn(x.v[k]);
  return x;
}
SMGS_FI VF vsqrt_pos(VF x) { return vsqrt(x); }  // one per softmax step: the exact root costs little
SMGS_FI VF vrcp(VF x) {
  for (int k = 0; k < kK; ++k) x.v[k] = rcpn(x.v[k]);
  return x;
}
SMGS_FI unsigned bits(VM m) {
  unsigned r = 0;
  for (int k = 0; k < kK; ++k) r |= bitsn(m.m[k]) << (kW * k);
  return r;
}
SMGS_FI bool any(VM m) {
  IN o = m.m[0];
  for (int k = 1; k < kK; ++k) o |= m.m[k];
  return bitsn(o) != 0;
}
SMGS_FI bool all(VM m) { return bits(m) == 0xFFFFu; }
SMGS_FI int popcount(VM m) { return __builtin_popcount(bits(m)); }
SMGS_FI VM mask_from_bits(unsigned b) {
  VM r;
  for (int k = 0; k < kK; ++k) {
    IN lane;
    for (int i = 0; i < kW; ++i) lane[i] = 1 << (kW * k + i);
    r.m[k] = (lane & int32_t(b)) != 0;
  }
  return r;
}
SMGS_FI float hsum(VF x) {
  FN s = x.v[0];
  for (int k = 1; k < kK; ++k) s += x.v[k];
  float t = 0.f;
  for (int i = 0; i < kW; ++i) t += s[i];
  return t;
}

#if defined(SMGS_ISA_AVX2)
// 16 vectors' lane sums as one vector: a transposing tree (the first level only adds halves).
SMGS_FI VF reduce16(const VF* v) {
  __m256 t[8][2];
  for (int i = 0; i < 8; ++i) {  // t[i][h] = 8 partial sums of v[2i+h]
    t[i][0] = _mm256_add_ps((__m256)v[2 * i].v[0], (__m256)v[2 * i].v[1]);
    t[i][1] = _mm256_add_ps((__m256)v[2 * i + 1].v[0], (__m256)v[2 * i + 1].v[1]);
  }
  __m256 u[4][2];
  for (int i = 0; i < 4; ++i)
    for (int h = 0; h < 2; ++h)
      u[i][h] = _mm256_add_ps(_mm256_permute2f128_ps(t[2 * i][h], t[2 * i + 1][h], 0x20),
                              _mm256_permute2f128_ps(t[2 * i][h], t[2 * i + 1][h], 0x31));
  __m256 w[2][2];
  for (int i = 0; i < 2; ++i)
    for (int h = 0; h < 2; ++h) {
      const __m256 a = u[2 * i][h], b = u[2 * i + 1][h];
      w[i][h] = _mm256_add_ps(_mm256_shuffle_ps(a, b, 0x44), _mm256_shuffle_ps(a, b, 0xEE));
    }
  __m256 s[2];
  for (int h = 0; h < 2; ++h) {
    const __m256 a = w[0][h], b = w[1][h];
    s[h] = _mm256_add_ps(_mm256_shuffle_ps(a, b, 0x88), _mm256_shuffle_ps(a, b, 0xDD));
  }
  // the tree leaves its sums in this order (checked by tests/simd_check.cpp)
  alignas(32) float raw[16], out[16];
  _mm256_store_ps(raw, s[0]);
  _mm256_store_ps(raw + 8, s[1]);
  constexpr int kOrder[16] = {0, 4, 8, 12, 2, 6, 10, 14, 1, 5, 9, 13, 3, 7, 11, 15};
  for (int k = 0; k < 16; ++k) out[kOrder[k]] = raw[k];
  return load(out);
}
#else
SMGS_FI VF reduce16(const VF* v) {
  alignas(64) float r[kLanes];
  for (int k = 0; k < kLanes; ++k) r[k] = hsum(v[k]);
  return load(r);
}
#endif

// Round to nearest even for |x| < 2^22: adding and subtracting 1.5·2^23 leaves the integer part
// (exact without -ffast-math, which no path uses).
SMGS_FI FN round_small(FN x) { return (x + 12582912.0f) - 12582912.0f; }
SMGS_FI FN pow2i(IN n) { return (FN)((n + 127) << 23); }  // 2^n for n in [-126, 127]

SMGS_FI FN vexpn(FN x) {
  using namespace cephes;
  const FN v = maxn(minn(x, FN{} + kExpHi), FN{} + kExpLo);
  const FN n = round_small(v * kLog2e);
  FN r = v - n * kLn2Hi;  // exact: n·kLn2Hi has at most 8 + 9 significant bits
  r = fman(n, FN{} - kLn2Lo, r);
  const FN r2 = r * r;
  const FN e01 = fman(FN{} + kE1, r, FN{} + kE0);
  const FN e23 = fman(FN{} + kE3, r, FN{} + kE2);
  const FN e45 = fman(FN{} + kE5, r, FN{} + kE4);
  const FN p = fman(fman(e45, r2, e23), r2, e01);
  const FN y = fman(p, r2, r) + 1.0f;
  // 2^n as two factors so that n in [-150, 128] stays representable: under/overflow go to the
  // denormals / 0 / inf as a true exp would.
  const IN ni = __builtin_convertvector(n, IN);
  const IN n1 = ni >> 1;
  return y * pow2i(n1) * pow2i(ni - n1);
}
SMGS_FI VF vexp(VF x) {
  for (int k = 0; k < kK; ++k) x.v[k] = vexpn(x.v[k]);
  return x;
}

SMGS_FI FN vlogn(FN x) {
  using namespace cephes;
  // denormals: scale into the normal range first
  const IN sub = x < 1.17549435e-38f;
  const FN xs = seln(sub, x * 8388608.0f, x);
  const IN b = (IN)xs;
  FN e = __builtin_convertvector(((b >> 23) & 0xFF) - 127, FN);
  e = seln(sub, e - 23.0f, e);
  FN m = (FN)((b & 0x007FFFFF) | 0x3F800000);  // in [1, 2)
  const IN big = m > kSqrtHalf2;
  m = seln(big, m * 0.5f, m);
  e = seln(big, e + 1.0f, e);
  const FN t = m - 1.0f;
  const FN z = t * t;
  FN y = FN{} + kL[0];
  for (int i = 1; i < 9; ++i) y = fman(y, t, FN{} + kL[i]);
  y = y * t * z;
  y = fman(e, FN{} + kLn2Lo, y);
  y = fman(z, FN{} - 0.5f, y);
  FN r = t + y;
  r = fman(e, FN{} + kLn2Hi, r);
  const float inf = std::numeric_limits<float>::infinity(), nan = std::numeric_limits<float>::quiet_NaN();
  r = seln(x == 0.0f, FN{} - inf, r);
  r = seln(x == inf, FN{} + inf, r);
  return seln((x < 0.0f) | (x != x), FN{} + nan, r);
}
SMGS_FI VF vlog(VF x) {
  for (int k = 0; k < kK; ++k) x.v[k] = vlogn(x.v[k]);
  return x;
}
#endif

}  // namespace smgs
