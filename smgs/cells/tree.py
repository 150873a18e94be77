"""A results tree read as one set of cells: every results.json below one or more directories, each
cell once (a copy of a cell, e.g. two copies of an experiment, keeps the ok one, then the newest),
the files that could not be read listed with why, and recorded strings cut to a readable length."""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field, fields
from pathlib import Path

from smgs.cells.result import RunResult, find_results, read_result

PATTERN_DATASETS = ("patterns",)
MAX_TEXT = 2000
"""The longest recorded string a report shows (an error of megabytes, a device name gone wrong):
longer ones are cut where the runs are read, so the results table, report.md, report.html and the
CSVs all hold the cut text, with a note of how much was left out and where the whole is."""


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


def one_line(text: str, limit: int = 160) -> str:
    """``text`` on one line, at most ``limit`` characters (an ellipsis where it was cut)."""
    text = " ".join(str(text).split())
    return text if len(text) <= limit else text[: limit - 1] + "…"


def _mtime(p: Path) -> float:
    try:
        return os.stat(p).st_mtime
    except OSError:
        return 0.0
