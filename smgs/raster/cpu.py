"""Compiled CPU backend (C++, SIMD over the pixels of a tile, threads over tiles): forward and
hand-written backward.

Built just in time with ``torch.utils.cpp_extension.load`` on first use and cached (in
``$TORCH_EXTENSIONS_DIR`` or ``~/.cache/torch_extensions``) by a key of the sources, flags and CPU
kind (``smgs.raster.buildcache``); later processes load the cached library in well under a second.
The sources are ``csrc/cpu_kernel.cpp`` (torch glue, binning, sort) and the compositing core
``csrc/cpu_{fwd,bwd,bwd_soft}.cpp`` over ``cpu_tiles.h``, with the SIMD layer ``simd.h``, the
threads ``parallel.h`` and the per-splat math ``splat_math.h`` (shared with the CUDA backend). Same images and gradients as ``smgs.raster.reference`` to float32
rounding (tests/test_raster_cpu.py states the tolerances).

SIMD path: avx512, avx2 (x86-64-v3), neon (aarch64) or scalar, the best the host runs unless
``SMGS_CPU_ISA`` names one (``isa()`` says which is in use). The renderer's threads are its own
(``torch.get_num_threads()`` of them, blocking waits); the projection and loss kernels use torch's
pool and need OpenMP for more than one thread (``openmp_flags``). ``t_min`` is a run-time argument.

Set ``SMGS_DISABLE_CPU_BACKEND=1`` to make ``is_available()`` report False (``auto`` then falls back
to the reference); so does a missing compiler or ninja. Any other build failure raises ``BuildError``.
"""

from __future__ import annotations

from pathlib import Path

import torch

from smgs.raster import constants as K
from smgs.raster.composite_inputs import CompositeSettings, Splats2D
from smgs.raster.cpu_build import cpu_extension
from smgs.raster.kernel_args import kernel_grads, kernel_inputs, kernel_output, no_splats, output_grads
from smgs.raster.kernel_clock import kernel
from smgs.raster.types import RayDepth, RenderOutput

_CSRC = Path(__file__).parent / "csrc"
# The torch glue first; the compositing core's three units build in parallel with it (ninja).
_SOURCES = ("cpu_kernel.cpp", "cpu_fwd.cpp", "cpu_bwd.cpp", "cpu_bwd_soft.cpp", "cpu_pixel.cpp")

_JIT = cpu_extension("smgs_raster_cpu", [_CSRC / s for s in _SOURCES], "renderer backend", [_CSRC])
is_available = _JIT.is_available
unavailable_reason = _JIT.unavailable_reason


def extension():
    """The loaded extension module of the selected SIMD path (builds it if needed); raises if it
    cannot be built. ``t_min`` is a run-time argument of its kernels: one build serves every value."""
    return _JIT.module()


def isa() -> str:
    """The SIMD path of the compiled renderer in use (builds it if needed): avx512, avx2, neon or
    scalar."""
    return extension().isa()


