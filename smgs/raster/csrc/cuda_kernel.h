// Host interface of the CUDA backend (smgs/raster/csrc/cuda_kernel.cu), plain C++ with raw device
// pointers and no CUDA or torch types, so that the torch binding (cuda_binding.cpp, built by torch's
// extension builder on a machine with a CUDA build of torch) and the kernels (built by nvcc alone)
// compile separately. Streams are passed as void* (a cudaStream_t). Every launcher enqueues its work
// on that stream and returns the cudaError_t of the launch as an int (0 = success).
#pragma once

#include <cstddef>
#include <cstdint>

#include "packed_row.h"  // the packed per-splat rows (input order here), the CPU kernel's layout

namespace smgs {
namespace cuda {

// Dynamic shared memory of a compositing block (a batch of packed rows; the default 48 KiB limit less
// room for the kernels' static shared variables), and so the longest packed row.
constexpr int kSharedBytes = 48 * 1024 - 256;
constexpr int kMaxRow = kSharedBytes / 4;

struct SplatsIn {
  const float *means2d, *conics, *opacities, *colors, *depths;  // [N,2] [N,3] [N] [N,C] [N]
  const float *alpha, *beta, *gamma;                            // [N] or null (then 1, 0, 0)
  const float* reg_values;                                      // [N,R] or null
  int n, nch, nreg;
};

// ---- binning: visibility and 3σ boxes, per-splat tile counts, prefix sum, (tile, depth) keys,
// radix sort, per-tile ranges -- the 3DGS pipeline.
// pk [N, P_COL + nch + nreg]; box [N,4] (x0, x1, y0, y1 inclusive); ntiles [N] (0 if invisible);
// dbits [N] (depth as order-preserving bits).
int prepare(const SplatsIn& in, int W, int H, float* pk, int32_t* box, int64_t* ntiles, uint32_t* dbits,
            void* stream);
size_t scan_temp_bytes(int n);
// offs = inclusive prefix sum of ntiles
int scan_tiles(void* temp, size_t temp_bytes, const int64_t* ntiles, int64_t* offs, int n, void* stream);
// keys = tile << 32 | dbits, vals = splat index, each visible splat at offs[i] - ntiles[i] ...
int emit_keys(const int32_t* box, const int64_t* ntiles, const int64_t* offs, const uint32_t* dbits, int n,
              int tiles_x, uint64_t* keys, int32_t* vals, void* stream);
int sort_key_bits(int ntiles);  // bits of the key to sort: 32 depth bits + enough for the tile ids
size_t sort_temp_bytes(int count, int end_bit);
int sort_keys(void* temp, size_t temp_bytes, const uint64_t* keys_in, uint64_t* keys_out, const int32_t* vals_in,
              int32_t* vals_out, int count, int end_bit, void* stream);
// ranges [ntiles, 2]: [start, end) of each tile in the sorted list (zeroed first; count may be 0)
int tile_ranges(const uint64_t* keys, int count, int ntiles, int32_t* ranges, void* stream);

// ---- compositing ---------------------------------------------------------------------------------
struct Scene {
  const float* pk;
  int S, nch, nreg;
  const int32_t* ranges;  // [tiles, 2]
  const int32_t* vals;    // sorted tile list: splat indices
  int W, H, tiles_x, tiles_y;
  bool gef, soft, solved;
  int kmax;
  // k_max scope (docs/kmax-scope.md): false = a pixel's first k_max composited splats form its
  // softmax head; true = the tile-list entries at positions < k_max, the same for every pixel of a tile
  bool patch;
  float reg_scale;
  const float* bg;  // [nch] or null
};

struct FwdOut {
  float *rgb, *alpha, *depth, *Tf;  // [H,W,nch] [H,W] [H,W] [H,W]
  float* reg;                       // [H,W,1+2R] or null
  int32_t *last, *cnt;              // [H,W]: 1 + tile-list position of the last composited splat; count
  unsigned long long* pairs;        // [1], zeroed by the caller
  float* chan;                      // [(nch+1), H*W] colour state when nch != 3 (else unused)
};
size_t fwd_chan_floats(int nch, int W, int H);

struct BwdIn {
  const float *g_rgb, *g_alpha, *g_depth, *g_reg;  // g_reg null when R = 0
  const float *alpha, *depth, *Tf;
  const int32_t *last, *cnt;
};

struct BwdWork {
  float* grad;       // [N, S] zeroed by the caller; gradients in the pk layout, input order
  float* head;       // softmax head scratch: kmax_eff · (5 + nch) floats per thread slot
  int64_t slots;     // thread slots of `head` (a multiple of 256: tiles per launch = slots / 256)
  int kmax_eff;      // min(k_max, largest per-pixel count); 0 when there is no softmax head
  float* chan;       // [2·(nch+1), H*W] colour state and its adjoint when nch != 3 (else unused)
};
size_t bwd_chan_floats(int nch, int W, int H);
size_t head_entry_floats(int nch);  // floats per head entry and thread: T, A, d_past, p_past, C[nch+1]

int forward(const Scene& sc, const FwdOut& out, void* stream);
int backward(const Scene& sc, const BwdIn& in, const BwdWork& work, void* stream);

const char* error_string(int code);
// Numeric conventions as compiled into the device code (see smgs/raster/constants.py).
void constants(double* out10);

}  // namespace cuda
}  // namespace smgs
