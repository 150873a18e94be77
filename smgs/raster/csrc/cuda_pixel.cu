// Per-pixel order on CUDA (sort="per_pixel" and the leading-splat map; part of the opt-in "v2"
// kernels, docs/cuda.md): the CUDA twin of cpu_pixel.cpp, one thread per pixel.
//
// Each pixel walks its tile's list in the global (centre depth) order. Every splat that reaches it
// enters a window keyed by its peak depth along the pixel's ray (peak_depth in splat_math.h). When
// the window holds `window` entries, its nearest is composited (the first of equal keys, so equal
// keys leave in arrival, i.e. global, order); at the end of the list the window drains. This is
// StopThePop's bounded re-sorting, and it composites the same splats in the same order as the CPU
// window: the same reach tests (splat_math.h, with mul_rn/add_rn so FMA contraction cannot change
// them), the same box test and pair count, the same compositing step (cpu_pixel.cpp's `step`), the
// same stop rule and k_max head (either scope). The batch of list rows in shared memory holds what
// the walk tests (mean, conic factor, opacity, depth, α, the nine peak-depth coefficients, the box);
// a window entry keeps its splat's index, so the step reads colours, β and γ from the packed rows.
//
// Backward: each pixel walks again (the same code, so the same order) and keeps, for every step it
// composites, the splat, its list position and the state before it (T, A, d_past, p_past, and for
// softmax the colour state) in per-thread records in global memory (max_cnt records per thread,
// float4-written, a persistent grid as the v2 compositing backward); then it runs the adjoint back
// to front, step by step the code of cpu_pixel.cpp's `pixel_bwd_tiles` (pixel_step_bwd.h), adding
// each step's gradients to its splat's row with atomics (the lanes of a warp composite different
// splats at a step).
#define SMGS_CUDA_FAST 1
#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>

#include "cuda_common.cuh"
#include "cuda_pixel.h"
#include "pixel_step_bwd.h"
#include "splat_math.h"

