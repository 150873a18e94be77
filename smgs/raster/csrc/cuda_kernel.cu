// CUDA backend of the smgs renderer: GPU tile binning and depth sort, and compositing forward and
// backward, one thread per pixel and one 256-thread block per 16x16 tile (the 3DGS layout).
//
// Semantics are those of the CPU kernel (cpu_kernel.cpp) and of smgs/raster/reference.py: the same
// conservative 3σ boxes decide which tiles a splat is listed in (so tiling never changes an image),
// the same depth order (ties by index), the same per-pixel reach tests, stop rule and k_max head,
// the same outputs (colour, alpha, depth, final T, regulariser sums, n_contrib, `last`). The
// per-splat math, forward and adjoint, is splat_math.h with the lane type V = float: this file adds
// only the loops, the binning and the bookkeeping around it.
//
// Binning (as 3DGS): per splat its box and tile count; an inclusive prefix sum gives each splat its
// slots; every (tile, splat) pair gets the key tile << 32 | depth bits; cub's radix sort over the
// 32 + ceil(log2(tiles)) key bits (stable, so equal depths stay in index order); a pass over the
// sorted keys writes each tile's [start, end).
//
// Backward: per pixel, back to front over the composited splats. Tail steps (after the pixel's
// softmax head -- its first k_max composited splats, or in patch scope the tile's first k_max list
// entries -- and every step of a mode without softmax) rebuild the state the
// 3DGS way, T_before = T_after / (1 - a). The softmax head is first recomputed front to back and the
// state before each head step (T, A, d_past, p_past, C) saved into per-thread scratch in global
// memory, k_max_eff entries per thread, for one chunk of tiles at a time (so the scratch is
// slots x k_max, never pixels x k_max). Splat gradients are summed over a warp with shuffles and
// added to a per-splat [N, S] buffer with one atomicAdd per warp, splat and parameter.
//
// Compiled without FMA contraction (--fmad=false, see smgs/raster/cuda.py): a·b + c stays two
// roundings, as PyTorch evaluates the reference, so the reach tests see the same numbers.
#include <cuda_runtime.h>

#include <cub/device/device_radix_sort.cuh>
#include <cub/device/device_scan.cuh>

#include <algorithm>
#include <cstdint>

#include "cuda_common.cuh"
#include "cuda_kernel.h"
#include "splat_math.h"

