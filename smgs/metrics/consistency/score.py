"""View-consistency scores (StopThePop / PoppingDetection mechanics, RAFT-free) and Table 4 rows.

For each pair (i, i+step) of trajectory frames, frame i is warped onto frame i+step with the
chosen flow; then over valid pixels only (inside the image after warping, not occluded, at least
``border`` px from the edge):
- MSE: per pixel the *sum over RGB* of the squared difference; the pair's score is the mean over
  the valid pixels; the method's score is the mean over pairs (PoppingDetection).
- FLIP: the LDR ꟻLIP map (67 ppd) between the warped frame and frame i+step, averaged over the
  same pixels. With ``flip_min_subtraction`` the per-pixel minimum over the compared methods is
  subtracted first (StopThePop's default, relative to the set of methods); the metric is then
  named ``flip_minsub``.
- Popping ratio (``leaders``): where the renders give a leading-splat map, the mean warped error
  over the pixels whose two leading splats swapped order divided by that over the other valid
  pixels, pooled over the pairs (``smgs.metrics.consistency.leaders``).
When several methods are compared they are scored on the same mask: the intersection of their
valid masks (StopThePop). Frames are quantised to 8 bits first, as a saved video's would be.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Callable, Mapping, Protocol, Sequence

import numpy as np
import torch

from smgs.camera import Camera
from smgs.metrics.consistency.flow import (ESTIMATORS, Flow, backward_warp, border_mask,
                                           geometric_flow, image_flow)
from smgs.data.trajectory import Trajectory, frame_pairs
from smgs.metrics.consistency.leaders import PopCount, pair_pop, pooled_ratio
from smgs.metrics.flip import FLIP_PPD, flip_available, flip_error_map
from smgs.metrics.image import evaluate_images, quantize_8bit
from smgs.metrics.result import Missing, json_value

RenderFn = Callable[[Camera], tuple]
"""``render(camera) -> (rgb [H, W, 3] in [0, 1], depth [H, W] camera z, 0 where empty[, leaders
[H, W, 2]])`` or a ``RenderOutput``; the leading-splat map is optional (the popping ratio)."""

BORDER_PX = 20
DEFAULT_STEPS = (7, 1)
TABLE_STEP = 7   # Table 4's pair: frame i warped onto frame i+7


@dataclass
class Frame:
    rgb: np.ndarray  # [H, W, 3] float32 in [0, 1] (8-bit values when quantised)
    depth: np.ndarray | None  # [H, W] float32
    leaders: np.ndarray | None = None  # [H, W, 2] int64 (RenderOutput.leaders)


@dataclass
class PairScore:
    i: int
    j: int
    mse: float | None  # None when the mask is empty
    flip: float | None
    valid_fraction: float
    pop: PopCount | None = None   # None where the renders give no leading-splat map


@dataclass
class ConsistencyScores:
    """One method's scores for one step. ``mse`` and ``flip`` are means over the pairs with a
    non-empty mask; ``flip_name`` is ``flip`` or ``flip_minsub``."""

    method: str
    step: int
    estimator: str
    estimator_params: dict
    mask: str  # "own" or "shared:<method>,<method>,..."
    border: int
    mse: float | Missing
    flip: float | Missing
    flip_name: str
    n_pairs: int
    n_empty: int
    per_pair: list[PairScore] = field(default_factory=list)
    pop_ratio: float | Missing = field(default_factory=lambda: Missing("not computed"))
    popped_fraction: float | Missing = field(default_factory=lambda: Missing("not computed"))

    def to_json(self) -> dict:
        d = asdict(self)
        for k in ("mse", "flip", "pop_ratio", "popped_fraction"):
            d[k] = json_value(getattr(self, k))
        return d


def _host(x) -> torch.Tensor:
    """A render or image as a float tensor on the host, whatever device it was rendered on: the
    flow estimators and FLIP work on numpy arrays."""
    if isinstance(x, torch.Tensor):
        return x.detach().float().cpu()
    return torch.from_numpy(np.asarray(x, dtype=np.float32))


def _to_frame(out, quantize: bool) -> Frame:
    if isinstance(out, (tuple, list)):
        rgb, depth = out[0], (out[1] if len(out) > 1 else None)
        leaders = out[2] if len(out) > 2 else None
    else:  # a RenderOutput
        rgb, depth, leaders = out.rgb, out.depth, out.leaders
    rgb_t = _host(rgb)
    if rgb_t.dim() != 3 or rgb_t.shape[-1] != 3:
        raise ValueError(f"render must return rgb [H, W, 3], got {tuple(rgb_t.shape)}")
    rgb_t = quantize_8bit(rgb_t) if quantize else rgb_t.clamp(0, 1)
    d = None if depth is None else _host(depth).numpy().reshape(rgb_t.shape[:2])
    lead = None if leaders is None else leaders.detach().cpu().long().numpy().reshape(rgb_t.shape[:2] + (2,))
    return Frame(np.ascontiguousarray(rgb_t.numpy()), d, lead)


class FrameTap(Protocol):
    """What sees a method's frames and pairs as the scoring has them (``score_consistency(taps=...)``),
    e.g. to encode the video (``smgs.io.flythrough``) without rendering a frame again. ``frame`` is
    called once per frame, when it is rendered (not in order: a window of max(steps)+1 frames is
    rendered ahead); ``pair`` once per scored pair (every step), after the warp and the mask."""

    def frame(self, k: int, rgb: np.ndarray) -> None:
        """Frame ``k`` as scored: [H, W, 3] float32 in [0, 1] (8-bit values when quantised)."""

    def pair(self, i: int, j: int, warped: np.ndarray, target: np.ndarray, valid: np.ndarray) -> None:
        """Frame ``i`` warped onto frame ``j`` ([H, W, 3]), frame ``j`` and the mask it is scored on."""


class _FrameWindow:
    """Renders each trajectory frame once per method and keeps only the frames still needed."""

    def __init__(self, render: RenderFn, cameras: Sequence[Camera], quantize: bool, tap: FrameTap | None = None) -> None:
        self.render, self.cameras, self.quantize, self.tap = render, cameras, quantize, tap
        self.cache: dict[int, Frame] = {}

    def get(self, k: int) -> Frame:
        if k not in self.cache:
            with torch.no_grad():
                self.cache[k] = _to_frame(self.render(self.cameras[k]), self.quantize)
            if self.tap is not None:
                self.tap.frame(k, self.cache[k].rgb)
        return self.cache[k]

    def forget_below(self, k: int) -> None:
        for key in [key for key in self.cache if key < k]:
            del self.cache[key]


def _pair_flow(estimator: str, src: Frame, tgt: Frame, cam_src: Camera, cam_tgt: Camera,
               rel_depth_tol: float) -> Flow:
    if estimator == "geometric":
        if tgt.depth is None or src.depth is None:
            raise ValueError("the geometric estimator needs depth from render(camera) -> (rgb, depth)")
        return geometric_flow(tgt.depth, cam_tgt, cam_src, src.depth, rel_depth_tol)
    return image_flow(tgt.rgb, src.rgb, estimator)


@dataclass(frozen=True)
class _PairSettings:
    """How every pair is scored (the arguments of ``score_consistency``)."""

    estimator: str
    border: int
    shared_mask: bool
    flip_min_subtraction: bool
    rel_depth_tol: float
    ppd: float
    flip_ok: object   # True, or the Missing that says why FLIP is not computed


def _score_pair(windows: dict[str, _FrameWindow], cameras: Sequence[Camera], i: int, j: int, ps: _PairSettings,
                est_params: dict[str, dict]) -> dict[str, PairScore]:
    """Every method's score of the pair (frame i warped onto frame j)."""
    names = list(windows)
    warped, valid, flips, flows = {}, {}, {}, {}
    for m in names:
        src, tgt = windows[m].get(i), windows[m].get(j)
        fl = _pair_flow(ps.estimator, src, tgt, cameras[i], cameras[j], ps.rel_depth_tol)
        est_params.setdefault(m, {"estimator": fl.estimator, **fl.params})
        w, inside = backward_warp(src.rgb, fl.flow)
        h, wd = inside.shape
        warped[m], flows[m] = w, fl.flow
        valid[m] = inside & fl.valid & border_mask(h, wd, ps.border)
    if ps.shared_mask:
        common = np.logical_and.reduce([valid[m] for m in names])
        valid = {m: common for m in names}
    for m in names:
        if windows[m].tap is not None:
            windows[m].tap.pair(i, j, warped[m], windows[m].get(j).rgb, valid[m])
    if ps.flip_ok is True:
        for m in names:
            flips[m] = flip_error_map(windows[m].get(j).rgb, np.clip(warped[m], 0, 1), ps.ppd)
        if ps.flip_min_subtraction:
            floor = np.minimum.reduce([flips[m] for m in names])
            flips = {m: flips[m] - floor for m in names}
    out = {}
    for m in names:
        mask = valid[m]
        n = int(mask.sum())
        if n == 0:
            out[m] = PairScore(i, j, None, None, 0.0)
            continue
        src, tgt = windows[m].get(i), windows[m].get(j)
        se = ((warped[m] - tgt.rgb) ** 2).sum(-1)  # summed over RGB
        pop = (pair_pop(se, mask, src.leaders, tgt.leaders, flows[m])
               if src.leaders is not None and tgt.leaders is not None else None)
        out[m] = PairScore(i, j, float(se[mask].mean()), float(flips[m][mask].mean()) if ps.flip_ok is True else None,
                           n / mask.size, pop)
    return out