namespace smgs {
namespace cuda {
namespace pixel {

namespace {

// Fields of a batch row (field f of row j at rows[f·B + j]): what the walk tests.
enum { G_MX = 0, G_MY, G_HA, G_R, G_HS, G_O, G_D, G_CORE };
template <bool GEF>
struct Fields {
  static constexpr int AL = G_CORE;                     // only where GEF
  static constexpr int COEF = G_CORE + (GEF ? 1 : 0);   // nine peak-depth coefficients
  static constexpr int N = COEF + 9;                    // floats per row; then 5 ints: box, index
};

inline int batch_rows(int floats) { return std::min(kBlock, int(kSharedBytes / (sizeof(float) * (floats + 5)))); }
inline size_t batch_bytes(int B, int floats) { return size_t(B) * (floats + 5) * sizeof(float); }

template <bool GEF>
__device__ __forceinline__ void load_batch(float* rows, int* ints, int B, const Scene& sc, const PixelIn& pin,
                                           int start, int b0, int nb) {
  using Fd = Fields<GEF>;
  for (int j = threadIdx.x; j < nb; j += kBlock) {
    const int id = sc.vals[start + b0 + j];
    const float* s = sc.pk + int64_t(id) * sc.S;
    rows[G_MX * B + j] = s[P_MX];
    rows[G_MY * B + j] = s[P_MY];
    rows[G_HA * B + j] = s[P_CA];
    rows[G_R * B + j] = s[P_CB];
    rows[G_HS * B + j] = s[P_CC];
    rows[G_O * B + j] = s[P_O];
    rows[G_D * B + j] = s[P_D];
    if (GEF) rows[Fd::AL * B + j] = s[P_AL];
#pragma unroll
    for (int k = 0; k < 9; ++k) rows[(Fd::COEF + k) * B + j] = pin.coefs[int64_t(id) * 9 + k];
#pragma unroll
    for (int k = 0; k < 4; ++k) ints[k * B + j] = pin.box[4 * int64_t(id) + k];
    ints[4 * B + j] = id;
  }
}

// The window, in arrival order.
struct Window {
  float t[kMaxWindow], q[kMaxWindow], a[kMaxWindow];
  int id[kMaxWindow], pos[kMaxWindow];
  int n = 0;
};

struct Entry {
  float q, a;
  int id, pos;
};

// Removes and returns the window's nearest entry (the first of equal keys).
__device__ __forceinline__ Entry pop(Window& w) {
  int m = 0;
  for (int k = 1; k < w.n; ++k)
    if (w.t[k] < w.t[m]) m = k;
  const Entry e{w.q[m], w.a[m], w.id[m], w.pos[m]};
  for (int k = m + 1; k < w.n; ++k) {
    w.t[k - 1] = w.t[k];
    w.q[k - 1] = w.q[k];
    w.a[k - 1] = w.a[k];
    w.id[k - 1] = w.id[k];
    w.pos[k - 1] = w.pos[k];
  }
  --w.n;
  return e;
}

// One pixel's state before a step.
struct State {
  float T = 1.f, A = 0.f, dp = 0.f, pp = 0.f;
  int cnt = 0;
};

// cpu_pixel.cpp's in_head: the pixel's first k_max composited splats, or (patch scope) the tile's
// first k_max list entries.
__device__ __forceinline__ bool in_head(const Scene& sc, int cnt, int pos) { return (sc.patch ? pos : cnt) < sc.kmax; }

// cpu_pixel.cpp's step<SOFT>: false (and no change) where the pixel stops before this splat. Written
// out again here: the forward kernels calling one shared copy got another register allocation from
// ptxas, with spills in the kernels for other channel counts than 3.
template <bool SOFT, int NCT>
__device__ __forceinline__ bool step(const Scene& sc, State& px, Chan<NCT>& C, int nch, const Entry& e) {
  const float* s = sc.pk + int64_t(e.id) * sc.S;
  const float a = e.a, d = s[P_D];
  const float T0 = px.T * (1.f - a);
  const bool head = SOFT && in_head(sc, px.cnt, e.pos);
  if (T0 < kTStop && !head) return false;   // vanilla steps only (constants.T_MIN)
  const float* col = s + P_COL;
  if (SOFT) {
    const float p = -e.q;
    Coef<float> cf;
    cf.aT = a * px.T;
    cf.An = px.A + cf.aT;
    cf.wk = 1.f;   // a head step at A = 0 is vanilla with wk = 1
    cf.Tn = T0;
    cf.r = 1.f;
    if (head && px.A > 0.f) {
      const SoftFwd<float> f = softmax_fwd(px.T, px.A, px.dp, px.pp, a, p, d, s[P_BE], s[P_GA], sc.solved);
      cf.Tn = f.T0;
      cf.An = f.U;
      cf.r = f.r;
      cf.aT = f.aT;
      cf.wk = f.wk;
    }
    for (int c = 0; c < nch; ++c) C[c] = C[c] * cf.r + col[c] * cf.aT;
    C[nch] = C[nch] * cf.r + d * cf.aT;
    if (head) {
      px.dp = px.dp + (d - px.dp) * cf.wk;
      px.pp = px.pp + (p - px.pp) * cf.wk;
    }
    px.T = cf.Tn;
    px.A = cf.An;
  } else {
    const float aT = a * px.T;
    for (int c = 0; c < nch; ++c) C[c] = C[c] + col[c] * aT;
    C[nch] = C[nch] + d * aT;
    px.A = px.A + aT;
    px.T = T0;
  }
  ++px.cnt;
  return true;
}

// The tile's list in this pixel's windowed order: take(entry) for each composited candidate until
// it returns false. Call with the whole block (it synchronises between batches); `active` false for
// threads outside the image. Returns the pairs this pixel evaluated.
template <bool GEF, class Take>
__device__ unsigned long long walk(const Scene& sc, const PixelIn& pin, const Pixel& P, float* rows, int* ints,
                                   int B, bool active, Take&& take) {
  using Fd = Fields<GEF>;
  const float u = (P.px - pin.cx) / pin.fx, v = (P.py - pin.cy) / pin.fy;
  Window win;
  bool live = active;
  unsigned long long pairs = 0;
  for (int b0 = 0; b0 < P.n; b0 += B) {
    if (__syncthreads_count(live) == 0) break;   // also keeps the previous batch until all used it
    const int nb = min(B, P.n - b0);
    load_batch<GEF>(rows, ints, B, sc, pin, P.start, b0, nb);
    __syncthreads();
    for (int jj = 0; jj < nb && live; ++jj) {
      if (P.x < ints[jj] || P.x > ints[B + jj] || P.y < ints[2 * B + jj] || P.y > ints[3 * B + jj]) continue;
      ++pairs;
      const Quad<float> k = splat_quad(P.px, P.py, rows[G_MX * B + jj], rows[G_MY * B + jj],
                                       Factor{rows[G_HA * B + jj], rows[G_R * B + jj], rows[G_HS * B + jj]});
      if (!(k.q <= kQMax)) continue;
      const float a = splat_absorb<GEF>(k.q, rows[G_O * B + jj], GEF ? rows[Fd::AL * B + jj] : 1.f).a;
      if (!(a >= kAlphaMin)) continue;
      float c[9];
#pragma unroll
      for (int m = 0; m < 9; ++m) c[m] = rows[(Fd::COEF + m) * B + jj];
      const int w = win.n++;
      win.t[w] = peak_depth(u, v, c, rows[G_D * B + jj]);
      win.q[w] = k.q;
      win.a[w] = a;
      win.id[w] = ints[4 * B + jj];
      win.pos[w] = b0 + jj;
      if (win.n >= pin.window) live = take(pop(win));
    }
  }
  while (live && win.n > 0) live = take(pop(win));
  return pairs;
}

template <bool GEF, bool SOFT, int NCT>
__global__ void __launch_bounds__(kBlock) fwd_kernel(Scene sc, PixelIn pin, FwdOut o, PixelOut po, int B) {
  extern __shared__ float smem[];
  float* rows = smem;
  int* ints = reinterpret_cast<int*>(smem + B * Fields<GEF>::N);
  const Pixel P(sc, blockIdx.x);
  const int nch = NCT ? NCT : sc.nch;
  Chan<NCT> C(NCT ? nullptr : o.chan + P.pix, P.npix);
  if (P.inside)
    for (int c = 0; c <= nch; ++c) C[c] = 0.f;
  State px;
  int lead0 = -1, lead1 = -1, lend = 0;
  unsigned long long pairs = walk<GEF>(sc, pin, P, rows, ints, B, P.inside, [&](const Entry& e) {
    if (!step<SOFT, NCT>(sc, px, C, nch, e)) return false;
    lend = max(lend, e.pos + 1);
    if (po.lead && e.a >= po.lead_alpha && lead1 < 0) (lead0 < 0 ? lead0 : lead1) = e.id;
    return true;
  });
  if (P.inside) {
    for (int c = 0; c < nch; ++c) o.rgb[P.pix * nch + c] = C[c] + (sc.bg ? px.T * sc.bg[c] : 0.f);
    o.alpha[P.pix] = px.A;
    o.depth[P.pix] = px.A > 0.f ? C[nch] / px.A : 0.f;
    o.Tf[P.pix] = px.T;
    o.cnt[P.pix] = px.cnt;
    if (po.lend) po.lend[P.pix] = lend;
    if (po.lead) {
      po.lead[2 * P.pix] = lead0;
      po.lead[2 * P.pix + 1] = lead1;
    }
  }
  for (int off = 16; off > 0; off >>= 1) pairs += __shfl_xor_sync(kFull, pairs, off);
  if ((threadIdx.x & 31) == 0 && pairs) atomicAdd(o.pairs, pairs);
}

// ---- backward ----------------------------------------------------------------------------------------
// A step record: float4 (T, A, d_past, p_past), float4 (splat index, list position as bits, 0, 0),
// then (softmax) the channel state before the step, padded to whole float4.
__host__ __device__ constexpr int record_floats(int nch, bool soft) { return 8 + (soft ? (nch + 1 + 3) / 4 * 4 : 0); }

template <bool GEF, bool SOFT, int NCT>
__global__ void __launch_bounds__(kBlock, 2) bwd_kernel(Scene sc, PixelIn pin, BwdIn in, PixelBwdWork w, int B) {
  extern __shared__ float smem[];
  __shared__ int s_tile;
  float* rows = smem;
  int* ints = reinterpret_cast<int*>(smem + B * Fields<GEF>::N);
  const int tiles = sc.tiles_x * sc.tiles_y;
  const int nch = NCT ? NCT : sc.nch;
  const int nc = nch + 1;
  const int RW = record_floats(NCT ? NCT : sc.nch, SOFT);
  float* mine = w.steps + (int64_t(blockIdx.x) * kBlock + threadIdx.x) * w.max_cnt * RW;
  for (;;) {
    __syncthreads();
    if (threadIdx.x == 0) s_tile = atomicAdd(w.counter, 1);
    __syncthreads();
    const int tile = s_tile;
    if (tile >= tiles) break;   // block-uniform
    const Pixel P(sc, tile);
    Chan<NCT> C(NCT ? nullptr : w.chan + P.pix, P.npix);              // forward colour state
    Chan<NCT> gC(NCT ? nullptr : w.chan + nc * P.npix + P.pix, P.npix);  // its adjoint
    const int ncomp = P.inside ? in.cnt[P.pix] : 0;
    if (P.inside)
      for (int c = 0; c < nc; ++c) C[c] = 0.f;
    // the forward's steps again, in its order, keeping the state before each
    State px;
    walk<GEF>(sc, pin, P, rows, ints, B, P.inside && ncomp > 0, [&](const Entry& e) {
      if (px.cnt >= ncomp) return false;   // the forward stopped here
      float4* r4 = reinterpret_cast<float4*>(mine + int64_t(px.cnt) * RW);
      r4[0] = make_float4(px.T, px.A, px.dp, px.pp);
      r4[1] = make_float4(__int_as_float(e.id), __int_as_float(e.pos), 0.f, 0.f);
      if (SOFT)
        for (int c0 = 0; c0 < nc; c0 += 4)
          r4[2 + c0 / 4] = make_float4(C[c0], c0 + 1 < nc ? C[c0 + 1] : 0.f, c0 + 2 < nc ? C[c0 + 2] : 0.f,
                                       c0 + 3 < nc ? C[c0 + 3] : 0.f);
      return step<SOFT, NCT>(sc, px, C, nch, e);
    });
    if (ncomp == 0) continue;
    // dL/d outputs -> dL/d final state: rgb = C + T·bg, alpha = A, depth = C_d / A
    float gT = 0.f;
    for (int c = 0; c < nch; ++c) {
      gC[c] = in.g_rgb[P.pix * nch + c];
      if (sc.bg) gT += gC[c] * sc.bg[c];
    }
    const float Aout = in.alpha[P.pix];
    gC[nch] = Aout > 0.f ? in.g_depth[P.pix] / Aout : 0.f;
    float gA = in.g_alpha[P.pix] - (Aout > 0.f ? in.g_depth[P.pix] * in.depth[P.pix] / Aout : 0.f);
    float gdp = 0.f, gpp = 0.f;   // adjoints of the running means (softmax head only)
    for (int k = ncomp - 1; k >= 0; --k) {
      const float4* r4 = reinterpret_cast<const float4*>(mine + int64_t(k) * RW);
      const float4 pre = r4[0], idp = r4[1];
      const int id = __float_as_int(idp.x), pos = __float_as_int(idp.y);
      float* g = w.grad + int64_t(id) * sc.S;
      const auto chan = [&](int c0, float* h) {   // the channel state before the step (softmax)
        const float4 v = r4[2 + c0 / 4];
        h[0] = v.x;
        h[1] = v.y;
        h[2] = v.z;
        h[3] = v.w;
      };
      pixel_step_bwd<GEF, SOFT>(sc.pk + int64_t(id) * sc.S, P.px, P.py, pre.x, pre.y, pre.z, pre.w,
                                SOFT && in_head(sc, k, pos), sc.solved, nch, gC, chan,
                                [&](int col, float v) { atomicAdd(g + col, v); }, gT, gA, gdp, gpp);
    }
  }
}

template <bool GEF, bool SOFT, int NCT>
struct Launch {
  static int fwd(const Scene& sc, const PixelIn& pin, const FwdOut& o, const PixelOut& po, cudaStream_t st) {
    const int F = Fields<GEF>::N, B = batch_rows(F);
    fwd_kernel<GEF, SOFT, NCT><<<sc.tiles_x * sc.tiles_y, kBlock, batch_bytes(B, F), st>>>(sc, pin, o, po, B);
    return last_error();
  }
  static int per_sm(int* out) {
    const int F = Fields<GEF>::N, B = batch_rows(F);
    return int(cudaOccupancyMaxActiveBlocksPerMultiprocessor(out, bwd_kernel<GEF, SOFT, NCT>, kBlock,
                                                             batch_bytes(B, F)));
  }
  static int bwd(const Scene& sc, const PixelIn& pin, const BwdIn& in, const PixelBwdWork& w, cudaStream_t st) {
    const int F = Fields<GEF>::N, B = batch_rows(F);
    bwd_kernel<GEF, SOFT, NCT><<<w.grid, kBlock, batch_bytes(B, F), st>>>(sc, pin, in, w, B);
    return last_error();
  }
};

}  // namespace

size_t step_record_floats(int nch, bool soft) { return size_t(record_floats(nch, soft)); }

int backward_grid(const Scene& sc, int max_cnt, int64_t budget_bytes) {
  int occ = 1;
  if (dispatch_mode<Launch>(sc, [&](auto L) { return L.per_sm(&occ); }) != 0 || occ < 1) occ = 1;
  const int64_t per_block =
      int64_t(kBlock) * max_cnt * int64_t(step_record_floats(sc.nch, sc.soft)) * int64_t(sizeof(float));
  return persistent_grid(occ, int64_t(sc.tiles_x) * sc.tiles_y, per_block, budget_bytes);
}

int forward(const Scene& sc, const PixelIn& pin, const FwdOut& out, const PixelOut& pout, void* stream) {
  if (pin.window < 1 || pin.window > kMaxWindow) return int(cudaErrorInvalidValue);
  return dispatch_mode<Launch>(sc, [&](auto L) { return L.fwd(sc, pin, out, pout, as_stream(stream)); });
}

int backward(const Scene& sc, const PixelIn& pin, const BwdIn& in, const PixelBwdWork& work, void* stream) {
  if (pin.window < 1 || pin.window > kMaxWindow) return int(cudaErrorInvalidValue);
  return dispatch_mode<Launch>(sc, [&](auto L) { return L.bwd(sc, pin, in, work, as_stream(stream)); });
}

}  // namespace pixel
}  // namespace cuda
}  // namespace smgs
