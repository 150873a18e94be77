"""The report's numbers, computed from the results table (``smgs.cells.table.cells``) in one place.

- ``Cells``: the table of the runs a report reads, row i being ``runs[i]``, and each quantity a table
  shows (``QUANTITIES``) as a value or the reason there is none ("failed: …", "LPIPS missing: …").
- ``seed_means``: a group-by of the cells: mean ± sd over the seeds of a row, n, the seeds behind it,
  a note for seeds without the value, and no mean where the seeds' configs differ
  (``reports.runs.config_difference``, the one pooling rule).
- ``scene_means``: a group-by of the seed means over scenes (``reports.stats.mean_of_means``).
- ``paired``: a merge of two rows' per-seed values on the seed number, with its t interval.
- ``seed_bands``: a group-by of the curves of each row's seeds by evaluation step (the plots' bands).
- ``ranks``: a group-by of a table's competing cells: best / second, and a tie where the lead is
  inside the seeds' spread.

A report never prints a number that is not there: every result is a ``reports.runs.Value``.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Iterable, Literal, Sequence

import pandas as pd

from protocols.results import RunResult
from reports.runs import Value, config_difference
from reports.stats import CONFIDENCE, mean_of_means, t_interval
from smgs.cells.table import CELL_COLUMNS, NOT_RECORDED, cell_record, frame
from smgs.cells.tree import LoadedRuns, one_line

NO_RESULT = "no result in the runs directory"
TIE = "tie"            # rank of values that share the best place within their seeds' spread
Rank = Literal[1, 2, "tie"]


@dataclass(frozen=True)
class Quantity:
    """One number a table shows: the cells' column it is read from, its name in a reason, a scale."""

    column: str
    label: str
    kind: Literal["metric", "field", "consistency"]
    scale: float = 1.0


QUANTITIES = {
    "psnr": Quantity("psnr", "PSNR", "metric"), "ssim": Quantity("ssim", "SSIM", "metric"),
    "lpips": Quantity("lpips", "LPIPS", "metric"), "flip": Quantity("flip", "FLIP", "metric"),
    "num_gaussians": Quantity("num_gaussians", "#GS", "field"),
    "train_minutes": Quantity("train_seconds", "train time", "field", 1 / 60),
    "render_fps": Quantity("render_fps", "render FPS", "field"),
    "frac_within_kmax": Quantity("frac_within_kmax", "k_max coverage", "field"),
    **{f"consistency_{k}": Quantity(k, k, "consistency") for k in ("psnr", "mse", "flip", "pop_ratio",
                                                                    "popped_fraction")},
}


class Cells:
    """The results table of a report's runs; row i of ``frame`` is ``runs[i]``."""

    def __init__(self, table: pd.DataFrame, runs: list[RunResult]):
        self.frame = table.reset_index(drop=True)
        self.runs = runs
        self._values: dict[str, pd.DataFrame] = {}

    @staticmethod
    def of(runs: Sequence[RunResult], paths: Sequence[Path | str] | None = None) -> "Cells":
        paths = paths if paths is not None else [""] * len(runs)
        return Cells(frame([cell_record(r, p) for r, p in zip(runs, paths)], CELL_COLUMNS), list(runs))

    @staticmethod
    def loaded(loaded: LoadedRuns) -> "Cells":
        return Cells.of([x.result for x in loaded.runs], [x.path for x in loaded.runs])

    def runs_at(self, rows: Iterable[int]) -> list[RunResult]:
        return [self.runs[i] for i in rows]

    def rows(self, mask: pd.Series | None = None) -> pd.Index:
        return self.frame.index if mask is None else self.frame.index[mask.fillna(False).to_numpy(bool)]

    def quantity(self, name: str) -> pd.DataFrame:
        """``value`` (NaN where there is none) and ``reason`` (why not) of every row."""
        if name not in self._values:
            q = QUANTITIES[name]
            pairs = [_value(row, q) for row in self.frame.to_dict("records")]
            self._values[name] = pd.DataFrame(pairs, columns=["value", "reason"], index=self.frame.index,
                                              dtype=object).astype({"value": "float64"})
        return self._values[name]