namespace smgs {
namespace cuda {

namespace {

inline int blocks_for(int64_t n, int threads) { return int((n + threads - 1) / threads); }

// ---- binning --------------------------------------------------------------------------------------

// Pixel range of a splat whose float32 q can be <= 4.5: the CPU kernel's splat_box (see there for
// the error bound). Non-finite or non-positive-definite conics, or a bound too loose, cover the whole
// image, which is always correct.
__device__ bool splat_box(float mx, float my, float ca, float cb, float cc, int W, int H, int32_t* out) {
  int x0 = 0, x1 = W - 1, y0 = 0, y1 = H - 1;
  const bool finite = isfinite(mx) && isfinite(my) && isfinite(ca) && isfinite(cb) && isfinite(cc);
  const double a = ca, b = cb, c = cc;
  const double det = a * c - b * b;
  if (finite && a > 0 && c > 0 && det > 0) {
    const double lmax = 0.5 * (a + c) + sqrt(0.25 * (a - c) * (a - c) + b * b);
    const double lmin = det / lmax;
    const double kappa = 1.0 + 2.0 * fabs(b) / lmin;
    const double g = 16.0 * 5.9604644775390625e-8 * kappa;  // 2·γ6 with u = 2^-24
    if (g < 0.5) {
      const double qmax = double(kQMax) / (1.0 - g);
      const double rx = sqrt(2.0 * qmax * c / det), ry = sqrt(2.0 * qmax * a / det);
      const double sx = 1e-6 * (1.0 + fabs(double(mx)) + rx), sy = 1e-6 * (1.0 + fabs(double(my)) + ry);
      const double fx0 = ceil(mx - rx - sx - 0.5), fx1 = floor(mx + rx + sx - 0.5);
      const double fy0 = ceil(my - ry - sy - 0.5), fy1 = floor(my + ry + sy - 0.5);
      if (fx1 < 0 || fy1 < 0 || fx0 > W - 1 || fy0 > H - 1 || fx0 > fx1 || fy0 > fy1) return false;
      x0 = int(fmax(fx0, 0.0));
      x1 = int(fmin(fx1, double(W - 1)));
      y0 = int(fmax(fy0, 0.0));
      y1 = int(fmin(fy1, double(H - 1)));
    }
  }
  out[0] = x0;
  out[1] = x1;
  out[2] = y0;
  out[3] = y1;
  return true;
}

// Depth as bits whose unsigned order is the numeric order, -0 = +0, NaN last (as torch.sort and the
// CPU kernel's depth_key).
__device__ uint32_t depth_bits(float d) {
  if (isnan(d)) return 0xFFFFFFFFu;
  if (d == 0.f) d = 0.f;
  const uint32_t u = __float_as_uint(d);
  return (u & 0x80000000u) ? ~u : (u | 0x80000000u);
}

__global__ void prepare_kernel(SplatsIn in, int W, int H, int S, float* pk, int32_t* box, int64_t* ntiles,
                               uint32_t* dbits) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= in.n) return;
  float* r = pk + int64_t(i) * S;
  r[P_MX] = in.means2d[2 * i];
  r[P_MY] = in.means2d[2 * i + 1];
  const float ca = in.conics[3 * i], cb = in.conics[3 * i + 1], cc = in.conics[3 * i + 2];
  const Factor f = splat_factor(ca, cb, cc);  // the conic's slots hold its factor
  r[P_CA] = f.ha;
  r[P_CB] = f.r;
  r[P_CC] = f.hs;
  r[P_O] = in.opacities[i];
  r[P_D] = in.depths[i];
  r[P_AL] = in.alpha ? in.alpha[i] : 1.f;
  r[P_BE] = in.beta ? in.beta[i] : 0.f;
  r[P_GA] = in.gamma ? in.gamma[i] : 0.f;
  for (int c = 0; c < in.nch; ++c) r[P_COL + c] = in.colors[int64_t(i) * in.nch + c];
  for (int c = 0; c < in.nreg; ++c) r[P_COL + in.nch + c] = in.reg_values[int64_t(i) * in.nreg + c];
  int32_t b[4] = {0, -1, 0, -1};
  // a <= o·1, so o < 1/255 never reaches (NaN never reaches either)
  const bool vis = (r[P_O] >= kAlphaMin) && splat_box(r[P_MX], r[P_MY], ca, cb, cc, W, H, b);
  for (int c = 0; c < 4; ++c) box[4 * i + c] = b[c];
  ntiles[i] = vis ? int64_t(b[1] / kTileSize - b[0] / kTileSize + 1) * (b[3] / kTileSize - b[2] / kTileSize + 1)
                  : 0;
  dbits[i] = depth_bits(r[P_D]);
}

__global__ void emit_kernel(const int32_t* box, const int64_t* ntiles, const int64_t* offs, const uint32_t* dbits,
                            int n, int tiles_x, uint64_t* keys, int32_t* vals) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= n || ntiles[i] == 0) return;
  int64_t k = offs[i] - ntiles[i];
  const int32_t* b = box + 4 * i;
  const uint64_t lo = dbits[i];
  for (int y = b[2] / kTileSize; y <= b[3] / kTileSize; ++y)
    for (int x = b[0] / kTileSize; x <= b[1] / kTileSize; ++x) {
      keys[k] = (uint64_t(uint32_t(y * tiles_x + x)) << 32) | lo;
      vals[k] = i;
      ++k;
    }
}

__global__ void ranges_kernel(const uint64_t* keys, int count, int32_t* ranges) {
  const int k = blockIdx.x * blockDim.x + threadIdx.x;
  if (k >= count) return;
  const uint32_t t = uint32_t(keys[k] >> 32);
  if (k == 0 || uint32_t(keys[k - 1] >> 32) != t) ranges[2 * t] = k;
  if (k == count - 1 || uint32_t(keys[k + 1] >> 32) != t) ranges[2 * t + 1] = k + 1;
}

