"""The interactive plots of report.html as Plotly figure specs (data + layout), drawn by the page.

Same content as the PNG plots: PSNR against train seconds (one curve per run), PSNR against FPS and
against #Gaussians (one point per method × budget × preset, the Pareto front of each preset), plus the
view-consistency error along the video (per pair i → i+7) and the learned α, β, γ. Hover names the
run(s), method, budget, seed(s) and value; clicking a legend entry toggles a method (one legend group
per method). Every string Plotly draws is escaped (``plotly_text``).
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

from reports.diagnostics import PARAM_LABELS, param_names, param_groups, param_summary
from reports.html.escape import plotly_text as pt
from reports.paper import budget_rank, dataset_rank, method_label, method_rank, scene_rank
from reports.aggregate import Band, Cells, seed_bands
from reports.plots import Point, color, pareto_front, panel_name
from reports.runs import Run, budget_label, is_pattern
from reports.tables import row_order
from reports.tradeoff import tradeoff_points

DASHES = ["solid", "dash", "dot", "dashdot", "longdash", "longdashdot"]
SYMBOLS = {"paper": "circle", "cpu": "square"}


@dataclass
class Figure:
    id: str
    title: str
    caption: str
    data: list[dict]
    layout: dict

    def spec(self) -> dict:
        return {"id": self.id, "data": self.data, "layout": self.layout}


def run_name(run: Run, runs_dir: Path) -> str:
    """A run as the user finds it on disk: its directory relative to the runs directory."""
    try:
        return run.path.parent.resolve().relative_to(Path(runs_dir).resolve()).as_posix()
    except ValueError:
        return run.path.parent.as_posix()


def _layout(title: str, xlabel: str, ylabel: str, log_x: bool = False) -> dict:
    return {"title": {"text": pt(title), "font": {"size": 14}}, "height": 380, "margin": {"l": 60, "r": 10, "t": 40, "b": 50},
            "xaxis": {"title": {"text": pt(xlabel)}, "type": "log" if log_x else "linear"},
            "yaxis": {"title": {"text": pt(ylabel)}}, "hovermode": "closest",
            "legend": {"font": {"size": 10}}}


def _legend(seen: set, method: str) -> dict:
    first = method not in seen
    seen.add(method)
    return {"legendgroup": pt(method), "showlegend": first, "name": pt(method_label(method))}


# ---- PSNR against train seconds -----------------------------------------------------------------

def time_figures(runs: list[Run], runs_dir: Path) -> list[Figure]:
    panels: dict[str, list[Run]] = defaultdict(list)
    for run in sorted(runs, key=lambda x: (dataset_rank(x.r.dataset), scene_rank(x.r.dataset, x.r.scene))):
        if run.r.status == "ok" and run.r.curve:
            panels[f"{run.r.dataset}/{run.r.scene}"].append(run)
    figs = []
    for k, (panel, rs) in enumerate(panels.items()):
        rs.sort(key=lambda x: (method_rank(x.r.method), budget_rank(budget_label(x.r)), x.r.seed))
        budgets = list(dict.fromkeys(sorted((budget_label(x.r) for x in rs), key=budget_rank)))
        seen: set = set()
        data = [_band_trace(b) for b in seed_bands([x.r for x in rs])]  # under the curves
        for run in rs:
            r = run.r
            xs = [c.seconds for c in r.curve]
            name = run_name(run, runs_dir)
            data.append({
                "type": "scatter", "mode": "lines+markers", "x": xs, "y": [c.psnr for c in r.curve],
                **_legend(seen, r.method),
                "line": {"color": color(r.method), "dash": DASHES[budgets.index(budget_label(run.r)) % len(DASHES)],
                         "width": 1.5},
                "marker": {"symbol": SYMBOLS.get(r.preset, "triangle-up"), "size": 6},
                "customdata": [[pt(name), pt(method_label(r.method)), pt(budget_label(run.r)), r.seed, pt(r.preset),
                                c.step, c.num_gaussians] for c in r.curve],
                "hovertemplate": "run %{customdata[0]}<br>method %{customdata[1]} · budget %{customdata[2]} · "
                                 "seed %{customdata[3]} · preset %{customdata[4]}<br>step %{customdata[5]}: "
                                 "%{x:.1f} s, PSNR %{y:.2f} dB, %{customdata[6]} Gaussians<extra></extra>"})
        if len(budgets) > 1:  # a legend entry per line style (hover names the budget of each curve too)
            data += [{"type": "scatter", "mode": "lines", "x": [None], "y": [None], "name": pt(f"budget {b}"),
                      "legendgroup": pt(f"budget {b}"), "hoverinfo": "skip",
                      "line": {"color": "black", "dash": DASHES[i % len(DASHES)], "width": 1.5}}
                     for i, b in enumerate(budgets)]
        xs_all = [x for d in data for x in d["x"] if x and x > 0]
        log_x = bool(xs_all) and max(xs_all) / min(xs_all) > 50
        figs.append(Figure(f"fig-time-{k}", panel, "Test-view PSNR against train seconds (evaluation excluded), "
                           "one curve per run; colour = method, dash = budget, marker = preset; shaded: the band "
                           "from the lowest to the highest seed of a method × budget × preset with two or more "
                           "seeds (at their mean seconds).", data,
                           _layout(panel, "train seconds", "PSNR (dB)", log_x)))
    return figs


def _band_trace(b: Band) -> dict:
    """The seeds' min–max band as a filled polygon (hover: which seeds)."""
    h = color(b.method).lstrip("#")
    rgb = ", ".join(str(int(h[i:i + 2], 16)) for i in (0, 2, 4))
    seeds = ", ".join(map(str, b.seeds))
    return {"type": "scatter", "mode": "lines", "x": b.seconds + b.seconds[::-1], "y": b.high + b.low[::-1],
            "fill": "toself", "fillcolor": f"rgba({rgb}, 0.18)", "line": {"width": 0},
            "legendgroup": pt(b.method), "showlegend": False, "hoveron": "fills",
            "name": pt(f"{method_label(b.method)} {b.budget}: seeds {seeds}, min–max"),
            "hoverinfo": "name"}


