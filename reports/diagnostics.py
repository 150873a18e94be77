"""Softmax-GS diagnostics: k_max coverage against the paper's figure and the learned α, β, γ.

Read from ``RunResult.diagnostics`` (the runner writes these keys):

- ``diagnostics["frac_within_kmax"]``: float in [0, 1], the fraction of test-view pixels whose splats all
  fell within the first k_max along the ray (mean over the test views). Recorded for methods with
  softmax competition. The paper (supp. Sec. 12) reports ≈85% for Mip-NeRF360 indoor scenes and ≈70%
  for outdoor scenes at k_max = 128.
- ``diagnostics["params"][name]``: summary of one learned per-Gaussian parameter at the end of training,
  ``{"p05", "p25", "p50", "p75", "p95", "mean"}`` (floats; quantiles over the Gaussians). Names:
  ``alpha`` (GEF sharpness), ``beta`` and ``gamma`` (softmax competition); any other name is shown
  too, after these.

k_max itself is read from ``config["method"]["train"]["k_max"]`` (or ``config["k_max"]``).
"""

from __future__ import annotations

import math
import statistics
from collections import defaultdict

from matplotlib.figure import Figure

from protocols.results import RunResult
from reports.paper import (KMAX_COVERAGE, KMAX_COVERAGE_RANGE, dataset_label, dataset_rank,
                           method_label, row_label, scene_rank)
from reports.plots import Plot, _png, color
from reports.aggregate import groups, seed_means
from reports.runs import PATTERN_DATASETS, Value, is_pattern
from reports.table_model import Column, Row, Section, Table, percent, sig
from reports.tables import Context, row_order

QUANTILES = ("p05", "p25", "p50", "p75", "p95", "mean")
PARAM_ORDER = ["alpha", "beta", "gamma"]
PARAM_LABELS = {"alpha": "α (GEF sharpness)", "beta": "β (softmax)", "gamma": "γ (softmax depth)"}


def k_max(r: RunResult) -> str:
    c = r.config or {}
    method = c.get("method") if isinstance(c.get("method"), dict) else {}
    train = method.get("train") if isinstance(method.get("train"), dict) else {}
    v = train.get("k_max", c.get("k_max"))
    scope = train.get("k_max_scope", "pixel")   # docs/kmax-scope.md; results before the switch: pixel
    return ("not recorded" if v is None else str(v)) + ("" if scope == "pixel" else f" ({scope})")


def coverage_table(ctx: Context) -> tuple[Table | None, list[str]]:
    f, cov = ctx.cells.frame, ctx.cells.quantity("frac_within_kmax")
    has, pattern = cov["reason"].isna(), f["dataset"].isin(PATTERN_DATASETS)
    notes: list[str] = []
    pats = cov.loc[has & pattern, "value"]
    if len(pats):
        notes.append(f"2D pattern fits ({len(pats)} runs): coverage from {percent(pats.min())} to {percent(pats.max())} "
                     f"(median {percent(pats.median())}); a capped fit has few splats per ray.")
    keys = ["dataset", "scene", "method", "budget", "preset"]
    rows_ = ctx.cells.rows(~pattern & has)
    if not len(rows_):
        return None, notes
    means = seed_means(ctx.cells, keys, ["frac_within_kmax"], rows_)   # seeds of different configs: not pooled
    col = Column("frac_within_kmax", "Pixels within k_max", percent, None, "diff",
                 delta_fmt=lambda d: f"{100 * d:+.1f} pt")
    rows = []
    cells = groups(ctx.cells, keys, rows_)
    for key in sorted(cells, key=lambda k: (dataset_rank(k[0]), scene_rank(k[0], k[1]), row_order(k[2:]))):
        ds, scene, m, b, p = key
        rs = sorted(cells[key], key=lambda r: r.seed)
        v = means.get(key, "frac_within_kmax")
        label, lnotes = ctx.label((m, b, p), rs)
        if ds == "mipnerf360" and scene in KMAX_COVERAGE:
            kind = "indoor" if KMAX_COVERAGE[scene] > 0.8 else "outdoor"
            paper = Value.of(KMAX_COVERAGE[scene])
            where = f"≈ paper, Mip-NeRF360 {kind}"
        else:
            paper = Value.absent("the paper gives ≈85% (Mip-NeRF360 indoor) and ≈70% (outdoor) only")
            where = ""
        lo, hi = KMAX_COVERAGE_RANGE
        verdict = "—" if not v.ok else \
            "below 70–85%" if v.mean < lo else ("above 70–85%" if v.mean > hi else "within 70–85%")
        rows.append(Row([dataset_label(ds), scene, label], {col.key: v}, {col.key: paper}, label_notes=lnotes,
                        info={"k_max": ", ".join(sorted({k_max(r) for r in rs})), "vs paper range": verdict},
                        csv={"dataset": ds, "scene": scene, "method": m, "budget": b, "preset": p,
                             "paper_reference": where}))
    notes.insert(0, "The paper's reference (supp. Sec. 12, k_max = 128): ≈85% of pixels on Mip-NeRF360 indoor "
                    "scenes, ≈70% outdoor; Δ in percentage points. Pixels beyond k_max are composited the "
                    "vanilla way, so low coverage means the softmax acts on fewer pixels.")
    return Table("", ["Dataset", "Scene", "Method"], [col], rows,
                 ["k_max", "vs paper range"], rank="none", seeds=True), notes


def param_groups(runs: list[RunResult]) -> dict[tuple, list[dict]]:
    """(dataset, method, budget, preset) -> the runs' params dicts; pattern fits pooled over caps."""
    groups: dict[tuple, list[dict]] = defaultdict(list)
    for r in runs:
        params = (r.diagnostics or {}).get("params")
        if r.status != "ok" or not isinstance(params, dict) or not params:
            continue
        budget = "all caps" if is_pattern(r) else r.budget
        groups[(r.dataset, r.method, budget, r.preset)].append(params)
    return groups