// ---- compositing helpers ----------------------------------------------------------------------------

// Rows [b0, b0 + nb) of a tile's list into shared memory (row-major, S floats each).
__device__ __forceinline__ void load_rows(float* rows, const Scene& sc, int start, int b0, int nb) {
  const int S = sc.S;
  for (int e = threadIdx.x; e < nb * S; e += kBlock) {
    const int r = e / S;
    rows[e] = sc.pk[int64_t(sc.vals[start + b0 + r]) * S + (e - r * S)];
  }
}

// ---- forward -------------------------------------------------------------------------------------------
template <bool GEF, bool SOFT, int NCT>
__global__ void __launch_bounds__(kBlock) fwd_kernel(Scene sc, FwdOut o, int B) {
  extern __shared__ float rows[];
  const Pixel P(sc, blockIdx.x);
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.nreg;
  const int S = sc.S;
  Chan<NCT> C(NCT ? nullptr : o.chan + P.pix, P.npix);
  float* RG = R ? o.reg + P.pix * (1 + 2 * R) : nullptr;  // reg sums: Σw, Σw·v_r, Σw·v_r²
  if (P.inside) {
    for (int c = 0; c < nc; ++c) C[c] = 0.f;
    for (int c = 0; c < (R ? 1 + 2 * R : 0); ++c) RG[c] = 0.f;
  }
  float T = 1.f, A = 0.f, dp = 0.f, pp = 0.f, dfront = 0.f;
  int cnt = 0, last = 0;
  bool done = !P.inside;
  const bool need_head = SOFT || R > 0;
  unsigned long long pairs = 0;
  for (int b0 = 0; b0 < P.n; b0 += B) {
    if (__syncthreads_count(done) == kBlock) break;  // also keeps the previous batch until all used it
    const int nb = min(B, P.n - b0);
    load_rows(rows, sc, P.start, b0, nb);
    __syncthreads();
    for (int jj = 0; jj < nb && !done; ++jj) {
      const float* s = rows + jj * S;
      ++pairs;
      const Quad<float> k = splat_quad(P.px, P.py, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
      if (!(k.q <= kQMax)) continue;
      const Absorb<float> ab = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]);
      if (!(ab.a >= kAlphaMin)) continue;
      const float a = ab.a;
      const float T0 = T * (1.f - a);
      // the softmax head: the pixel's first k_max composited splats, or (patch scope) the tile's
      // first k_max list entries
      const bool in_head = (sc.patch ? b0 + jj : cnt) < sc.kmax;
      // 3DGS: not composited, the pixel is done. Only where the step is vanilla: inside the softmax
      // head a later splat can take the pixel from those before it (constants.T_MIN).
      if (T0 < kTStop && !(SOFT && in_head)) {
        done = true;
        break;
      }
      const float d = s[P_D];
      const float* col = s + P_COL;
      const bool head = need_head ? in_head : true;
      if (SOFT) {
        const bool soft = head && A > 0.f;
        const float p = -k.q;
        Coef<float> cf = vanilla_coef(T, A, a);
        if (soft) cf = softmax_coef(softmax_fwd(T, A, dp, pp, a, p, d, s[P_BE], s[P_GA], sc.solved));
        for (int c = 0; c < nch; ++c) C[c] = C[c] * cf.r + col[c] * cf.aT;
        C[nch] = C[nch] * cf.r + d * cf.aT;
        if (head) {
          dp = dp + (d - dp) * cf.wk;
          pp = pp + (p - pp) * cf.wk;
        }
        T = cf.Tn;
        A = cf.An;
      } else {
        const float aT = a * T;
        for (int c = 0; c < nch; ++c) C[c] = C[c] + col[c] * aT;
        C[nch] = C[nch] + d * aT;
        A = A + aT;
        T = T0;
      }
      if (R) {  // variance regulariser sums over the first k_max composited splats
        if (head && cnt == 0) dfront = d;
        float w = 1.f / (1.f + (d - dfront) / sc.reg_scale);
        if (!head) w = 0.f;
        RG[0] = RG[0] + w;
        for (int r = 0; r < R; ++r) {
          const float v = s[P_COL + nch + r];
          RG[1 + r] = RG[1 + r] + w * v;
          RG[1 + R + r] = RG[1 + R + r] + w * v * v;
        }
      }
      ++cnt;
      last = b0 + jj + 1;
    }
  }
  if (P.inside) {
    for (int c = 0; c < nch; ++c) {
      float v = C[c];
      if (sc.bg) v = v + T * sc.bg[c];
      o.rgb[P.pix * nch + c] = v;
    }
    o.alpha[P.pix] = A;
    o.depth[P.pix] = A > 0.f ? C[nch] / A : 0.f;
    o.Tf[P.pix] = T;
    o.last[P.pix] = last;
    o.cnt[P.pix] = cnt;
  }
  for (int off = 16; off > 0; off >>= 1) pairs += __shfl_xor_sync(kFull, pairs, off);
  if ((threadIdx.x & 31) == 0 && pairs) atomicAdd(o.pairs, pairs);
}

