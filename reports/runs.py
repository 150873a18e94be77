"""Reading a results tree and reducing runs to numbers-with-reasons.

A report never prints a number that is not there: every value is a ``Value`` that either holds a
mean (with std and count over the runs it came from, and notes such as "2 of 3 seeds") or the
reason it is absent ("failed: RuntimeError: ...", "LPIPS weights not installed").
"""

from __future__ import annotations

import math
import os
import re
from dataclasses import dataclass, field, fields
from pathlib import Path
from typing import Callable, Iterable

from protocols.results import VOLATILE, RunResult, find_results, read_result
from reports.stats import mean_sd

PATTERN_DATASETS = ("patterns",)


@dataclass(frozen=True)
class Absent:
    """Why a run has no value for something."""

    reason: str


Getter = Callable[[RunResult], "float | Absent"]


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


@dataclass
class Run:
    path: Path
    result: RunResult

    @property
    def r(self) -> RunResult:
        return self.result


@dataclass
class LoadedRuns:
    runs: list[Run] = field(default_factory=list)
    unreadable: list[tuple[Path, str]] = field(default_factory=list)
    duplicates: list[tuple[Path, Path]] = field(default_factory=list)  # (ignored, kept)
    roots: list[Path] = field(default_factory=list)                     # the directories read


def identity(r: RunResult) -> tuple:
    """What makes two results the same run (a pattern fit's cap included: budget "cap" alone does not
    tell 4 from 4096)."""
    return (r.method, r.dataset, r.scene, r.budget, r.preset, r.seed, pattern_cap(r) if is_pattern(r) else None)


def load_runs(root: Path | str, *more: Path | str) -> LoadedRuns:
    """Every results.json below ``root`` and the ``more`` directories (the parts of a grid that ran
    apart, e.g. split by pattern on two machines). Unreadable files are listed, not fatal. Two
    results for the same (method, dataset, scene, budget, preset, seed), e.g. two copies of an
    experiment, keep one: an ok result over a failed one, then the newest file. (A pattern fit's
    cap is part of its identity.)"""
    out = LoadedRuns(roots=[Path(r) for r in (root, *more)])
    kept: dict[tuple, Run] = {}
    for p in [p for r in out.roots for p in find_results(r)]:
        try:
            run = Run(p, cut_long_strings(read_result(p), p))
        except (OSError, ValueError) as e:
            out.unreadable.append((p, one_line(str(e), MAX_TEXT)))
            continue
        key = identity(run.r)
        old = kept.get(key)
        if old is None:
            kept[key] = run
            continue
        new_wins = ((run.r.status == "ok", _mtime(p)) > (old.r.status == "ok", _mtime(old.path)))
        keep, drop = (run, old) if new_wins else (old, run)
        kept[key] = keep
        out.duplicates.append((drop.path, keep.path))
    out.runs = list(kept.values())
    return out


MAX_TEXT = 2000
"""The longest recorded string a report shows (an error of megabytes, a device name gone wrong):
longer ones are cut where the runs are read, so report.md, report.html and the CSVs all hold the
cut text, with a note of how much was left out and where the whole is."""


def cut_long_strings(r: RunResult, path: Path) -> RunResult:
    """``r`` with every string of every field (nested in dicts and lists too) at most ``MAX_TEXT``
    characters long."""
    def cut(x):
        if isinstance(x, str):
            return x if len(x) <= MAX_TEXT else \
                x[:MAX_TEXT] + f"… [{len(x) - MAX_TEXT} more characters, in {path}]"
        if isinstance(x, dict):
            return {k: cut(v) for k, v in x.items()}
        if isinstance(x, list):
            return [cut(v) for v in x]
        return x

    for f in fields(r):
        setattr(r, f.name, cut(getattr(r, f.name)))
    return r


def _mtime(p: Path) -> float:
    try:
        return os.stat(p).st_mtime
    except OSError:
        return 0.0


# ---- classification ---------------------------------------------------------------------------

def is_pattern(r: RunResult) -> bool:
    return r.dataset in PATTERN_DATASETS


def pattern_cap(r: RunResult) -> int | None:
    """The Gaussian cap of a Table 1 fit: ``config["cap"]``, the budget config's ``cap``, a budget
    named ``capN``, or (last resort) the final count."""
    c = r.config or {}
    budget_cfg = c.get("budget") if isinstance(c.get("budget"), dict) else {}
    for v in (c.get("cap"), budget_cfg.get("cap")):
        if v is not None:
            return int(v)
    m = re.fullmatch(r"cap(\d+)", r.budget)
    if m:
        return int(m.group(1))
    return int(r.num_gaussians) if r.num_gaussians is not None else None


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


