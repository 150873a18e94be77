"""The paper's Tables 1–5 built from run results, each value beside the paper's.

Rows are (method, budget, preset); a reduced preset (``cpu``) is labelled on its row, explained in a
footnote and ranked only against rows of the same preset (and, for speed, the same device).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from typing import TYPE_CHECKING, Iterable

from protocols.results import RunResult
from reports.collapse import LABEL as COLLAPSED
from reports.collapse import collapse_note, collapsed_runs
from reports.ordering import ordering_section
from reports.paper import (DATASET_SCENES, PATTERNS, GROUP_LABELS, GROUP_ORDER, PaperTables, budget_group,
                           budget_rank, dataset_label, dataset_rank, method_label, method_rank, paper_key,
                           row_label, scene_rank)
from reports.aggregate import Cells, SeedMeans, groups, scene_means, scene_reasons, seed_means
from reports.runs import PATTERN_DATASETS, Value, flow_estimator, preset_description
from reports.paired import table1_paired, table2_paired, table4_paired, table5_paired
from reports.table_model import Column, Row, Section, Table, count, fixed

if TYPE_CHECKING:
    import pandas as pd

RowKey = tuple[str, str, str]  # (method, budget, preset)
REFERENCE_NOTE = ("[reference renderer] = rendered with the PyTorch reference backend (results.json versions), "
                  "100–1000× slower than the compiled ones: its quality is the method's, its times and FPS are "
                  "not")
SCENE_KEYS = ["dataset", "scene", "method", "budget", "preset"]   # a row of Tables 3–5


@dataclass
class Context:
    """What every table builder shares: the paper's numbers, the presets' descriptions and the results
    table of the runs (every number of a table is computed from it: ``reports.aggregate``)."""

    paper: PaperTables
    presets: dict[str, str]  # reduced preset -> footnote text
    cells: Cells

    @staticmethod
    def of(runs: list[RunResult], paper: PaperTables, cells: Cells | None = None) -> "Context":
        cells = cells if cells is not None else Cells.of(runs)
        presets = {}
        for (p,), rs in groups(cells, ["preset"]).items():
            if p != "paper":
                desc = preset_description(rs)
                presets[p] = (f"[{p}] = the {p} preset{f' ({desc})' if desc else ''}, a reduced protocol, not "
                              f"the paper's: its Δ to the paper is context, not a reproduction check")
        return Context(paper, presets, cells)

    def rows(self, real: bool) -> "pd.Index":
        """The rows of the real-scene runs, or (``real=False``) of the 2D pattern fits."""
        f = self.cells.frame
        return self.cells.rows(~f["dataset"].isin(PATTERN_DATASETS) if real else f["dataset"].isin(PATTERN_DATASETS))

    def paper_value(self, x: float | None, where: str) -> Value:
        if self.paper.error:
            return Value.absent(self.paper.error)
        return Value.of(x, f"not in the paper's {where}")

    def label(self, key: RowKey, runs: Iterable[RunResult] = ()) -> tuple[str, list[str]]:
        """The row's label and its footnotes: [preset] for a reduced preset, [reference renderer]
        when any of its ``runs`` rendered with the PyTorch reference backend, [collapsed] when any
        of them collapsed (``reports.collapse``)."""
        method, budget, preset = key
        runs = list(runs)
        text, notes = row_label(method, budget), []
        if preset != "paper":
            text += f" [{preset}]"
            notes.append(self.presets.get(preset, f"[{preset}] = a reduced preset"))
        if any(r.versions.get("backend") == "reference" for r in runs):
            text += " [reference renderer]"
            notes.append(REFERENCE_NOTE)
        collapsed = collapsed_runs(runs)
        if collapsed:
            text += " " + COLLAPSED
            notes.append(collapse_note(collapsed))
        return text, notes


def row_order(key: RowKey) -> tuple:
    method, budget, preset = key
    return (GROUP_ORDER.index(budget_group(budget)), budget_rank(budget), method_rank(method),
            preset != "paper", preset)


def mix_notes(runs: Iterable[RunResult], what: str = "This table") -> list[str]:
    """Say when a table mixes protocol presets, devices or renderers (backends or their variants)."""
    runs = list(runs)
    notes = []
    presets = sorted({r.preset for r in runs})
    if len(presets) > 1:
        notes.append(f"{what} mixes protocol presets ({', '.join(presets)}); rows of a reduced preset are "
                     f"labelled [preset] and ranked only among themselves.")
    elif presets and presets[0] != "paper":
        notes.append(f"Every row uses the reduced [{presets[0]}] preset, not the paper's protocol.")
    devices = sorted({str(r.render_device or r.versions.get("device")) for r in runs if r.status == "ok"}
                     - {"None"})
    if len(devices) > 1:
        notes.append(f"{what} mixes devices ({', '.join(devices)}).")
    # what rendered: the backend and its variants where the run recorded them (results.json versions)
    renderers = sorted({str(r.versions.get("renderer") or r.versions.get("backend")) for r in runs
                        if r.versions.get("renderer") or r.versions.get("backend")})
    if len(renderers) > 1:
        notes.append(f"{what} mixes renderer backends or variants ({'; '.join(renderers)}).")
    pre = sorted({f"{r.scene}/{r.method} ← {r.source.get('ply')}" for r in runs
                  if (r.source or {}).get("kind") == "pretrained"})
    if pre:
        notes.append("Rows marked (pretrained) are models read from a PLY (another tool's, or a run's own, "
                     "exported) and only evaluated here under the same protocol (no train time): " + "; ".join(pre[:5])
                     + (f"; … {len(pre) - 5} more" if len(pre) > 5 else "") + ".")
    alpha = {f"{r.dataset}/{r.scene}": r.data["alpha_dropped"] for r in runs
             if isinstance(r.data, dict) and r.data.get("alpha_dropped")}
    for scene, text in sorted(alpha.items()):
        notes.append(f"Scene {scene}: {text}.")
    for key, what_ran in (("fps_conditions", "FPS"), ("train_conditions", "Train time")):
        shared = [(r.diagnostics or {}).get(key) or {} for r in runs if r.status == "ok"]
        shared = [c for c in shared if c.get("cells_in_parallel", 1) > 1]
        if shared:
            turns = " (the cells measure FPS one at a time)" if key == "fps_conditions" else ""
            notes.append(f"{what_ran} of {len(shared)} run(s) was measured while up to "
                         f"{max(c['cells_in_parallel'] for c in shared) - 1} other cell(s), of this or another "
                         f"sweep, were running on the same machine{turns}, with "
                         f"{'/'.join(sorted({str(c.get('threads')) for c in shared}))} thread(s) each.")
    q = {bool(r.diagnostics.get("metrics_on_8bit")) for r in runs
         if r.status == "ok" and "metrics_on_8bit" in (r.diagnostics or {})}
    if q == {False}:
        notes.append("Metrics on float renders, not 8-bit quantised ones (eval.quantize=false).")
    elif len(q) > 1:
        notes.append(f"{what} mixes metrics on 8-bit quantised renders and on float renders (eval.quantize).")
    return notes


def _csv_id(key: RowKey, **extra) -> dict[str, object]:
    method, budget, preset = key
    return {**extra, "method": method, "budget": budget, "preset": preset, "label": row_label(method, budget)}


# ---- Table 1 ----------------------------------------------------------------------------------

def table1(runs: list[RunResult], ctx: Context) -> Section:
    sec = Section("table1_patterns", "Table 1 — 2D pattern fits (PSNR ↑, capped #Gaussians)")
    rows_ = ctx.rows(real=False)
    pats = ctx.cells.runs_at(rows_)
    if not pats:
        sec.empty_reason = ("no 2D pattern fits (dataset=patterns) below the runs directory; "
                            "`python -m protocols.run +experiment=patterns` makes them.")
        return sec
    sec.intro.append("Mean ± std over seeds of the test-view PSNR of each fit; one block per pattern, one row "
                     "per Gaussian cap, methods side by side (the paper's table transposed so that its value "
                     "sits beside ours). Best of a row in bold, second in italics (among methods of one preset).")
    capped = rows_[ctx.cells.frame.loc[rows_, "cap"].notna().to_numpy(bool)]
    no_cap = ctx.cells.runs_at(rows_.difference(capped))
    means = seed_means(ctx.cells, ["scene", "cap", "method", "preset"], ["psnr", "num_gaussians"], capped)
    records = []
    patterns = sorted({k[0] for k in means.keys()}, key=lambda p: (PATTERNS.index(p) if p in PATTERNS else 99, p))
    for pattern in patterns:
        caps = sorted({k[1] for k in means.keys() if k[0] == pattern})
        cols_keys = sorted({(k[2], k[3]) for k in means.keys() if k[0] == pattern},
                           key=lambda mp: (mp[1] != "paper", mp[1], method_rank(mp[0])))
        columns = []
        for m, p in cols_keys:
            label = method_label(m) + ("" if p == "paper" else f" [{p}]")
            columns.append(Column(f"{m}@{p}", label, fixed(2), "higher", "diff", 2, show_std=True, group=p))
        rows = []
        for cap in caps:
            row = Row([str(cap)], {}, csv={"pattern": pattern, "cap": cap})
            for m, p in cols_keys:
                row.values[f"{m}@{p}"] = means.get((pattern, cap, m, p), "psnr")
                row.paper[f"{m}@{p}"] = ctx.paper_value(ctx.paper.t1(pattern, m, cap), "Table 1")
            rows.append(row)
        notes = [ctx.presets[p] for p in sorted({p for _, p in cols_keys}) if p in ctx.presets]
        sec.blocks.append(Table(f"{pattern}", ["#GS cap"], columns, rows, notes=notes, rank="row", seeds=True))
        for pt, cap, m, p in sorted(k for k in means.keys() if k[0] == pattern):
            v = means.get((pt, cap, m, p), "psnr")
            gs = means.get((pt, cap, m, p), "num_gaussians")
            pv = ctx.paper.t1(pattern, m, cap)
            records.append({"pattern": pattern, "method": m, "preset": p, "cap": cap, "psnr": v.mean,
                            "psnr_std": v.std, "n_seeds": v.n, "paper_psnr": pv,
                            "delta_psnr": (v.mean - pv) if v.ok and pv is not None else None,
                            "num_gaussians": gs.mean, "note": "; ".join(([v.reason] if v.reason else [])
                                                                        + list(v.notes))})
    sec.records = records
    sec.subsections.append(_table1_ordering(means, ctx))
    _add(sec, table1_paired(_table1_rows(means, ctx), [Column("psnr", "PSNR↑", fixed(2), "higher")]))
    sec.notes += mix_notes(pats)
    if no_cap:
        sec.notes.append(f"{len(no_cap)} pattern run(s) record no Gaussian cap and are left out: "
                         + ", ".join(f"{r.scene}/{r.method}/{r.budget}/seed{r.seed}" for r in no_cap[:10]))
    return sec


def _table1_rows(means: SeedMeans, ctx: Context) -> list[Row]:
    """One row per pattern × cap × method × preset (for the paired differences)."""
    return [Row([], {"psnr": means.get((pt, cap, m, p), "psnr")},
                {"psnr": ctx.paper_value(ctx.paper.t1(pt, m, cap), "Table 1")},
                csv={"pattern": pt, "cap": cap, "method": m, "budget": f"cap{cap}", "preset": p})
            for pt, cap, m, p in sorted(means.keys())]


def _add(sec: Section, sub: Section | None) -> None:
    if sub is not None:
        sec.subsections.append(sub)


def _table1_ordering(means: SeedMeans, ctx: Context) -> Section:
    """The ordering check on the seed means of each (pattern, cap, preset) (``reports.ordering``)."""
    by_cell: dict[tuple, dict[str, float]] = defaultdict(dict)
    for pattern, cap, m, p in means.keys():
        v = means.get((pattern, cap, m, p), "psnr")
        if v.ok:
            by_cell[(pattern, cap, p)][m] = v.mean
    paper = {(pt, cap): ctx.paper.t1(pt, "softmax_gs", cap) for pt, cap, _ in by_cell}
    return ordering_section(dict(sorted(by_cell.items())), paper)


# ---- Table 2 ----------------------------------------------------------------------------------

T2_COLUMNS = [
    Column("psnr", "PSNR↑", fixed(2), "higher", "diff", 2),
    Column("ssim", "SSIM↑", fixed(3), "higher", "diff", 3),
    Column("lpips", "LPIPS↓", fixed(3), "lower", "diff", 3),
    Column("num_gaussians", "#GS↓", count, "lower", "ratio"),
]


def expected_scenes(dataset: str, runs: list[RunResult]) -> list[str]:
    """The scenes a dataset mean is over: the paper's list for its datasets, else every scene seen."""
    if dataset in DATASET_SCENES:
        return list(DATASET_SCENES[dataset])
    return sorted({r.scene for r in runs if r.dataset == dataset})