// ---- backward ----------------------------------------------------------------------------------------------
template <bool GEF, bool SOFT, int NCT>
__global__ void __launch_bounds__(kBlock) bwd_kernel(Scene sc, BwdIn in, BwdWork w, int tile0, int B) {
  extern __shared__ float rows[];
  __shared__ int s_maxlast;
  const Pixel P(sc, tile0 + int(blockIdx.x));
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.nreg;
  const int S = sc.S;
  Chan<NCT> gC(NCT ? nullptr : w.chan + P.pix, P.npix);               // adjoint of the colour state
  Chan<NCT> C1(NCT ? nullptr : w.chan + nc * P.npix + P.pix, P.npix);  // phase 1 colour state
  // head scratch of this thread: entry e, field f at head[(e·esz + f)·slots + slot] (coalesced)
  const int64_t slots = int64_t(gridDim.x) * kBlock;
  const int64_t slot = int64_t(blockIdx.x) * kBlock + threadIdx.x;
  const int esz = 4 + nc;
  auto hd = [&](int e, int f) -> float& { return w.head[(int64_t(e) * esz + f) * slots + slot]; };

  // dL/d outputs -> dL/d final state
  float gT = 0.f, gA = 0.f, T = 1.f;
  int mylast = 0, ncomp = 0;
  if (P.inside) {
    const float Aout = in.alpha[P.pix], dout = in.depth[P.pix];
    const float g_alpha = in.g_alpha[P.pix], g_depth = in.g_depth[P.pix];
    for (int c = 0; c < nch; ++c) {
      gC[c] = in.g_rgb[P.pix * nch + c];
      if (sc.bg) gT = gT + gC[c] * sc.bg[c];  // rgb += T·bg
    }
    const bool posA = Aout > 0.f;
    const float Asafe = posA ? Aout : 1.f;
    gC[nch] = posA ? g_depth / Asafe : 0.f;  // depth = C_d / A
    gA = g_alpha - (posA ? g_depth * dout / Asafe : 0.f);
    T = in.Tf[P.pix];
    mylast = in.last[P.pix];
    ncomp = in.cnt[P.pix];
  }
  if (threadIdx.x == 0) s_maxlast = 0;
  __syncthreads();
  if (mylast) atomicMax(&s_maxlast, mylast);
  __syncthreads();
  const int maxlast = s_maxlast;
  if (maxlast == 0) return;  // block-uniform
  const int kmax = sc.kmax;

  // Phase 1: recompute the pixel's head (its first k_max composited splats, or in patch scope its
  // composited splats among the tile's first k_max list entries) front to back, saving the state
  // before every head step (softmax modes) and taking the regulariser's gradients. Either way the
  // head steps come first in the pixel's order, so entry cnt1 is the head step of ordinal cnt1.
  if ((SOFT || R) && kmax > 0) {
    float T1 = 1.f, A1 = 0.f, dp1 = 0.f, pp1 = 0.f, dfront = 0.f;
    int cnt1 = 0;
    if (P.inside)
      for (int c = 0; c < nc; ++c) C1[c] = 0.f;
    const float* gR = R && P.inside ? in.g_reg + P.pix * (1 + 2 * R) + 1 : nullptr;  // dL/d Σw·v, Σw·v²
    for (int b0 = 0; b0 < maxlast; b0 += B) {
      if (__syncthreads_count(b0 < mylast && (sc.patch ? b0 : cnt1) < kmax) == 0) break;
      const int nb = min(B, maxlast - b0);
      load_rows(rows, sc, P.start, b0, nb);
      __syncthreads();
      for (int jj = 0; jj < nb; ++jj) {
        const bool hv = b0 + jj < mylast && (sc.patch ? b0 + jj : cnt1) < kmax;
        if (!__any_sync(kFull, hv)) break;  // warp-uniform
        const float* s = rows + jj * S;
        bool rv = false;
        float wr = 0.f;
        if (hv) {
          const Quad<float> k = splat_quad(P.px, P.py, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
          if (k.q <= kQMax) {
            const Absorb<float> ab = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]);
            rv = ab.a >= kAlphaMin;  // before `last`: composited, never stopped
            if (rv) {
              const float a = ab.a, d = s[P_D];
              if (SOFT) {
                hd(cnt1, 0) = T1;
                hd(cnt1, 1) = A1;
                hd(cnt1, 2) = dp1;
                hd(cnt1, 3) = pp1;
                for (int c = 0; c < nc; ++c) hd(cnt1, 4 + c) = C1[c];
                const float p = -k.q;
                Coef<float> cf = vanilla_coef(T1, A1, a);
                if (A1 > 0.f) cf = softmax_coef(softmax_fwd(T1, A1, dp1, pp1, a, p, d, s[P_BE], s[P_GA], sc.solved));
                const float* col = s + P_COL;
                for (int c = 0; c < nch; ++c) C1[c] = C1[c] * cf.r + col[c] * cf.aT;
                C1[nch] = C1[nch] * cf.r + d * cf.aT;
                dp1 = dp1 + (d - dp1) * cf.wk;
                pp1 = pp1 + (p - pp1) * cf.wk;
                T1 = cf.Tn;
                A1 = cf.An;
              }
              if (R) {
                if (cnt1 == 0) dfront = d;
                wr = 1.f / (1.f + (d - dfront) / sc.reg_scale);
              }
              ++cnt1;
            }
          }
        }
        if (R && __any_sync(kFull, rv)) {
          const int id = sc.vals[P.start + b0 + jj];
          for (int r = 0; r < R; ++r) {
            const float v = s[P_COL + nch + r];
            // reg = Σ w·[1, v, v·v]: d/dv = w·g1 + 2·w·v·g2 (the weights carry no gradient)
            warp_add(w.grad + int64_t(id) * S + P_COL + nch + r, rv ? wr * gR[r] + 2.f * wr * v * gR[R + r] : 0.f);
          }
        }
      }
    }
  }

  // Phase 2: back to front over every composited splat.
  float gdp = 0.f, gpp = 0.f;  // adjoints of the running means, non-zero only inside the head
  int ord = ncomp - 1;         // ordinal of the next composited splat (going backward)
  for (int b1 = maxlast; b1 > 0; b1 -= B) {
    const int b0 = max(0, b1 - B), nb = b1 - b0;
    __syncthreads();  // the rows of the previous batch (or of phase 1) are no longer read
    load_rows(rows, sc, P.start, b0, nb);
    __syncthreads();
    for (int jj = nb - 1; jj >= 0; --jj) {
      const int i = b0 + jj;
      if (!__any_sync(kFull, i < mylast)) continue;  // warp-uniform
      const float* s = rows + jj * S;
      bool rv = false;
      float caT = 0.f, cr = 1.f;  // the step's C' = C·cr + c·caT
      float g_mx = 0.f, g_my = 0.f, g_ca = 0.f, g_cb = 0.f, g_cc = 0.f, g_o = 0.f, g_d = 0.f, g_al = 0.f,
            g_be = 0.f, g_ga = 0.f;
      if (i < mylast) {
        const Quad<float> k = splat_quad(P.px, P.py, s[P_MX], s[P_MY], Factor{s[P_CA], s[P_CB], s[P_CC]});
        Absorb<float> ab{};
        if (k.q <= kQMax) {
          ab = splat_absorb<GEF>(k.q, s[P_O], s[P_AL]);
          rv = ab.a >= kAlphaMin;
        }
        if (rv) {
          const float a = ab.a, p = -k.q, d = s[P_D];
          const float* col = s + P_COL;
          // state before the step: the 3DGS inverse for tail steps, the saved state for head steps
          float Tpre = T / (1.f - a), Apre = 0.f, dpre = 0.f, ppre = 0.f;
          const bool hm = SOFT && ord >= 0 && (sc.patch ? i < kmax : ord < w.kmax_eff);
          if (hm) {
            Tpre = hd(ord, 0);
            Apre = hd(ord, 1);
            dpre = hd(ord, 2);
            ppre = hd(ord, 3);
          }
          float g_a, g_p = 0.f, gTn, gAn;
          if (SOFT) {
            const bool soft = hm && Apre > 0.f;
            Coef<float> cf = vanilla_coef(Tpre, Apre, a);
            SoftFwd<float> f{};
            if (soft) {
              f = softmax_fwd(Tpre, Apre, dpre, ppre, a, p, d, s[P_BE], s[P_GA], sc.solved);
              cf.r = f.r;
              cf.aT = f.aT;
              cf.wk = f.wk;
            }
            // adjoint of C' = C·r + c·aT (depth is channel nch); the colour gradients and the
            // rescaling of gC by r follow below, outside the divergent branch
            float g_r = 0.f, g_aT = 0.f;
            for (int c = 0; c < nch; ++c) g_aT = g_aT + gC[c] * col[c];
            g_aT = g_aT + gC[nch] * d;
            caT = cf.aT;
            g_d = gC[nch] * cf.aT;
            if (soft) {
              for (int c = 0; c < nc; ++c) g_r = g_r + gC[c] * hd(ord, 4 + c);
              cr = cf.r;
            }
            // adjoint of the running means d' = d + (d_k - d)·wk, p' likewise (head steps only)
            float g_wk = 0.f;
            if (hm) {
              g_wk = gdp * (d - dpre) + gpp * (p - ppre);
              g_d = g_d + gdp * cf.wk;
              g_p = gpp * cf.wk;
              gdp = gdp - gdp * cf.wk;
              gpp = gpp - gpp * cf.wk;
            }
            vanilla_coef_bwd(Tpre, Apre, a, gT, gA, g_aT, g_wk, gTn, gAn, g_a);
            if (soft) {
              const SoftGrad<float> sg =
                  softmax_bwd(f, Tpre, Apre, dpre, ppre, a, p, s[P_BE], s[P_GA], sc.solved, gT, gA, g_r, g_aT, g_wk);
              gTn = sg.T;
              gAn = sg.A;
              g_a = sg.a;
              g_p = g_p + sg.p;
              g_d = g_d + sg.d;
              gdp = gdp + sg.dp;
              gpp = gpp + sg.pp;
              g_be = sg.beta;
              g_ga = sg.gamma;
            }
          } else {
            // 3DGS: C' = C + c·aT, A' = A + aT, T' = T(1-a)
            const float aT = a * Tpre;
            float g_aT = gA;
            for (int c = 0; c < nch; ++c) g_aT = g_aT + gC[c] * col[c];
            g_aT = g_aT + gC[nch] * d;
            caT = aT;
            g_d = gC[nch] * aT;
            g_a = g_aT * Tpre - gT * Tpre;
            gTn = g_aT * a + gT * (1.f - a);
            gAn = gA;
          }
          gT = gTn;
          gA = gAn;
          T = Tpre;
          const KernGrad<float> kg =
              splat_kernel_bwd<GEF>(k, ab, Factor{s[P_CA], s[P_CB], s[P_CC]}, s[P_O], s[P_AL], g_a, g_p);
          g_mx = kg.mx;
          g_my = kg.my;
          g_ca = kg.ca;
          g_cb = kg.cb;
          g_cc = kg.cc;
          g_o = kg.o;
          g_al = kg.alpha;
          --ord;
        }
      }
      if (__any_sync(kFull, rv)) {  // warp-uniform: sum over the warp, one atomic per parameter
        float* g = w.grad + int64_t(sc.vals[P.start + i]) * S;
        warp_add(g + P_MX, g_mx);
        warp_add(g + P_MY, g_my);
        warp_add(g + P_CA, g_ca);
        warp_add(g + P_CB, g_cb);
        warp_add(g + P_CC, g_cc);
        warp_add(g + P_O, g_o);
        warp_add(g + P_D, g_d);
        if (GEF) warp_add(g + P_AL, g_al);
        if (SOFT) {
          warp_add(g + P_BE, g_be);
          warp_add(g + P_GA, g_ga);
        }
        for (int c = 0; c < nch; ++c) warp_add(g + P_COL + c, rv ? gC[c] * caT : 0.f);
        if (rv)
          for (int c = 0; c < nc; ++c) gC[c] = gC[c] * cr;
      }
    }
  }
}

