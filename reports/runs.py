"""What a report's numbers are made of: a ``Value`` (a mean with its spread, or the reason there is
none), the seeds' pooling rule (``seed_config`` / ``config_difference``) and a few names of the runs
(read by ``smgs.cells.tree``, whose names the reports' modules import from here).

A report never prints a number that is not there: every value is a ``Value`` that either holds a
mean (with std and count over the runs it came from, and notes such as "2 of 3 seeds") or the
reason it is absent ("failed: RuntimeError: ...", "LPIPS weights not installed"). The values are
computed from the results table in reports/aggregate.py; the runs are read by ``smgs.cells.tree``.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass
from typing import Iterable

from protocols.results import RunResult
from smgs.cells.tree import (PATTERN_DATASETS, LoadedRuns, Run, is_pattern, load_runs, one_line,  # noqa: F401
                             pattern_cap)
from smgs.identity import SeedRecord, pooling_key, seeds_difference


@dataclass(frozen=True)
class Value:
    """A mean over runs (or scenes), or the reason there is none."""

    mean: float | None
    std: float | None = None       # sd over seeds (or propagated over scenes: reports.stats.mean_of_means)
    n: int = 0                     # seeds behind the mean
    reason: str | None = None
    notes: tuple[str, ...] = ()
    seeds: tuple[tuple[int, float], ...] = ()   # (seed, value) behind the mean: paired differences
    ci: tuple[float, float] | None = None       # a confidence interval of the mean (paired differences)

    @property
    def ok(self) -> bool:
        return self.mean is not None

    @staticmethod
    def absent(reason: str) -> "Value":
        return Value(None, reason=reason)

    @staticmethod
    def of(x: float | None, reason: str = "") -> "Value":
        return Value(float(x), n=1) if x is not None else Value(None, reason=reason)


def preset_description(runs: Iterable[RunResult]) -> str:
    """What a reduced preset changes, from the runs' protocol config: "3000 steps, images ≤ 400 px";
    runs of different lengths: "300 or 3000 steps". A model only evaluated here (a PLY) has no steps."""
    steps: list[int] = []
    widths: list[int] = []
    for r in runs:
        proto = (r.config or {}).get("protocol") or {}
        n = r.steps or proto.get("steps")
        if n and (r.source or {}).get("kind") != "pretrained" and n not in steps:
            steps.append(n)
        w = proto.get("max_width")
        if w and w not in widths:
            widths.append(w)
    parts = [f"{' or '.join(str(n) for n in sorted(steps))} steps"] if steps else []
    return ", ".join(parts + [f"images ≤ {' or '.join(str(w) for w in sorted(widths))} px wide"] * bool(widths))


def presets_summary(runs: list[RunResult]) -> str:
    """Each protocol preset of ``runs`` with its count of runs and what a reduced one changes, as the
    report's header says it: "cpu (8 runs, 3000 steps, images ≤ 400 px wide); paper (2 runs)"."""
    presets = Counter(r.preset for r in runs)
    return "; ".join(f"{p} ({n} runs{', ' + preset_description([r for r in runs if r.preset == p]) if p != 'paper' else ''})"
                     for p, n in sorted(presets.items()))


def budget_label(r: RunResult) -> str:
    """A run's budget as the plots and report.html name it: a 2D pattern fit's "cap N", else its budget."""
    cap = pattern_cap(r) if is_pattern(r) else None
    return r.budget if cap is None else f"cap {cap}"


def flow_estimator(r: RunResult) -> str:
    c = r.consistency or {}
    return str(c.get("estimator") or c.get("flow") or "unknown")


# ---- pooling: which seeds may be averaged ------------------------------------------------------

def seed_config(r: RunResult) -> dict[str, str]:
    """What the seeds of one row must share, as dotted keys (``smgs.identity.pooling_key``: the
    config without its seed, the keys that change no number and the inputs' locations; the device
    by its kind)."""
    return pooling_key(r.config or {}, r.hparams)


def config_difference(runs: list[RunResult], shown: int = 3) -> str | None:
    """Why the seeds ``runs`` of one row must not be pooled (``smgs.identity.seeds_difference``): the
    config keys other than the seed in which they differ, with each seed's value, else the input
    files whose content differs (None when they agree; runs that record no config or no inputs,
    written before those were recorded, are not compared on them)."""
    return seeds_difference([SeedRecord(r.seed, r.config or {}, r.hparams, r.inputs or None) for r in runs], shown)
