"""What a report's numbers are made of: a ``Value`` (a mean with its spread, or the reason there is
none), the seeds' pooling rule (``seed_config`` / ``config_difference``) and a few names of the runs.

A report never prints a number that is not there: every value is a ``Value`` that either holds a
mean (with std and count over the runs it came from, and notes such as "2 of 3 seeds") or the
reason it is absent ("failed: RuntimeError: ...", "LPIPS weights not installed"). The values are
computed from the results table in reports/aggregate.py; the runs are read by ``smgs.cells.tree``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Iterable

from protocols.results import VOLATILE, RunResult
from smgs.cells.tree import (MAX_TEXT, PATTERN_DATASETS, LoadedRuns, Run, identity, is_pattern,  # noqa: F401
                            load_runs, one_line, pattern_cap)


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
    """What a reduced preset changes, from the runs' protocol config: "3000 steps, images ≤ 400 px"."""
    parts: list[str] = []
    for r in runs:
        proto = (r.config or {}).get("protocol") or {}
        steps = r.steps or proto.get("steps")
        if steps and f"{steps} steps" not in parts:
            parts.append(f"{steps} steps")
        w = proto.get("max_width")
        if w and f"images ≤ {w} px wide" not in parts:
            parts.append(f"images ≤ {w} px wide")
    return ", ".join(parts)


def flow_estimator(r: RunResult) -> str:
    c = r.consistency or {}
    return str(c.get("estimator") or c.get("flow") or "unknown")


# ---- pooling: which seeds may be averaged ------------------------------------------------------

LOCATIONS = ("dataset.path", "ply.path")
"""Config keys that say where a run read its input, not what (a grid split over machines)."""


def seed_config(r: RunResult) -> dict[str, str]:
    """A run's config as dotted keys, without its seed, the keys that do not change a result
    (``protocols.results.VOLATILE``) and the input's location (``LOCATIONS``); the device by its
    kind (``cuda:1`` is ``cuda``)."""
    flat: dict[str, str] = {}

    def walk(prefix: str, x) -> None:
        if isinstance(x, dict) and x:
            for k, v in x.items():
                walk(f"{prefix}.{k}" if prefix else str(k), v)
        else:
            flat[prefix] = repr(x)

    cfg = {k: v for k, v in (r.config or {}).items() if k not in VOLATILE and k != "seed"}
    if isinstance(cfg.get("device"), str):
        cfg["device"] = cfg["device"].split(":")[0]
    walk("", cfg)
    for k in LOCATIONS:
        flat.pop(k, None)
    if r.hparams:
        flat["hparams"] = repr(r.hparams)
    return flat


def config_difference(runs: list[RunResult], shown: int = 3) -> str | None:
    """Why the seeds ``runs`` of one row must not be pooled: the config keys other than the seed in
    which they differ, with each seed's value (None when they agree; runs that record no config,
    written before configs were recorded, are not compared)."""
    configs = [(r.seed, seed_config(r)) for r in sorted(runs, key=lambda r: r.seed) if r.config]
    if len(configs) < 2:
        return None
    keys = sorted({k for _, c in configs for k in c})
    differ = [k for k in keys if len({c.get(k, "<not set>") for _, c in configs}) > 1]
    if not differ:
        return None
    parts = []
    for k in differ[:shown]:
        by_value: dict[str, list[int]] = {}
        for seed, c in configs:
            by_value.setdefault(c.get(k, "<not set>"), []).append(seed)
        parts.append(f"{k} (" + "; ".join(f"seed{'s' if len(ss) > 1 else ''} {', '.join(map(str, ss))}: "
                                          f"{one_line(v, 60)}" for v, ss in by_value.items()) + ")")
    more = f"; and {len(differ) - shown} more key(s)" if len(differ) > shown else ""
    return ("seeds trained under different configs, not pooled: " + "; ".join(parts) + more
            + " (rerun them under one config)")