// ---- dispatch ------------------------------------------------------------------------------------------------
// rows per shared-memory batch: up to one per thread, within kSharedBytes of dynamic shared memory
int batch_rows(int S) { return std::min(kBlock, int(kSharedBytes / (sizeof(float) * S))); }

template <bool GEF, bool SOFT, int NCT>
int launch_fwd(const Scene& sc, const FwdOut& o, cudaStream_t st) {
  const int B = batch_rows(sc.S);
  const int tiles = sc.tiles_x * sc.tiles_y;
  fwd_kernel<GEF, SOFT, NCT><<<tiles, kBlock, size_t(B) * sc.S * sizeof(float), st>>>(sc, o, B);
  return last_error();
}

template <bool GEF, bool SOFT, int NCT>
int launch_bwd(const Scene& sc, const BwdIn& in, const BwdWork& w, cudaStream_t st) {
  const int B = batch_rows(sc.S);
  const int tiles = sc.tiles_x * sc.tiles_y;
  // tiles per launch: all of them unless the head scratch bounds it
  const bool head = SOFT && w.kmax_eff > 0;
  const int per = head ? int(std::min<int64_t>(tiles, std::max<int64_t>(1, w.slots / kBlock))) : tiles;
  for (int t0 = 0; t0 < tiles; t0 += per) {
    const int nt = std::min(per, tiles - t0);
    bwd_kernel<GEF, SOFT, NCT><<<nt, kBlock, size_t(B) * sc.S * sizeof(float), st>>>(sc, in, w, t0, B);
    const int err = last_error();
    if (err) return err;
  }
  return 0;
}

