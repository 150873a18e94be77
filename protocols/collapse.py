"""Collapse watch: a run whose Gaussians are pruned (almost) all away, and test views that render
(almost) nothing. The train loop feeds every step's count and refinement events to a
``CollapseWatch``; it logs the step at which the count falls under ``COLLAPSE_FRACTION`` of its peak,
and at the end ``CollapseWatch.assess`` says, for results.json's ``diagnostics["collapse"]``, what
happened and its likely cause, which the report prints as a footnote on the row
(docs/studies/fox-collapse.md has a measured case: a random initialisation at the 5 % budget).

The thresholds only label a run; they change nothing it computes (and are not part of its config
hash).
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, field
from typing import Any

COLLAPSE_FRACTION = 0.05
"""A run that falls (or ends) under this fraction of its peak Gaussian count has collapsed."""

EMPTY_VIEW_ALPHA = 0.02
"""A test view whose mean alpha (the share of the image the model covers) is under this renders
(almost) empty."""

EVENTS = ("cloned", "split", "pruned", "pruned_transparent", "pruned_big", "pruned_big_screen", "relocated", "added")


@dataclass
class CollapseWatch:
    """Peak count, refinement totals and the step the count fell under the threshold (if it did);
    plain data, kept in the run's checkpoint so a resumed run keeps its history."""

    peak: int = 0
    peak_step: int = 0
    fell_at: int | None = None        # the step the count first fell under COLLAPSE_FRACTION × peak
    resets: int = 0
    totals: dict[str, int] = field(default_factory=lambda: {k: 0 for k in EVENTS})

    @classmethod
    def start(cls, n: int) -> "CollapseWatch":
        """A watch of a run that starts with ``n`` Gaussians."""
        return cls(peak=n, peak_step=0)

    def restore(self, state: dict[str, Any]) -> None:
        """Continue the history saved with a checkpoint (``to_json``)."""
        self.peak, self.peak_step = int(state["peak"]), int(state["peak_step"])
        self.fell_at, self.resets = state.get("fell_at"), int(state.get("resets", 0))
        self.totals = {k: int(state.get("totals", {}).get(k, 0)) for k in EVENTS}

    def step(self, done: int, n: int, logs: dict[str, Any], log: logging.Logger) -> None:
        """After step ``done`` (1-based) with ``n`` Gaussians and the method's step ``logs``."""
        for k in EVENTS:
            self.totals[k] += int(logs.get(k, 0) or 0)
        self.resets += int(bool(logs.get("opacity_reset")))
        if n > self.peak:
            self.peak, self.peak_step = n, done
        if self.fell_at is None and self.peak and n < COLLAPSE_FRACTION * self.peak:
            self.fell_at = done
            log.warning("step %d: %d Gaussians left, %s of the peak %d (step %d): the model is collapsing "
                        "(%s so far)", done, n, _pct(n, self.peak), self.peak, self.peak_step, self._events())

    def _events(self) -> str:
        t = self.totals
        parts = [f"{t['pruned']} pruned ({t['pruned_transparent']} as transparent, {t['pruned_big']} as too big)",
                 f"{t['cloned']} cloned", f"{t['split']} split", f"{self.resets} opacity reset(s)"]
        if t["relocated"] or t["added"]:
            parts += [f"{t['relocated']} relocated", f"{t['added']} added"]
        return ", ".join(parts)

    def to_json(self) -> dict[str, Any]:
        return asdict(self)

    def assess(self, final: int, coverage: dict[str, float], plan: list[str], grad_threshold: float | None,
               log: logging.Logger) -> dict[str, Any]:
        """``diagnostics["collapse"]``: the counts and totals always; ``collapsed``, ``what`` and
        ``likely_cause`` (logged too) when the run ended under the threshold or a test view
        (``coverage``: name -> mean alpha) rendered (almost) empty."""
        empty = sorted(k for k, v in coverage.items() if v < EMPTY_VIEW_ALPHA)
        out: dict[str, Any] = {
            "peak_gaussians": self.peak, "peak_step": self.peak_step, "final_gaussians": final,
            "final_fraction": final / self.peak if self.peak else None, "fell_under_threshold_at": self.fell_at,
            "threshold_fraction": COLLAPSE_FRACTION, "empty_view_alpha": EMPTY_VIEW_ALPHA,
            "min_view_alpha": min(coverage.values()) if coverage else None, "empty_views": empty,
            "opacity_resets": self.resets, **self.totals, "collapsed": False}
        what = []
        shrunk = self.peak > 0 and final < COLLAPSE_FRACTION * self.peak
        if shrunk:
            what.append(f"ended with {final} of its peak {self.peak} Gaussians ({_pct(final, self.peak)}; "
                        f"peak at step {self.peak_step}, under {_pct(COLLAPSE_FRACTION, 1)} from step {self.fell_at})")
        if empty:
            what.append(f"{len(empty)} of {len(coverage)} test views render (almost) empty (mean alpha under "
                        f"{EMPTY_VIEW_ALPHA:g}: {', '.join(empty[:4])}{' …' if len(empty) > 4 else ''})")
        if what:
            out.update(collapsed=True, what="; ".join(what),
                       likely_cause=self._cause(final, shrunk, plan, grad_threshold))
            log.warning("collapse: %s. Likely cause: %s", out["what"], out["likely_cause"])
        return out

    def _cause(self, final: int, shrunk: bool, plan: list[str], grad_threshold: float | None) -> str:
        t = self.totals
        from smgs.train.trainer import RANDOM_INIT_PLAN

        random_init = any(RANDOM_INIT_PLAN in line for line in plan)
        grown = t["cloned"] + t["split"] + t["added"]
        if not shrunk:
            return ("the model does not cover those views (its Gaussians are outside their frusta or transparent "
                    "there)")
        if t["pruned"] and t["pruned_transparent"] >= t["pruned_big"]:
            cause = (f"Gaussians pruned as transparent ({t['pruned_transparent']} of {t['pruned']} pruned, "
                     f"{self.resets} opacity reset(s)) faster than densification replaced them ({t['cloned']} "
                     f"cloned, {t['split']} split"
                     + (f" at the gradient threshold {grad_threshold:g})" if grad_threshold else ")"))
        elif t["pruned"] and 2 * t["pruned_big_screen"] >= t["pruned_big"]:
            cause = (f"Gaussians pruned as too big on screen ({t['pruned_big_screen']} of {t['pruned']} pruned; the "
                     f"screen-size rule densify.prune_screen_px, which 3DGS as released never applies) faster than "
                     f"densification replaced them ({grown} added)")
        elif t["pruned"]:
            cause = (f"Gaussians pruned as too big in the world ({t['pruned_big']} of {t['pruned']} pruned, over "
                     f"densify.size_prune x the scene extent) faster than densification replaced them ({grown} added)")
        else:
            cause = f"the count fell from {self.peak} to {final} without pruning events the method reports"
        if random_init:
            cause += ("; the model started from random points (the scene has no SfM points), and a sparse "
                      "budget's threshold densifies them too little to hold on to the surfaces: "
                      "docs/studies/fox-collapse.md")
        return cause


def _pct(n: float, of: float) -> str:
    x = 100.0 * n / of
    return f"{x:.2g} %" if x < 1 else f"{x:.1f} %"
