"""The opt-in CUDA kernels ("v2"; docs/cuda.md): the fused projection (``projection_cuda``), the
v2 compositing kernels (``csrc/cuda_v2_kernel.cu``: FMA with bit-equal reach and stop decisions, a
lean shared-memory batch, the softmax backward's head as whole 32-byte records in a persistent grid)
and the per-pixel order and leading-splat map on the GPU (``csrc/cuda_pixel.cu``, the twin of the
CPU backend's re-sorting window).

The cuda backend's kernel set "v2" (``smgs.raster.backends``): selected with
``rasterize(..., backend=Renderer("cuda", kernels="v2"))`` (or ``"auto"``), ``renderer.kernels=v2`` in
a run's config or ``SMGS_CUDA_KERNELS=v2``; the default stays ``smgs.raster.cuda`` (the kernels that
ran on a GPU once, changed since: docs/cuda.md#what-has-run-on-a-gpu) until a GPU run has verified
these (tests/test_raster_cuda_v2.py, marked gpu). The interface mirrors ``smgs.raster.cuda``; the
compositing takes ``radii`` in addition, the fused projection's cull marks.
"""

from __future__ import annotations

import os
from pathlib import Path

import torch

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster import cuda
from smgs.raster.buildcache import ExtensionSpec, compile_and_load
from smgs.raster.jit import JitExtension
from smgs.raster.composite_inputs import CompositeSettings, Splats2D
from smgs.raster.kernel_args import kernel_grads, kernel_inputs, kernel_output, no_splats
from smgs.raster.types import RenderOutput

_CSRC = Path(__file__).parent / "csrc"
# cuda_kernel.cu brings the default backend's binning (prepare, prefix sum, keys, sort, ranges)
SOURCES = ("cuda_v2_binding.cpp", "cuda_kernel.cu", "cuda_v2_kernel.cu", "cuda_pixel.cu")
# FMA contraction on (nvcc's default); the reach arithmetic is written with mul_rn/add_rn, which are
# never fused (splat_math.h), so the decisions stay the other backends'.
CUDA_CFLAGS = ["-O3", "--fmad=true"]
CFLAGS = ["-O3"]
# Bound of the softmax backward's head scratch (the persistent grid shrinks to fit it).
HEAD_BUDGET_BYTES = 512 * 2**20
# Bound of the per-pixel backward's step records (every composited step of the pixels in flight).
PIXEL_BUDGET_BYTES = 512 * 2**20

def _why_not_buildable() -> str | None:
    return cuda._why_not_buildable()


def _build(suffix: str = "", defines: tuple[str, ...] = ()):
    return compile_and_load(ExtensionSpec(
        name=f"smgs_raster_cuda_v2{suffix}", sources=tuple(_CSRC / s for s in SOURCES),
        what="CUDA renderer kernels (v2)", include_dirs=(_CSRC,), cflags=tuple(CFLAGS) + defines,
        cuda_cflags=tuple(CUDA_CFLAGS) + defines,
        target=f"sm{cuda._arch_tag()} {os.environ.get('TORCH_CUDA_ARCH_LIST', '')}"))


_JIT = JitExtension("cuda", _build, _why_not_buildable, quiet_precheck=True, what="renderer kernels (v2)",
                    disable="SMGS_DISABLE_CUDA_BACKEND")
is_available = _JIT.is_available
unavailable_reason = _JIT.unavailable_reason


def extension(t_min: float = K.T_MIN):
    """The loaded v2 extension (builds it if needed; a non-default ``t_min`` is compiled in)."""
    return _JIT.module(t_min)


class _RasterizeCUDAv2(torch.autograd.Function):
    """``cuda._RasterizeCUDA`` with the v2 extension and the cull marks ``radii``; the backward's
    gradient comes packed ([N, S], ``split_packed``)."""

    @staticmethod
    def forward(ctx, *args):   # the ten tensors of kernel_args.INPUTS, radii, the settings, the extension
        *inputs, radii, st, ext = args
        return cuda.composite_forward(ctx, ext, tuple(inputs), st, radii)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_reg, _g_cnt, _g_pairs, _g_t, _g_last):
        (grad,), g_rgb, t_final = cuda.composite_backward(ctx, g_rgb, g_alpha, g_depth, g_reg, HEAD_BUDGET_BYTES)
        grads = split_packed(grad, ctx.ext.layout(), ctx.n_channels, ctx.n_reg)
        return kernel_grads(ctx, grads, g_rgb, t_final, n_settings=3)   # radii, settings, ext