template <template <bool, bool, int> class F, class... Args>
int dispatch(const Scene& sc, Args&&... args) {
  if (sc.nch == 3) {
    if (sc.gef) return sc.soft ? F<true, true, 3>::run(sc, args...) : F<true, false, 3>::run(sc, args...);
    return sc.soft ? F<false, true, 3>::run(sc, args...) : F<false, false, 3>::run(sc, args...);
  }
  if (sc.gef) return sc.soft ? F<true, true, 0>::run(sc, args...) : F<true, false, 0>::run(sc, args...);
  return sc.soft ? F<false, true, 0>::run(sc, args...) : F<false, false, 0>::run(sc, args...);
}

template <bool GEF, bool SOFT, int NCT>
struct FwdF {
  static int run(const Scene& sc, const FwdOut& o, cudaStream_t st) { return launch_fwd<GEF, SOFT, NCT>(sc, o, st); }
};
template <bool GEF, bool SOFT, int NCT>
struct BwdF {
  static int run(const Scene& sc, const BwdIn& in, const BwdWork& w, cudaStream_t st) {
    return launch_bwd<GEF, SOFT, NCT>(sc, in, w, st);
  }
};

}  // namespace

// ---- host interface (cuda_kernel.h) ------------------------------------------------------------------------------
int prepare(const SplatsIn& in, int W, int H, float* pk, int32_t* box, int64_t* ntiles, uint32_t* dbits,
            void* stream) {
  if (in.n == 0) return 0;
  const int S = P_COL + in.nch + in.nreg;
  prepare_kernel<<<blocks_for(in.n, 256), 256, 0, as_stream(stream)>>>(in, W, H, S, pk, box, ntiles, dbits);
  return last_error();
}