# ---- Pareto plots -------------------------------------------------------------------------------

def _point_runs(runs: list[Run]) -> dict[tuple, list[Run]]:
    """(panel, method, budget label, preset) -> the runs behind a trade-off point."""
    out: dict[tuple, list[Run]] = defaultdict(list)
    for run in runs:
        r = run.r
        panel = panel_name("patterns", r.scene) if is_pattern(r) else panel_name(r.dataset)
        out[(panel, r.method, budget_label(run.r), r.preset)].append(run)
    return out


def pareto_figures(runs: list[Run], runs_dir: Path, cells: Cells | None = None) -> list[Figure]:
    fps_pts, gs_pts = tradeoff_points([x.r for x in runs], cells)
    behind = _point_runs(runs)
    figs = []
    for pts, key, xlabel, higher, what in ((fps_pts, "fps", "render FPS", True, "higher PSNR at higher FPS"),
                                           (gs_pts, "gs", "#Gaussians", False, "higher PSNR with fewer Gaussians")):
        panels: dict[str, list[Point]] = defaultdict(list)
        for p in pts:
            if p.psnr.ok and p.x.ok and p.x.mean > 0:
                panels[p.panel].append(p)
        for k, (panel, ps) in enumerate(panels.items()):
            figs.append(_pareto_figure(f"fig-{key}-{k}", panel, ps, behind, runs_dir, xlabel, higher, what))
    return figs


def _error_bars(pts: list[Point], rgb: str) -> dict:
    """± sd over seeds on both axes, where any point has one."""
    out = {}
    for axis, get in (("error_y", lambda p: p.psnr.std), ("error_x", lambda p: p.x.std)):
        sds = [get(p) for p in pts]
        if any(sd is not None for sd in sds):
            out[axis] = {"type": "data", "array": [sd or 0.0 for sd in sds], "color": rgb, "thickness": 1, "width": 3}
    return out