def groups(cells: Cells, by: Sequence[str], rows: pd.Index | None = None) -> dict[tuple, list[RunResult]]:
    """The runs of each group of ``rows`` (default: all) with equal ``by`` columns, in first-seen order."""
    rows = cells.frame.index if rows is None else rows
    return {_native(key): cells.runs_at(g.index)
            for key, g in cells.frame.loc[rows].groupby(list(by), sort=False, dropna=False)}


# ---- one cell: a value or why not -----------------------------------------------------------------

def _value(row: dict, q: Quantity) -> tuple[float | None, str | None]:
    if row["status"] != "ok":
        return None, f"{row['status']}: {one_line(row['reason'] if _set(row['reason']) else 'no error recorded')}"
    if q.kind == "consistency":
        if not _set(row["consistency_flow"]):
            return None, "view consistency not computed"
        key = row["consistency_flip_name"] if q.column == "flip" else q.column
        column = f"consistency_{q.column}"
        if q.column == "psnr" and _set(row[f"{column}_missing"]) and row[f"{column}_missing"] == NOT_RECORDED:
            return _value(row, QUANTITIES["psnr"])   # the test-view PSNR: the same quantity
        return _recorded(row, column, key, q.scale)
    if q.kind == "field" and not _set(row[q.column]):
        return None, f"{q.label} {NOT_RECORDED}"
    return _recorded(row, q.column, q.label, q.scale)


def _recorded(row: dict, column: str, label: str, scale: float) -> tuple[float | None, str | None]:
    """A recorded number (a non-finite one is no value: "recorded as nan"), or why there is none (the
    table's ``<column>_missing``: why a finished cell has no value)."""
    why = row.get(f"{column}_missing")
    if _set(why):
        if why == NOT_RECORDED or why.startswith("not a number ("):
            return None, f"{label} {why}"
        return None, f"{label} missing: {one_line(why)}"
    x = float(row[column])
    return (x * scale, None) if abs(x) != float("inf") and x == x else (None, f"{label} recorded as {x}")


def _set(x: object) -> bool:
    """Not missing (None, <NA>, NaN)."""
    return x is not None and not (isinstance(x, float) and x != x) and x is not pd.NA


# ---- seed means: a group-by of the cells -------------------------------------------------------------

class SeedMeans:
    """Seed means keyed by the group-by's columns, one ``Value`` per key and quantity."""

    def __init__(self, by: Sequence[str], values: dict[tuple, dict[str, Value]]):
        self.by = list(by)
        self.values = values

    def get(self, key: tuple, name: str) -> Value:
        return self.values.get(tuple(key), {}).get(name) or Value.absent(NO_RESULT)

    def keys(self) -> list[tuple]:
        return list(self.values)


def seed_means(cells: Cells, by: Sequence[str], names: Iterable[str], rows: pd.Index | None = None) -> SeedMeans:
    """Mean ± sd over the seeds of each group of ``rows`` (default: all) with equal ``by`` columns, for
    each quantity of ``names``; a group whose seeds lack a value is noted ("2 of 3 seeds; …"), one whose
    seeds trained under different configs has no mean (``config_difference`` says which keys)."""
    rows = cells.frame.index if rows is None else rows
    keys = cells.frame.loc[rows, [*by, "seed"]]
    out: dict[tuple, dict[str, Value]] = {}
    for name in names:
        q = cells.quantity(name).loc[rows]
        long = keys.assign(value=q["value"], reason=q["reason"]).sort_values("seed", kind="stable")
        grouped = long.groupby(list(by), sort=False, dropna=False)
        stats = grouped["value"].agg(["mean", "std", "count"])
        for key, g in grouped:
            key = _native(key)
            out.setdefault(key, {})[name] = _seed_value(cells, g, stats.loc[key if len(by) > 1 else key[0]])
    return SeedMeans(by, out)


