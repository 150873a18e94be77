"""EWA projection and SH colours of 3D Gaussians on a CUDA device, one fused kernel each way
(``csrc/projection_cuda.cu``), part of the opt-in CUDA kernels (the cuda backend's kernel set "v2",
``smgs.raster.backends``; docs/cuda.md).

Unlike ``smgs.raster.projection.project_gaussians`` nothing is compacted: every Gaussian keeps its
row, a culled one (behind the near plane, or its 3σ box off the image) with zeros and radii (0, 0),
which the v2 compositing leaves out of the binning. So there are no gathers, no ``nonzero`` and no
host synchronisation, and the camera enters as 25 host floats (kernel arguments, no device copy).
The backward recomputes the per-Gaussian intermediates from the inputs (nothing but the inputs and
the radii is saved). The per-Gaussian math is ``csrc/projection_math.h``, the header of the compiled
CPU projection; built, as that is, without FMA contraction, the two give the same bits
(tests/test_raster_projection_cuda.py, marked gpu).

Nothing here touches CUDA at import time; ``is_available()`` says whether the kernels can be built
and run here, ``unavailable_reason()`` why not.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import torch
from torch.autograd.function import once_differentiable

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster.buildcache import ExtensionSpec, compile_and_load
from smgs.raster.jit import JitExtension
from smgs.raster.projection import host_view

_CSRC = Path(__file__).parent / "csrc"
SOURCES = ("projection_cuda_binding.cpp", "projection_cuda.cu")
# As the CPU projection's -ffp-contract=off: no FMA contraction, IEEE division and square root, so
# the CUDA and the CPU build of projection_math.h agree bit for bit.
CUDA_CFLAGS = ["-O3", "--fmad=false"]
CFLAGS = ["-O3"]


def _why_not_buildable() -> str | None:
    from smgs.raster import cuda

    return cuda._why_not_buildable()   # the CUDA backend's prerequisites, its switch included


def _build(suffix: str = "", defines: tuple[str, ...] = ()):
    from smgs.raster.cuda import _arch_tag

    return compile_and_load(ExtensionSpec(
        name=f"smgs_projection_cuda{suffix}", sources=tuple(_CSRC / s for s in SOURCES), what="CUDA projection kernels",
        include_dirs=(_CSRC,), cflags=tuple(CFLAGS) + defines, cuda_cflags=tuple(CUDA_CFLAGS) + defines,
        target=f"sm{_arch_tag()} {os.environ.get('TORCH_CUDA_ARCH_LIST', '')}"))


_JIT = JitExtension("cuda", _build, _why_not_buildable, quiet_precheck=True, what="projection kernels",
                    disable="SMGS_DISABLE_CUDA_BACKEND")
is_available = _JIT.is_available
unavailable_reason = _JIT.unavailable_reason


def extension():
    """The loaded extension module (builds it if needed); raises if it cannot be built."""
    return _JIT.module()


def camera_floats(camera: Camera) -> list[float]:
    """The 25 host floats the kernels take: ``projection.host_view`` with the camera centre, in
    float32 (rw, tw, f, c, lo, hi, size, centre; the centre is the SH directions' origin), made once
    per camera (``Camera.memo``). A camera on a device is read back (a synchronisation); the
    trainer's cameras live on the host."""
    return list(camera.memo(("floats",), lambda: host_view(camera, torch.float32, center=True).tolist()))


@dataclass
class FusedProjection:
    """Every Gaussian's splat (no compaction): culled rows are zeros with radii (0, 0)."""

    means2d: torch.Tensor   # [N, 2]
    conics: torch.Tensor    # [N, 3]
    depths: torch.Tensor    # [N]
    radii: torch.Tensor     # [N, 2] (no gradient); (0, 0) where culled
    colors: torch.Tensor | None   # [N, C] from SH where sh_degree was given, else None
    bad: torch.Tensor | None = None   # [1] int32, non-zero where an input failed the kernel's checks


@dataclass
class KernelChecks:
    """The renderer's input checks the forward kernel makes beside its own inputs (the lean glue,
    smgs.raster.checks.InputChecks.in_kernel): these per-Gaussian tensors ([N] or [N, w]; +inf allowed
    in those named in ``pos_inf_ok``) and the background. A Gaussian holding NaN or ±inf in any of
    them or in means3d, quats, scales, sh, or a negative scale, is culled (nothing of it renders)
    and raises the output's ``bad``."""

    rows: list[tuple[str, torch.Tensor]]
    pos_inf_ok: tuple[str, ...] = ()
    background: torch.Tensor | None = None

    def args(self, like: torch.Tensor) -> tuple[list[torch.Tensor], list[int], torch.Tensor]:
        rows = [(n, t.detach().contiguous()) for n, t in self.rows if t is not None and t.numel()]
        bg = like.new_empty(0) if self.background is None else self.background.detach().contiguous().to(like.device)
        return [t for _, t in rows], [int(n in self.pos_inf_ok) for n, _ in rows], bg


class _ProjectCUDA(torch.autograd.Function):
    """(means3d, quats, scales, sh) -> (means2d, conics, depths, radii, colours) on every row."""

    @staticmethod
    def forward(ctx, means3d, quats, scales, sh, cam: list[float], near_plane: float, eps2d: float,
                degree: int, clamp: bool, ext, checks: KernelChecks | None):  # type: ignore[override]
        rows, inf_ok, bg = checks.args(means3d) if checks is not None else ([], [], means3d.new_empty(0))
        m2, con, dep, radii, col, bad = ext.forward(means3d, quats, scales, sh, cam, near_plane, eps2d,
                                                    K.SIGMA_EXTENT, degree, clamp, checks is not None, rows, inf_ok, bg)
        ctx.save_for_backward(means3d, quats, scales, sh, radii)
        ctx.args = (cam, near_plane, eps2d, degree, clamp)
        ctx.ext = ext
        ctx.mark_non_differentiable(radii, bad)
        ctx.set_materialize_grads(False)   # no zero-filled gradients for outputs the loss did not reach
        if sh.numel() == 0:
            ctx.mark_non_differentiable(col)
        return m2, con, dep, radii, col, bad

    @staticmethod
    @once_differentiable
    def backward(ctx, g_m2d, g_con, g_dep, _g_radii, g_col, _g_bad):  # type: ignore[override]
        means3d, quats, scales, sh, radii = ctx.saved_tensors
        cam, near_plane, eps2d, degree, clamp = ctx.args
        n = means3d.shape[0]
        # absent gradients are zeros; row-strided ones (columns of the compositing's packed
        # gradient) are read in place
        rows = lambda g, k: g if g is not None and (k == 1 or g.stride(-1) == 1) else (  # noqa: E731
            means3d.new_zeros(n, k).squeeze(-1) if g is None else g.contiguous())
        g_col = rows(g_col, sh.shape[2]) if sh.numel() else means3d.new_empty(0)
        g_means, g_quats, g_scales, g_sh = ctx.ext.backward(
            means3d, quats, scales, sh, cam, near_plane, eps2d, degree, clamp, radii, rows(g_m2d, 2),
            rows(g_con, 3), rows(g_dep, 1), g_col)
        return g_means, g_quats, g_scales, (g_sh if sh.numel() else None), None, None, None, None, None, None, None


def project_fused(means3d: torch.Tensor, quats: torch.Tensor, scales: torch.Tensor, camera: Camera,
                  sh: torch.Tensor | None = None, sh_degree: int | None = None, clamp_sh_colors: bool = True,
                  near_plane: float = K.NEAR_PLANE, eps2d: float = K.EPS2D, ext=None,
                  checks: KernelChecks | None = None) -> FusedProjection:
    """The projection of every Gaussian (float32 CUDA tensors) in one kernel, and with ``sh [N,K,C]``
    and ``sh_degree`` their colours (rasterize's: SH + 0.5, clamped at 0 unless
    ``clamp_sh_colors=False``). ``checks``: the renderer's input checks made in the same kernel
    (``KernelChecks``; the output's ``bad``). ``ext`` stands in for the extension in the CPU
    plumbing test."""
    ext = extension() if ext is None else ext
    c = lambda t: t.contiguous()  # noqa: E731
    if sh is not None and sh_degree is None:
        raise ValueError("sh needs sh_degree (0..3)")
    sh_t = c(sh) if sh is not None else means3d.new_empty(0)
    m2, con, dep, radii, col, bad = _ProjectCUDA.apply(c(means3d), c(quats), c(scales), sh_t, camera_floats(camera),
                                                       float(near_plane), float(eps2d),
                                                       -1 if sh_degree is None else int(sh_degree),
                                                       bool(clamp_sh_colors), ext, checks)
    return FusedProjection(m2, con, dep, radii, col if sh is not None else None, bad if checks is not None else None)