def split_packed(grad: torch.Tensor, layout: list[int], nch: int, nreg: int) -> list[torch.Tensor]:
    """The gradients of means2d, conics, opacities, colors, depths, alpha, beta, gamma, reg_values as
    column views of the packed [N, S] gradient (no copies; ``layout`` is the binding's ``layout()``)."""
    mx, my, ca, cc, o, d, al, be, ga, col = layout
    assert my == mx + 1 and cc == ca + 2, layout
    return [grad[:, mx:my + 1], grad[:, ca:cc + 1], grad[:, o], grad[:, col:col + nch], grad[:, d], grad[:, al],
            grad[:, be], grad[:, ga], grad[:, col + nch:col + nch + nreg]]


def composite(ext, splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """The v2 compositing with the extension passed in (the CPU plumbing test passes a stand-in);
    ``splats.radii`` [N,2] (optional): rows with radii (0, 0) are not splats (the fused
    projection's culled Gaussians)."""
    if splats.n == 0:   # nothing to composite (kernel_args.no_splats, as the default kernels' wrapper)
        return no_splats(splats, st)
    cuda.check_splat_count(splats.n)
    args = kernel_inputs(splats, st)
    r = None if splats.radii is None else splats.radii.detach().contiguous()
    rgb, alpha_out, depth, reg, cnt, pairs, _, last = _RasterizeCUDAv2.apply(*args, r, st, ext)
    return kernel_output(st, rgb, alpha_out, depth, reg if splats.reg_values is not None else None, cnt, pairs,
                         list_end=last)


def rasterize_splats_cuda_v2(splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """``smgs.raster.cuda.rasterize_splats_cuda`` through the v2 kernels (``composite``)."""
    return composite(extension(st.t_min), splats, st)


def rasterize_fused(means3d: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, opacities: torch.Tensor,
                    colors_or_sh: torch.Tensor, camera: Camera, alpha: torch.Tensor | None,
                    beta: torch.Tensor | None, gamma: torch.Tensor | None, background: torch.Tensor | None,
                    reg_values: torch.Tensor | None, st: CompositeSettings, sh_degree: int | None, near_plane: float,
                    eps2d: float, clamp_sh_colors: bool, exts: tuple | None = None, input_checks=None) -> RenderOutput:
    """``smgs.raster.rasterize`` on CUDA tensors through the opt-in kernels, the inputs already checked
    there: the fused projection (and SH) of every Gaussian, then the v2 compositing, which skips the
    culled rows. No gathers: the extras' ``ids`` are all Gaussians (``arange``), ``radii`` (0, 0)
    marking the culled ones, as the densification statistics read them. ``exts`` = (projection,
    compositing) stand-ins for the CPU plumbing test. ``input_checks`` (``checks.InputChecks``)
    where it left the input checks to the kernels (the lean glue, ``in_kernel``): the projection
    makes them, culling what is bad, and its flag is copied to the host before the compositing's
    wait, which it then rides on."""
    from smgs.raster import projection_cuda

    pext, cext = exts if exts is not None else (projection_cuda.extension(), extension(st.t_min))
    sh = colors_or_sh if sh_degree is not None else None
    chk, checks = input_checks, None
    if chk is not None and chk.awaits_kernel_flag:
        checks = projection_cuda.KernelChecks(
            [("opacities", opacities), ("colors", None if sh is not None else colors_or_sh),
             ("alpha", alpha if st.use_gef else None), ("beta", beta if st.use_softmax else None),
             ("gamma", gamma if st.use_softmax else None), ("reg_values", reg_values)],
            pos_inf_ok=("gamma",), background=background)
    proj = projection_cuda.project_fused(means3d, quats, scales, camera, sh=sh, sh_degree=sh_degree,
                                         clamp_sh_colors=clamp_sh_colors, near_plane=near_plane, eps2d=eps2d,
                                         ext=pext, checks=checks)
    if checks is not None:
        chk.kernel_flag(proj.bad)
        chk.start()
    colors = proj.colors if sh is not None else colors_or_sh
    out = composite(cext, Splats2D(proj.means2d, proj.conics, opacities, colors, proj.depths, alpha, beta, gamma,
                                   background, reg_values, radii=proj.radii), st)
    ids = torch.arange(means3d.shape[0], device=means3d.device)
    out.extras.update(ids=ids, means2d=proj.means2d, radii=proj.radii)
    return out


class _RasterizePixelCUDA(torch.autograd.Function):
    """sort="per_pixel" / the leading-splat map through csrc/cuda_pixel.cu (the twin of
    ``cpu._RasterizePixelCPU``): inputs as ``rasterize_splats`` (no reg_values), then the peak-depth
    coefficients and the settings."""

    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, coefs,
                settings: CompositeSettings, intr: list[float], window: int, lead_alpha: float, ext):
        st = settings
        empty = means2d.new_empty(0)
        opt = lambda t: empty if t is None else t  # noqa: E731
        (rgb, alpha_out, depth, cnt, t_final, pairs, leaders, list_end, pk, ranges, tile_list,
         box) = ext.forward_pixel(means2d, conics, opacities, colors, depths, opt(alpha), opt(beta), opt(gamma),
                                  opt(background), coefs, intr, st.width, st.height, st.use_gef, st.use_softmax,
                                  st.k_max, st.solved, window, lead_alpha, st.patch)
        ctx.save_for_backward(alpha_out, depth, cnt, t_final, pk, ranges, tile_list, box, coefs, opt(background))
        ctx.settings, ctx.ext, ctx.intr, ctx.window = st, ext, intr, window
        ctx.n_splats, ctx.n_channels, ctx.n_reg = means2d.shape[0], colors.shape[1], 0
        ctx.mark_non_differentiable(cnt, pairs, t_final, leaders, list_end)
        return rgb, alpha_out, depth, cnt, pairs, t_final, leaders, list_end

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, _g_cnt, _g_pairs, _g_t, _g_lead, _g_end):
        alpha_out, depth, cnt, t_final, pk, ranges, tile_list, box, coefs, bg = ctx.saved_tensors
        st = ctx.settings
        g_rgb, g_alpha, g_depth = (g.contiguous().float() for g in (g_rgb, g_alpha, g_depth))
        (grad,) = ctx.ext.backward_pixel(
            g_rgb, g_alpha, g_depth, alpha_out, depth, cnt, pk, ranges, tile_list, box, coefs, ctx.intr, bg,
            ctx.n_splats, ctx.n_channels, st.width, st.height, st.use_gef, st.use_softmax, st.k_max, st.solved,
            ctx.window, st.patch, PIXEL_BUDGET_BYTES)
        grads = split_packed(grad, ctx.ext.layout(), ctx.n_channels, 0)
        # kernel_grads' ten inputs end with reg_values, here the coefficients (no gradient); then the
        # settings, intrinsics, window, lead_alpha and the extension
        return kernel_grads(ctx, grads, g_rgb, t_final, n_settings=0)[:9] + (None,) * 6