size_t scan_temp_bytes(int n) {
  size_t bytes = 0;
  cub::DeviceScan::InclusiveSum(nullptr, bytes, static_cast<const int64_t*>(nullptr), static_cast<int64_t*>(nullptr),
                                n);
  return bytes;
}

int scan_tiles(void* temp, size_t temp_bytes, const int64_t* ntiles, int64_t* offs, int n, void* stream) {
  if (n == 0) return 0;
  return int(cub::DeviceScan::InclusiveSum(temp, temp_bytes, ntiles, offs, n, as_stream(stream)));
}

int emit_keys(const int32_t* box, const int64_t* ntiles, const int64_t* offs, const uint32_t* dbits, int n,
              int tiles_x, uint64_t* keys, int32_t* vals, void* stream) {
  if (n == 0) return 0;
  emit_kernel<<<blocks_for(n, 256), 256, 0, as_stream(stream)>>>(box, ntiles, offs, dbits, n, tiles_x, keys, vals);
  return last_error();
}

int sort_key_bits(int ntiles) {
  int b = 1;
  while (b < 32 && (int64_t(1) << b) < ntiles) ++b;
  return 32 + b;
}

size_t sort_temp_bytes(int count, int end_bit) {
  size_t bytes = 0;
  cub::DeviceRadixSort::SortPairs(nullptr, bytes, static_cast<const uint64_t*>(nullptr),
                                  static_cast<uint64_t*>(nullptr), static_cast<const int32_t*>(nullptr),
                                  static_cast<int32_t*>(nullptr), count, 0, end_bit);
  return bytes;
}

