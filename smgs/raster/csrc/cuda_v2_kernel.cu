// Opt-in CUDA compositing kernels ("v2"; docs/cuda.md says how to select them and what a GPU run
// has verified). Same semantics as the default kernels of cuda_kernel.cu (and the CPU kernel and
// smgs/raster/reference.py): the same tile lists (the default's binning), the same per-pixel reach
// tests, stop rule and k_max head (either scope, docs/kmax-scope.md), the same outputs; the per-splat math is splat_math.h. What
// differs is how the work is laid out on the GPU:
//
// * Arithmetic. Built with FMA contraction; the reach arithmetic (q of splat_quad) goes through
//   mul_rn/add_rn, which are never fused, and the stop rule T·(1 − a) has no product to fuse, so
//   every reach, skip and stop decision, hence n_contrib and `last`, is the other backends' bit for
//   bit. vrcp and vsqrt_pos are the hardware approximations (SMGS_CUDA_FAST; ~1 ulp, as a SIMD
//   lane's on the CPU), and a tail step of the backward rebuilds T with one of them. The quotient
//   wk = aT / A' stays a division (its first value must be exactly 1), expf and logf stay accurate
//   (a >= 1/255 is decided on exp(−q)).
// * Shared memory. A batch of splats is kept field by field (structure of arrays), only the fields
//   the mode reads (7 for 3dgs, + α for GEF, + β, γ for softmax, then the colours and regularised
//   values), each thread loading whole rows: no integer division per element, and reads that every
//   lane of a warp shares are broadcasts.
// * Softmax backward. Each thread keeps its pixel's head state as whole records of 32 bytes (two
//   float4 for RGB), its records contiguous: a lane's record is one sector whatever step its pixel
//   is at (the default's field-major layout touches eight sectors per lane and step). The grid is
//   persistent: as many blocks as the device holds at once take tiles from an atomic counter, so
//   one launch covers the frame and the scratch is sized by the threads in flight.
#define SMGS_CUDA_FAST 1
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>

#include "cuda_common.cuh"
#include "cuda_v2_kernel.h"
#include "splat_math.h"