def param_names(groups: dict[tuple, list[dict]]) -> list[str]:
    names = {n for ps in groups.values() for p in ps for n in p}
    return [n for n in PARAM_ORDER if n in names] + sorted(names - set(PARAM_ORDER))


def param_summary(params: list[dict], name: str) -> dict[str, float] | None:
    """Median over runs of each run's quantile (runs that lack a key are left out of that key)."""
    out = {}
    for q in QUANTILES:
        vals = []
        for p in params:
            summary = p.get(name)
            try:
                x = float(summary.get(q)) if isinstance(summary, dict) else math.nan
            except (TypeError, ValueError):
                continue
            if math.isfinite(x):
                vals.append(x)
        if vals:
            out[q] = statistics.median(vals)
    return out or None


def params_table(runs: list[RunResult], ctx: Context) -> Table | None:
    groups = param_groups(runs)
    if not groups:
        return None
    cols = [Column(q, q, sig) for q in QUANTILES]
    rows = []
    order = sorted(groups, key=lambda k: (dataset_rank(k[0]), row_order((k[1], k[2], k[3]))))
    for name in param_names(groups):
        for key in order:
            s = param_summary(groups[key], name)
            if s is None:
                continue
            ds, m, b, p = key
            label = (method_label(m) + f" ({b})" if b == "all caps" else row_label(m, b)) + \
                ("" if p == "paper" else f" [{p}]")
            vals = {q: (Value(s[q], None, len(groups[key])) if q in s else Value.absent(f"{q} not recorded"))
                    for q in QUANTILES}
            rows.append(Row([PARAM_LABELS.get(name, name), dataset_label(ds), label], vals,
                            info={"runs": str(len(groups[key]))},
                            csv={"param": name, "dataset": ds, "method": m, "budget": b, "preset": p}))
    return Table("At the end of training: quantiles over the Gaussians, median over runs",
                 ["Parameter", "Dataset", "Method"], cols, rows, ["runs"], rank="none")


def params_plot(runs: list[RunResult]) -> Plot | None:
    groups = param_groups(runs)
    names = param_names(groups)
    if not names:
        return None
    fig = Figure(figsize=(4.5 * len(names), 3.6), layout="constrained")
    order = sorted(groups, key=lambda k: (dataset_rank(k[0]), row_order((k[1], k[2], k[3]))))
    for i, name in enumerate(names):
        ax = fig.add_subplot(1, len(names), i + 1)
        stats, colors, labels = [], [], []
        for key in order:
            s = param_summary(groups[key], name)
            if not s or not all(q in s for q in ("p05", "p25", "p50", "p75", "p95")):
                continue
            ds, m, b, p = key
            stats.append({"whislo": s["p05"], "q1": s["p25"], "med": s["p50"], "q3": s["p75"],
                          "whishi": s["p95"], "mean": s.get("mean", s["p50"]), "fliers": []})
            colors.append(color(m))
            labels.append(f"{ds}\n{method_label(m)} {b}" + ("" if p == "paper" else f" [{p}]"))
        if not stats:
            continue
        boxes = ax.bxp(stats, showmeans=True, patch_artist=True)
        for patch, c in zip(boxes["boxes"], colors):
            patch.set_facecolor(c)
            patch.set_alpha(0.5)
        ax.set_xticks(range(1, len(labels) + 1), labels, rotation=60, ha="right", fontsize=6)
        lo = min(s["whislo"] for s in stats)
        hi = max(s["whishi"] for s in stats)
        if lo > 0 and hi / lo > 100:
            ax.set_yscale("log")
        ax.set_title(PARAM_LABELS.get(name, name), fontsize=9)
        ax.grid(alpha=0.3, axis="y")
    return Plot("params.png", "Learned α, β, γ: box p25–p75, line median, whiskers p05–p95, triangle mean "
                "(median over runs of each quantile).", _png(fig))


def diagnostics_section(runs: list[RunResult], ctx: Context) -> tuple[Section, list[Plot]]:
    """"Softmax-GS diagnostics" with two sub-sections (k_max coverage, learned parameters), each with
    its CSV, and the parameters' box plot."""
    sec = Section("diagnostics", "Softmax-GS diagnostics")
    cov, cov_notes = coverage_table(ctx)
    par = params_table(runs, ctx)
    f = ctx.cells.frame
    lacking = f[(f["status"] == "ok") & f["method"].isin(["softmax_gs", "softmax_only"])
                & ctx.cells.quantity("frac_within_kmax")["reason"].notna()]
    if len(lacking):
        x = lacking.iloc[0]
        cov_notes.append(f"{len(lacking)} ok softmax run(s) record no frac_within_kmax, e.g. "
                         f"{x['dataset']}/{x['scene']}/{x['method']}/{x['budget']}.")
    if cov is None and par is None:
        sec.empty_reason = ("no run records diagnostics (frac_within_kmax, params); they come from methods with "
                            "GEF or softmax competition.") + (" " + " ".join(cov_notes) if cov_notes else "")
        return sec, []
    kmax = Section("diagnostics_kmax", "Pixels within k_max", notes=cov_notes)
    if cov is not None:
        kmax.blocks.append(cov)
    elif not cov_notes:
        kmax.empty_reason = "no run records frac_within_kmax."
    params = Section("diagnostics_params", "Learned α, β, γ")
    if par is not None:
        params.blocks.append(par)
    else:
        params.empty_reason = "no run records diagnostics[\"params\"]."
    sec.subsections = [kmax, params]
    plot = params_plot(runs)
    return sec, [plot] if plot else []