@dataclass
class DatasetMeans:
    """Table 2's numbers for one dataset: per row, the mean over the common scenes, or why not."""

    dataset: str
    expected: list[str]
    common: dict[str, list[str]]            # preset -> scenes every row of that preset ran
    values: dict[RowKey, dict[str, Value]]  # row -> metric -> mean over common scenes
    subset_note: dict[RowKey, str]
    extra_scenes: list[str]
    row_runs: dict[RowKey, list[RunResult]]  # row -> its runs

    @property
    def runs(self) -> list[RunResult]:
        return [r for rs in self.row_runs.values() for r in rs]


def dataset_means(cells: Cells, dataset: str, names: list[str]) -> DatasetMeans:
    """Per row (method, budget, preset) of ``dataset``'s runs and quantity of ``names``: the mean over the
    scenes every row of the preset ran (``reports.aggregate.scene_means``), or why there is none."""
    f = cells.frame
    rows = cells.rows((f["dataset"] == dataset) & ~f["dataset"].isin(PATTERN_DATASETS))
    runs = cells.runs_at(rows)
    expected = expected_scenes(dataset, runs)
    extra = sorted({r.scene for r in runs} - set(expected))
    row_runs = groups(cells, ["method", "budget", "preset"], rows)
    keys = sorted(row_runs, key=row_order)
    seeds = seed_means(cells, ["method", "budget", "preset", "scene"], dict.fromkeys(["psnr", *names]), rows)
    psnr = {(k, s): seeds.get((*k, s), "psnr") for k in keys for s in expected}
    common: dict[str, list[str]] = {}
    for preset in sorted({k[2] for k in keys}):
        ran = [{s for s in expected if psnr[(k, s)].ok} for k in keys if k[2] == preset]
        ran = [s for s in ran if s]
        common[preset] = [s for s in expected if ran and all(s in x for x in ran)]
    values: dict[RowKey, dict[str, Value]] = {}
    subset: dict[RowKey, str] = {}
    for k in keys:
        scenes = common[k[2]]
        if not any(psnr[(k, s)].ok for s in expected):
            why = scene_reasons({s: psnr[(k, s)].reason for s in expected})
        elif not scenes:
            why = (f"no {dataset_label(dataset)} scene was run by every row of this preset, so no comparable "
                   "mean (per-scene values in Table 5)")
        else:
            values[k] = scene_means(seeds, [k], scenes, names)[k]
            if len(scenes) < len(expected):
                missing = [s for s in expected if s not in scenes]
                subset[k] = (f"mean over {len(scenes)} of {len(expected)} scenes ({', '.join(scenes)}), those every "
                             f"row of this preset ran; not in the mean: {', '.join(missing)} (Table 5 says why); "
                             f"the paper's value is over all {len(expected)}")
            continue
        values[k] = {m: Value.absent(why) for m in names}
    return DatasetMeans(dataset, expected, common, values, subset, extra, row_runs)