class _RasterizeCPU(torch.autograd.Function):
    """Inputs in the order of ``rasterize_splats`` (optional ones None), then the settings; the
    outputs' counters and final transmittance carry no gradient."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, alpha, beta, gamma, background,
                reg_values, settings: CompositeSettings):
        ext = extension()
        empty = means2d.new_empty(0)
        opt = lambda t: empty if t is None else t  # noqa: E731
        st = settings
        nthreads = torch.get_num_threads()
        with kernel("composite fwd"):
            (rgb, alpha_out, depth, reg, cnt, t_final, last, pairs, ids, pk, box, toff, tlist, soff,
             spos, list_end) = ext.forward(means2d, conics, opacities, colors, depths, opt(alpha), opt(beta),
                                           opt(gamma), opt(background), opt(reg_values), st.width, st.height,
                                           st.use_gef, st.use_softmax, st.k_max, st.solved, st.reg_depth_scale,
                                           nthreads, st.t_min, st.patch)
        ctx.save_for_backward(alpha_out, depth, t_final, last, ids, pk, box, toff, tlist, soff, spos,
                              opt(background))
        ctx.settings = st
        ctx.n_splats = means2d.shape[0]
        ctx.n_channels = colors.shape[1]
        ctx.n_reg = 0 if reg_values is None else reg_values.shape[1]
        ctx.nthreads = nthreads   # the backward sums per-tile rows in the forward's order
        ctx.mark_non_differentiable(cnt, pairs, t_final, list_end)
        ctx.set_materialize_grads(False)   # no zero gradients made for the counters (output_grads)
        return rgb, alpha_out, depth, reg, cnt, pairs, t_final, list_end

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_reg, _g_cnt, _g_pairs, _g_t, _g_end):
        alpha_out, depth, t_final, last, ids, pk, box, toff, tlist, soff, spos, bg = ctx.saved_tensors
        st = ctx.settings
        g_rgb, g_alpha, g_depth, g_reg = output_grads(ctx, g_rgb, g_alpha, g_depth, g_reg, alpha_out)
        with kernel("composite bwd"):
            grads = extension().backward(
                g_rgb, g_alpha, g_depth, g_reg, alpha_out, depth, t_final, last, ids, pk, box, toff, tlist, soff,
                spos, bg, ctx.n_splats, ctx.n_channels, ctx.n_reg, st.width, st.height, st.use_gef, st.use_softmax,
                st.k_max, st.solved, st.reg_depth_scale, ctx.nthreads, st.patch)
        return kernel_grads(ctx, grads, g_rgb, t_final)


class _RasterizePixelCPU(torch.autograd.Function):
    """sort="per_pixel" through the re-sorting window (csrc/cpu_pixel.cpp): inputs as
    ``_RasterizeCPU`` without reg_values, then the coefficients and intrinsics of the peak depths
    and the settings. Where a gradient is needed the forward records each pixel's composited steps
    in its order (the order carries no gradient), and the backward replays them. With
    ``lead_alpha >= 0`` it also returns the leading-splat map (else an empty tensor)."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, coefs, intr,
                settings: CompositeSettings, window: int, lead_alpha: float):
        empty = means2d.new_empty(0)
        opt = lambda t: empty if t is None else t  # noqa: E731
        st = settings
        with kernel("composite fwd"):
            (rgb, alpha_out, depth, cnt, t_final, pairs, ids, pk, box, toff, tlist, soff, spos, order,
             order_off, leaders, list_end) = extension().forward_pixel(
                means2d, conics, opacities, colors, depths, opt(alpha), opt(beta), opt(gamma), opt(background),
                coefs, intr, st.width, st.height, st.use_gef, st.use_softmax, st.k_max, st.solved,
                torch.get_num_threads(), st.t_min, window, any(ctx.needs_input_grad[:9]), lead_alpha, st.patch)
        ctx.save_for_backward(alpha_out, depth, cnt, t_final, ids, pk, box, toff, tlist, soff, spos, order, order_off,
                              opt(background))
        ctx.settings = st
        ctx.n_splats = means2d.shape[0]
        ctx.n_channels = colors.shape[1]
        ctx.mark_non_differentiable(cnt, pairs, t_final, leaders, list_end)
        return rgb, alpha_out, depth, cnt, pairs, t_final, leaders, list_end

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, _g_cnt, _g_pairs, _g_t, _g_lead, _g_end):
        alpha_out, depth, cnt, t_final, ids, pk, box, toff, tlist, soff, spos, order, order_off, bg = ctx.saved_tensors
        st = ctx.settings
        g_rgb, g_alpha, g_depth = (g.contiguous().float() for g in (g_rgb, g_alpha, g_depth))
        with kernel("composite bwd"):
            grads = extension().backward_pixel(
                g_rgb, g_alpha, g_depth, alpha_out, depth, cnt, ids, pk, box, toff, tlist, soff, spos, order,
                order_off, bg, ctx.n_splats, ctx.n_channels, st.width, st.height, st.use_gef, st.use_softmax,
                st.k_max, st.solved, torch.get_num_threads(), st.t_min, st.patch)
        # kernel_grads' order ends with reg_values (none here): then coefs, intr, settings, window,
        # lead_alpha
        return kernel_grads(ctx, grads, g_rgb, t_final, n_settings=0)[:-1] + (None,) * 5


def _per_pixel(st: CompositeSettings, args: tuple, ray_depth: RayDepth | None) -> RenderOutput:
    """The per-pixel kernel (csrc/cpu_pixel.cpp), with gradients: sort="per_pixel" through the
    re-sorting window, or (``ray_depth`` None) the global order, for the leading-splat map: zero
    peak-depth coefficients make every key the centre depth, which the window keeps in order."""
    means2d, conics, opacities, colors, depths, alpha, beta, gamma, bg, reg_values = args
    what = "sort='per_pixel'" if ray_depth is not None else "leaders=True"
    if reg_values is not None:
        raise ValueError(f"{what} on the cpu backend has no variance-regulariser sums (reg_values); "
                         "render without reg_values or with backend='reference'")
    window = st.window
    if ray_depth is None:
        coefs, intr = means2d.new_zeros(means2d.shape[0], 9), means2d.new_tensor([1.0, 1.0, 0.0, 0.0])
        window = 1
    else:
        coefs = ray_depth.coefs.detach().to(torch.float32).contiguous()
        intr = means2d.new_tensor([ray_depth.fx, ray_depth.fy, ray_depth.cx, ray_depth.cy])   # on its device
    rgb, alpha_out, depth, cnt, pairs, _, leaders, list_end = _RasterizePixelCPU.apply(
        means2d, conics, opacities, colors, depths, alpha, beta, gamma, bg, coefs, intr, st, int(window),
        K.LEADER_ALPHA if st.leaders else -1.0)
    return kernel_output(st, rgb, alpha_out, depth, None, cnt, pairs, leaders if st.leaders else None, list_end)


def rasterize_splats_cpu(splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """Composite projected splats on the CPU: float32 CPU tensors, checked by
    ``smgs.raster.rasterize_splats`` (which has the arguments) before they arrive here. With
    ``splats.ray_depth``: per-pixel order through a re-sorting window of ``st.window`` splats (no
    ``reg_values``). ``st.leaders`` renders through the per-pixel kernel (a scalar path, in either
    order) to give the leading-splat map too."""
    if splats.n == 0:   # nothing to composite (smgs.raster.kernel_args.no_splats)
        return no_splats(splats, st)
    args = kernel_inputs(splats, st)
    if splats.ray_depth is not None or st.leaders:
        return _per_pixel(st, args, splats.ray_depth)
    rgb, alpha_out, depth, reg, cnt, pairs, _, list_end = _RasterizeCPU.apply(*args, st)
    return kernel_output(st, rgb, alpha_out, depth, reg if splats.reg_values is not None else None, cnt, pairs,
                         list_end=list_end)
