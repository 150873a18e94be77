// Host interface of the CUDA projection (projection_cuda.cu): plain C++ with raw device pointers and
// no CUDA or torch types, as cuda_kernel.h, so that the torch binding (projection_cuda_binding.cpp)
// and the kernels (nvcc alone) compile separately. The camera arrives as plain host floats (kernel
// arguments: no device copy, no synchronisation). Launchers return the cudaError_t of the launch as
// an int (0 = success).
#pragma once

#include <cstdint>

#include "projection_math.h"

namespace smgs {
namespace cuda {

// The renderer's input checks done by the forward kernel itself (the lean glue; null `bad`: none):
// a Gaussian whose means3d, quats, scales, SH or any row of `rows` holds NaN or ±inf (+inf allowed
// where pos_inf_ok: γ), or a negative scale, is culled and sets `bad`; so is a background [nbg]
// holding one. The host reads `bad` after the render and names the input (smgs/raster/checks.py).
constexpr int kMaxRowChecks = 6;
struct RowCheck {
  const float* p;  // [N, width]
  int width;
  bool pos_inf_ok;
};
struct ProjChecks {
  RowCheck rows[kMaxRowChecks];
  int nrows, nbg;
  const float* bg;
  int* bad;  // [1], zeroed by the binding
};

struct ProjIn {
  const float *means3d, *quats, *scales;  // [N,3] [N,4] [N,3]
  const float* sh;                        // [N,K,C] SH coefficients, or null (colours are not computed)
  int n, nbases, nch, degree;             // nbases = K >= (degree + 1)²
  bool clamp;                             // colours clamped at 0 (rasterize's clamp_sh_colors)
  float near, eps2d, ext;                 // near plane, 2D dilation, sigma extent of the radii
  proj::Cam cam;
  float center[3];                        // camera centre in world coordinates (the SH directions)
  ProjChecks chk;                         // the forward's input checks (chk.bad null: none)
};

// Every Gaussian's row, no compaction: means2d [N,2], conics [N,3], depths [N], radii [N,2] and
// (with sh) colours [N,C]. A culled Gaussian (behind the near plane, or its 3σ box off the image)
// gets zeros in every output, radii (0, 0) included: the binning skips it.
int project_forward(const ProjIn& in, float* means2d, float* conics, float* depths, float* radii, float* colors,
                    void* stream);
// Gradients of the forward's outputs, each row-strided (the compositing backward hands them as
// columns of one packed [N, S] buffer, no copies): row i of means2d at m2d + i·m2d_stride, etc.
// Within a row the entries are contiguous. g_col is null without sh.
struct ProjGrad {
  const float *m2d, *con, *depth, *col;
  int64_t m2d_stride, con_stride, depth_stride, col_stride;
};

// Gradients of means3d [N,3], quats [N,4], scales [N,3] and (with sh) sh [N,K,C]; zeros for culled
// rows (radii (0, 0)). Every output row is written (no zeroing needed).
int project_backward(const ProjIn& in, const float* radii, const ProjGrad& g, float* g_means, float* g_quats,
                     float* g_scales, float* g_sh, void* stream);

const char* projection_error_string(int code);

}  // namespace cuda
}  // namespace smgs