def table2(runs: list[RunResult], ctx: Context) -> Section:
    sec = Section("table2_realworld", "Table 2 — real scenes, dataset means (PSNR, SSIM, LPIPS, #GS)")
    real = ctx.cells.runs_at(ctx.rows(real=True))
    if not real:
        sec.empty_reason = "no real-scene runs below the runs directory."
        return sec
    sec.intro.append("Per dataset, the mean over scenes of each scene's test-view mean (seeds averaged first). "
                     "A mean is only over scenes that every row of the same preset ran; a mean over fewer "
                     "scenes than the dataset has is footnoted. Groups as in the paper: extreme sparse (5%), "
                     "sparse (mini, light), dense (full, and MCMC at a cap: mcmc_<cap>). Best of a group in bold, "
                     "second in italics. ± of a dataset mean is the sd one seed's mean over its S scenes would have, "
                     "from the scenes' seed sds: √(Σ sd²) / S; n is the fewest seeds of a scene.")
    all_rows = []
    for ds in sorted({r.dataset for r in real}, key=dataset_rank):
        dm = dataset_means(ctx.cells, ds, [c.key for c in T2_COLUMNS])
        rows = []
        for k, vals in dm.values.items():
            label, notes = ctx.label(k, dm.row_runs[k])
            if k in dm.subset_note:
                notes.append(dm.subset_note[k])
            method, budget, preset = k
            group = budget_group(budget)
            row = Row([GROUP_LABELS[group], label], dict(vals), rank_group=(group, preset), label_notes=notes,
                      csv=_csv_id(k, dataset=ds, group=group, scenes=";".join(dm.common.get(preset, []))))
            for c in T2_COLUMNS:
                row.paper[c.key] = ctx.paper_value(ctx.paper.t2(method, budget, ds, c.key), "Table 2")
            nets = {r.lpips_net for r in dm.row_runs[k] if r.lpips_net and "lpips" in r.metrics}
            odd = sorted(n for n in nets if "vgg" not in n.lower())
            if odd:
                row.no_compare["lpips"] = f"LPIPS net {', '.join(odd)}; the paper's is VGG"
            rows.append(row)
        notes = []
        nets = sorted({r.lpips_net for r in dm.runs if r.lpips_net and "lpips" in r.metrics})
        if nets:
            notes.append(f"LPIPS computed with {', '.join(nets)}.")
        if dm.extra_scenes:
            notes.append(f"Scenes outside the paper's {dataset_label(ds)} list, not in these means: "
                         f"{', '.join(dm.extra_scenes)} (see Table 5).")
        notes += mix_notes(dm.runs, "This block")
        sec.blocks.append(Table(f"{dataset_label(ds)} ({ds})", ["Group", "Method"], list(T2_COLUMNS), rows,
                                notes=notes, seeds=True))
        all_rows += rows
    ran = {(r.method, r.budget) for r in real}
    if not ctx.paper.error:
        others = [k for k in ctx.paper.table2_rows if not any(k == paper_key(m, b) for m, b in ran)]
        if others:
            sec.notes.append(not_run_note(others, {r.method for r in real}))
    _add(sec, table2_paired(all_rows, T2_COLUMNS[:3], ctx.paper))
    return sec