int sort_keys(void* temp, size_t temp_bytes, const uint64_t* keys_in, uint64_t* keys_out, const int32_t* vals_in,
              int32_t* vals_out, int count, int end_bit, void* stream) {
  if (count == 0) return 0;
  return int(cub::DeviceRadixSort::SortPairs(temp, temp_bytes, keys_in, keys_out, vals_in, vals_out, count, 0, end_bit,
                                             as_stream(stream)));
}

int tile_ranges(const uint64_t* keys, int count, int ntiles, int32_t* ranges, void* stream) {
  const int err = int(cudaMemsetAsync(ranges, 0, sizeof(int32_t) * 2 * size_t(ntiles), as_stream(stream)));
  if (err || count == 0) return err;
  ranges_kernel<<<blocks_for(count, 256), 256, 0, as_stream(stream)>>>(keys, count, ranges);
  return last_error();
}

size_t fwd_chan_floats(int nch, int W, int H) { return nch == 3 ? 0 : size_t(nch + 1) * W * H; }
size_t bwd_chan_floats(int nch, int W, int H) { return nch == 3 ? 0 : 2 * size_t(nch + 1) * W * H; }
size_t head_entry_floats(int nch) { return size_t(4 + nch + 1); }

int forward(const Scene& sc, const FwdOut& out, void* stream) {
  return dispatch<FwdF>(sc, out, as_stream(stream));
}

int backward(const Scene& sc, const BwdIn& in, const BwdWork& work, void* stream) {
  return dispatch<BwdF>(sc, in, work, as_stream(stream));
}

const char* error_string(int code) { return cudaGetErrorString(cudaError_t(code)); }

void constants(double* out10) {
  const double v[10] = {kAlphaMax, kAlphaMin, kTMin, kQMax, kExpArgMax, kDecayArgMax, kPixelCenter, double(kTileSize),
                        kTStop, kTiny};
  for (int i = 0; i < 10; ++i) out10[i] = v[i];
}

}  // namespace cuda
}  // namespace smgs