def _seed_value(cells: Cells, g: pd.DataFrame, stats: pd.Series) -> Value:
    has = g["reason"].isna()
    vals = [(int(s), float(v)) for s, v in zip(g["seed"][has], g["value"][has])]
    gone = [(int(s), str(w)) for s, w in zip(g["seed"][~has], g["reason"][~has])]
    if not vals:
        return Value.absent(_join_reasons(gone))
    scored = {s for s, _ in vals}
    split = config_difference([r for r in cells.runs_at(g.index) if r.seed in scored])
    if split:
        return Value.absent(split)
    std = None if pd.isna(stats["std"]) else float(stats["std"])
    notes = (f"{len(vals)} of {len(g)} seeds; {_join_reasons(gone)}",) if gone else ()
    return Value(float(stats["mean"]), std, int(stats["count"]), None, notes, tuple(vals))


def _join_reasons(gone: list[tuple[int, str]]) -> str:
    reasons = sorted({reason for _, reason in gone})
    if len(reasons) == 1 and len(gone) > 1:
        return reasons[0]
    if len(gone) == 1:
        return gone[0][1]
    return "; ".join(f"seed {s}: {reason}" for s, reason in gone)


def _native(key: object) -> tuple:
    """A group key as a tuple of Python values (numpy integers as int: keys go into CSVs and JSON)."""
    key = key if isinstance(key, tuple) else (key,)
    return tuple(k.item() if hasattr(k, "item") else k for k in key)


# ---- scene means: a group-by of the seed means ----------------------------------------------------------

def scene_means(seeds: SeedMeans, rows: Iterable[tuple], scenes: Sequence[str], names: Iterable[str]
                ) -> dict[tuple, dict[str, Value]]:
    """For each row key (``seeds``' keys less the last column, the scene) and quantity: the mean over
    ``scenes`` of the scenes' seed means (``scene_mean``)."""
    table = pd.DataFrame([(*k, name, v) for k, by_name in seeds.values.items() for name, v in by_name.items()],
                         columns=[*seeds.by, "quantity", "value"])
    row_keys = seeds.by[:-1]
    wanted = table[table[seeds.by[-1]].isin(scenes)]
    out: dict[tuple, dict[str, Value]] = {tuple(k): {} for k in rows}
    for name in names:
        for k in out:
            out[k][name] = Value.absent(NO_RESULT)
    for key, g in wanted.groupby([*row_keys, "quantity"], sort=False):
        *k, name = _native(key)
        if tuple(k) in out and name in out[tuple(k)]:
            by_scene = dict(zip(g[seeds.by[-1]], g["value"]))
            out[tuple(k)][name] = scene_mean([by_scene.get(s, Value.absent(NO_RESULT)) for s in scenes], scenes)
    return out


def scene_mean(values: list[Value], scenes: Sequence[str]) -> Value:
    """The mean over scenes of the scenes' seed means. Its sd is what one seed's mean over these scenes
    would spread by (reports.stats.mean_of_means), its n the fewest seeds of a scene, and its per-seed
    values the seeds every scene ran (for paired differences)."""
    bad = [(s, v.reason) for s, v in zip(scenes, values) if not v.ok]
    if bad:
        return Value.absent(scene_reasons(dict(bad)))
    notes = tuple(dict.fromkeys(f"{s}: {n}" for s, v in zip(scenes, values) for n in v.notes))
    mean, sd = mean_of_means([(v.mean, v.std) for v in values])
    ns = sorted({v.n for v in values})
    if len(ns) > 1:
        notes += (f"seeds per scene: {', '.join(f'{s} {v.n}' for s, v in zip(scenes, values))}; n is the fewest"
                  + ("; no sd: a scene has one seed" if sd is None else ""),)
    per_seed = pd.DataFrame([(s, x) for v in values for s, x in v.seeds], columns=["seed", "value"])
    by_seed = per_seed.groupby("seed").agg(mean=("value", "mean"), scenes=("value", "size"))
    common = by_seed[by_seed["scenes"] == len(values)].sort_index()
    seeds = tuple((int(s), float(x)) for s, x in common["mean"].items())
    return Value(mean, sd, ns[0], None, notes, seeds)


