"""Plain data returned by the renderer."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

import torch

MODES: tuple[str, ...] = ("3dgs", "gef_only", "softmax_only", "softmax_gs")
Eq15 = Literal["solved", "printed"]
KMaxScope = Literal["pixel", "patch"]
K_MAX_SCOPES: tuple[str, ...] = ("pixel", "patch")


def mode_flags(mode: str) -> tuple[bool, bool]:
    """(uses GEF sharpness α, uses softmax competition β, γ) for a mode name."""
    if mode not in MODES:
        raise ValueError(f"unknown render mode {mode!r}; expected one of {', '.join(MODES)}")
    return mode in ("gef_only", "softmax_gs"), mode in ("softmax_only", "softmax_gs")


def scope_is_patch(scope: str) -> bool:
    """Whether a k_max scope is ``patch`` (the softmax head is the tile list's first k_max entries)
    rather than ``pixel`` (each pixel's first k_max composited splats); docs/kmax-scope.md."""
    if scope not in K_MAX_SCOPES:
        raise ValueError(f"unknown k_max scope {scope!r}; expected one of {', '.join(K_MAX_SCOPES)} "
                         "(docs/kmax-scope.md)")
    return scope == "patch"


class RenderStats:
    """Per-render counters (no gradients).

    n_contrib: [H, W] number of splats composited at each pixel.
    pairs_evaluated: splat-pixel pairs the backend tested (backend-specific: the dense reference
        tests every pair, the tiled kernels only pairs inside a splat's tiles).
    frac_within_kmax: fraction of pixels reached by at least one splat whose composited splats all
        fell within the softmax head (the paper's "coverage", 70-85% on Mip-NeRF360): the first
        k_max composited (``scope`` "pixel"), or the first k_max entries of the pixel's tile list
        ("patch", read from ``list_end``); 1.0 for modes without softmax competition.
    scope: the k_max scope rendered with (docs/kmax-scope.md).
    list_end: [H, W] in patch scope (None in pixel scope): 1 + the furthest position in its tile's
        list that each pixel composited (0 where none).

    Lazy: a kernel hands its counters over as they are (int32 maps, the pair count as a 1-element
    tensor on its device); they become ``long`` tensors and an ``int`` when first read, so a render
    whose caller never reads them pays no conversion and, on a GPU, no wait for the pair count.
    """

    def __init__(self, n_contrib: torch.Tensor, pairs_evaluated: int | torch.Tensor, k_max: int,
                 scope: str = "pixel", list_end: torch.Tensor | None = None) -> None:
        self._n_contrib = n_contrib
        self._pairs = pairs_evaluated
        self.k_max = k_max
        self.scope = scope
        self._list_end = list_end

    @property
    def n_contrib(self) -> torch.Tensor:
        if self._n_contrib.dtype != torch.long:
            self._n_contrib = self._n_contrib.long()
        return self._n_contrib

    @n_contrib.setter
    def n_contrib(self, value: torch.Tensor) -> None:
        self._n_contrib = value

    @property
    def pairs_evaluated(self) -> int:
        if isinstance(self._pairs, torch.Tensor):
            self._pairs = int(self._pairs.reshape(-1)[0].item())
        return self._pairs

    @pairs_evaluated.setter
    def pairs_evaluated(self, value: int) -> None:
        self._pairs = value

    @property
    def list_end(self) -> torch.Tensor | None:
        if self._list_end is not None and self._list_end.dtype != torch.long:
            self._list_end = self._list_end.long()
        return self._list_end

    @list_end.setter
    def list_end(self, value: torch.Tensor | None) -> None:
        self._list_end = value

    def __repr__(self) -> str:
        return (f"RenderStats(n_contrib={tuple(self._n_contrib.shape)}, pairs_evaluated={self._pairs!r}, "
                f"k_max={self.k_max}, scope={self.scope!r})")

    @property
    def contributions(self) -> int:
        return int(self.n_contrib.sum())

    @property
    def splats_per_pixel(self) -> float:
        return float(self.n_contrib.float().mean())

    @property
    def frac_within_kmax(self) -> float:
        hit = self.n_contrib > 0
        n = int(hit.sum())
        if n == 0:
            return 1.0
        within = self.list_end <= self.k_max if self.list_end is not None else self.n_contrib <= self.k_max
        return float((within & hit).sum()) / n


@dataclass
class RenderOutput:
    """rgb [H, W, C]; alpha [H, W] = 1 - final T; depth [H, W] expected depth normalised by alpha
    (0 where alpha is 0); reg [H, W, 1 + 2R] or None: per-pixel sums of the β/γ variance
    regulariser (Σw, then Σw·v_r and Σw·v_r² for each regularised value r); leaders [H, W, 2] long
    or None: only when asked for (``leaders=True``), each pixel's first two composited splats whose
    own absorbance is at least ``constants.LEADER_ALPHA``, in its compositing order (indices of the
    input splats; -1 where it has fewer)."""

    rgb: torch.Tensor
    alpha: torch.Tensor
    depth: torch.Tensor
    stats: RenderStats
    reg: torch.Tensor | None = None
    leaders: torch.Tensor | None = None
    extras: dict = field(default_factory=dict)


@dataclass(frozen=True)
class RayDepth:
    """What a backend needs to order each pixel's splats by the peak depth along its ray
    (``smgs.raster.ray_depth``).

    coefs [M, 9] per projected splat, float64: (Qxx, Qxy, Qxz, Qyy, Qyz, Qzz, bx, by, bz) in camera
    coordinates; fx, fy, cx, cy: the camera's intrinsics (pixel centres at +0.5).
    """

    coefs: torch.Tensor
    fx: float
    fy: float
    cx: float
    cy: float