def composite_pixel(ext, splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """The per-pixel kernels with the extension passed in: sort="per_pixel" through the re-sorting
    window of ``st.window`` splats (``splats.ray_depth``), or (``ray_depth`` None) the global order
    for the leading-splat map (zero peak-depth coefficients make every key the centre depth, which a
    window of 1 keeps in order), as ``cpu._per_pixel``."""
    cuda.check_splat_count(splats.n)
    args = kernel_inputs(splats, st)
    ray_depth = splats.ray_depth
    what = "sort='per_pixel'" if ray_depth is not None else "leaders=True"
    if args[9] is not None:
        raise ValueError(f"{what} on the cuda backend has no variance-regulariser sums (reg_values); "
                         "render without reg_values or with backend='reference'")
    if ray_depth is None:
        coefs, intr, window = splats.means2d.new_zeros(splats.n, 9), [1.0, 1.0, 0.0, 0.0], 1
    else:
        coefs = ray_depth.coefs.detach().to(torch.float32).contiguous()
        intr = [float(ray_depth.fx), float(ray_depth.fy), float(ray_depth.cx), float(ray_depth.cy)]
        window = st.window
    rgb, alpha_out, depth, cnt, pairs, _, leaders, list_end = _RasterizePixelCUDA.apply(
        *args[:9], coefs, st, intr, int(window), K.LEADER_ALPHA if st.leaders else -1.0, ext)
    return kernel_output(st, rgb, alpha_out, depth, None, cnt, pairs, leaders if st.leaders else None, list_end)


def rasterize_splats_pixel_cuda(splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """``rasterize_splats`` with ``ray_depth`` and/or ``leaders`` on CUDA tensors, through the
    per-pixel kernels (csrc/cuda_pixel.cu, the CPU window's twin; windows up to 32 splats)."""
    return composite_pixel(extension(st.t_min), splats, st)
