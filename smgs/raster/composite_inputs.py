"""What every compositing backend takes: the projected splats' tensors (``Splats2D``) and the
non-tensor settings of the call (``CompositeSettings``, made and checked by ``composite_settings``).
A backend is ``fn(splats, settings) -> RenderOutput``; the flat argument list is written once, in
``smgs.raster.api.rasterize_splats`` (the public entry point, which has the arguments' meanings)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable

import torch

from smgs.raster import checks
from smgs.raster import constants as K
from smgs.raster.types import MODES, Eq15, KMaxScope, RayDepth, mode_flags, scope_is_patch


@dataclass(frozen=True)
class Splats2D:
    """The tensors of one compositing call (``rasterize_splats`` has their shapes): the projected
    splats, the per-splat parameters a mode uses (None where it ignores them), the background, the
    regulariser's values, the peak-depth coefficients of a per-pixel order (``ray_depth``), and the
    fused projection's cull marks (``radii`` [N,2], read by the opt-in CUDA kernels only)."""

    means2d: torch.Tensor
    conics: torch.Tensor
    opacities: torch.Tensor
    colors: torch.Tensor
    depths: torch.Tensor
    alpha: torch.Tensor | None = None
    beta: torch.Tensor | None = None
    gamma: torch.Tensor | None = None
    background: torch.Tensor | None = None
    reg_values: torch.Tensor | None = None
    ray_depth: RayDepth | None = None
    radii: torch.Tensor | None = None

    @property
    def n(self) -> int:
        return self.means2d.shape[0]

    def per_splat(self) -> tuple[torch.Tensor | None, ...]:
        """means2d, conics, opacities, colors, depths, alpha, beta, gamma (the order of the kernels'
        gradients)."""
        return (self.means2d, self.conics, self.opacities, self.colors, self.depths, self.alpha, self.beta,
                self.gamma)

    def mapped(self, fn: Callable[[torch.Tensor], torch.Tensor]) -> Splats2D:
        """``fn`` applied to every tensor (None stays None; the ray-depth coefficients detached)."""
        opt = lambda t: None if t is None else fn(t)  # noqa: E731
        rd = self.ray_depth
        return Splats2D(*(opt(t) for t in self.per_splat()), background=opt(self.background),
                        reg_values=opt(self.reg_values), radii=opt(self.radii),
                        ray_depth=None if rd is None else RayDepth(fn(rd.coefs.detach()), rd.fx, rd.fy, rd.cx, rd.cy))


@dataclass(frozen=True)
class CompositeSettings:
    """The non-tensor settings of one compositing call, kept whole on the autograd context."""

    width: int
    height: int
    use_gef: bool
    use_softmax: bool
    k_max: int
    solved: bool
    reg_depth_scale: float
    t_min: float
    patch: bool = False     # k_max scope "patch" (docs/kmax-scope.md)
    leaders: bool = False   # the leading-splat map too (RenderOutput.leaders)
    window: int = K.SORT_WINDOW   # the cpu and v2 re-sorting window of a per-pixel order

    @property
    def mode(self) -> str:
        return MODES[2 * self.use_softmax + self.use_gef]

    @property
    def eq15(self) -> Eq15:
        return "solved" if self.solved else "printed"

    @property
    def scope(self) -> KMaxScope:
        return "patch" if self.patch else "pixel"


def composite_settings(width: int, height: int, mode: str = "softmax_gs", k_max: int = K.DEFAULT_K_MAX,
                       eq15: Eq15 = "solved", reg_depth_scale: float = 1.0, t_min: float = K.T_MIN,
                       k_max_scope: KMaxScope = K.DEFAULT_K_MAX_SCOPE, leaders: bool = False,
                       window: int = K.SORT_WINDOW) -> CompositeSettings:
    """The settings of ``rasterize_splats``' arguments (which has their meanings), each checked: a
    bad value is refused with an error that names it."""
    width, height = checks.image_size(width, height)
    use_gef, use_softmax = mode_flags(mode)   # refuses an unknown mode
    if eq15 not in ("solved", "printed"):
        raise ValueError(f"eq15 must be 'solved' or 'printed', got {eq15!r}")
    if k_max < 0:
        raise ValueError(f"k_max must be >= 0, got {k_max}")
    patch = scope_is_patch(k_max_scope)   # refuses an unknown scope
    if not 0.0 <= t_min < 1.0:
        raise ValueError(f"t_min must be in [0, 1), got {t_min}")
    return CompositeSettings(width, height, use_gef, use_softmax, int(k_max), eq15 == "solved",
                             float(reg_depth_scale), float(t_min), patch, bool(leaders), int(window))