def scene_reasons(reasons: dict[str, str | None]) -> str:
    distinct = set(reasons.values())
    if len(distinct) == 1:
        why = next(iter(distinct)) or "no value"
        return why if len(reasons) == 1 else f"{why} (every scene)"
    return one_line("; ".join(f"{s}: {w}" for s, w in reasons.items()), 400)


# ---- paired differences: a merge on the seed -----------------------------------------------------------

@dataclass(frozen=True)
class Paired:
    """A − B over the seeds both ran, seed s of A with seed s of B."""

    diffs: tuple[tuple[int, float], ...]   # (seed, A − B), by seed
    mean: float
    sd: float | None                       # of the per-seed differences
    low: float | None                      # the t interval; None with one pair
    high: float | None
    t: float | None                        # the quantile used: t_{(1+CONFIDENCE)/2, n−1}
    only_a: tuple[int, ...] = ()           # seeds one side ran and the other did not (left out)
    only_b: tuple[int, ...] = ()

    @property
    def n(self) -> int:
        return len(self.diffs)

    @property
    def excludes_zero(self) -> bool:
        return self.low is not None and self.high is not None and (self.low > 0 or self.high < 0)


def paired(a: Sequence[tuple[int, float]], b: Sequence[tuple[int, float]],
           confidence: float = CONFIDENCE) -> Paired | None:
    """The paired difference of two methods' per-seed values ``(seed, value)``: d_s = a_s − b_s over the
    seeds both have; mean d̄ ± t_{(1+c)/2, n−1} · sd(d) / √n (Student t; with one pair, no interval).
    None when the two share no seed."""
    m = pd.merge(pd.DataFrame(list(a), columns=["seed", "a"]), pd.DataFrame(list(b), columns=["seed", "b"]),
                 on="seed", how="outer", indicator=True).sort_values("seed")
    both = m[m["_merge"] == "both"]
    if both.empty:
        return None
    d = both["a"] - both["b"]
    diffs = tuple((int(s), float(x)) for s, x in zip(both["seed"], d))
    mean = float(d.mean())
    sd = float(d.std()) if len(d) > 1 else None
    low = high = t = None
    if sd is not None:
        low, high, t = t_interval(mean, sd, len(d), confidence)
    only = lambda side: tuple(int(s) for s in m.loc[m["_merge"] == side, "seed"])  # noqa: E731
    return Paired(diffs, mean, sd, low, high, t, only("left_only"), only("right_only"))


def paired_value(a: Value, b: Value, a_name: str, b_name: str) -> Value:
    """A − B over the seeds both ran, with its interval, or why there is none."""
    for v, name in ((a, a_name), (b, b_name)):
        if not v.ok:
            return Value.absent(f"{name}: {v.reason}")
        if not v.seeds:
            return Value.absent(f"{name}: no per-seed values")
    p = paired(a.seeds, b.seeds)
    if p is None:
        return Value.absent(f"no seed in common ({a_name}: seeds {_seed_list(a)}; {b_name}: seeds {_seed_list(b)})")
    notes = []
    for only, name in ((p.only_a, a_name), (p.only_b, b_name)):
        if only:
            notes.append(f"unpaired, left out: seed{'s' if len(only) > 1 else ''} "
                         f"{', '.join(map(str, only))} of {name} only")
    if p.n == 1:
        notes.append("one seed pair: no interval")
    ci = (p.low, p.high) if p.low is not None and p.high is not None else None
    return Value(p.mean, p.sd, p.n, None, tuple(notes), p.diffs, ci)


def _seed_list(v: Value) -> str:
    return ", ".join(str(s) for s, _ in v.seeds) or "none"


# ---- the seeds' band of an error-against-time curve: a group-by of the curves by step --------------------

@dataclass
class Band:
    """The seeds of one method × budget × preset on one panel, at the evaluation steps all of them
    made: mean train seconds, mean / lowest / highest PSNR."""

    method: str
    budget: str
    preset: str
    seeds: list[int]
    steps: list[int]
    seconds: list[float]
    mean: list[float]
    low: list[float]
    high: list[float]


