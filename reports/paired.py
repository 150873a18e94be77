"""Paired seed differences of the methods a protocol compares: the sub-tables under Tables 1, 2, 4, 5.

For each pair (Softmax-GS − 3D GS at the same budget and preset; in Table 4 each method − 3D GS), per
scene (dataset, or pattern and cap) and metric: the mean over seeds of the per-seed difference (seed s
of one method with seed s of the other: ``reports.aggregate.paired``), its Student t interval, ✱ where
the interval excludes 0, and the paper's difference beside it. Why t, and what ✱ does and does not say:
docs/reports.md ("Seeds, spread and paired differences").
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import Callable, Iterable

from reports.paper import DATASET_ORDER, GROUP_LABELS, PaperTables, dataset_label, method_label, row_label
from reports.aggregate import paired_value
from reports.runs import Value
from reports.stats import CONFIDENCE, t_quantile
from reports.table_model import Column, Row, Section, Table

BASELINE = "3dgs"
NO_SEEDS = ("one seed per run: a paired difference needs two or more seeds of both methods (seeds=3 or "
            "grid.seeds=[0,1,2]; docs/reports.md)")


def signed(decimals: int) -> Callable[[float], str]:
    return lambda x: f"{x:+.{decimals}f}"


def delta_column(c: Column) -> Column:
    """The paired-difference column of a table's metric column: A − B with its interval, the paper's
    A − B beside it (the arrow says which sign favours A)."""
    return Column(c.key, f"Δ{c.label} [{CONFIDENCE:.0%} CI]", signed(c.decimals), compare="paper")


def paper_delta(a: Value, b: Value, context: str | None) -> Value:
    """The paper's A − B, or why not (with ``context``: the paper's claim elsewhere, e.g. its Table 2
    means at this budget, for a scene the paper did not run)."""
    if a.ok and b.ok:
        return Value(a.mean - b.mean, n=1)
    why = a.reason if not a.ok else b.reason
    return Value.absent(f"{why}; {context}" if context else (why or "not in the paper"))


@dataclass
class Comparison:
    """Which rows of a results table compete, and how a paired row is named."""

    key_columns: list[str]                       # of the paired table, before "Comparison"
    keys: Callable[[Row], list[str]]             # a competing row -> its key cells
    group: Callable[[Row], tuple]                # rows with the same group compete (method aside)
    challengers: Iterable[str] | None = ("softmax_gs",)   # None: every method but the baseline
    context: Callable[[Row, Row, str], str | None] = lambda a, b, key: None  # the paper's claim elsewhere
    label: Callable[[str, str], str] = row_label          # (method, budget) -> its name in "A − B"


def paired_section(name: str, title: str, rows: list[Row], columns: list[Column], how: Comparison) -> Section | None:
    """The paired differences of ``rows`` (Rows whose ``csv`` names method, budget and preset and whose
    values carry per-seed values), or None when no row has a baseline to compare with."""
    groups: dict[tuple, list[Row]] = defaultdict(list)
    for r in rows:
        groups[how.group(r)].append(r)
    challengers = None if how.challengers is None else set(how.challengers)
    out: list[Row] = []
    for members in groups.values():
        base = [r for r in members if r.csv.get("method") == BASELINE]
        if len(base) != 1:
            continue
        b = base[0]
        for a in members:
            m = str(a.csv.get("method"))
            if m == BASELINE or (challengers is not None and m not in challengers):
                continue
            out.append(_paired_row(a, b, columns, how))
    if not out:
        return None
    sec = Section(name, title)
    if not any(v.ok and v.n >= 2 for r in out for v in r.values.values()):
        sec.empty_reason = _why_no_pairs(out)
        return sec
    sec.intro.append(_intro())
    sec.blocks.append(Table("", [*how.key_columns, "Comparison"], [delta_column(c) for c in columns], out,
                            info_columns=["Seeds"], rank="none"))
    return sec


def _why_no_pairs(rows: list[Row], shown: int = 4) -> str:
    """Why no row has a paired difference over two or more seeds: one seed per run where some
    difference is there (of one pair), else each comparison's reasons (a failed method, seeds of
    different configs, no seed in common)."""
    if any(v.ok for r in rows for v in r.values.values()):
        return NO_SEEDS
    why = {}
    for r in rows:
        for v in r.values.values():
            why.setdefault(v.reason or "no value", []).append(" ".join(r.keys))
    parts = [f"{', '.join(dict.fromkeys(where))}: {reason}" for reason, where in list(why.items())[:shown]]
    more = f"; … {len(why) - shown} more" if len(why) > shown else ""
    return "no paired difference: " + "; ".join(parts) + more


def _paired_row(a: Row, b: Row, columns: list[Column], how: Comparison) -> Row:
    ma, mb = str(a.csv["method"]), str(b.csv["method"])
    budget, preset = str(a.csv.get("budget", "")), str(a.csv.get("preset", "paper"))
    la, lb = how.label(ma, budget), how.label(mb, budget)
    label = f"{la} − {lb}" + ("" if preset == "paper" else f" [{preset}]")
    values, paper = {}, {}
    for c in columns:
        v = paired_value(a.values.get(c.key, Value.absent("not computed")),
                         b.values.get(c.key, Value.absent("not computed")), method_label(ma), method_label(mb))
        values[c.key] = v
        pv = paper_delta(a.paper.get(c.key, Value.absent("not in the paper")),
                         b.paper.get(c.key, Value.absent("not in the paper")), how.context(a, b, c.key))
        if v.ok and v.ci is not None and pv.ok and (v.ci[0] > 0 or v.ci[1] < 0) and (v.mean > 0) != (pv.mean > 0):
            pv = Value(pv.mean, n=1, notes=("our interval excludes 0 on the other side of the paper's difference",))
        paper[c.key] = pv
    seeds = sorted({s for v in values.values() for s, _ in v.seeds})
    notes = list(dict.fromkeys(a.label_notes + b.label_notes))
    csv = {k: v for k, v in a.csv.items() if k not in ("method", "label")}
    csv.update({"a": ma, "b": mb, "comparison": label})
    return Row([*how.keys(a), label], values, paper, label_notes=notes, info={"Seeds": ", ".join(map(str, seeds))},
               csv=csv)


def _intro() -> str:
    t3 = t_quantile((1 + CONFIDENCE) / 2, 2)
    return (f"Paired differences A − B: seed s of A minus seed s of B (same seed number), the mean over the n "
            f"pairs and its {CONFIDENCE:.0%} Student t interval [mean ± t·sd/√n], t = t_(0.975, n−1) (n = 3: "
            f"t = {t3:.2f}); ✱ = the interval excludes 0, a difference the seeds resolve. The arrow of a metric "
            "says which sign favours A. paper = the paper's A − B (single runs, no interval); its footnote says "
            "when our resolved difference has the other sign. Seeds: the pairs behind each row.")


# ---- the pairs each paper table compares ----------------------------------------------------------

DECIMALS = {"psnr": 2, "ssim": 3, "lpips": 3}


def table2_claims(paper: PaperTables, a: Row, b: Row, key: str) -> str | None:
    """The paper's Table 2 A − B at the rows' budget on each of its datasets: the direction it claims,
    for a scene or dataset it did not run."""
    if paper.error or key not in DECIMALS:
        return None
    budget = str(a.csv.get("budget"))
    parts = []
    for ds in DATASET_ORDER:
        x, y = paper.t2(str(a.csv["method"]), budget, ds, key), paper.t2(str(b.csv["method"]), budget, ds, key)
        if x is not None and y is not None:
            parts.append(f"{x - y:+.{DECIMALS[key]}f} ({dataset_label(ds)})")
    return "the paper's Table 2 A − B at this budget: " + ", ".join(parts) if parts else None


def table1_paired(rows: list[Row], columns: list[Column]) -> Section | None:
    """Softmax-GS − 3D GS per pattern and cap (rows: one per pattern × cap × method × preset)."""
    how = Comparison(["Pattern", "#GS cap"], lambda r: [str(r.csv["pattern"]), str(r.csv["cap"])],
                     lambda r: (r.csv["pattern"], r.csv["cap"], r.csv["preset"]), label=lambda m, b: method_label(m))
    return paired_section("table1_paired", "Paired differences: Softmax-GS − 3D GS at each cap", rows, columns, how)


def table2_paired(rows: list[Row], columns: list[Column], paper: PaperTables) -> Section | None:
    """Softmax-GS − 3D GS per dataset at each budget and preset (the dataset means' per-seed values)."""
    how = Comparison(["Dataset", "Group"], lambda r: [dataset_label(str(r.csv["dataset"])),
                                                      GROUP_LABELS[str(r.csv["group"])]],
                     lambda r: (r.csv["dataset"], r.csv["budget"], r.csv["preset"]),
                     context=lambda a, b, k: table2_claims(paper, a, b, k))
    return paired_section("table2_paired", "Paired differences: Softmax-GS − 3D GS per dataset and budget", rows,
                          columns, how)


def table4_paired(rows: list[Row], columns: list[Column]) -> Section | None:
    """Each method − 3D GS per scene, budget, preset and flow estimator."""
    how = Comparison(["Scene"], lambda r: [str(r.csv["scene"])],
                     lambda r: (r.csv["dataset"], r.csv["scene"], r.csv["budget"], r.csv["preset"],
                                r.info.get("Flow")), challengers=None)
    return paired_section("table4_paired", "Paired differences: each method − 3D GS per scene", rows, columns, how)


def table5_paired(rows: list[Row], columns: list[Column], paper: PaperTables) -> Section | None:
    """Softmax-GS − 3D GS per scene at each budget and preset."""
    how = Comparison(["Dataset", "Scene"], lambda r: [dataset_label(str(r.csv["dataset"])), str(r.csv["scene"])],
                     lambda r: (r.csv["dataset"], r.csv["scene"], r.csv["budget"], r.csv["preset"]),
                     context=lambda a, b, k: table2_claims(paper, a, b, k))
    return paired_section("table5_paired", "Paired differences: Softmax-GS − 3D GS per scene", rows, columns, how)
