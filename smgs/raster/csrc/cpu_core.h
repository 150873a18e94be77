// Interface of the compiled CPU renderer's compositing core (forward and backward over 16x16 tiles,
// OpenMP across tiles, the 16 pixels of a 4x4 block as SIMD lanes; templates in cpu_tiles.h, compiled
// in cpu_fwd.cpp, cpu_bwd.cpp and cpu_bwd_soft.cpp, which build in parallel). No torch headers, so
// that the SIMD paths and the core compile on their own (tests cross-compile them for aarch64). The
// torch glue, binning and depth sort are in cpu_kernel.cpp.
#pragma once

#include <algorithm>
#include <cmath>
#include <cstdint>
#include <cstring>
#include <vector>

#include "packed_row.h"  // the packed per-splat rows (depth order here)
#include "splat_math.h"

namespace smgs {

struct Scene {
  int W = 0, H = 0, nch = 0, R = 0, S = 0, M = 0;
  int tiles_x = 0, tiles_y = 0;
  int kmax = 0;
  // k_max scope (docs/kmax-scope.md): false = a pixel's first k_max composited splats form its
  // softmax head; true = the tile-list entries at positions < k_max, the same for every pixel of a tile
  bool patch = false;
  bool solved = true;
  float reg_scale = 1.f;
  const float* pk = nullptr;       // [M, S]
  const int32_t* box = nullptr;    // [M, 4] inclusive pixel ranges x0, x1, y0, y1
  const int32_t* toff = nullptr;   // [tiles + 1]
  const int32_t* tlist = nullptr;  // [L] rows of pk, ascending = depth order
  const float* bg = nullptr;       // [nch] or null
  int nthreads = 1;
  float tstop = kTStop;             // stop before T < t_min: t_min·(1 - T_STOP_SLACK), in float32
};

struct FwdOut {
  float *rgb, *alpha, *depth, *Tf, *reg;
  int32_t *last, *cnt;
  // [H, W] or null: 1 + the furthest tile-list position composited (0 where none), for the patch
  // scope's coverage statistic
  int32_t* lend = nullptr;
  // per-pixel path only: [H, W, 2] the first two composited splats with a >= lead_alpha, as pk rows
  // (-1 where fewer), or null
  int32_t* lead = nullptr;
  float lead_alpha = 1.f;
};

struct BwdIn {
  const float *g_rgb, *g_alpha, *g_depth, *g_reg;  // g_reg may be null; g_alpha, g_depth too in backward()
  const float *alpha, *depth, *Tf;
  const int32_t* last;
};

inline int padded(int S) { return (S + 15) & ~15; }  // rows on 64-byte boundaries

// The compositing passes (the mode's template instance chosen at run time) and the SIMD path
// compiled in (simd.h: avx512, avx2, neon or scalar).
int64_t forward_tiles(const Scene& sc, const FwdOut& o, bool gef, bool soft);
void backward_tiles(const Scene& sc, const BwdIn& in, float* G, bool gef, bool soft);
void backward_tiles_soft(const Scene& sc, const BwdIn& in, float* G, bool gef);
const char* simd_isa();
// sort="per_pixel" (cpu_pixel.cpp): each pixel re-sorts its tile's depth-ordered list in a window of
// `window` splats by peak depth (coefs [M, 9] in pk row order; intrinsics fx, fy, cx, cy). o.reg
// and o.last are not written. With `order`, the forward records per tile the tile-list positions of
// every composited step, pixel by pixel in row-major order within the tile; the backward (in.Tf,
// in.last and in.g_reg are not read) replays them and fills G as backward_tiles does.
struct PixelOrder {
  const int32_t* pos;   // the tiles' records one after another
  const int64_t* off;   // [tiles + 1] where each tile's records start
  const int32_t* cnt;   // [H, W] composited steps per pixel (the forward's n_contrib)
};
int64_t forward_pixel_tiles(const Scene& sc, const FwdOut& o, const float* coefs, const float* intr, int window,
                            bool gef, bool soft, std::vector<std::vector<int32_t>>* order);
void backward_pixel_tiles(const Scene& sc, const BwdIn& in, float* G, const PixelOrder& order, bool gef, bool soft);

}  // namespace smgs