def seed_bands(runs: list[RunResult]) -> list[Band]:
    """One Band per method × budget (a fit's: "cap N") × preset of ``runs`` (one panel's) with two or more
    seeds of one config whose curves share at least one evaluation step (seeds of different configs are
    drawn apart, ``config_difference``)."""
    cells = Cells.of(runs)
    f = cells.frame
    label = f["budget"].where(f["cap"].isna(), "cap " + f["cap"].astype("string"))
    bands = []
    for (m, b, p), g in f.assign(label=label).groupby(["method", "label", "preset"], sort=False):
        rs = cells.runs_at(g.index)
        if len(rs) < 2 or config_difference(rs):
            continue
        pts = pd.DataFrame([(k, c.step, c.seconds, c.psnr) for k, r in enumerate(rs) for c in r.curve],
                           columns=["run", "step", "seconds", "psnr"]).drop_duplicates(["run", "step"], keep="last")
        at = pts.groupby("step").agg(runs=("run", "size"), seconds=("seconds", "mean"), mean=("psnr", "mean"),
                                     low=("psnr", "min"), high=("psnr", "max"))
        at = at[at["runs"] == len(rs)].sort_index()
        if len(at):
            bands.append(Band(m, b, p, sorted(r.seed for r in rs), at.index.tolist(), at["seconds"].tolist(),
                              at["mean"].tolist(), at["low"].tolist(), at["high"].tolist()))
    return bands


# ---- best / second / tie: a group-by of a table's competing cells ------------------------------------

def ranks(candidates: list[tuple[object, object, float, str, float | None, bool]]) -> dict[object, Rank]:
    """``candidates``: (the set it competes in, cell, mean, text as printed, sd, higher is better) of
    every cell with a value. Per set: 1 (best), 2 (second) or "tie".

    Without a spread (no value of the set has an sd: one seed) values equal as printed share a rank; a
    set with a single value, or whose values all tie, is not ranked. With a spread, a value ties the
    best when it is equal as printed or behind by no more than the larger sd of the two: a lone best is
    rank 1, several are each "tie" (and nobody is second); the runner-up is rank 2 only when it leads
    the next value by more than their spread (or is the last)."""
    sets: dict[object, int] = {}
    table = pd.DataFrame([(sets.setdefault(k, len(sets)), *rest) for k, *rest in candidates],
                         columns=["set", "cell", "mean", "text", "sd", "higher"], dtype=object)
    out: dict[object, Rank] = {}
    for _, g in table.groupby("set", sort=False):
        if len(g) < 2:
            continue
        scored = [(m, t, sd, cell) for m, t, sd, cell in zip(g["mean"], g["text"], g["sd"], g["cell"])]
        best_first = sorted(scored, key=lambda s: s[0], reverse=bool(g["higher"].iloc[0]))
        if any(sd is not None for _, _, sd, _ in scored):
            out.update(_spread_ranks(best_first))
            continue
        texts = list(dict.fromkeys(t for _, t, _, _ in best_first))  # equal as printed = tie
        if len(texts) < 2:
            continue  # all equal: nothing stands out
        for _, t, _, cell in scored:
            if texts.index(t) < 2:
                out[cell] = texts.index(t) + 1
    return out


def _spread_ranks(best_first: list[tuple]) -> dict[object, Rank]:
    """``ranks`` for a set with a spread: ``best_first`` holds (mean, text as printed, sd, cell)."""
    def ties(a: tuple, b: tuple) -> bool:
        sds = [x[2] for x in (a, b) if x[2] is not None]
        return a[1] == b[1] or abs(a[0] - b[0]) <= max(sds, default=0.0)

    top = best_first[0]
    best = [x for x in best_first if ties(top, x)]
    if len(best) > 1:
        return {x[3]: TIE for x in best}
    out: dict[object, Rank] = {top[3]: 1}
    rest = best_first[1:]
    if len(rest) == 1 or not ties(rest[0], rest[1]):
        out[rest[0][3]] = 2
    return out