def not_run_note(paper_rows: list[str], methods_run: set[str]) -> str:
    """The paper's Table 2 rows absent here: the methods of this harness at budgets not run (named
    with the budget, so "3dgs" is not read as "3D GS did not run") apart from the paper's other methods."""
    budgets = ("5pct", "mini", "light")
    ours, theirs = [], []
    for key in paper_rows:
        method, _, budget = key.rpartition("_")
        method, budget = (method, budget) if budget in budgets else (key, "full")
        (ours if method in methods_run else theirs).append(f"{method} at budget {budget}" if method in methods_run
                                                            else key)
    parts = []
    if ours:
        parts.append("methods run here, at budgets not run: " + ", ".join(ours))
    if theirs:
        parts.append("other methods: " + ", ".join(theirs))
    return ("The paper's Table 2 also has rows not run here (" + "; ".join(parts)
            + "); values in reports/paper_tables/table2_realworld.csv.")


# ---- Tables 3, 4, 5: one row per scene × method -------------------------------------------------

def _scene_rows(rows: "pd.Index", names: dict[str, str], columns: list[Column], ctx: Context, paper_lookup,
                rank_extra=lambda rs: (), info=lambda rs: {}) -> list[tuple[str, Row, list[RunResult]]]:
    """(dataset, row, its runs) for each (dataset, scene, method, budget, preset) of ``rows`` (each
    column's value: the seed mean of the quantity ``names[column key]``)."""
    means = seed_means(ctx.cells, SCENE_KEYS, dict.fromkeys(names.values()), rows)
    out = []
    for (ds, scene, m, b, p), rs in sorted(groups(ctx.cells, SCENE_KEYS, rows).items(), key=lambda kv: (
            dataset_rank(kv[0][0]), scene_rank(kv[0][0], kv[0][1]), row_order(kv[0][2:]))):
        label, notes = ctx.label((m, b, p), rs)
        row = Row([scene, label], {c.key: means.get((ds, scene, m, b, p), names[c.key]) for c in columns},
                  rank_group=(scene, budget_group(b), p, *rank_extra(rs)), label_notes=notes,
                  info=info(rs), csv=_csv_id((m, b, p), dataset=ds, scene=scene))
        for c in columns:
            row.paper[c.key] = paper_lookup(m, b, scene, c.key)
        out.append((ds, row, rs))
    return out