def _pareto_figure(fid: str, panel: str, pts: list[Point], behind: dict, runs_dir: Path, xlabel: str,
                   higher: bool, what: str) -> Figure:
    pts = sorted(pts, key=lambda p: row_order((p.method, p.budget, p.preset)))
    seen: set = set()
    data = []
    for m, preset in dict.fromkeys((p.method, p.preset) for p in pts):
        sub = [p for p in pts if (p.method, p.preset) == (m, preset)]
        custom = []
        for p in sub:
            rs = sorted(behind.get((panel, m, p.budget, p.preset), []), key=lambda x: x.r.seed)
            names = [run_name(x, runs_dir) for x in rs if x.r.status == "ok"]
            shown = ", ".join(names[:4]) + (f" … ({len(names)} runs)" if len(names) > 4 else "")
            seeds = ", ".join(str(s) for s in sorted({x.r.seed for x in rs if x.r.status == "ok"}))
            custom.append([pt(shown or "—"), pt(method_label(m)), pt(p.budget), pt(seeds or "—"), pt(p.preset),
                           p.psnr.n])
        data.append({"type": "scatter", "mode": "markers+text", "x": [p.x.mean for p in sub],
                     "y": [p.psnr.mean for p in sub], "text": [pt(p.label) for p in sub],
                     "textposition": "top right", "textfont": {"size": 9}, **_legend(seen, m),
                     "marker": {"color": color(m), "size": 9, "symbol": SYMBOLS.get(preset, "triangle-up")},
                     **_error_bars(sub, color(m)),
                     "customdata": custom,
                     "hovertemplate": "run(s) %{customdata[0]}<br>method %{customdata[1]} · budget %{customdata[2]} · "
                                      "seed(s) %{customdata[3]} · preset %{customdata[4]}<br>" + pt(xlabel)
                                      + " %{x:.4g}, PSNR %{y:.2f} dB (mean over %{customdata[5]} seed(s))"
                                      "<extra></extra>"})
    for i, preset in enumerate(sorted({p.preset for p in pts})):
        sub = [p for p in pts if p.preset == preset]
        front = sorted((sub[j] for j in pareto_front([(p.x.mean, p.psnr.mean) for p in sub], higher)),
                       key=lambda p: p.x.mean)
        data.append({"type": "scatter", "mode": "lines+markers", "x": [p.x.mean for p in front],
                     "y": [p.psnr.mean for p in front], "name": pt(f"Pareto front [{preset}]"),
                     "legendgroup": "pareto", "line": {"color": "black", "dash": "dash", "width": 1},
                     "marker": {"size": 14, "color": "rgba(0,0,0,0)", "line": {"color": "black", "width": 1}},
                     "hoverinfo": "skip"})
    caption = (f"PSNR against {xlabel}, one point per method × budget (dataset means as in Table 2; per pattern for "
               f"the 2D fits); dashed line and rings: the Pareto front ({what}), per preset; bars: ± sd over seeds.")
    return Figure(fid, f"{panel}: PSNR vs {xlabel}", caption, data,
                  _layout(f"{panel}: PSNR vs {xlabel}", xlabel, "PSNR (dB)", log_x=True))


# ---- view consistency along the video ------------------------------------------------------------

