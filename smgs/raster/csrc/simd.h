// 16-lane float SIMD layer of the compiled CPU kernels: VF (16 floats) and VM (16 lane masks) with
// the operations smgs/raster/csrc/splat_math.h asks of a lane type, on one of four paths chosen at
// build time (smgs/raster/cpu.py passes -DSMGS_ISA_<path> with that path's compiler flags):
//
//   avx512  one __m512 per VF, __mmask16 masks; rcp14/rsqrt14, scalef, getexp/getmant
//   avx2    x86-64-v3 (AVX2 + FMA): a GCC/Clang 64-byte vector, lowered to two __m256; the few
//           operations the vector extension lacks (sqrt, rcp, masks as bits, reductions) by intrinsics
//   neon    aarch64 Advanced SIMD: the same vector, lowered to four float32x4_t; intrinsics likewise
//   scalar  no intrinsics and no ISA flags: the same vector as the compiler lowers it for the
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
// ---- avx2 / neon / scalar: one 64-byte GCC/Clang vector ---------------------------------------------
typedef float F16v __attribute__((vector_size(64)));
typedef int32_t I16v __attribute__((vector_size(64)));

struct VM {
  I16v m;  // all ones (true) or zero per lane, as vector comparisons give
};
struct VF {
  F16v v;
  VF() = default;
  VF(F16v x) : v(x) {}
  VF(float x) : v(F16v{} + x) {}
};
SMGS_FI VF operator+(VF a, VF b) { return a.v + b.v; }
SMGS_FI VF operator-(VF a, VF b) { return a.v - b.v; }
SMGS_FI VF operator*(VF a, VF b) { return a.v * b.v; }
SMGS_FI VF operator/(VF a, VF b) { return a.v / b.v; }
SMGS_FI VF operator-(VF a) { return -a.v; }
SMGS_FI VM operator<(VF a, VF b) { return {a.v < b.v}; }
SMGS_FI VM operator<=(VF a, VF b) { return {a.v <= b.v}; }
SMGS_FI VM operator>(VF a, VF b) { return {a.v > b.v}; }
SMGS_FI VM operator>=(VF a, VF b) { return {a.v >= b.v}; }
SMGS_FI VM operator==(VF a, VF b) { return {a.v == b.v}; }
SMGS_FI VM operator!=(VF a, VF b) { return {a.v != b.v}; }
SMGS_FI VM mand(VM a, VM b) { return {a.m & b.m}; }
SMGS_FI VM mor(VM a, VM b) { return {a.m | b.m}; }
SMGS_FI VM mnot(VM a) { return {~a.m}; }
// a bitwise blend (the lane masks are all ones or zero): what every target lowers well
SMGS_FI VF sel(VM m, VF a, VF b) {
  return (F16v)((m.m & (I16v)a.v) | (~m.m & (I16v)b.v));
}
// min/max with a constant second argument; a NaN first argument propagates (as torch.clamp)
SMGS_FI VF min_c(VF x, VF c) { return sel({c.v < x.v}, c, x); }
SMGS_FI VF max_c(VF x, VF c) { return sel({c.v > x.v}, c, x); }
SMGS_FI VF vabs(VF x) { return (F16v)((I16v)x.v & 0x7FFFFFFF); }
SMGS_FI VF load(const float* p) {
  VF r;
  std::memcpy(&r.v, p, sizeof r.v);
  return r;
}
SMGS_FI void store(float* p, VF x) { std::memcpy(p, &x.v, sizeof x.v); }