def _devices(rs: list[RunResult]) -> str:
    devs = sorted({str(r.render_device) for r in rs if r.render_device})
    return ", ".join(devs) if devs else "not recorded"


def table3(runs: list[RunResult], ctx: Context) -> Section:
    sec = Section("table3_speed", "Table 3 — training minutes and rendering speed")
    rows_ = ctx.rows(real=True)
    real = ctx.cells.runs_at(rows_)
    if not real:
        sec.empty_reason = "no real-scene runs below the runs directory."
        return sec
    sec.intro.append("Train minutes exclude evaluation; FPS is the median over repeats of rendering the test "
                     "views after a warm-up, on the device named. ×paper is ours / paper. Ranked within a "
                     "scene among rows of the same preset and device (all budgets compete, as in the paper).")
    cols = [Column("train_minutes", "Train min↓", fixed(1), "lower", "ratio"),
            Column("render_fps", "FPS↑", fixed(1), "higher", "ratio")]
    rows = _scene_rows(rows_, {"train_minutes": "train_minutes", "render_fps": "render_fps"}, cols, ctx,
                       lambda m, b, s, k: ctx.paper_value(ctx.paper.t3(m, b, s, k), "Table 3"),
                       rank_extra=lambda rs: (_devices(rs),),
                       info=lambda rs: {"Device": _devices(rs),
                                        "Steps": ", ".join(sorted({str(r.steps) for r in rs if r.steps})) or "not recorded"})
    for _, row, _ in rows:  # the paper ranks all budgets together
        row.rank_group = (row.rank_group[0], *row.rank_group[2:])
    notes = ["The paper's times are on its own GPU (not stated) at 30K steps; a ratio across devices "
             "measures the hardware as much as the method."]
    notes += mix_notes(real)
    sec.blocks.append(Table("", ["Scene", "Method"], cols, [r for _, r, _ in rows], ["Device", "Steps"], notes,
                            seeds=True))
    return sec