def consistency_figures(runs: list[Run], runs_dir: Path) -> list[Figure]:
    panels: dict[str, list[Run]] = defaultdict(list)
    for run in runs:
        if run.r.status == "ok" and consistency_pairs(run):
            panels[f"{run.r.dataset}/{run.r.scene}"].append(run)
    figs = []
    for k, (panel, rs) in enumerate(sorted(panels.items())):
        rs.sort(key=lambda x: (method_rank(x.r.method), budget_rank(budget_label(x.r)), x.r.seed))
        seen: set = set()
        data = []
        for run in rs:
            pairs = [p for p in consistency_pairs(run) if p.get("mse") is not None]
            r = run.r
            step = (r.consistency or {}).get("step", 7)
            data.append({"type": "scatter", "mode": "lines", "x": [p["i"] for p in pairs],
                         "y": [p["mse"] for p in pairs], **_legend(seen, r.method),
                         "line": {"color": color(r.method), "width": 1.2},
                         "customdata": [[pt(run_name(run, runs_dir)), pt(method_label(r.method)), pt(budget_label(run.r)),
                                         r.seed, p["j"]] for p in pairs],
                         "hovertemplate": "run %{customdata[0]}<br>method %{customdata[1]} · budget %{customdata[2]} · "
                                          "seed %{customdata[3]}<br>frames %{x} → %{customdata[4]}: MSE %{y:.4g}"
                                          "<extra></extra>"})
        figs.append(Figure(f"fig-cons-{k}", panel, f"Flow-warped MSE (summed over RGB) of each pair i → i+{step} "
                           "along the interpolated video, per run: spikes are popping.", data,
                           _layout(f"{panel}: warped MSE per frame pair", "frame i", "MSE")))
    return figs


def consistency_pairs(run: Run) -> list[dict]:
    c = run.r.consistency or {}
    step = c.get("step", 7)
    scores = c.get("scores") or {}
    s = scores.get(str(step)) or scores.get(step) or {}
    pairs = s.get("per_pair") if isinstance(s, dict) else None
    return [p for p in pairs if isinstance(p, dict) and "i" in p] if isinstance(pairs, list) else []


# ---- learned α, β, γ ----------------------------------------------------------------------------

def params_figure(runs: list[Run]) -> Figure | None:
    groups = param_groups([x.r for x in runs])
    names = param_names(groups)
    if not names:
        return None
    order = sorted(groups, key=lambda k: (dataset_rank(k[0]), row_order((k[1], k[2], k[3]))))
    data = []
    seen: set = set()
    for i, name in enumerate(names):
        for key in order:
            s = param_summary(groups[key], name)
            if not s or not all(q in s for q in ("p05", "p25", "p50", "p75", "p95")):
                continue
            ds, m, b, p = key
            label = f"{ds} {b}" + ("" if p == "paper" else f" [{p}]")
            data.append({"type": "box", "x": [pt(label)], "q1": [s["p25"]], "median": [s["p50"]], "q3": [s["p75"]],
                         "lowerfence": [s["p05"]], "upperfence": [s["p95"]], "mean": [s.get("mean", s["p50"])],
                         "xaxis": f"x{i + 1}", "yaxis": f"y{i + 1}", **_legend(seen, m),
                         "marker": {"color": color(m)}, "boxpoints": False})
    if not data:
        return None
    n = len(names)
    layout = {"height": 420, "margin": {"l": 50, "r": 10, "t": 40, "b": 90}, "boxmode": "group",
              "grid": {"rows": 1, "columns": n, "pattern": "independent"}, "legend": {"font": {"size": 10}},
              "annotations": [{"text": pt(PARAM_LABELS.get(nm, nm)), "xref": f"x{i + 1} domain", "yref": "paper",
                               "x": 0.5, "y": 1.08, "showarrow": False} for i, nm in enumerate(names)]}
    for i, nm in enumerate(names):
        vals = [v for d in data if d["yaxis"] == f"y{i + 1}" for v in d["lowerfence"] + d["upperfence"]]
        log = bool(vals) and min(vals) > 0 and max(vals) / min(vals) > 100
        layout[f"yaxis{i + 1 if i else ''}"] = {"type": "log" if log else "linear"}
    return Figure("fig-params", "Learned α, β, γ", "Box p25–p75, line median, whiskers p05–p95, dashed mean "
                  "(median over runs of each quantile).", data, layout)
