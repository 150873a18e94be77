// Per-splat math of the smgs renderer: the forward step of Algorithm 1 (Softmax-GS supplementary)
// and its hand-written adjoint. The one header every compiled backend includes.
//
// Every function is a template over a lane type V: `float` (one pixel per thread, e.g. a CUDA
// kernel) or a SIMD vector of pixels (the CPU kernel). The code is branch-free on per-pixel values
// (`sel` instead of `if`), so one source serves both. The lane type provides, found by overload or
// argument-dependent lookup: + - * / and unary -, comparisons giving a mask, mand/mor/mnot on masks,
// sel(mask, a, b), min_c/max_c(x, c) (NaN in x propagates, as torch.clamp), vabs, vsqrt, vexp, vlog,
// vrcp (1/x) and vsqrt_pos (√x), both only for x > 0 normal, where a SIMD backend may use a fast
// approximation accurate to ~1 ulp.
// The scalar overloads are below. No containers, no host-only calls.
//
// The arithmetic is a transcription of smgs/raster/reference.py (the oracle) in the same operation
// order, so that the float32 results agree with it to rounding; see that file's docstring for why
// each stable form is used. Adjoints reverse each forward statement in turn. One deliberate change:
// every quotient by the same denominator (U, S, E, Q) multiplies by one shared reciprocal, since
// divisions dominate the cost of a step (a rounding-level change, ~1 ulp); and the solved softmax
// step uses the sigmoid weights without their common normaliser (see softmax_fwd).
#pragma once

#if defined(__CUDACC__)
#define SMGS_HD __host__ __device__ __attribute__((always_inline))  // __forceinline__ would repeat `inline`
#elif defined(__GNUC__)
// Forced: a call that returns SoftFwd (27 vectors) through memory costs more than the step itself.
#define SMGS_HD __attribute__((always_inline))
#else
#define SMGS_HD
#endif

#include <math.h>