def table4(runs: list[RunResult], ctx: Context) -> Section:
    sec = Section("table4_consistency", "Table 4 — view consistency (PSNR, flow-warped MSE and FLIP, i → i+7)")
    real_rows = ctx.rows(real=True)
    rows_ = real_rows[[bool(r.consistency or (r.status != "ok" and _wants_consistency(r)))
                       for r in ctx.cells.runs_at(real_rows)]]
    real = ctx.cells.runs_at(rows_)
    if not real:
        sec.empty_reason = ("no run computed view consistency (`result.consistency`); the `consistency` "
                            "experiment (eval.consistency=true) does.")
        return sec
    sec.intro.append("PSNR of the test views; MSE (summed over RGB) and FLIP between frame i warped onto frame "
                     "i+7 and frame i+7 of a 128-frames-per-segment interpolated video, over valid pixels. "
                     "Pop7 (ours, not in the paper): the same warped error over the pixels whose two leading "
                     "splats swapped order between the frames, divided by that over the other valid pixels "
                     "(1 = a depth-order flip costs nothing); Popped: those pixels' share of the valid ones. "
                     "Ranked within a scene among rows of the same preset and flow estimator.")
    cols = [Column("psnr", "PSNR↑", fixed(2), "higher", "diff", 2),
            Column("mse", "MSE↓", fixed(4), "lower", "diff", 4),
            Column("flip", "FLIP7↓", fixed(3), "lower", "diff", 3),
            Column("pop_ratio", "Pop7↓", fixed(2), "lower"),
            Column("popped_fraction", "Popped %", lambda v: f"{100 * v:.2f}")]
    names = {k: f"consistency_{k}" for k in ("psnr", "mse", "flip", "pop_ratio", "popped_fraction")}
    rows = _scene_rows(rows_, names, cols, ctx,
                       lambda m, b, s, k: ctx.paper_value(ctx.paper.t4(m, b, s, k), "Table 4"),
                       rank_extra=lambda rs: (_flows(rs),), info=lambda rs: {"Flow": _flows(rs)})
    for _, row, rs in rows:
        names = {r.consistency.get("flip_name") for r in rs if r.consistency} - {None, "flip"}
        if names:
            row.no_compare["flip"] = f"{', '.join(sorted(names))}: minimum-subtracted FLIP, not the paper's"
    notes = ["The paper's flow is RAFT; ours is named per row (geometric: exact, from rendered depth and the "
             "known camera motion; opencv: DIS optical flow). Numbers from different flow estimators are not "
             "comparable, so a Δ to the paper is indicative."]
    masks = sorted({str(r.consistency.get("mask")) for r in real if r.consistency and r.consistency.get("mask")})
    if any(m in ("own", "per-method") for m in masks):
        notes.append("Scored on each method's own valid mask (StopThePop scores the compared methods on the "
                     "intersection of their masks), so a difference between rows includes their masks.")
    notes += mix_notes(real)
    sec.blocks.append(Table("", ["Scene", "Method"], cols, [r for _, r, _ in rows], ["Flow"], notes, seeds=True))
    _add(sec, table4_paired([r for _, r, _ in rows], cols[:3]))
    return sec


