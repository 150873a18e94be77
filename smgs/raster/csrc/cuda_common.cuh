// Device code the CUDA compositing kernels share: the default ones (cuda_kernel.cu) and the opt-in
// v2 ones (cuda_v2_kernel.cu, cuda_pixel.cu). Only what is the same to the letter in each lives
// here; each file compiles it with its own flags (the default without FMA contraction, v2 with it).
// In an anonymous namespace, as it was in each file: every translation unit keeps its own copy.
#pragma once

#include <cuda_runtime.h>

#include <algorithm>
#include <cstdint>

#include "cuda_kernel.h"
#include "splat_math.h"

namespace smgs {
namespace cuda {
namespace {

constexpr int kBlock = kTileSize * kTileSize;  // threads per block, one per pixel of a tile
constexpr unsigned kFull = 0xffffffffu;

inline cudaStream_t as_stream(void* s) { return static_cast<cudaStream_t>(s); }
inline int last_error() { return int(cudaGetLastError()); }

// Per-pixel channel state (colours, then the depth channel): registers when the channel count is a
// compile-time constant, else a pixel-private column of a [channels, pixels] buffer in global memory.
template <int NCT>
struct Chan {
  float v[NCT + 1];
  __device__ Chan(float*, int64_t) {}
  __device__ float& operator[](int c) { return v[c]; }
};
template <>
struct Chan<0> {
  float* p;
  int64_t stride;
  __device__ Chan(float* base, int64_t s) : p(base), stride(s) {}
  __device__ float& operator[](int c) { return p[c * stride]; }
};

__device__ __forceinline__ float warp_sum(float v) {
  for (int o = 16; o > 0; o >>= 1) v += __shfl_xor_sync(kFull, v, o);
  return v;
}

// Adds a per-lane value, summed over the warp, to *dst (one atomic per warp; lanes that do not
// contribute pass 0). Call with the whole warp.
__device__ __forceinline__ void warp_add(float* dst, float v) {
  v = warp_sum(v);
  if ((threadIdx.x & 31) == 0) atomicAdd(dst, v);
}

// This thread's pixel of a tile (one thread per pixel, one block per 16x16 tile) and the tile's
// range in the sorted list.
struct Pixel {
  int x, y;
  bool inside;
  int64_t pix, npix;
  float px, py;
  int start, n;  // the tile's range in the sorted list
  __device__ Pixel(const Scene& sc, int tile) {
    x = (tile % sc.tiles_x) * kTileSize + int(threadIdx.x) % kTileSize;
    y = (tile / sc.tiles_x) * kTileSize + int(threadIdx.x) / kTileSize;
    inside = x < sc.W && y < sc.H;
    npix = int64_t(sc.W) * sc.H;
    pix = inside ? int64_t(y) * sc.W + x : 0;
    px = float(x) + kPixelCenter;
    py = float(y) + kPixelCenter;
    start = sc.ranges[2 * tile];
    n = sc.ranges[2 * tile + 1] - start;
  }
};

// f(L<GEF, SOFT, NCT>{}) for the scene's mode, NCT = 3 for three channels, else 0 (any count): the
// opt-in kernels' launchers (cuda_v2_kernel.cu, cuda_pixel.cu) are instantiated per mode this way.
template <template <bool, bool, int> class L, class F>
int dispatch_mode(const Scene& sc, F&& f) {
  if (sc.nch == 3) {
    if (sc.gef) return sc.soft ? f(L<true, true, 3>{}) : f(L<true, false, 3>{});
    return sc.soft ? f(L<false, true, 3>{}) : f(L<false, false, 3>{});
  }
  if (sc.gef) return sc.soft ? f(L<true, true, 0>{}) : f(L<true, false, 0>{});
  return sc.soft ? f(L<false, true, 0>{}) : f(L<false, false, 0>{});
}

// Blocks of a persistent grid (blocks that take tiles from a counter until none is left): as many as
// the device holds at once (per_sm blocks on each multiprocessor), at most `tiles`, and at most what
// `budget_bytes` of scratch holds at `block_bytes` a block; at least 1.
inline int persistent_grid(int per_sm, int64_t tiles, int64_t block_bytes, int64_t budget_bytes) {
  int dev = 0, sms = 1;
  cudaGetDevice(&dev);
  cudaDeviceGetAttribute(&sms, cudaDevAttrMultiProcessorCount, dev);
  int64_t grid = std::min<int64_t>(int64_t(per_sm) * sms, tiles);
  if (block_bytes > 0) grid = std::min<int64_t>(grid, std::max<int64_t>(1, budget_bytes / block_bytes));
  return int(std::max<int64_t>(1, grid));
}

}  // namespace
}  // namespace cuda
}  // namespace smgs