#if defined(SMGS_ISA_AVX2)
// The two 256-bit halves: register names under -mavx2, no instructions.
SMGS_FI __m256 lo(VF x) { return __builtin_shufflevector(x.v, x.v, 0, 1, 2, 3, 4, 5, 6, 7); }
SMGS_FI __m256 hi(VF x) { return __builtin_shufflevector(x.v, x.v, 8, 9, 10, 11, 12, 13, 14, 15); }
SMGS_FI VF join(__m256 a, __m256 b) {
  return VF(__builtin_shufflevector(a, b, 0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13, 14, 15));
}
SMGS_FI VF fmadd(VF a, VF b, VF c) {
  return join(_mm256_fmadd_ps(lo(a), lo(b), lo(c)), _mm256_fmadd_ps(hi(a), hi(b), hi(c)));
}
SMGS_FI VF vsqrt(VF x) { return join(_mm256_sqrt_ps(lo(x)), _mm256_sqrt_ps(hi(x))); }
// rcp_ps has 12 bits: one Newton step leaves ~1.9 ulp, which the deep softmax stacks of the stiff
// battery see; r·(1 + e + e²) with e = 1 - x·r (one FMA more) is good to ~0.5 ulp, as rcp14 + Newton.
SMGS_FI __m256 rcp8(__m256 x) {
  const __m256 r = _mm256_rcp_ps(x);
  const __m256 e = _mm256_fnmadd_ps(x, r, _mm256_set1_ps(1.0f));
  return _mm256_fmadd_ps(r, _mm256_fmadd_ps(e, e, e), r);
}
SMGS_FI VF vrcp(VF x) { return join(rcp8(lo(x)), rcp8(hi(x))); }
SMGS_FI VF vsqrt_pos(VF x) { return vsqrt(x); }  // one per softmax step: the exact root costs little
SMGS_FI unsigned bits(VM m) {
  const VF f((F16v)m.m);
  return unsigned(_mm256_movemask_ps(lo(f))) | (unsigned(_mm256_movemask_ps(hi(f))) << 8);
}
SMGS_FI bool any(VM m) {
  const VF f((F16v)m.m);
  return !_mm256_testz_ps(_mm256_or_ps(lo(f), hi(f)), _mm256_castsi256_ps(_mm256_set1_epi32(-1)));
}
// 16 vectors' lane sums as one vector: a transposing tree (the first level only renames halves).
SMGS_FI VF reduce16(const VF* v) {
  __m256 t[8][2];
  for (int i = 0; i < 8; ++i) {  // t[i] = [8 partials of v[2i] | 8 partials of v[2i+1]]
    t[i][0] = _mm256_add_ps(lo(v[2 * i]), hi(v[2 * i]));
    t[i][1] = _mm256_add_ps(lo(v[2 * i + 1]), hi(v[2 * i + 1]));
  }
  // from here on each 256-bit register holds one vector's partials per 128-bit lane:
  // u[i] = [4 of v[4i] | 4 of v[4i+1]], [4 of v[4i+2] | 4 of v[4i+3]]
  __m256 u[4][2];
  for (int i = 0; i < 4; ++i)
    for (int h = 0; h < 2; ++h)
      u[i][h] = _mm256_add_ps(_mm256_permute2f128_ps(t[2 * i][h], t[2 * i + 1][h], 0x20),
                              _mm256_permute2f128_ps(t[2 * i][h], t[2 * i + 1][h], 0x31));
  // u[i][h] lane 0-3: v[4i+h... ]; see the index bookkeeping in the final store
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
  // s[h] lane (128-bit half g, element k) holds the sum of v[8·(k&1) ... ]: reorder by a table
  alignas(32) float raw[16], out[16];
  _mm256_store_ps(raw, s[0]);
  _mm256_store_ps(raw + 8, s[1]);
  // lane bookkeeping: t[i][h] holds v[2i+h]; u[i][h] lanes 0-3 ← t[2i][h], 4-7 ← t[2i+1][h], i.e.
  // v[4i+h] and v[4i+2+h]; w[i][h] 128-bit lane L, pairs (0,1) ← u[2i][h] lane L, (2,3) ← u[2i+1][h]
  // lane L; s[h] element 2L+... see kOrder (computed once by hand and checked by the tests).
  constexpr int kOrder[16] = {0, 4, 8, 12, 2, 6, 10, 14, 1, 5, 9, 13, 3, 7, 11, 15};
  for (int k = 0; k < 16; ++k) out[kOrder[k]] = raw[k];
  return load(out);
}
#elif defined(SMGS_ISA_NEON)
SMGS_FI float32x4_t q(VF x, int i) {
  float32x4_t r;
  std::memcpy(&r, reinterpret_cast<const char*>(&x.v) + 16 * i, 16);
  return r;
}
SMGS_FI VF join4(float32x4_t a, float32x4_t b, float32x4_t c, float32x4_t d) {
  VF r;
  std::memcpy(reinterpret_cast<char*>(&r.v), &a, 16);
  std::memcpy(reinterpret_cast<char*>(&r.v) + 16, &b, 16);
  std::memcpy(reinterpret_cast<char*>(&r.v) + 32, &c, 16);
  std::memcpy(reinterpret_cast<char*>(&r.v) + 48, &d, 16);
  return r;
}
SMGS_FI VF fmadd(VF a, VF b, VF c) {
  return join4(vfmaq_f32(q(c, 0), q(a, 0), q(b, 0)), vfmaq_f32(q(c, 1), q(a, 1), q(b, 1)),
               vfmaq_f32(q(c, 2), q(a, 2), q(b, 2)), vfmaq_f32(q(c, 3), q(a, 3), q(b, 3)));
}
SMGS_FI VF vsqrt(VF x) { return join4(vsqrtq_f32(q(x, 0)), vsqrtq_f32(q(x, 1)), vsqrtq_f32(q(x, 2)), vsqrtq_f32(q(x, 3))); }
SMGS_FI VF vrcp(VF x) { return VF(1.0f) / x; }
SMGS_FI VF vsqrt_pos(VF x) { return vsqrt(x); }
SMGS_FI unsigned bits(VM m) {
  const uint32x4_t w = {1u, 2u, 4u, 8u};
  unsigned r = 0;
  for (int i = 0; i < 4; ++i) {
    uint32x4_t x;
    std::memcpy(&x, reinterpret_cast<const char*>(&m.m) + 16 * i, 16);
    r |= vaddvq_u32(vandq_u32(x, w)) << (4 * i);
  }
  return r;
}
SMGS_FI bool any(VM m) {
  uint32x4_t a[4];
  std::memcpy(a, &m.m, sizeof a);
  return vmaxvq_u32(vorrq_u32(vorrq_u32(a[0], a[1]), vorrq_u32(a[2], a[3]))) != 0;
}
#else  // scalar
SMGS_FI VF fmadd(VF a, VF b, VF c) { return a * b + c; }  // no FMA in the baseline ISA: two roundings
SMGS_FI VF vsqrt(VF x) {
  VF r;
  for (int i = 0; i < kLanes; ++i) r.v[i] = std::sqrt(x.v[i]);
  return r;
}
SMGS_FI VF vrcp(VF x) { return VF(1.0f) / x; }
SMGS_FI VF vsqrt_pos(VF x) { return vsqrt(x); }
SMGS_FI unsigned bits(VM m) {
  unsigned r = 0;
  for (int i = 0; i < kLanes; ++i) r |= unsigned(m.m[i] & 1) << i;
  return r;
}
SMGS_FI bool any(VM m) { return bits(m) != 0; }
#endif