def _wants_consistency(r: RunResult) -> bool:
    ev = (r.config or {}).get("eval") or {}
    return bool(ev.get("consistency")) if isinstance(ev, dict) else False


def _flows(rs: list[RunResult]) -> str:
    flows = sorted({flow_estimator(r) for r in rs if r.consistency})
    return ", ".join(flows) if flows else "not computed"


def table5(runs: list[RunResult], ctx: Context) -> Section:
    sec = Section("table5_per_scene", "Table 5 — per-scene PSNR and number of Gaussians")
    rows_ = ctx.rows(real=True)
    real = ctx.cells.runs_at(rows_)
    if not real:
        sec.empty_reason = "no real-scene runs below the runs directory."
        return sec
    sec.intro.append("Test-view PSNR and final Gaussian count per scene (mean over seeds). Best PSNR of a "
                     "scene within a budget group in bold, second in italics. ×paper is ours / paper.")
    cols = [Column("psnr", "PSNR↑", fixed(2), "higher", "diff", 2),
            Column("num_gaussians", "#GS", count, None, "ratio")]
    rows = _scene_rows(rows_, {"psnr": "psnr", "num_gaussians": "num_gaussians"}, cols, ctx,
                       lambda m, b, s, k: ctx.paper_value(ctx.paper.t5(m, b, s, k), "Table 5"))
    for ds in sorted({d for d, _, _ in rows}, key=dataset_rank):
        block = [r for d, r, _ in rows if d == ds]
        dsr = [r for r in real if r.dataset == ds]
        sec.blocks.append(Table(f"{dataset_label(ds)} ({ds})", ["Scene", "Method"], cols, block,
                                notes=mix_notes(dsr, "This block"), seeds=True))
    _add(sec, table5_paired([r for _, r, _ in rows], cols[:1], ctx.paper))
    return sec