def _summarise(m: str, s: int, ps: list[PairScore], n_frames: int, settings: _PairSettings, est_params: dict,
               mask_label: str, flip_name: str) -> ConsistencyScores:
    """One method's scores for one step from its pairs."""
    good = [p for p in ps if p.mse is not None]
    if not frame_pairs(n_frames, s):
        mse: float | Missing = Missing(f"trajectory of {n_frames} frames has no pair at step {s}")
        fl: float | Missing = mse
    elif not good:
        mse = fl = Missing(f"no valid pixel in any of the {len(ps)} pairs at step {s}")
    else:
        mse = float(np.mean([p.mse for p in good]))
        fl = float(np.mean([p.flip for p in good])) if settings.flip_ok is True else settings.flip_ok
    ratio, share = pooled_ratio([p.pop for p in good if p.pop is not None])
    return ConsistencyScores(m, s, settings.estimator, est_params.get(m, {}), mask_label, settings.border, mse, fl,
                             flip_name, len(ps), len(ps) - len(good), ps, ratio, share)


def score_consistency(renders: Mapping[str, RenderFn], trajectory: Trajectory | Sequence[Camera], *,
                      steps: Sequence[int] = DEFAULT_STEPS, estimator: str = "geometric",
                      border: int = BORDER_PX, shared_mask: bool = True,
                      flip_min_subtraction: bool = False, quantize: bool = True,
                      rel_depth_tol: float = 0.02, ppd: float = FLIP_PPD,
                      progress: Callable[[int, int], None] | None = None,
                      taps: Mapping[str, FrameTap] | None = None) -> dict[str, dict[int, ConsistencyScores]]:
    """Scores of every method for every step: ``result[method][step]``.

    Each method's frames are rendered once (a sliding window keeps max(steps)+1 of them).
    ``shared_mask`` intersects the valid masks of all methods (needs >= 2 methods to matter).
    ``taps``: per method, what also sees its frames and pairs (``FrameTap``).
    """
    if estimator not in ESTIMATORS:
        raise ValueError(f"unknown flow estimator {estimator!r}; expected one of {ESTIMATORS}")
    if not renders:
        raise ValueError("no method to score")
    if flip_min_subtraction and len(renders) < 2:
        raise ValueError("flip_min_subtraction needs at least two methods (it is relative to the set)")
    cameras = trajectory.cameras() if isinstance(trajectory, Trajectory) else list(trajectory)
    steps = sorted(set(int(s) for s in steps))
    names = list(renders)
    settings = _PairSettings(estimator, border, shared_mask, flip_min_subtraction, rel_depth_tol, ppd,
                             flip_available())
    flip_name = "flip_minsub" if flip_min_subtraction else "flip"
    windows = {m: _FrameWindow(renders[m], cameras, quantize, (taps or {}).get(m)) for m in names}
    acc: dict[str, dict[int, list[PairScore]]] = {m: {s: [] for s in steps} for m in names}
    est_params: dict[str, dict] = {}
    mask_label = "shared:" + ",".join(names) if shared_mask and len(names) > 1 else "own"
    n_src = max(0, len(cameras) - steps[0])
    for i in range(n_src):
        for s in steps:
            if i + s < len(cameras):
                for m, score in _score_pair(windows, cameras, i, i + s, settings, est_params).items():
                    acc[m][s].append(score)
        for m in names:
            windows[m].forget_below(i + 1)
        if progress is not None:
            progress(i + 1, n_src)
    return {m: {s: _summarise(m, s, acc[m][s], len(cameras), settings, est_params, mask_label, flip_name)
                for s in steps} for m in names}