SMGS_FI bool all(VM m) { return bits(m) == 0xFFFFu; }
SMGS_FI int popcount(VM m) { return __builtin_popcount(bits(m)); }
SMGS_FI VM mask_from_bits(unsigned b) {
  const I16v lane = {1 << 0, 1 << 1, 1 << 2, 1 << 3, 1 << 4, 1 << 5, 1 << 6, 1 << 7,
                     1 << 8, 1 << 9, 1 << 10, 1 << 11, 1 << 12, 1 << 13, 1 << 14, 1 << 15};
  return {(lane & int32_t(b)) != 0};
}
SMGS_FI float hsum(VF x) {
  float s = 0.f;
  for (int i = 0; i < kLanes; ++i) s += x.v[i];
  return s;
}
#if !defined(SMGS_ISA_AVX2)
SMGS_FI VF reduce16(const VF* v) {
  alignas(64) float r[kLanes];
  for (int k = 0; k < kLanes; ++k) r[k] = hsum(v[k]);
  return load(r);
}
#endif

// Round to nearest even for |x| < 2^22: adding and subtracting 1.5·2^23 leaves the integer part
// (exact without -ffast-math, which no path uses).
SMGS_FI VF round_small(VF x) {
  const VF magic(12582912.0f);
  return (x + magic) - magic;
}
SMGS_FI I16v to_int(VF x) { return __builtin_convertvector(x.v, I16v); }
SMGS_FI VF pow2i(I16v n) { return (F16v)((n + 127) << 23); }  // 2^n for n in [-126, 127]

SMGS_FI VF vexp(VF x) {
  using namespace cephes;
  VF v = max_c(min_c(x, VF(kExpHi)), VF(kExpLo));
  const VF n = round_small(v * VF(kLog2e));
  VF r = v - n * VF(kLn2Hi);  // exact: n·kLn2Hi has at most 8 + 9 significant bits
  r = fmadd(n, VF(-kLn2Lo), r);
  const VF r2 = r * r;
  const VF e01 = fmadd(VF(kE1), r, VF(kE0));
  const VF e23 = fmadd(VF(kE3), r, VF(kE2));
  const VF e45 = fmadd(VF(kE5), r, VF(kE4));
  const VF p = fmadd(fmadd(e45, r2, e23), r2, e01);
  const VF y = fmadd(p, r2, r) + VF(1.0f);
  // 2^n as two factors so that n in [-150, 128] stays representable: under/overflow go to the
  // denormals / 0 / inf as a true exp would.
  const I16v ni = to_int(n);
  const I16v n1 = ni >> 1;
  return y * pow2i(n1) * pow2i(ni - n1);
}

SMGS_FI VF vlog(VF x) {
  using namespace cephes;
  // denormals: scale into the normal range first
  const VM sub = x < VF(1.17549435e-38f);
  const VF xs = sel(sub, x * VF(8388608.0f), x);
  const I16v b = (I16v)xs.v;
  VF e(__builtin_convertvector(((b >> 23) & 0xFF) - 127, F16v));
  e = sel(sub, e - VF(23.0f), e);
  VF m((F16v)((b & 0x007FFFFF) | 0x3F800000));  // in [1, 2)
  const VM big = m > VF(kSqrtHalf2);
  m = sel(big, m * VF(0.5f), m);
  e = sel(big, e + VF(1.0f), e);
  const VF t = m - VF(1.0f);
  const VF z = t * t;
  VF y(kL[0]);
  for (int i = 1; i < 9; ++i) y = fmadd(y, t, VF(kL[i]));
  y = y * t * z;
  y = fmadd(e, VF(kLn2Lo), y);
  y = fmadd(z, VF(-0.5f), y);
  VF r = t + y;
  r = fmadd(e, VF(kLn2Hi), r);
  const float inf = std::numeric_limits<float>::infinity(), nan = std::numeric_limits<float>::quiet_NaN();
  r = sel(x == VF(0.0f), VF(-inf), r);
  r = sel(x == VF(inf), VF(inf), r);
  return sel(mor(x < VF(0.0f), x != x), VF(nan), r);
}
#endif

}  // namespace smgs
