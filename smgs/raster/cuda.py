"""Compiled CUDA backend: GPU tile binning and (tile, depth) radix sort, compositing forward and a
hand-written backward, one thread per pixel (the 3DGS layout).

Built just in time with ``torch.utils.cpp_extension.load`` on first use, when PyTorch is a CUDA
build, a CUDA device is visible and the CUDA toolkit (nvcc) is found; cached like the CPU
backend (``smgs.raster.buildcache``, keyed by the sources, flags and GPU archs). Sources:
``csrc/cuda_kernel.cu`` (kernels and launchers, no torch types), ``csrc/cuda_binding.cpp``
(tensors and the binning pipeline's host steps) and ``csrc/splat_math.h``, the per-splat math the CPU
kernel includes too, so the GPU runs the math the CPU tests check.

The interface mirrors ``smgs.raster.cpu``: ``rasterize_splats_cuda`` takes the splats and settings
of ``smgs.raster.rasterize_splats`` (``composite_inputs``; float32 CUDA tensors) and returns the
same ``RenderOutput``.
Nothing here touches CUDA at import time, so importing this module is safe on any machine;
``is_available()`` is False with ``unavailable_reason()`` saying why. Set
``SMGS_DISABLE_CUDA_BACKEND=1`` to switch it off (``auto`` then falls back to the reference).
"""

from __future__ import annotations

import logging
import os
from pathlib import Path

import torch

from smgs.raster import constants as K
from smgs.raster.buildcache import ExtensionSpec, compile_and_load
from smgs.raster.jit import JitExtension
from smgs.raster.composite_inputs import CompositeSettings, Splats2D
from smgs.raster.kernel_args import kernel_grads, kernel_inputs, kernel_output, no_splats
from smgs.raster.types import RenderOutput

log = logging.getLogger(__name__)

_CSRC = Path(__file__).parent / "csrc"
SOURCES = ("cuda_binding.cpp", "cuda_kernel.cu")
# --fmad=false keeps a·b + c as two roundings, as PyTorch evaluates the reference, so the reach
# tests (q <= 4.5, a >= 1/255, T < 1e-4) see the same numbers as the other backends.
CUDA_CFLAGS = ["-O3", "--fmad=false"]
CFLAGS = ["-O3"]
# The binning indexes each splat's four-int pixel box with 32-bit arithmetic (4·i in prepare and
# emit, csrc/cuda_kernel.cu), so one render bins at most 2^29 splats; more are refused here with the
# fix rather than overflowing on the GPU.
MAX_SPLATS = 2**29
# Bound of the backward's softmax-head scratch (k_max entries per pixel of the tiles in flight);
# larger frames are processed in chunks of tiles, so memory never grows with pixels x k_max.
HEAD_BUDGET_BYTES = 512 * 2**20


def _why_not_buildable() -> str | None:
    """The first missing prerequisite, or None (cheap checks only; never initialises a device
    beyond torch.cuda.is_available())."""
    if os.environ.get("SMGS_DISABLE_CUDA_BACKEND", "") not in ("", "0"):
        return "disabled by SMGS_DISABLE_CUDA_BACKEND"
    if torch.version.cuda is None:
        return f"PyTorch {torch.__version__} is not a CUDA build (torch.version.cuda is None)"
    if not torch.cuda.is_available():
        return "no CUDA device visible (torch.cuda.is_available() is False)"
    from torch.utils.cpp_extension import CUDA_HOME

    if CUDA_HOME is None:
        return "no CUDA toolkit found (set CUDA_HOME, or put nvcc on PATH)"
    from torch.utils.cpp_extension import is_ninja_available

    if not is_ninja_available():
        return "no ninja build tool (pip install ninja)"
    return None


def _arch_tag() -> str:
    """Compute capabilities of the visible devices: the JIT build targets them, so a cache shared
    with another GPU kind must not load this one's binary."""
    caps = sorted({"%d%d" % torch.cuda.get_device_capability(i) for i in range(torch.cuda.device_count())})
    return "_".join(caps)


def _build(suffix: str = "", defines: tuple[str, ...] = ()):
    return compile_and_load(ExtensionSpec(
        name=f"smgs_raster_cuda{suffix}", sources=tuple(_CSRC / s for s in SOURCES), what="CUDA renderer backend",
        include_dirs=(_CSRC,), cflags=tuple(CFLAGS) + defines, cuda_cflags=tuple(CUDA_CFLAGS) + defines,
        target=f"sm{_arch_tag()} {os.environ.get('TORCH_CUDA_ARCH_LIST', '')}"))


# no CUDA here is the common case, not worth a warning: quiet_precheck
_JIT = JitExtension("cuda", _build, _why_not_buildable, quiet_precheck=True, disable="SMGS_DISABLE_CUDA_BACKEND")
is_available = _JIT.is_available
unavailable_reason = _JIT.unavailable_reason


def extension(t_min: float = K.T_MIN):
    """The loaded extension module (builds it if needed); raises if it cannot be built. A ``t_min``
    other than the default is compiled in (``-DSMGS_T_MIN``; the CPU backend takes it at run
    time): one more build per value, cached like the default one."""
    return _JIT.module(t_min)


