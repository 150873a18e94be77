"""Compiled CPU backend (C++/OpenMP, SIMD over the pixels of a tile): forward and hand-written backward.

Built just in time with ``torch.utils.cpp_extension.load`` on first use and cached (in
``$TORCH_EXTENSIONS_DIR`` or ``~/.cache/torch_extensions``) by a key of the sources, flags and CPU
kind (``smgs.raster.buildcache``); later processes load the cached library in well under a second.
The sources are ``csrc/cpu_kernel.cpp`` and ``csrc/splat_math.h`` (the per-splat math shared with
other compiled backends). Same images and gradients as
``smgs.raster.reference`` to float32 rounding (tests/test_raster_cpu.py states the tolerances).

Set ``SMGS_DISABLE_CPU_BACKEND=1`` to make ``is_available()`` report False (``auto`` then falls back
to the reference); so does a missing compiler or ninja. Any other build failure raises ``BuildError``.
"""

from __future__ import annotations

import hashlib
import logging
import os
import platform
import shutil
from pathlib import Path

import torch

from smgs.raster import constants as K
from smgs.raster.buildcache import ExtensionSpec, compile_and_load
from smgs.raster.jit import JitExtension
from smgs.raster.types import Eq15, RenderOutput, RenderStats, mode_flags

log = logging.getLogger(__name__)

_CSRC = Path(__file__).parent / "csrc"
DISABLE = "SMGS_DISABLE_CPU_BACKEND"
_SOURCES = ("cpu_kernel.cpp",)
_HEADERS = ("splat_math.h",)
# -ffp-contract=off keeps a·b + c as two roundings, as PyTorch evaluates the reference, so the
# reach tests (q <= 4.5, a >= 1/255, T < 1e-4) see the same numbers; FMAs are written explicitly
# where wanted. -fno-math-errno / -fno-trapping-math only let sqrt and selects vectorise: unlike
# -ffast-math they keep NaN/inf semantics.
_CFLAGS = ["-O3", "-march=native", "-fopenmp", "-ffp-contract=off", "-fno-math-errno",
           "-fno-trapping-math", "-std=c++17"]


def _cpu_tag() -> str:
    """-march=native code must not be loaded on another CPU kind sharing the cache directory."""
    ident = platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "flags", "Features")):
                    ident += line
                if line.strip() == "":
                    break
    except OSError:
        ident += platform.processor()
    return hashlib.sha1(ident.encode()).hexdigest()[:10]


def _precheck() -> str | None:
    """A missing toolchain (or the switch) is "unavailable"; any other build failure is an error."""
    if os.environ.get(DISABLE, "") not in ("", "0"):
        return f"disabled by {DISABLE}"
    if shutil.which(os.environ.get("CXX", "c++")) is None:
        return f"no C++ compiler ({os.environ.get('CXX', 'c++')!r} not on PATH)"
    from torch.utils.cpp_extension import is_ninja_available

    if not is_ninja_available():
        return "no ninja build tool (pip install ninja)"
    return None


def cpu_extension(name: str, sources: list[Path], what: str, include: list[Path] | None = None) -> JitExtension:
    """A compiled CPU extension of smgs (``_CFLAGS``, OpenMP), built just in time on first use and
    cached by a key of its sources, flags and CPU kind (``smgs.raster.buildcache``): the renderer
    here, the projection and the training loss elsewhere."""

    def build(suffix: str, defines: tuple[str, ...]):
        return compile_and_load(ExtensionSpec(
            name=f"{name}{suffix}", sources=tuple(sources), what=what, include_dirs=tuple(include or ()),
            cflags=tuple(_CFLAGS) + tuple(defines), ldflags=("-fopenmp",), target=_cpu_tag()))

    return JitExtension("cpu", build, _precheck, what=what, disable=DISABLE)


class UnsupportedInput(ValueError, RuntimeError):
    """Inputs a compiled CPU kernel does not take, where it was required (``fused=True``): a bad
    argument (ValueError), and like the kernel's other refusals a RuntimeError."""


def use_cpu_kernel(ext: JitExtension, fused: bool | None, tensors: tuple[torch.Tensor, ...], takes: str) -> bool:
    """Whether to run a compiled CPU kernel (the projection, the training loss) rather than its
    PyTorch path: ``fused`` None = wherever it applies (float32 CPU ``tensors``) and builds; True =
    required (UnsupportedInput naming what it takes, RuntimeError naming why it cannot build);
    False = never."""
    if fused is False:
        return False
    applies = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
    if fused is True:
        if not applies:
            got = ", ".join(f"{t.dtype} on {t.device}" for t in tensors)
            raise UnsupportedInput(f"the compiled {ext.what} takes float32 CPU {takes}; got {got}")
        if not ext.is_available():
            raise RuntimeError(f"the compiled {ext.what} is unavailable: {ext.unavailable_reason()}")
        return True
    return applies and ext.is_available()


_JIT = cpu_extension("smgs_raster_cpu", [_CSRC / s for s in _SOURCES], "renderer backend", [_CSRC])
is_available = _JIT.is_available
unavailable_reason = _JIT.unavailable_reason


def extension(t_min: float = K.T_MIN):
    """The loaded extension module (builds it if needed); raises if it cannot be built. A
    ``t_min`` other than the default is compiled in (``-DSMGS_T_MIN``): one more build per value,
    cached like the default one."""
    return _JIT.module(t_min)


class _RasterizeCPU(torch.autograd.Function):
    @staticmethod
    def forward(ctx, means2d, conics, opacities, colors, depths, alpha, beta, gamma, background,
                reg_values, cfg):
        ext = extension(cfg[-1])
        empty = means2d.new_empty(0)
        opt = lambda t: empty if t is None else t  # noqa: E731
        width, height, use_gef, use_soft, k_max, solved, reg_scale, _ = cfg
        nthreads = torch.get_num_threads()
        (rgb, alpha_out, depth, reg, cnt, t_final, last, pairs, ids, pk, box, toff, tlist, soff,
         spos) = ext.forward(means2d, conics, opacities, colors, depths, opt(alpha), opt(beta), opt(gamma),
                              opt(background), opt(reg_values), width, height, use_gef, use_soft, k_max,
                              solved, reg_scale, nthreads)
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
        gm, gc, go, gcol, gd, gal, gbe, gga, grv = extension(t_min).backward(
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
