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
from smgs.raster.cpu_build import cpu_extension
from smgs.raster.types import Eq15, RenderOutput, RenderStats, mode_flags

_CSRC = Path(__file__).parent / "csrc"
# The torch glue first; the compositing core's three units build in parallel with it (ninja).
_SOURCES = ("cpu_kernel.cpp", "cpu_fwd.cpp", "cpu_bwd.cpp", "cpu_bwd_soft.cpp")

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
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, alpha, beta, gamma, background,
                reg_values, cfg):
        ext = extension()
        empty = means2d.new_empty(0)
        opt = lambda t: empty if t is None else t  # noqa: E731
        width, height, use_gef, use_soft, k_max, solved, reg_scale, _ = cfg
        nthreads = torch.get_num_threads()
        (rgb, alpha_out, depth, reg, cnt, t_final, last, pairs, ids, pk, box, toff, tlist, soff,
         spos) = ext.forward(means2d, conics, opacities, colors, depths, opt(alpha), opt(beta), opt(gamma),
                              opt(background), opt(reg_values), width, height, use_gef, use_soft, k_max,
                              solved, reg_scale, nthreads, cfg[-1])
        ctx.save_for_backward(alpha_out, depth, t_final, last, ids, pk, box, toff, tlist, soff, spos,
                              opt(background))
        ctx.cfg = cfg
        ctx.meta = (means2d.shape[0], colors.shape[1], 0 if reg_values is None else reg_values.shape[1],
                    alpha is not None, beta is not None, background is not None, nthreads)
        ctx.mark_non_differentiable(cnt, pairs, t_final)
        return rgb, alpha_out, depth, reg, cnt, pairs, t_final

    @staticmethod
    def backward(ctx, g_rgb, g_alpha, g_depth, g_reg, _g_cnt, _g_pairs, _g_t):
        alpha_out, depth, t_final, last, ids, pk, box, toff, tlist, soff, spos, bg = ctx.saved_tensors
        width, height, use_gef, use_soft, k_max, solved, reg_scale, t_min = ctx.cfg
        n, nch, n_reg, has_alpha, has_soft, has_bg, nthreads = ctx.meta
        g_rgb, g_alpha, g_depth = (g.contiguous().float() for g in (g_rgb, g_alpha, g_depth))
        g_reg = g_reg.contiguous().float() if n_reg else g_rgb.new_empty(0)
        gm, gc, go, gcol, gd, gal, gbe, gga, grv = extension().backward(
            g_rgb, g_alpha, g_depth, g_reg, alpha_out, depth, t_final, last, ids, pk, box, toff, tlist, soff,
            spos, bg,
            n, nch, n_reg, width, height, use_gef, use_soft, k_max, solved, reg_scale, nthreads)
        g_bg = (g_rgb * t_final[..., None]).sum((0, 1)) if has_bg else None   # rgb += T·bg
        return (gm, gc, go, gcol, gd, gal if has_alpha else None, gbe if has_soft else None,
                gga if has_soft else None, g_bg, grv if n_reg else None, None)


def rasterize_splats_cpu(
    means2d: torch.Tensor,
    conics: torch.Tensor,
    opacities: torch.Tensor,
    colors: torch.Tensor,
    depths: torch.Tensor,
    alpha: torch.Tensor | None,
    beta: torch.Tensor | None,
    gamma: torch.Tensor | None,
    width: int,
    height: int,
    mode: str = "softmax_gs",
    k_max: int = K.DEFAULT_K_MAX,
    background: torch.Tensor | None = None,
    eq15: Eq15 = "solved",
    reg_values: torch.Tensor | None = None,
    reg_depth_scale: float = 1.0,
    t_min: float = K.T_MIN,
) -> RenderOutput:
    """Composite projected splats on the CPU; see ``smgs.raster.rasterize_splats`` for the arguments.
    float32 CPU tensors only."""
    use_gef, use_soft = mode_flags(mode)
    if eq15 not in ("solved", "printed"):
        raise ValueError(f"eq15 must be 'solved' or 'printed', got {eq15!r}")
    for name, t in (("means2d", means2d), ("conics", conics), ("opacities", opacities), ("colors", colors),
                    ("depths", depths)):
        if t.device.type != "cpu" or t.dtype != torch.float32:
            raise TypeError(f"cpu backend: {name} must be a float32 CPU tensor, got {t.dtype} on {t.device}")
    if width <= 0 or height <= 0:
        raise ValueError(f"image size must be positive, got {width}x{height}")
    f32 = lambda t: None if t is None else t.to(torch.float32).contiguous()  # noqa: E731
    bg = None if background is None else background.to(torch.float32).reshape(-1).contiguous()
    if bg is not None and bg.numel() != colors.shape[1]:
        raise ValueError(f"background must have {colors.shape[1]} channels, got {bg.numel()}")
    cfg = (int(width), int(height), use_gef, use_soft, int(k_max), eq15 == "solved", float(reg_depth_scale),
           float(t_min))
    rgb, alpha_out, depth, reg, cnt, pairs, _ = _RasterizeCPU.apply(
        means2d.contiguous(), conics.contiguous(), opacities.contiguous(), colors.contiguous(),
        depths.contiguous(), f32(alpha) if use_gef else None, f32(beta) if use_soft else None,
        f32(gamma) if use_soft else None, bg, f32(reg_values), cfg)
    stats = RenderStats(n_contrib=cnt.long(), pairs_evaluated=int(pairs.item()),
                        k_max=int(k_max) if use_soft else 2**31 - 1)
    return RenderOutput(rgb=rgb, alpha=alpha_out, depth=depth, stats=stats,
                        reg=reg if reg_values is not None else None)