def check_splat_count(n: int) -> None:
    """Refuse more splats than the CUDA binning indexes (``MAX_SPLATS``), naming the way out."""
    if n > MAX_SPLATS:
        raise ValueError(f"{n:,} splats in one render: the CUDA kernels bin at most {MAX_SPLATS:,} (2^29, their "
                         "32-bit box indexing); prune the model below that, or render with backend='cpu'")


def composite_forward(ctx, ext, inputs: tuple, st: CompositeSettings, *cull: torch.Tensor | None) -> tuple:
    """The forward of a CUDA compositing Function (default or v2): ``ext.forward`` on the ten tensors
    of ``kernel_args.INPUTS`` (empty where None), then ``cull`` (v2: the cull marks), then the
    settings; keeps what the backward needs on ``ctx``."""
    means2d, conics, opacities, colors, depths, alpha, beta, gamma, background, reg_values = inputs
    empty = means2d.new_empty(0)
    opt = lambda t: empty if t is None else t  # noqa: E731
    rgb, alpha_out, depth, reg, cnt, t_final, last, pairs, pk, ranges, tile_list = ext.forward(
        means2d, conics, opacities, colors, depths, opt(alpha), opt(beta), opt(gamma), opt(background),
        opt(reg_values), *(opt(t) for t in cull), st.width, st.height, st.use_gef, st.use_softmax, st.k_max,
        st.solved, st.reg_depth_scale, st.patch)
    ctx.save_for_backward(alpha_out, depth, t_final, last, cnt, pk, ranges, tile_list, opt(background))
    ctx.settings = st
    ctx.ext = ext
    ctx.n_splats = means2d.shape[0]
    ctx.n_channels = colors.shape[1]
    ctx.n_reg = 0 if reg_values is None else reg_values.shape[1]
    ctx.mark_non_differentiable(cnt, pairs, t_final, last)
    # `last` (1 + the tile-list position of the last composited splat) is the stats' list_end
    return rgb, alpha_out, depth, reg, cnt, pairs, t_final, last


def composite_backward(ctx, g_rgb, g_alpha, g_depth, g_reg, head_budget_bytes: int) -> tuple:
    """``ext.backward``'s outputs for the image gradients, with the ``g_rgb`` and final transmittance
    that ``kernel_args.kernel_grads`` reads the background's gradient from."""
    alpha_out, depth, t_final, last, cnt, pk, ranges, tile_list, bg = ctx.saved_tensors
    st = ctx.settings
    g_rgb, g_alpha, g_depth = (g.contiguous().float() for g in (g_rgb, g_alpha, g_depth))
    g_reg = g_reg.contiguous().float() if ctx.n_reg else g_rgb.new_empty(0)
    grads = ctx.ext.backward(
        g_rgb, g_alpha, g_depth, g_reg, alpha_out, depth, t_final, last, cnt, pk, ranges, tile_list, bg,
        ctx.n_splats, ctx.n_channels, ctx.n_reg, st.width, st.height, st.use_gef, st.use_softmax, st.k_max,
        st.solved, st.reg_depth_scale, head_budget_bytes, st.patch)
    return grads, g_rgb, t_final


class _RasterizeCUDA(torch.autograd.Function):
    """Same inputs and outputs as ``cpu._RasterizeCPU``, then the loaded extension."""

    @staticmethod
    def forward(ctx, *args):   # the ten tensors of kernel_args.INPUTS, the settings, the extension
        *inputs, st, ext = args
        return composite_forward(ctx, ext, tuple(inputs), st)

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_reg, _g_cnt, _g_pairs, _g_t, _g_last):
        grads, g_rgb, t_final = composite_backward(ctx, g_rgb, g_alpha, g_depth, g_reg, HEAD_BUDGET_BYTES)
        return kernel_grads(ctx, grads, g_rgb, t_final, n_settings=2)


def composite(ext, splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """``rasterize_splats_cuda`` with the extension passed in (the argument plumbing is tested
    without a GPU by passing a stand-in extension). ``st.t_min`` is already compiled into ``ext``."""
    if splats.ray_depth is not None or st.leaders or splats.radii is not None:
        raise ValueError("the default CUDA kernels composite in the global order without the leading-splat map "
                         "or cull marks; rasterize_splats routes those elsewhere (docs/cuda.md)")
    if splats.n == 0:   # nothing to composite (kernel_args.no_splats); the kernel is not called
        return no_splats(splats, st)
    check_splat_count(splats.n)
    args = kernel_inputs(splats, st)
    rgb, alpha_out, depth, reg, cnt, pairs, _, last = _RasterizeCUDA.apply(*args, st, ext)
    return kernel_output(st, rgb, alpha_out, depth, reg if splats.reg_values is not None else None, cnt, pairs,
                         list_end=last)


def rasterize_splats_cuda(splats: Splats2D, st: CompositeSettings) -> RenderOutput:
    """Composite projected splats on a CUDA device: float32 tensors on one device, checked by
    ``smgs.raster.rasterize_splats`` (which has the arguments) before they arrive here. ``st.t_min``
    (the early-stop transmittance) is compiled into the kernel: a value other than the default
    costs one more build."""
    return composite(extension(st.t_min), splats, st)