@dataclass
class Table4Row:
    """One scene × method cell of the paper's Table 4: test-view PSNR, then MSE and FLIP of
    frame i warped onto frame i+7 (``long``), plus the short-range (i, i+1) scores."""

    scene: str
    method: str
    psnr: float | Missing
    mse: float | Missing
    flip: float | Missing
    flip_name: str
    estimator: str
    step: int
    scores: dict[int, ConsistencyScores]
    trajectory: dict

    @property
    def pop_ratio(self) -> float | Missing:
        return self.scores[self.step].pop_ratio

    @property
    def popped_fraction(self) -> float | Missing:
        return self.scores[self.step].popped_fraction

    def to_json(self) -> dict:
        return {"scene": self.scene, "method": self.method, "psnr": json_value(self.psnr),
                "mse": json_value(self.mse), self.flip_name: json_value(self.flip),
                "pop_ratio": json_value(self.pop_ratio), "popped_fraction": json_value(self.popped_fraction),
                "flip_name": self.flip_name, "estimator": self.estimator, "step": self.step,
                "scores": {str(s): sc.to_json() for s, sc in self.scores.items()},
                "trajectory": self.trajectory}


def mean_test_psnr(render: RenderFn, test_views: Sequence[tuple[Camera, torch.Tensor]]) -> float | Missing:
    """Mean PSNR over the test views (8-bit quantised, per image then mean)."""
    if not test_views:
        return Missing("no test views given")
    with torch.no_grad():
        preds = [_to_frame(render(cam), quantize=False).rgb for cam, _ in test_views]
    res = evaluate_images([torch.from_numpy(p) for p in preds], [_host(g) for _, g in test_views],
                          lpips=Missing("not part of Table 4"), flip=False)
    return res.means()["psnr"]