namespace smgs {

// Mirrors smgs/raster/constants.py (tests/test_raster_cpu.py checks they agree).
constexpr float kAlphaMax = 0.99f;            // a = min(0.99, o·kernel)
constexpr float kAlphaMin = 1.0f / 255.0f;    // a splat with a < 1/255 at a pixel is skipped there
#ifndef SMGS_T_MIN
#define SMGS_T_MIN 1e-4                       // a double literal: kTStop is formed in double, as in Python
#endif
constexpr float kTMin = float(SMGS_T_MIN);    // stop before T < 1e-4 (a variant build may set another)
constexpr double kTStopSlack = 1e-5;          // T_STOP_SLACK: float32 rounding at the a = 0.99 clamp
constexpr float kTStop = float(SMGS_T_MIN * (1.0 - kTStopSlack));  // the threshold actually tested
constexpr float kQMax = 4.5f;                 // -P_MIN: reach only inside the 3σ ellipse
constexpr float kExpArgMax = 80.0f;           // -EXP_ARG_MIN: exp(-min(e, 80))
constexpr float kDecayArgMax = 1e3f;          // DECAY_ARG_MAX: γ|Δd| capped where s = 0 anyway
constexpr float kPixelCenter = 0.5f;
constexpr float kTiny = 1.17549435e-38f;       // TINY: the smallest normal float32
constexpr int kTileSize = 16;

// ---- scalar lane primitives ---------------------------------------------------------------------
SMGS_HD inline bool mand(bool a, bool b) { return a && b; }
SMGS_HD inline bool mor(bool a, bool b) { return a || b; }
SMGS_HD inline bool mnot(bool a) { return !a; }
SMGS_HD inline float sel(bool m, float a, float b) { return m ? a : b; }
SMGS_HD inline float min_c(float x, float c) { return c < x ? c : x; }   // NaN x -> x
SMGS_HD inline float max_c(float x, float c) { return c > x ? c : x; }
SMGS_HD inline float vabs(float x) { return fabsf(x); }
SMGS_HD inline float vsqrt(float x) { return sqrtf(x); }
SMGS_HD inline float vexp(float x) { return expf(x); }
SMGS_HD inline float vlog(float x) { return logf(x); }
#if defined(SMGS_CUDA_FAST) && defined(__CUDA_ARCH__)
// The opt-in CUDA kernels (cuda_v2_kernel.cu, docs/cuda.md): the MUFU approximations (~1 ulp, as a
// SIMD lane's), for x > 0 normal only, as documented above.
SMGS_HD inline float vrcp(float x) {
  float r;
  asm("rcp.approx.f32 %0, %1;" : "=f"(r) : "f"(x));
  return r;
}
SMGS_HD inline float vsqrt_pos(float x) {
  float r;
  asm("sqrt.approx.f32 %0, %1;" : "=f"(r) : "f"(x));
  return r;
}
#else
SMGS_HD inline float vrcp(float x) { return 1.0f / x; }
SMGS_HD inline float vsqrt_pos(float x) { return sqrtf(x); }
#endif
// a·b and a + b rounded on their own, never fused into an FMA: the arithmetic behind the reach,
// skip and stop decisions, so that a kernel built with FMA contraction (the opt-in CUDA kernels)
// decides as the other backends do. Elsewhere (contraction off) they are the plain operators.
template <class V>
SMGS_HD inline V mul_rn(V a, V b) { return a * b; }
template <class V>
SMGS_HD inline V add_rn(V a, V b) { return a + b; }
SMGS_HD inline float mul_rn(float a, float b) {
#if defined(__CUDA_ARCH__)
  return __fmul_rn(a, b);
#else
  return a * b;
#endif
}
SMGS_HD inline float add_rn(float a, float b) {
#if defined(__CUDA_ARCH__)
  return __fadd_rn(a, b);
#else
  return a + b;
#endif
}

// ---- the kernel: q = -p, the GEF exponent and the absorbance a ----------------------------------

// q = -p = ½(a·dx² + 2b·dx·dy + c·dy²) (Alg. 1 line 4), dx = pixel centre - mean, evaluated in the
// LDLᵀ form q = ½a·w² + ½s·dy², w = dx + (b/a)·dy, s = c - b²/a (the Schur complement). Summed as
// written, the three terms of an elongated splat (condition number κ) cancel to an absolute error of
// ~eps·λmax·|d|², up to 0.1 in float32 at κ = 1e8; here both terms are >= 0 for a positive-definite
// conic and only w = ±|u|/cos θ (u the distance across the thin axis) cancels, so the error drops to
// ~eps·√(λmax·q)·|d| (tests/test_raster_quad.py). The factor is formed once per splat in double
// (splat_factor) and stored in the conic's three slots of the packed row: (½a, b/a, ½s); it costs
// fewer operations per pixel than the summed form. a = 0 (never positive definite) cannot be
// pivoted on: it stores (0, b, ½c) and is evaluated as b·dx·dy + ½c·dy².
struct Factor {
  float ha, r, hs;
};

SMGS_HD inline Factor splat_factor(float ca, float cb, float cc) {
  if (ca == 0.f) return {0.f, cb, 0.5f * cc};
  const double a = ca, b = cb, c = cc;
  const double det = a * c - b * b;   // exact products of float32 inputs: one rounding in double
  return {0.5f * ca, float(b / a), float(0.5 * (det / a))};
}

template <class V>
struct Quad {
  V dx, dy, w, qraw, q;
};

template <class V>
SMGS_HD inline Quad<V> splat_quad(V px, V py, float mx, float my, Factor f) {
  Quad<V> k;
  k.dx = px - V(mx);
  k.dy = py - V(my);
  // mul_rn/add_rn: q decides reach (q <= 4.5) and the absorbance (a >= 1/255), never fused
  if (f.ha != 0.f) {   // per splat, so the same branch for every lane
    k.w = add_rn(k.dx, mul_rn(V(f.r), k.dy));
    k.qraw = add_rn(mul_rn(V(f.ha), mul_rn(k.w, k.w)), mul_rn(V(f.hs), mul_rn(k.dy, k.dy)));
  } else {
    k.w = k.dx;
    k.qraw = add_rn(mul_rn(V(f.r), mul_rn(k.dx, k.dy)), mul_rn(V(f.hs), mul_rn(k.dy, k.dy)));
  }
  k.q = max_c(k.qraw, V(0.0f));   // an indefinite conic has qraw < 0 somewhere
  return k;
}

// e = q (3dgs, softmax_only) or q^α (GEF, Alg. 1 line 5) with q^α := 0 at q = 0, kernel exp(-e),
// a = min(0.99, o·kernel).
template <class V>
struct Absorb {
  V lq, e, kern, oa, a;
};

template <bool GEF, class V>
SMGS_HD inline Absorb<V> splat_absorb(V q, float o, float alpha) {
  Absorb<V> s;
  if (GEF) {
    auto pos = q > V(0.0f);
    s.lq = vlog(sel(pos, q, V(1.0f)));
    s.e = sel(pos, vexp(V(alpha) * s.lq), V(0.0f));
  } else {
    s.lq = V(0.0f);
    s.e = q;
  }
  s.kern = vexp(-min_c(s.e, V(kExpArgMax)));
  s.oa = V(o) * s.kern;
  s.a = min_c(s.oa, V(kAlphaMax));
  return s;
}

// Depth along the pixel's ray d = (u, v, 1) (camera space) where the splat's 3D response peaks
// (sort="per_pixel", StopThePop): t* = b·d / dᵀQd with c = (Qxx, Qxy, Qxz, Qyy, Qyz, Qzz, bx, by, bz)
// from smgs/raster/ray_depth.py (Q the splat's inverse covariance up to scale, b = Qμ); `fallback`
// (the centre depth) where dᵀQd vanishes. The twin of peak_depth in smgs/raster/reference.py.
// Written with mul_rn/add_rn in the order the plain expression evaluates: the key orders each
// pixel's splats, so a kernel built with FMA contraction (cuda_pixel.cu) must key them as the CPU
// window does, bit for bit (n_contrib and the leaders are compared exactly).
SMGS_HD inline float peak_depth(float u, float v, const float* c, float fallback) {
  // c6·u + c7·v + c8
  const float num = add_rn(add_rn(mul_rn(c[6], u), mul_rn(c[7], v)), c[8]);
  // c0·u·u + c3·v·v + c5 + 2·(c1·u·v + c2·u + c4·v)
  const float quad = add_rn(add_rn(mul_rn(mul_rn(c[0], u), u), mul_rn(mul_rn(c[3], v), v)), c[5]);
  const float cross = add_rn(add_rn(mul_rn(mul_rn(c[1], u), v), mul_rn(c[2], u)), mul_rn(c[4], v));
  const float den = add_rn(quad, mul_rn(2.f, cross));
  return den > mul_rn(1e-12f, add_rn(add_rn(mul_rn(u, u), mul_rn(v, v)), 1.f)) ? num / den : fallback;
}

// Adjoint of splat_quad + splat_absorb: from dL/da and dL/dp (p = -q) to the splat's parameters.
template <class V>
struct KernGrad {
  V mx, my, ca, cb, cc, o, alpha;
};

template <bool GEF, class V>
SMGS_HD inline KernGrad<V> splat_kernel_bwd(const Quad<V>& k, const Absorb<V>& s, Factor f, float o,
                                            float alpha, V g_a, V g_p) {
  KernGrad<V> g;
  auto pass_a = s.oa <= V(kAlphaMax);                       // clamp(max=0.99) passes at <=
  g.o = sel(pass_a, g_a * s.kern, V(0.0f));
  V g_kern = sel(pass_a, g_a * V(o), V(0.0f));
  V g_e = sel(s.e <= V(kExpArgMax), -(g_kern * s.kern), V(0.0f));
  V g_q;
  if (GEF) {
    // d(q^α)/dq = α·q^α/q, d(q^α)/dα = q^α·ln q; both := 0 at q = 0 (infinite for α < 1)
    auto pos = k.q > V(0.0f);
    g_q = sel(pos, g_e * V(alpha) * (s.e / sel(pos, k.q, V(1.0f))), V(0.0f));
    g.alpha = sel(pos, g_e * s.e * s.lq, V(0.0f));
  } else {
    g_q = g_e;
    g.alpha = V(0.0f);
  }
  g_q = g_q - g_p;
  g_q = sel(k.qraw >= V(0.0f), g_q, V(0.0f));                // clamp(min=0) passes at >=
  V h = V(0.5f) * g_q;
  g.ca = h * k.dx * k.dx;
  g.cc = h * k.dy * k.dy;
  g.cb = g_q * k.dx * k.dy;
  // dq/dd = Q·d = (a·w, b·w + s·dy) in the factored form: no cancellation either
  V qx, qy;
  if (f.ha != 0.f) {
    const V aw = V(2.0f * f.ha) * k.w;
    qx = aw;
    qy = V(f.r) * aw + V(2.0f * f.hs) * k.dy;
  } else {
    qx = V(f.r) * k.dy;
    qy = V(2.0f * f.hs) * k.dy + V(f.r) * k.dx;
  }
  g.mx = -(g_q * qx);
  g.my = -(g_q * qy);
  return g;
}

// ---- one compositing step, as coefficients --------------------------------------------------------
// Both steps update the pixel state (T, A, C[], d_past, p_past) as
//   T' = Tn, A' = An, C' = C·r + c·aT, d' = d + (d_k - d)·wk, p' = p + (p_k - p)·wk,
// so the colour update ("apply") is shared and the modes differ only in (Tn, An, r, aT, wk).
template <class V>
struct Coef {
  V Tn, An, r, aT, wk;
};

// 3DGS front-to-back step; wk only matters where softmax steps follow (running means).
template <class V>
SMGS_HD inline Coef<V> vanilla_coef(V T, V A, V a) {
  Coef<V> c;
  c.aT = a * T;
  c.An = A + c.aT;
  c.wk = c.aT / c.An;  // a true quotient: the first step's wk must be exactly 1 (mean of equal depths)
  c.Tn = T * (V(1.0f) - a);
  c.r = V(1.0f);
  return c;
}

// Adjoint of vanilla_coef: given dL/d(Tn, An, aT, wk) (dL/dr is unused, r ≡ 1), returns dL/dT,
// dL/dA, dL/da.
template <class V>
SMGS_HD inline void vanilla_coef_bwd(V T, V A, V a, V g_Tn, V g_An, V g_aT, V g_wk, V& g_T, V& g_A,
                                     V& g_a) {
  V aT = a * T;
  V U = A + aT;
  V iU = vrcp(U);
  V wk = aT * iU;
  g_aT = g_aT + g_wk * iU;
  V g_U = g_An - g_wk * wk * iU;
  g_A = g_U;
  g_aT = g_aT + g_U;
  g_a = g_aT * T - g_Tn * T;
  g_T = g_aT * a + g_Tn * (V(1.0f) - a);
}

// Adjoint of the plain 3DGS step C' = C + c·aT, A' = A + aT, T' = T(1 - a), aT = a·T, where the
// running means are not needed (no softmax step follows): dL/d(aT, T') -> dL/dT, dL/da.
template <class V>
SMGS_HD inline void vanilla_step_bwd(V T, V a, V g_aT, V g_Tn, V& g_T, V& g_a) {
  g_a = g_aT * T - g_Tn * T;
  g_T = g_aT * a + g_Tn * (V(1.0f) - a);
}

// Softmax-competition step (Alg. 1 lines 7-27), the stable forms of reference.softmax_step.
// Valid where A > 0 and a > 0 (the caller masks other lanes). `solved` selects eq. (15) solved
// (default) or as printed in line 14.
template <class V>
struct SoftFwd {
  V T0, U, iU, w_cur, w_past, h_cur, h_past, S, iS, t_past, X, E, iE, t_cur, dd, ad, s, b_past, b_cur,
      diff, sq, Q, iQ, m, a_cur, F, R1, r, T_past, aT, wk;
  decltype(V() < V()) flat, exact;
};

template <class V>
SMGS_HD inline SoftFwd<V> softmax_fwd(V T, V A, V dp, V pp, V a, V p, float d, float beta, float gamma,
                                      bool solved) {
  SoftFwd<V> f;
  const V one(1.0f), zero(0.0f);
  f.T0 = T * (one - a);                       // line 7, the original transmittance
  f.U = A + a * T;                            // 1 - T0 without cancellation
  f.iU = vrcp(f.U);
  V x = V(beta) * (p - pp);                   // line 9
  // w_cur = σ(x), w_past = σ(-x) (line 11 as a second sigmoid, never 1 - w_cur): one exp.
  // Solved eq. (15): every later quantity is a ratio of h_cur, h_past (t_past, t_cur, F), so the
  // common factor 1/(1 + e^-|x|) is left out: (w_cur, w_past) = (1, e^-x) or (e^x, 1), which saves
  // a reciprocal on the step's dependency chain. The printed form mixes h_cur with t_past, so it
  // keeps the normalised weights.
  V ex = vexp(-vabs(x));
  auto xpos = x >= zero;
  if (solved) {
    f.w_cur = sel(xpos, one, ex);
    f.w_past = sel(xpos, ex, one);
  } else {
    V big = vrcp(one + ex), small = ex * big;
    f.w_cur = sel(xpos, big, small);
    f.w_past = sel(xpos, small, big);
  }
  f.h_cur = f.w_cur * a;                      // line 10
  f.h_past = f.w_past * A;                    // line 12
  f.S = f.h_past + f.h_cur;
  f.iS = vrcp(f.S);
  f.t_past = f.h_past * f.U * f.iS;           // eq. (15), ã_past
  f.X = solved ? f.h_past : f.t_past;         // solved: un-updated â_past; printed: line 14
  f.E = f.h_cur + f.X * f.T0;
  // E falls below the float32 normal range only where T0 did and the current splat's softmax weight
  // did too (β·Δp beyond ~90, behind ~19 saturated splats): 0/0 at E = 0, and rcp14 of a denormal
  // is inf. There ã_past = U ≈ 1 already closes the pixel, so ã_cur := 0 (the limit as w_cur -> 0
  // first); iE = 0 also zeroes the adjoint of this step. Every backend uses this threshold.
  f.iE = sel(f.E >= V(kTiny), vrcp(f.E), zero);
  f.t_cur = f.h_cur * f.U * f.iE;
  f.dd = V(d) - dp;                           // line 15, γ|Δd| := 0 at Δd = 0, capped where s = 0
  f.ad = vabs(f.dd);
  auto z = f.dd == zero;
  f.flat = mor(z, V(gamma) * f.ad > V(kDecayArgMax));
  V g = sel(f.flat, sel(z, zero, V(kDecayArgMax)), V(gamma) * f.ad);
  f.s = vexp(-g);
  f.b_past = f.s * f.t_past + (one - f.s) * A;   // line 16
  f.b_cur = f.s * f.t_cur + (one - f.s) * a;     // line 17
  // line 18, smaller root of (1 - m·ā_past)(1 - m·ā_cur) = T0 as 2C/(A + √D), D a sum of
  // non-negative terms; m = 1 exactly where it is 1 by construction
  f.diff = f.b_cur - f.b_past;
  V D = f.diff * f.diff + V(4.0f) * f.b_cur * f.b_past * f.T0;
  f.sq = vsqrt_pos(D);                        // D > 0: b_cur and b_past are never both 0
  f.Q = f.b_past + f.b_cur + f.sq;
  f.iQ = vrcp(f.Q);
  f.exact = mor(f.s == zero, mand(f.s == one, solved ? (zero == zero) : (zero != zero)));
  f.m = sel(f.exact, one, V(2.0f) * f.U * f.iQ);
  f.a_cur = f.m * f.b_cur;                    // line 20
  f.F = f.s * f.w_past * f.U * f.iS;
  f.R1 = f.F + (one - f.s);
  f.r = f.m * f.R1;                           // ā_past / a_past, line 22
  f.T_past = T + A * (one - f.r);             // lines 19, 21 without cancellation
  f.aT = f.a_cur * f.T_past;                  // line 24
  f.wk = f.aT * f.iU;                         // share in the running means, lines 25-26
  return f;
}

template <class V>
SMGS_HD inline Coef<V> softmax_coef(const SoftFwd<V>& f) {
  Coef<V> c;
  c.Tn = f.T0;
  c.An = f.U;
  c.r = f.r;
  c.aT = f.aT;
  c.wk = f.wk;
  return c;
}

template <class V>
struct SoftGrad {
  V T, A, dp, pp, a, p, d, beta, gamma;
};

// Adjoint of softmax_fwd: dL/d(Tn, An, r, aT, wk) -> dL/d(T, A, d_past, p_past, a, p, d, β, γ).
// Each block reverses one forward statement, bottom to top.
template <class V>
SMGS_HD inline SoftGrad<V> softmax_bwd(const SoftFwd<V>& f, V T, V A, V dp, V pp, V a, V p, float beta,
                                       float gamma, bool solved, V g_Tn, V g_An, V g_r, V g_aT, V g_wk) {
  const V one(1.0f), zero(0.0f);
  SoftGrad<V> g;
  V g_T0 = g_Tn, g_U = g_An;
  // wk = aT / U
  g_aT = g_aT + g_wk * f.iU;
  g_U = g_U - g_wk * f.wk * f.iU;
  // aT = a_cur · T_past
  V g_acur = g_aT * f.T_past;
  V g_Tpast = g_aT * f.a_cur;
  // T_past = T + A·(1 - r)
  g.T = g_Tpast;
  g.A = g_Tpast * (one - f.r);
  g_r = g_r - g_Tpast * A;
  // r = m · R1
  V g_m = g_r * f.R1;
  V g_R1 = g_r * f.m;
  // R1 = F + (1 - s), F = s·w_past·U / S
  V g_s = -g_R1;
  V g_swp = g_R1 * f.U * f.iS;
  g_U = g_U + g_R1 * (f.s * f.w_past) * f.iS;
  V g_S = -(g_R1 * f.F * f.iS);
  g_s = g_s + g_swp * f.w_past;
  V g_wpast = g_swp * f.s;
  // a_cur = m · b_cur
  g_m = g_m + g_acur * f.b_cur;
  V g_bcur = g_acur * f.m;
  V g_bpast = zero;
  // m = 2U / Q (no gradient where m := 1), Q = b_past + b_cur + √D, D = diff² + 4·b_cur·b_past·T0
  g_m = sel(f.exact, zero, g_m);
  g_U = g_U + g_m * V(2.0f) * f.iQ;
  V g_Q = -(g_m * f.m * f.iQ);
  g_bpast = g_bpast + g_Q;
  g_bcur = g_bcur + g_Q;
  V g_D = sel(f.exact, zero, V(0.5f) * g_Q * vrcp(f.sq));
  g_bcur = g_bcur + g_D * (V(2.0f) * f.diff + V(4.0f) * f.b_past * f.T0);
  g_bpast = g_bpast + g_D * (V(4.0f) * f.b_cur * f.T0 - V(2.0f) * f.diff);
  g_T0 = g_T0 + g_D * V(4.0f) * f.b_cur * f.b_past;
  // b_cur = s·t_cur + (1-s)·a ; b_past = s·t_past + (1-s)·A
  g_s = g_s + g_bcur * (f.t_cur - a) + g_bpast * (f.t_past - A);
  V g_tcur = g_bcur * f.s;
  g.a = g_bcur * (one - f.s);
  V g_tpast = g_bpast * f.s;
  g.A = g.A + g_bpast * (one - f.s);
  // s = exp(-g), g = γ·|Δd| where not flat (constant where flat)
  V g_g = -(g_s * f.s);
  g.gamma = sel(f.flat, zero, g_g * f.ad);
  V sgn = sel(f.dd > zero, one, sel(f.dd < zero, -one, zero));
  V g_dd = sel(f.flat, zero, g_g * V(gamma) * sgn);
  g.d = g_dd;
  g.dp = -g_dd;
  // t_cur = h_cur·U / E, E = h_cur + X·T0
  V g_hcU = g_tcur * f.iE;
  V g_E = -(g_tcur * f.t_cur * f.iE);
  V g_hcur = g_hcU * f.U;
  g_U = g_U + g_hcU * f.h_cur;
  g_hcur = g_hcur + g_E;
  V g_X = g_E * f.T0;
  g_T0 = g_T0 + g_E * f.X;
  V g_hpast = zero;
  if (solved) g_hpast = g_X; else g_tpast = g_tpast + g_X;
  // t_past = h_past·U / S
  V g_hpU = g_tpast * f.iS;
  g_S = g_S - g_tpast * f.t_past * f.iS;
  g_hpast = g_hpast + g_hpU * f.U;
  g_U = g_U + g_hpU * f.h_past;
  // S = h_past + h_cur
  g_hpast = g_hpast + g_S;
  g_hcur = g_hcur + g_S;
  // h_past = w_past·A ; h_cur = w_cur·a
  g_wpast = g_wpast + g_hpast * A;
  g.A = g.A + g_hpast * f.w_past;
  V g_wcur = g_hcur * a;
  g.a = g.a + g_hcur * f.w_cur;
  // w_cur = σ(x), w_past = σ(-x): dσ(x)/dx = w_cur·w_past; solved: the unnormalised weights
  // (1, e^-x) for x >= 0, (e^x, 1) below
  V g_x;
  const V dpp = p - pp;
  if (solved) g_x = sel(V(beta) * dpp >= zero, -(g_wpast * f.w_past), g_wcur * f.w_cur);
  else g_x = (g_wcur - g_wpast) * f.w_cur * f.w_past;
  // x = β·(p - p_past)
  g.beta = g_x * dpp;
  g.p = g_x * V(beta);
  g.pp = -g.p;
  // U = A + a·T
  g.A = g.A + g_U;
  g.a = g.a + g_U * T;
  g.T = g.T + g_U * a;
  // T0 = T·(1 - a)
  g.T = g.T + g_T0 * (one - a);
  g.a = g.a - g_T0 * T;
  return g;
}

}  // namespace smgs
