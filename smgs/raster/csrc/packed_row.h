// The packed per-splat row every compiled kernel reads (the CPU core, cpu_core.h; the CUDA kernels,
// cuda_kernel.h): the parameters, then the colours, then the regularised values.
// P_CA..P_CC: in a parameter row the conic's factor (splat_factor), in a gradient row dL/d(a, b, c).
#pragma once

namespace smgs {

enum { P_MX = 0, P_MY, P_CA, P_CB, P_CC, P_O, P_D, P_AL, P_BE, P_GA, P_COL };

}  // namespace smgs
