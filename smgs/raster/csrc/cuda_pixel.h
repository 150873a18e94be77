// Host interface of the per-pixel order on CUDA (cuda_pixel.cu; part of the opt-in "v2" kernels,
// docs/cuda.md): StopThePop's bounded re-sorting window and the leading-splat map, forward and
// backward, the CUDA twin of cpu_pixel.cpp. It takes the default binning's packed rows, tile lists
// and boxes (cuda_kernel.h). Plain C++, no CUDA or torch types; launchers return the cudaError_t of
// the launch as an int (0 = success).
#pragma once

#include <cstddef>
#include <cstdint>

#include "cuda_kernel.h"

namespace smgs {
namespace cuda {
namespace pixel {

constexpr int kMaxWindow = 32;   // the longest window the kernels hold (per-thread arrays)

struct PixelIn {
  const int32_t* box;   // [N, 4] inclusive pixel boxes (x0, x1, y0, y1) of the binning
  const float* coefs;   // [N, 9] peak-depth coefficients (smgs/raster/ray_depth.py), input order
  float fx, fy, cx, cy; // intrinsics of the rays (host floats)
  int window;           // 1..kMaxWindow (1: the global order)
};

struct PixelOut {
  int32_t* lead;     // [H, W, 2] first two composited splats with a >= lead_alpha (-1 where fewer), or null
  float lead_alpha;
  int32_t* lend;     // [H, W] 1 + the furthest tile-list position composited (0 where none)
};

// Backward workspace: per thread, one record per composited step of its pixel (the splat, its list
// position and the state before the step), max_cnt records per thread, the thread's records
// contiguous; a persistent grid as the v2 compositing backward.
struct PixelBwdWork {
  float* grad;      // [N, S] zeroed by the caller
  float* steps;     // grid · 256 · max_cnt · step_record_floats(nch, soft) floats, 16-byte aligned
  int max_cnt;      // the largest per-pixel count
  int grid;
  int* counter;     // [1] zeroed by the caller
  float* chan;      // [2·(nch+1), H*W] when nch != 3 (else unused)
};

size_t step_record_floats(int nch, bool soft);
int backward_grid(const Scene& sc, int max_cnt, int64_t budget_bytes);

int forward(const Scene& sc, const PixelIn& pin, const FwdOut& out, const PixelOut& pout, void* stream);
int backward(const Scene& sc, const PixelIn& pin, const BwdIn& in, const PixelBwdWork& work, void* stream);

}  // namespace pixel
}  // namespace cuda
}  // namespace smgs
