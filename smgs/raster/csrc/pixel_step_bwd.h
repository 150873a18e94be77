// The adjoint of one compositing step of a pixel that takes its splats in its own order
// (sort="per_pixel" and the leading-splat map): the backward of the CPU backend's re-sorting window
// (cpu_pixel.cpp) and of its CUDA twin (cuda_pixel.cu) run this same code. The step is `step` in
// either file (fwd_block's step, cpu_tiles.h, for one pixel); the per-splat math is splat_math.h's.
#pragma once

#include "packed_row.h"
#include "splat_math.h"

namespace smgs {

// The adjoint of one composited step, back to front (as bwd_block in cpu_tiles.h): splat row
// `s` at the pixel centre (fx, fy), the state before the step (T, A, dp, pp; pre(c0, h) puts its
// channel state at channels c0..c0+3 into h, read only by a softmax step) and whether the step is
// in the head. Takes the adjoints of
// the state after the step (gT, gA, gdp, gpp, gC: colours, then depth) to those before it, and hands
// the splat's gradients to add(column of the packed row, value), always in the same order.
template <bool GEF, bool SOFT, class Ch, class Pre, class Add>
SMGS_HD inline void pixel_step_bwd(const float* s, float fx, float fy, float T, float A, float dp, float pp, bool head,
                                   bool solved, int nch, Ch& gC, Pre&& pre, Add&& add, float& gT, float& gA,
                                   float& gdp, float& gpp) {
  const int nc = nch + 1;
  const Factor f{s[P_CA], s[P_CB], s[P_CC]};
  const float al = GEF ? s[P_AL] : 1.f;
  const Quad<float> q = splat_quad(fx, fy, s[P_MX], s[P_MY], f);
  const Absorb<float> ab = splat_absorb<GEF>(q.q, s[P_O], al);
  const float a = ab.a, p = -q.q, d = s[P_D];
  const bool soft = head && A > 0.f;
  SoftFwd<float> sf{};
  float aT = a * T, r = 1.f, wk = 1.f;   // a head step at A = 0 has wk = 1 (`step`)
  if (soft) {
    sf = softmax_fwd(T, A, dp, pp, a, p, d, s[P_BE], s[P_GA], solved);
    aT = sf.aT;
    r = sf.r;
    wk = sf.wk;
  }
  // adjoint of C' = C·r + c·aT (depth is channel nch)
  float g_aT = 0.f, g_r = 0.f;
  for (int c = 0; c < nch; ++c) {
    g_aT += gC[c] * s[P_COL + c];
    add(P_COL + c, gC[c] * aT);
  }
  g_aT += gC[nch] * d;
  float g_d = gC[nch] * aT, g_p = 0.f, g_wk = 0.f, g_a, gTpre;
  if (soft)
    for (int c0 = 0; c0 < nc; c0 += 4) {   // four channels at a time (CUDA keeps them as a float4)
      float h[4];
      pre(c0, h);
      for (int m = 0; m < 4 && c0 + m < nc; ++m) {
        g_r += gC[c0 + m] * h[m];
        gC[c0 + m] = gC[c0 + m] * r;
      }
    }
  if (head) {   // adjoint of the running means d' = d + (d_k - d)·wk, p' likewise
    g_wk = gdp * (d - dp) + gpp * (p - pp);
    g_d += gdp * wk;
    g_p = gpp * wk;
    gdp -= gdp * wk;
    gpp -= gpp * wk;
  }
  if (soft) {
    const SoftGrad<float> sg = softmax_bwd(sf, T, A, dp, pp, a, p, s[P_BE], s[P_GA], solved, gT, gA, g_r, g_aT, g_wk);
    gTpre = sg.T;
    gA = sg.A;
    g_a = sg.a;
    g_p += sg.p;
    g_d += sg.d;
    gdp += sg.dp;
    gpp += sg.pp;
    add(P_BE, sg.beta);
    add(P_GA, sg.gamma);
  } else if (SOFT) {
    float gAv;
    vanilla_coef_bwd(T, A, a, gT, gA, g_aT, g_wk, gTpre, gAv, g_a);
    gA = gAv;
  } else {
    vanilla_step_bwd(T, a, g_aT + gA, gT, gTpre, g_a);   // A' = A + aT: dL/dA passes through
  }
  gT = gTpre;
  add(P_D, g_d);
  const KernGrad<float> kg = splat_kernel_bwd<GEF>(q, ab, f, s[P_O], al, g_a, g_p);
  add(P_MX, kg.mx);
  add(P_MY, kg.my);
  add(P_CA, kg.ca);
  add(P_CB, kg.cb);
  add(P_CC, kg.cc);
  add(P_O, kg.o);
  if (GEF) add(P_AL, kg.alpha);
}

}  // namespace smgs