namespace smgs {
namespace cuda {
namespace v2 {

namespace {

// ---- the lean shared-memory batch ----------------------------------------------------------------
// Fields of a batch row, in this order: the seven every mode reads, α (GEF), β and γ (softmax),
// then the colours and the regularised values. Field f of row j is at rows[f·B + j].
enum { F_MX = 0, F_MY, F_HA, F_R, F_HS, F_O, F_D, F_CORE };

template <bool GEF, bool SOFT>
struct Fields {
  static constexpr int AL = F_CORE;              // only where GEF
  static constexpr int BE = F_CORE + (GEF ? 1 : 0);
  static constexpr int GA = BE + 1;
  static constexpr int CORE = F_CORE + (GEF ? 1 : 0) + (SOFT ? 2 : 0);
  __host__ __device__ static constexpr int n(int nch, int nreg) { return CORE + nch + nreg; }
};

// The packed-row column of each core field (cuda_kernel.h: P_*).
template <bool GEF, bool SOFT>
__device__ __forceinline__ int core_column(int f) {
  constexpr int cols[10] = {P_MX, P_MY, P_CA, P_CB, P_CC, P_O, P_D, GEF ? P_AL : P_BE, GEF ? P_BE : P_GA, P_GA};
  return cols[f];
}

// Rows [b0, b0 + nb) of a tile's list into the batch: thread j loads row j whole (and its splat
// index into ids[j]).
template <bool GEF, bool SOFT>
__device__ __forceinline__ void load_batch(float* rows, int* ids, int B, const Scene& sc, int start, int b0, int nb,
                                           int nch, int nreg) {
  using Fd = Fields<GEF, SOFT>;
  for (int j = threadIdx.x; j < nb; j += kBlock) {
    const int id = sc.vals[start + b0 + j];
    ids[j] = id;
    const float* src = sc.pk + int64_t(id) * sc.S;
#pragma unroll
    for (int f = 0; f < Fd::CORE; ++f) rows[f * B + j] = src[core_column<GEF, SOFT>(f)];
    for (int c = 0; c < nch + nreg; ++c) rows[(Fd::CORE + c) * B + j] = src[P_COL + c];
  }
}

struct Row {
  const float* p;  // rows + j
  int B;
  __device__ __forceinline__ float operator[](int f) const { return p[f * B]; }
};

// rows per batch: up to one per thread, within kSharedBytes of dynamic shared memory (rows + ids)
inline int batch_rows(int fields) { return std::min(kBlock, int(kSharedBytes / (sizeof(float) * (fields + 1)))); }
inline size_t batch_bytes(int B, int fields) { return size_t(B) * (fields + 1) * sizeof(float); }

// ---- forward -------------------------------------------------------------------------------------------
template <bool GEF, bool SOFT, int NCT>
__global__ void __launch_bounds__(kBlock) fwd_kernel(Scene sc, FwdOut o, int B) {
  using Fd = Fields<GEF, SOFT>;
  extern __shared__ float smem[];
  const int nch = NCT ? NCT : sc.nch;
  const int R = sc.nreg;
  float* rows = smem;
  int* ids = reinterpret_cast<int*>(smem + B * Fd::n(nch, R));
  const Pixel P(sc, blockIdx.x);
  const int nc = nch + 1;
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
    load_batch<GEF, SOFT>(rows, ids, B, sc, P.start, b0, nb, nch, R);
    __syncthreads();
    for (int jj = 0; jj < nb && !done; ++jj) {
      const Row s{rows + jj, B};
      ++pairs;
      const Quad<float> k = splat_quad(P.px, P.py, s[F_MX], s[F_MY], Factor{s[F_HA], s[F_R], s[F_HS]});
      if (!(k.q <= kQMax)) continue;
      const Absorb<float> ab = splat_absorb<GEF>(k.q, s[F_O], GEF ? s[Fd::AL] : 1.f);
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
      const float d = s[F_D];
      const bool head = need_head ? in_head : true;
      if (SOFT) {
        const bool soft = head && A > 0.f;
        const float p = -k.q;
        Coef<float> cf = vanilla_coef(T, A, a);
        if (soft) cf = softmax_coef(softmax_fwd(T, A, dp, pp, a, p, d, s[Fd::BE], s[Fd::GA], sc.solved));
        for (int c = 0; c < nch; ++c) C[c] = C[c] * cf.r + s[Fd::CORE + c] * cf.aT;
        C[nch] = C[nch] * cf.r + d * cf.aT;
        if (head) {
          dp = dp + (d - dp) * cf.wk;
          pp = pp + (p - pp) * cf.wk;
        }
        T = cf.Tn;
        A = cf.An;
      } else {
        const float aT = a * T;
        for (int c = 0; c < nch; ++c) C[c] = C[c] + s[Fd::CORE + c] * aT;
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
          const float v = s[Fd::CORE + nch + r];
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
// Record floats of one head step: T, A, d_past, p_past, then the nch + 1 channel states, padded to
// whole float4.
__host__ __device__ constexpr int record_floats(int nch) { return ((4 + nch + 1) + 3) / 4 * 4; }

// One head record written and read whole, in float4 (16-byte aligned: the scratch base is, and
// records are multiples of 4 floats).
template <int NCT>
__device__ __forceinline__ void put_record(float* rec, float T, float A, float dp, float pp, Chan<NCT>& C, int nc) {
  float4* r4 = reinterpret_cast<float4*>(rec);
  r4[0] = make_float4(T, A, dp, pp);
  for (int c0 = 0; c0 < nc; c0 += 4)
    r4[1 + c0 / 4] = make_float4(C[c0], c0 + 1 < nc ? C[c0 + 1] : 0.f, c0 + 2 < nc ? C[c0 + 2] : 0.f,
                                 c0 + 3 < nc ? C[c0 + 3] : 0.f);
}

// Occupancy target of the backward: 3 blocks of 256 threads per multiprocessor (<= 80 registers)
// without softmax, 2 (<= 128) with (tests/test_raster_cuda_v2_build.py checks ptxas's spill report).
template <bool SOFT>
constexpr int bwd_min_blocks() { return SOFT ? 2 : 3; }

template <bool GEF, bool SOFT, int NCT>
__global__ void __launch_bounds__(kBlock, bwd_min_blocks<SOFT>())
    bwd_kernel(Scene sc, BwdIn in, BwdWork w, int B) {
  using Fd = Fields<GEF, SOFT>;
  extern __shared__ float smem[];
  __shared__ int s_maxlast, s_tile;
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int R = sc.nreg;
  float* rows = smem;
  int* ids = reinterpret_cast<int*>(smem + B * Fd::n(nch, R));
  const int tiles = sc.tiles_x * sc.tiles_y;
  const int kmax = sc.kmax;
  const int RW = NCT ? record_floats(NCT) : record_floats(nch);
  // this thread's head records: slot-major, entry e at head + (slot·kmax_eff + e)·RW
  float* myhead = w.head + (int64_t(blockIdx.x) * kBlock + threadIdx.x) * w.kmax_eff * RW;

  for (;;) {
    __syncthreads();  // every thread has read s_tile and is done with the batch of the last tile
    if (threadIdx.x == 0) {
      s_tile = atomicAdd(w.counter, 1);
      s_maxlast = 0;
    }
    __syncthreads();
    const int tile = s_tile;
    if (tile >= tiles) break;  // block-uniform
    const Pixel P(sc, tile);
    Chan<NCT> gC(NCT ? nullptr : w.chan + P.pix, P.npix);               // adjoint of the colour state
    Chan<NCT> C1(NCT ? nullptr : w.chan + nc * P.npix + P.pix, P.npix);  // phase 1 colour state

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
    if (mylast) atomicMax(&s_maxlast, mylast);
    __syncthreads();
    const int maxlast = s_maxlast;
    if (maxlast == 0) continue;  // block-uniform

    // Phase 1: recompute the pixel's head (its first k_max composited splats, or in patch scope its
    // composited splats among the tile's first k_max list entries) front to back, saving the state
    // before every head step (softmax modes) and taking the regulariser's gradients. Either way the
    // head steps come first in the pixel's order, so record cnt1 is the head step of ordinal cnt1.
    if ((SOFT || R) && kmax > 0) {
      float T1 = 1.f, A1 = 0.f, dp1 = 0.f, pp1 = 0.f, dfront = 0.f;
      int cnt1 = 0;
      if (P.inside)
        for (int c = 0; c < nc; ++c) C1[c] = 0.f;
      const float* gR = R && P.inside ? in.g_reg + P.pix * (1 + 2 * R) + 1 : nullptr;  // dL/d Σw·v, Σw·v²
      for (int b0 = 0; b0 < maxlast; b0 += B) {
        if (__syncthreads_count(b0 < mylast && (sc.patch ? b0 : cnt1) < kmax) == 0) break;
        const int nb = min(B, maxlast - b0);
        load_batch<GEF, SOFT>(rows, ids, B, sc, P.start, b0, nb, nch, R);
        __syncthreads();
        for (int jj = 0; jj < nb; ++jj) {
          const bool hv = b0 + jj < mylast && (sc.patch ? b0 + jj : cnt1) < kmax;
          if (!__any_sync(kFull, hv)) break;  // warp-uniform
          const Row s{rows + jj, B};
          bool rv = false;
          float wr = 0.f;
          if (hv) {
            const Quad<float> k = splat_quad(P.px, P.py, s[F_MX], s[F_MY], Factor{s[F_HA], s[F_R], s[F_HS]});
            if (k.q <= kQMax) {
              const Absorb<float> ab = splat_absorb<GEF>(k.q, s[F_O], GEF ? s[Fd::AL] : 1.f);
              rv = ab.a >= kAlphaMin;  // before `last`: composited, never stopped
              if (rv) {
                const float a = ab.a, d = s[F_D];
                if (SOFT) {
                  put_record<NCT>(myhead + int64_t(cnt1) * RW, T1, A1, dp1, pp1, C1, nc);
                  const float p = -k.q;
                  Coef<float> cf = vanilla_coef(T1, A1, a);
                  if (A1 > 0.f)
                    cf = softmax_coef(softmax_fwd(T1, A1, dp1, pp1, a, p, d, s[Fd::BE], s[Fd::GA], sc.solved));
                  for (int c = 0; c < nch; ++c) C1[c] = C1[c] * cf.r + s[Fd::CORE + c] * cf.aT;
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
            const int id = ids[jj];
            for (int r = 0; r < R; ++r) {
              const float v = s[Fd::CORE + nch + r];
              // reg = Σ w·[1, v, v·v]: d/dv = w·g1 + 2·w·v·g2 (the weights carry no gradient)
              warp_add(w.grad + int64_t(id) * sc.S + P_COL + nch + r,
                       rv ? wr * gR[r] + 2.f * wr * v * gR[R + r] : 0.f);
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
      __syncthreads();  // the batch of the previous step (or of phase 1) is no longer read
      load_batch<GEF, SOFT>(rows, ids, B, sc, P.start, b0, nb, nch, R);
      __syncthreads();
      for (int jj = nb - 1; jj >= 0; --jj) {
        const int i = b0 + jj;
        if (!__any_sync(kFull, i < mylast)) continue;  // warp-uniform
        const Row s{rows + jj, B};
        bool rv = false;
        float caT = 0.f, cr = 1.f;  // the step's C' = C·cr + c·caT
        float g_mx = 0.f, g_my = 0.f, g_ca = 0.f, g_cb = 0.f, g_cc = 0.f, g_o = 0.f, g_d = 0.f, g_al = 0.f,
              g_be = 0.f, g_ga = 0.f;
        if (i < mylast) {
          const Factor fac{s[F_HA], s[F_R], s[F_HS]};
          const float o = s[F_O], al = GEF ? s[Fd::AL] : 1.f;
          const Quad<float> k = splat_quad(P.px, P.py, s[F_MX], s[F_MY], fac);
          Absorb<float> ab{};
          if (k.q <= kQMax) {
            ab = splat_absorb<GEF>(k.q, o, al);
            rv = ab.a >= kAlphaMin;
          }
          if (rv) {
            const float a = ab.a, p = -k.q, d = s[F_D];
            // state before the step: the 3DGS inverse for tail steps, the saved state for head steps
            float Tpre = T * vrcp(1.f - a), Apre = 0.f, dpre = 0.f, ppre = 0.f;
            const bool hm = SOFT && ord >= 0 && (sc.patch ? i < kmax : ord < w.kmax_eff);
            const float* rec = myhead + int64_t(hm ? ord : 0) * RW;
            if (hm) {
              const float4 h0 = reinterpret_cast<const float4*>(rec)[0];
              Tpre = h0.x;
              Apre = h0.y;
              dpre = h0.z;
              ppre = h0.w;
            }
            float g_a, g_p = 0.f, gTn, gAn;
            if (SOFT) {
              const bool soft = hm && Apre > 0.f;
              Coef<float> cf = vanilla_coef(Tpre, Apre, a);
              SoftFwd<float> f{};
              if (soft) {
                f = softmax_fwd(Tpre, Apre, dpre, ppre, a, p, d, s[Fd::BE], s[Fd::GA], sc.solved);
                cf.r = f.r;
                cf.aT = f.aT;
                cf.wk = f.wk;
              }
              // adjoint of C' = C·r + c·aT (depth is channel nch); the colour gradients and the
              // rescaling of gC by r follow below, outside the divergent branch
              float g_r = 0.f, g_aT = 0.f;
              for (int c = 0; c < nch; ++c) g_aT = g_aT + gC[c] * s[Fd::CORE + c];
              g_aT = g_aT + gC[nch] * d;
              caT = cf.aT;
              g_d = gC[nch] * cf.aT;
              if (soft) {
                const float4* r4 = reinterpret_cast<const float4*>(rec) + 1;
                for (int c0 = 0; c0 < nc; c0 += 4) {
                  const float4 h = r4[c0 / 4];
                  g_r = g_r + gC[c0] * h.x;
                  if (c0 + 1 < nc) g_r = g_r + gC[c0 + 1] * h.y;
                  if (c0 + 2 < nc) g_r = g_r + gC[c0 + 2] * h.z;
                  if (c0 + 3 < nc) g_r = g_r + gC[c0 + 3] * h.w;
                }
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
                const SoftGrad<float> sg = softmax_bwd(f, Tpre, Apre, dpre, ppre, a, p, s[Fd::BE], s[Fd::GA],
                                                       sc.solved, gT, gA, g_r, g_aT, g_wk);
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
              for (int c = 0; c < nch; ++c) g_aT = g_aT + gC[c] * s[Fd::CORE + c];
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
            const KernGrad<float> kg = splat_kernel_bwd<GEF>(k, ab, fac, o, al, g_a, g_p);
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
          float* g = w.grad + int64_t(ids[jj]) * sc.S;
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
}

__global__ void cull_kernel(const float* radii, int64_t* ntiles, int n) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i < n && radii[2 * i] == 0.f && radii[2 * i + 1] == 0.f) ntiles[i] = 0;
}

// ---- dispatch ------------------------------------------------------------------------------------------------
template <bool GEF, bool SOFT, int NCT>
struct Launch {
  static int fields(const Scene& sc) { return Fields<GEF, SOFT>::n(NCT ? NCT : sc.nch, sc.nreg); }

  static int fwd(const Scene& sc, const FwdOut& o, cudaStream_t st) {
    const int F = fields(sc), B = batch_rows(F);
    fwd_kernel<GEF, SOFT, NCT><<<sc.tiles_x * sc.tiles_y, kBlock, batch_bytes(B, F), st>>>(sc, o, B);
    return last_error();
  }

  static int per_sm(const Scene& sc, int* out) {
    const int F = fields(sc), B = batch_rows(F);
    return int(cudaOccupancyMaxActiveBlocksPerMultiprocessor(out, bwd_kernel<GEF, SOFT, NCT>, kBlock,
                                                             batch_bytes(B, F)));
  }

  static int bwd(const Scene& sc, const BwdIn& in, const BwdWork& w, cudaStream_t st) {
    const int F = fields(sc), B = batch_rows(F);
    bwd_kernel<GEF, SOFT, NCT><<<w.grid, kBlock, batch_bytes(B, F), st>>>(sc, in, w, B);
    return last_error();
  }
};

}  // namespace

// ---- host interface (cuda_v2_kernel.h) -----------------------------------------------------------------------
int cull_by_radii(const float* radii, int64_t* ntiles, int n, void* stream) {
  if (n == 0) return 0;
  cull_kernel<<<(n + 255) / 256, 256, 0, as_stream(stream)>>>(radii, ntiles, n);
  return last_error();
}

size_t head_record_floats(int nch) { return size_t(record_floats(nch)); }

int backward_grid(const Scene& sc, int kmax_eff, int64_t budget_bytes, int* per_sm) {
  int occ = 1;
  if (dispatch_mode<Launch>(sc, [&](auto L) { return L.per_sm(sc, &occ); }) != 0 || occ < 1) occ = 1;
  if (per_sm) *per_sm = occ;
  const int64_t per_block = int64_t(kBlock) * kmax_eff * int64_t(head_record_floats(sc.nch)) * int64_t(sizeof(float));
  return persistent_grid(occ, int64_t(sc.tiles_x) * sc.tiles_y, per_block, budget_bytes);
}

int forward(const Scene& sc, const FwdOut& out, void* stream) {
  return dispatch_mode<Launch>(sc, [&](auto L) { return L.fwd(sc, out, as_stream(stream)); });
}

int backward(const Scene& sc, const BwdIn& in, const BwdWork& work, void* stream) {
  return dispatch_mode<Launch>(sc, [&](auto L) { return L.bwd(sc, in, work, as_stream(stream)); });
}

}  // namespace v2
}  // namespace cuda
}  // namespace smgs
