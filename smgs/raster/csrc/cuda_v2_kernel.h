// Host interface of the opt-in CUDA compositing kernels ("v2", cuda_v2_kernel.cu; docs/cuda.md).
// They take the default backend's packed rows, tile lists and outputs (cuda_kernel.h: Scene, FwdOut,
// BwdIn; the binning is the default's), so only what differs is declared here. Plain C++, no CUDA or
// torch types; launchers return the cudaError_t of the launch as an int (0 = success).
#pragma once

#include <cstddef>
#include <cstdint>

#include "cuda_kernel.h"

namespace smgs {
namespace cuda {
namespace v2 {

// Leaves out of the binning the rows the fused projection culled (radii (0, 0)): their tile count
// becomes 0, so they get no keys. Run between prepare() and scan_tiles().
int cull_by_radii(const float* radii, int64_t* ntiles, int n, void* stream);

// Backward workspace. The softmax head of each thread is kept as whole 32-byte records (two float4:
// T, A, d_past, p_past, then the colour and depth state, padded to a multiple of four floats), the
// records of one thread contiguous, so that a lane's record is one sector whatever step its pixel is
// at. The grid is persistent: `grid` blocks take tiles from `counter` until none is left, so the
// scratch is sized by the blocks in flight (slots = grid · 256), not by the tiles.
struct BwdWork {
  float* grad;     // [N, S] zeroed by the caller; gradients in the pk layout, input order
  float* head;     // grid · 256 · kmax_eff · head_record_floats(nch) floats, 16-byte aligned (or null)
  int kmax_eff;    // min(k_max, largest per-pixel count); 0 when there is no softmax head
  int grid;        // blocks of the persistent backward (backward_grid)
  int* counter;    // [1] zeroed by the caller: the next tile to take
  float* chan;     // [2·(nch+1), H*W] colour state and its adjoint when nch != 3 (else unused)
};

size_t head_record_floats(int nch);
// Blocks of the persistent backward: the blocks the device holds at once (occupancy of the mode's
// kernel times the multiprocessors), at most the tiles, and at most what `budget_bytes` of head
// scratch holds (at least 1). Writes the occupancy per multiprocessor to *per_sm when given.
int backward_grid(const Scene& sc, int kmax_eff, int64_t budget_bytes, int* per_sm);

int forward(const Scene& sc, const FwdOut& out, void* stream);
int backward(const Scene& sc, const BwdIn& in, const BwdWork& work, void* stream);

}  // namespace v2
}  // namespace cuda
}  // namespace smgs