def consistency_rows(renders: Mapping[str, RenderFn], trajectory: Trajectory | Sequence[Camera], *, scene: str,
                     test_views: Sequence[tuple[Camera, torch.Tensor]] | None = None,
                     table_step: int = TABLE_STEP, steps: Sequence[int] = DEFAULT_STEPS,
                     estimator: str = "geometric", border: int = BORDER_PX, shared_mask: bool = True,
                     flip_min_subtraction: bool = False, quantize: bool = True,
                     progress: Callable[[int, int], None] | None = None,
                     taps: Mapping[str, FrameTap] | None = None) -> dict[str, Table4Row]:
    """Table 4 rows of several methods on one scene, scored on one shared mask."""
    steps = sorted(set(steps) | {table_step})
    scores = score_consistency(renders, trajectory, steps=steps, estimator=estimator, border=border,
                               shared_mask=shared_mask, flip_min_subtraction=flip_min_subtraction,
                               quantize=quantize, progress=progress, taps=taps)
    if isinstance(trajectory, Trajectory):
        traj = {"n_frames": len(trajectory), "n_targets": trajectory.n_targets,
                "n_between": trajectory.n_between, "n_dropped": len(trajectory.dropped)}
    else:  # a camera path given as is (e.g. a scene's own video trajectory)
        traj = {"n_frames": len(trajectory)}
    rows = {}
    for m, render in renders.items():
        long = scores[m][table_step]
        psnr = mean_test_psnr(render, test_views) if test_views is not None else Missing("no test views given")
        rows[m] = Table4Row(scene, m, psnr, long.mse, long.flip, long.flip_name, estimator, table_step,
                            scores[m], traj)
    return rows


def consistency_row(render: RenderFn, trajectory: Trajectory | Sequence[Camera], *, scene: str, method: str,
                    test_views: Sequence[tuple[Camera, torch.Tensor]] | None = None,
                    tap: FrameTap | None = None, **kwargs) -> Table4Row:
    """Table 4's row for one scene and one method (its own mask; see ``consistency_rows`` to
    score several methods on a shared mask). ``tap``: what also sees its frames (``FrameTap``)."""
    return consistency_rows({method: render}, trajectory, scene=scene, test_views=test_views,
                            taps={method: tap} if tap is not None else None, **kwargs)[method]