# ---- getters: one number of one run, or why not ----------------------------------------------

def _status_reason(r: RunResult) -> Absent | None:
    if r.status == "ok":
        return None
    err = one_line(r.error or "no error recorded")
    return Absent(f"{r.status}: {err}")


def one_line(text: str, limit: int = 160) -> str:
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _finite(x, what: str) -> "float | Absent":
    try:
        v = float(x)
    except (TypeError, ValueError):
        return Absent(f"{what} not a number ({x!r})")
    return v if math.isfinite(v) else Absent(f"{what} recorded as {v}")


METRIC_NAMES = {"psnr": "PSNR", "ssim": "SSIM", "lpips": "LPIPS", "flip": "FLIP"}


def metric(name: str) -> Getter:
    """A test-view mean from ``metrics``; absent with ``missing[name]`` as the reason."""
    def get(r: RunResult) -> "float | Absent":
        bad = _status_reason(r)
        if bad:
            return bad
        if name in r.metrics and r.metrics[name] is not None:
            return _finite(r.metrics[name], METRIC_NAMES.get(name, name))
        if name in r.missing:
            return Absent(f"{METRIC_NAMES.get(name, name)} missing: {one_line(r.missing[name])}")
        return Absent(f"{METRIC_NAMES.get(name, name)} not recorded")
    return get


def field_getter(name: str, label: str, scale: float = 1.0) -> Getter:
    """A top-level number of RunResult (num_gaussians, train_seconds, render_fps), times scale."""
    def get(r: RunResult) -> "float | Absent":
        bad = _status_reason(r)
        if bad:
            return bad
        v = getattr(r, name)
        if v is None:
            return Absent(f"{label} not recorded")
        x = _finite(v, label)
        return x * scale if isinstance(x, float) else x
    return get


def consistency_getter(name: str) -> Getter:
    """Table 4 numbers from ``result.consistency``: psnr (falls back to the test-view PSNR, the same
    quantity), mse, flip (read from the key named by ``flip_name`` if present)."""
    def get(r: RunResult) -> "float | Absent":
        bad = _status_reason(r)
        if bad:
            return bad
        c = r.consistency or {}
        if not c:
            return Absent("view consistency not computed")
        key = c.get("flip_name", "flip") if name == "flip" else name
        v = c.get(key, c.get("flip7") if name == "flip" else None)
        if isinstance(v, dict) and "missing" in v:
            return Absent(f"{key} missing: {one_line(v['missing'])}")
        if v is None:
            if name == "psnr":
                return metric("psnr")(r)
            return Absent(f"{key} not recorded")
        return _finite(v, key)
    return get


def flow_estimator(r: RunResult) -> str:
    c = r.consistency or {}
    return str(c.get("estimator") or c.get("flow") or "unknown")


# ---- aggregation ------------------------------------------------------------------------------

def aggregate(runs: list[RunResult], get: Getter) -> Value:
    """Mean ± std over runs (seeds). Runs without the value are named in a note; with none at all
    the value is absent with their reason(s)."""
    if not runs:
        return Value.absent("no result in the runs directory")
    vals: list[tuple[int, float]] = []
    gone: list[tuple[int, str]] = []
    for r in sorted(runs, key=lambda r: r.seed):
        v = get(r)
        if isinstance(v, Absent):
            gone.append((r.seed, v.reason))
        else:
            vals.append((r.seed, v))
    if not vals:
        return Value.absent(_join_reasons(gone))
    scored = {s for s, _ in vals}
    split = config_difference([r for r in runs if r.seed in scored])
    if split:
        return Value.absent(split)
    mean, std = mean_sd([x for _, x in vals])
    notes = ()
    if gone:
        notes = (f"{len(vals)} of {len(runs)} seeds; {_join_reasons(gone)}",)
    return Value(mean, std, len(vals), None, notes, tuple(vals))


def _join_reasons(gone: list[tuple[int, str]]) -> str:
    reasons = sorted({reason for _, reason in gone})
    if len(reasons) == 1 and len(gone) > 1:
        return reasons[0]
    if len(gone) == 1:
        return gone[0][1]
    return "; ".join(f"seed {s}: {reason}" for s, reason in gone)


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
