// CUDA projection: one thread per Gaussian, one kernel each way (EWA 3D → 2D and the SH colour in
// the forward; their adjoints in the backward, recomputing the forward's intermediates from the
// inputs instead of saving them). No compaction and no gathers: every Gaussian keeps its row, a
// culled one with zeros and radii (0, 0). The per-Gaussian math is projection_math.h, the header the
// CPU projection (projection_cpu.cpp) includes: built as that is (no FMA contraction, --fmad=false,
// IEEE division and square root; smgs/raster/projection_cuda.py), the two give the same bits.
#include <cuda_runtime.h>

#include "projection_cuda.h"

namespace smgs {
namespace cuda {

namespace {

constexpr int kThreads = 256;

__device__ __forceinline__ bool culled(const float* radii, int i) {
  return radii[2 * i] == 0.f && radii[2 * i + 1] == 0.f;
}

__device__ bool finite_row(const float* p, int64_t i, int w, bool pos_inf_ok = false) {
  bool ok = true;
  for (int k = 0; k < w; ++k) {
    const float v = p[i * w + k];
    ok &= pos_inf_ok ? !(isnan(v) || v == -INFINITY) : isfinite(v);
  }
  return ok;
}

// Row i passes the renderer's input checks (ProjChecks); the background by the first threads.
__device__ bool checked(const ProjIn& in, int64_t i) {
  if (!in.chk.bad) return true;
  if (i < in.chk.nbg && !isfinite(in.chk.bg[i])) atomicOr(in.chk.bad, 1);
  if (i >= in.n) return false;
  bool ok = finite_row(in.means3d, i, 3) && finite_row(in.quats, i, 4) && finite_row(in.scales, i, 3);
  for (int k = 0; k < 3; ++k) ok &= in.scales[3 * i + k] >= 0.f;
  if (in.sh) ok &= finite_row(in.sh, i, in.nbases * in.nch);
  for (int c = 0; c < in.chk.nrows; ++c)
    ok &= finite_row(in.chk.rows[c].p, i, in.chk.rows[c].width, in.chk.rows[c].pos_inf_ok);
  if (!ok) atomicOr(in.chk.bad, 1);
  return ok;
}

// DEG: the SH degree as a compile-time constant (-1: no colours), so that the basis arrays unroll
// into registers.
template <int DEG>
__global__ void __launch_bounds__(kThreads) project_fwd_kernel(ProjIn in, float* means2d, float* conics,
                                                               float* depths, float* radii, float* colors) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  const bool ok = checked(in, i);   // a row that fails the checks is culled: nothing of it renders
  if (i >= in.n) return;
  float m2[2], con[3], dep, rad[2];
  const bool keep = ok && proj::project_fwd(in.cam, in.means3d + 3 * int64_t(i), in.quats + 4 * int64_t(i),
                                            in.scales + 3 * int64_t(i), in.near, in.eps2d, in.ext, m2, con, &dep,
                                            rad);
  means2d[2 * int64_t(i)] = keep ? m2[0] : 0.f;
  means2d[2 * int64_t(i) + 1] = keep ? m2[1] : 0.f;
  for (int k = 0; k < 3; ++k) conics[3 * int64_t(i) + k] = keep ? con[k] : 0.f;
  depths[i] = keep ? dep : 0.f;
  radii[2 * int64_t(i)] = keep ? rad[0] : 0.f;
  radii[2 * int64_t(i) + 1] = keep ? rad[1] : 0.f;
  if (DEG < 0) return;
  float* col = colors + int64_t(i) * in.nch;
  if (keep)
    proj::sh_colour(DEG, in.sh + int64_t(i) * in.nbases * in.nch, in.nch, in.means3d + 3 * int64_t(i),
                    in.center, in.clamp, col);
  else
    for (int c = 0; c < in.nch; ++c) col[c] = 0.f;
}

template <int DEG>
__global__ void __launch_bounds__(kThreads) project_bwd_kernel(ProjIn in, const float* radii, ProjGrad g,
                                                               float* g_means, float* g_quats, float* g_scales,
                                                               float* g_sh) {
  const int i = blockIdx.x * blockDim.x + threadIdx.x;
  if (i >= in.n) return;
  const int64_t r = i;
  float* gm = g_means + 3 * r;
  float* gq = g_quats + 4 * r;
  float* gs = g_scales + 3 * r;
  float* gsh = DEG >= 0 ? g_sh + r * in.nbases * in.nch : nullptr;
  if (culled(radii, i)) {
    for (int k = 0; k < 3; ++k) gm[k] = gs[k] = 0.f;
    for (int k = 0; k < 4; ++k) gq[k] = 0.f;
    if (gsh)
      for (int k = 0; k < in.nbases * in.nch; ++k) gsh[k] = 0.f;
    return;
  }
  float m[3], q[4], s[3];   // registers: the header indexes them
  for (int k = 0; k < 3; ++k) {
    m[k] = in.means3d[3 * r + k];
    s[k] = in.scales[3 * r + k];
  }
  for (int k = 0; k < 4; ++k) q[k] = in.quats[4 * r + k];
  float g_means_k[3], g_quats_k[4], g_scales_k[3];
  proj::project_bwd(in.cam, m, q, s, in.near, in.eps2d, g.m2d + r * g.m2d_stride, g.con + r * g.con_stride,
                    g.depth[r * g.depth_stride], g_means_k, g_quats_k, g_scales_k);
  if (gsh)
    proj::sh_colour_bwd(DEG, in.nbases, in.sh + r * in.nbases * in.nch, in.nch, m, in.center, in.clamp,
                        g.col + r * g.col_stride, gsh, g_means_k);
  for (int k = 0; k < 3; ++k) {
    gm[k] = g_means_k[k];
    gs[k] = g_scales_k[k];
  }
  for (int k = 0; k < 4; ++k) gq[k] = g_quats_k[k];
}

inline int blocks_for(int n) { return (n + kThreads - 1) / kThreads; }

// F<DEG>::run(args...) for the input's degree (-1 without SH).
template <template <int> class F, class... A>
int by_degree(const ProjIn& in, A... args) {
  switch (in.sh ? in.degree : -1) {
    case -1: return F<-1>::run(in, args...);
    case 0: return F<0>::run(in, args...);
    case 1: return F<1>::run(in, args...);
    case 2: return F<2>::run(in, args...);
    case 3: return F<3>::run(in, args...);
    default: return int(cudaErrorInvalidValue);
  }
}

template <int DEG>
struct Fwd {
  static int run(const ProjIn& in, float* means2d, float* conics, float* depths, float* radii, float* colors,
                 cudaStream_t st) {
    const int threads = in.chk.bad ? (in.n > in.chk.nbg ? in.n : in.chk.nbg) : in.n;   // the background's too
    project_fwd_kernel<DEG><<<blocks_for(threads), kThreads, 0, st>>>(in, means2d, conics, depths, radii, colors);
    return int(cudaGetLastError());
  }
};

template <int DEG>
struct Bwd {
  static int run(const ProjIn& in, const float* radii, const ProjGrad& g, float* g_means, float* g_quats,
                 float* g_scales, float* g_sh, cudaStream_t st) {
    project_bwd_kernel<DEG><<<blocks_for(in.n), kThreads, 0, st>>>(in, radii, g, g_means, g_quats, g_scales, g_sh);
    return int(cudaGetLastError());
  }
};

}  // namespace

int project_forward(const ProjIn& in, float* means2d, float* conics, float* depths, float* radii, float* colors,
                    void* stream) {
  if (in.n == 0 && (!in.chk.bad || in.chk.nbg == 0)) return 0;
  return by_degree<Fwd>(in, means2d, conics, depths, radii, colors, static_cast<cudaStream_t>(stream));
}

int project_backward(const ProjIn& in, const float* radii, const ProjGrad& g, float* g_means, float* g_quats,
                     float* g_scales, float* g_sh, void* stream) {
  if (in.n == 0) return 0;
  return by_degree<Bwd>(in, radii, g, g_means, g_quats, g_scales, g_sh, static_cast<cudaStream_t>(stream));
}

const char* projection_error_string(int code) { return cudaGetErrorString(cudaError_t(code)); }

}  // namespace cuda
}  // namespace smgs
