"""Popping on real scenes: the flow-warped error where a pixel's leading splats swap order.

A renderer's leading-splat map (``RenderOutput.leaders``, ``leaders=True``) gives per pixel the
first two composited splats whose own absorbance is at least ``constants.LEADER_ALPHA``, in the
order it composited them. For a pair (frame i, frame i+step), the source's map is carried onto the
target's pixels by the same flow as the colours (nearest pixel: indices do not interpolate). A
valid pixel *pops* where both frames show the same two leading splats in the opposite order:
the depth order of two overlapping splats flipped between the frames. The popping ratio is the
mean warped error (per pixel the squared difference summed over RGB, as Table 4's MSE) over the
popped pixels divided by the mean over the other valid pixels, pooled over all pairs:
1 = a flip costs nothing; vanilla 3DGS, which recolours a pixel when its two leaders swap, is far
above 1; Softmax-GS, whose blend of two splats does not depend on their order, near 1.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from smgs.metrics.consistency.flow import pixel_grid
from smgs.metrics.result import Missing


def warp_leaders(leaders: np.ndarray, flow: np.ndarray) -> np.ndarray:
    """The source's [H, W, 2] leading-splat map seen from the target: target pixel p takes the
    source pixel nearest to p + flow(p); -1 where that falls outside the source."""
    h, w = flow.shape[:2]
    xs, ys = pixel_grid(h, w)
    sx = np.rint(xs + flow[..., 0])
    sy = np.rint(ys + flow[..., 1])
    inside = (sx >= 0) & (sx < leaders.shape[1]) & (sy >= 0) & (sy < leaders.shape[0])
    out = np.full((h, w, 2), -1, dtype=np.int64)
    out[inside] = leaders[sy[inside].astype(np.int64), sx[inside].astype(np.int64)]
    return out


def swapped(source_on_target: np.ndarray, target: np.ndarray) -> np.ndarray:
    """[H, W] bool: both maps name two leading splats, the same two, in the opposite order."""
    a0, a1 = source_on_target[..., 0], source_on_target[..., 1]
    b0, b1 = target[..., 0], target[..., 1]
    return (a0 >= 0) & (a1 >= 0) & (a0 == b1) & (a1 == b0) & (a0 != a1)


@dataclass
class PopCount:
    """One pair's share: popped pixels and the summed error over them and over the other valid ones."""

    popped: int
    popped_se: float
    rest: int
    rest_se: float


def pair_pop(se: np.ndarray, valid: np.ndarray, source_leaders: np.ndarray, target_leaders: np.ndarray,
             flow: np.ndarray) -> PopCount:
    """``se`` [H, W]: the pair's warped error per pixel; ``valid``: the pixels the pair scores."""
    pop = swapped(warp_leaders(source_leaders, flow), target_leaders) & valid
    rest = valid & ~pop
    return PopCount(int(pop.sum()), float(se[pop].sum()), int(rest.sum()), float(se[rest].sum()))


def pooled_ratio(counts: list[PopCount]) -> tuple[float | Missing, float | Missing]:
    """(popping ratio, popped share of the valid pixels) pooled over the pairs."""
    if not counts:
        return (Missing("the renders gave no leading-splat map (RenderOutput.leaders)"),) * 2
    popped = sum(c.popped for c in counts)
    rest = sum(c.rest for c in counts)
    if popped + rest == 0:
        return (Missing(f"no valid pixel in any of the {len(counts)} pairs"),) * 2
    share = popped / (popped + rest)
    if popped == 0:
        return Missing(f"no pixel's two leading splats swapped order in {len(counts)} pairs"), share
    rest_mean = sum(c.rest_se for c in counts) / rest if rest else 0.0
    pop_mean = sum(c.popped_se for c in counts) / popped
    if rest_mean == 0.0:
        return (float("inf") if pop_mean > 0 else 1.0), share
    return pop_mean / rest_mean, share
