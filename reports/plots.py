"""Error against run time, as PNG figures (matplotlib's Agg canvas; no pyplot, no global backend).

- PSNR against train seconds: one curve per method × budget × preset from the runs' intermediate
  evaluations, one panel per scene (per pattern for the 2D fits); with two or more seeds the mean over
  seeds and a band from the lowest to the highest seed (``seed_bands``).
- PSNR against render FPS and PSNR against #Gaussians: one point per method × budget (× preset), one
  panel per dataset (per pattern), the Pareto front of each preset marked.
"""

from __future__ import annotations

import io
import math
import zlib
from dataclasses import dataclass

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from matplotlib.lines import Line2D
from matplotlib.patches import Patch

from protocols.results import RunResult
from reports.aggregate import seed_bands
from reports.paper import budget_rank, dataset_label, dataset_rank, method_label, method_rank, scene_rank
from reports.runs import Value, budget_label

PANELS_PER_FIGURE = 9
COLORS = {"3dgs": "#1f77b4", "gef_only": "#2ca02c", "softmax_only": "#ff7f0e", "softmax_gs": "#d62728"}
EXTRA_COLORS = ["#9467bd", "#8c564b", "#e377c2", "#7f7f7f", "#bcbd22", "#17becf"]
LINESTYLES = ["-", "--", ":", "-."]
MARKERS = {"paper": "o", "cpu": "s"}


@dataclass
class Plot:
    name: str        # file name, e.g. "psnr_vs_time.png"
    caption: str
    png: bytes


@dataclass
class Point:
    """One method × budget (× preset) of one panel."""

    panel: str
    method: str
    budget: str
    preset: str
    psnr: Value
    x: Value          # FPS or #Gaussians

    @property
    def label(self) -> str:
        short = {"full": "full", "5pct": "5%", "mini": "mini", "light": "light"}.get(self.budget, self.budget)
        return short + ("" if self.preset == "paper" else f" [{self.preset}]")


def color(method: str) -> str:
    if method in COLORS:
        return COLORS[method]
    return EXTRA_COLORS[zlib.crc32(method.encode()) % len(EXTRA_COLORS)]  # stable across processes


def _png(fig: Figure) -> bytes:
    FigureCanvasAgg(fig)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=100)  # the constrained layout already fits the labels
    return buf.getvalue()


def _grid(n: int) -> tuple[int, int]:
    cols = min(3, n)
    return math.ceil(n / cols), cols


# ---- PSNR against train seconds ----------------------------------------------------------------

def time_curves(runs: list[RunResult]) -> list[Plot]:
    panels: dict[str, list[RunResult]] = {}
    for r in sorted(runs, key=lambda r: (dataset_rank(r.dataset), scene_rank(r.dataset, r.scene))):
        if r.status == "ok" and r.curve:
            panels.setdefault(f"{r.dataset}/{r.scene}", []).append(r)
    names = list(panels)
    plots = []
    for start in range(0, len(names), PANELS_PER_FIGURE):
        chunk = names[start:start + PANELS_PER_FIGURE]
        rows, cols = _grid(len(chunk))
        fig = Figure(figsize=(4.2 * cols, 3.2 * rows), layout="constrained")
        for i, name in enumerate(chunk):
            _curves_panel(fig.add_subplot(rows, cols, i + 1), name, panels[name])
        part = "" if start == 0 else f"_{start // PANELS_PER_FIGURE + 1}"
        plots.append(Plot(f"psnr_vs_time{part}.png",
                          "Test-view PSNR against train seconds (evaluation excluded), from the runs' "
                          "intermediate evaluations: with two or more seeds the mean over seeds (at the mean "
                          "seconds) and a shaded band from the lowest to the highest seed, else the one run's "
                          "curve; colour = method, line style (or the label at the end of a curve) = budget, "
                          "marker = preset.", _png(fig)))
    return plots


def _curves_panel(ax, name: str, runs: list[RunResult]) -> None:
    runs = sorted(runs, key=lambda r: (method_rank(r.method), budget_rank(budget_label(r)), r.seed))
    budgets = list(dict.fromkeys(budget_label(r) for r in sorted(runs, key=lambda r: budget_rank(budget_label(r)))))
    styled = len(budgets) <= len(LINESTYLES)  # otherwise the budget is written at the end of each curve
    labelled = set()
    xs_all = []
    bands = {(b.method, b.budget, b.preset): b for b in seed_bands(runs)}
    curves = [(b.method, b.budget, b.preset, b.seconds, b.mean, b) for b in bands.values()]
    curves += [(r.method, budget_label(r), r.preset, [c.seconds for c in r.curve], [c.psnr for c in r.curve], None)
               for r in runs if (r.method, budget_label(r), r.preset) not in bands]
    for method, budget, preset, xs, ys, band in curves:
        xs_all += [x for x in xs if x > 0]
        ls = LINESTYLES[budgets.index(budget)] if styled else "-"
        if band is not None:
            ax.fill_between(xs, band.low, band.high, color=color(method), alpha=0.2, linewidth=0)
        ax.plot(xs, ys, ls, color=color(method), marker=MARKERS.get(preset, "^"), markersize=3, linewidth=1,
                alpha=0.8)
        key = (method, budget, preset)
        if not styled and key not in labelled:
            ax.annotate(budget, (xs[-1], ys[-1]), fontsize=5, xytext=(2, 0), textcoords="offset points")
        labelled.add(key)
    handles = [Line2D([], [], color=color(m), label=method_label(m))
               for m in dict.fromkeys(r.method for r in runs)]
    if styled and len(budgets) > 1:
        handles += [Line2D([], [], color="k", linestyle=LINESTYLES[i], label=b) for i, b in enumerate(budgets)]
    presets = list(dict.fromkeys(r.preset for r in runs))
    if presets != ["paper"]:
        handles += [Line2D([], [], color="k", linestyle="", marker=MARKERS.get(p, "^"), label=f"[{p}]")
                    for p in presets]
    if bands:
        n = sorted({len(b.seeds) for b in bands.values()})
        handles.append(Patch(color="k", alpha=0.2, label=f"seeds min–max (n = {'/'.join(map(str, n))})"))
    if xs_all and max(xs_all) / min(xs_all) > 50:
        ax.set_xscale("log")
    ax.set_title(name, fontsize=9)
    ax.set_xlabel("train seconds")
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(handles=handles, fontsize=6, loc="lower right")


# ---- Pareto plots ------------------------------------------------------------------------------

def pareto_front(points: list[tuple[float, float]], x_higher_better: bool) -> list[int]:
    """Indices of the points no other point beats in both x and y (y = PSNR, higher is better)."""
    def beats(a: tuple[float, float], b: tuple[float, float]) -> bool:
        ax_ok = a[0] >= b[0] if x_higher_better else a[0] <= b[0]
        strict = (a[0] != b[0]) or (a[1] != b[1])
        return ax_ok and a[1] >= b[1] and strict
    return [i for i, p in enumerate(points) if not any(beats(q, p) for j, q in enumerate(points) if j != i)]


def pareto_plots(points: list[Point], name: str, xlabel: str, x_higher_better: bool, log_x: bool,
                 caption: str) -> list[Plot]:
    """One figure per PANELS_PER_FIGURE panels (``name``, then ``name_2.png``, ...). Points without a
    value (a failed run, an unrecorded FPS) are not drawn; the tables say why."""
    panels: dict[str, list[Point]] = {}
    for p in points:
        if p.psnr.ok and p.x.ok and (not log_x or p.x.mean > 0):
            panels.setdefault(p.panel, []).append(p)
    names = list(panels)
    plots = []
    for start in range(0, len(names), PANELS_PER_FIGURE):
        chunk = names[start:start + PANELS_PER_FIGURE]
        rows, cols = _grid(len(chunk))
        fig = Figure(figsize=(4.2 * cols, 3.4 * rows), layout="constrained")
        for i, panel in enumerate(chunk):
            _pareto_panel(fig.add_subplot(rows, cols, i + 1), panel, panels[panel], xlabel, x_higher_better, log_x)
        part = "" if start == 0 else f"_{start // PANELS_PER_FIGURE + 1}"
        plots.append(Plot(name.replace(".png", f"{part}.png"), caption, _png(fig)))
    return plots


def _pareto_panel(ax, panel: str, pts: list[Point], xlabel: str, x_higher_better: bool, log_x: bool) -> None:
    pts = sorted(pts, key=lambda p: (method_rank(p.method), p.budget))
    for m, preset in dict.fromkeys((p.method, p.preset) for p in pts):  # one scatter per method × preset
        sub = [p for p in pts if (p.method, p.preset) == (m, preset)]
        ax.scatter([p.x.mean for p in sub], [p.psnr.mean for p in sub], color=color(m), s=28, zorder=3,
                   marker=MARKERS.get(preset, "^"),
                   label=method_label(m) + ("" if preset == "paper" else f" [{preset}]"))
        spread = [p for p in sub if p.psnr.std is not None or p.x.std is not None]
        if spread:  # ± sd over seeds, where a point has two or more
            ax.errorbar([p.x.mean for p in spread], [p.psnr.mean for p in spread],
                        yerr=[p.psnr.std or 0.0 for p in spread], xerr=[p.x.std or 0.0 for p in spread],
                        fmt="none", ecolor=color(m), elinewidth=0.8, capsize=2, zorder=2)
    front_all: list[Point] = []
    for i_p, preset in enumerate(sorted({p.preset for p in pts})):
        sub = [p for p in pts if p.preset == preset]
        front = [sub[j] for j in pareto_front([(p.x.mean, p.psnr.mean) for p in sub], x_higher_better)]
        front.sort(key=lambda p: p.x.mean)
        front_all += front
        ax.plot([p.x.mean for p in front], [p.psnr.mean for p in front], "k--", linewidth=0.8, zorder=2,
                label="Pareto front" if i_p == 0 else None)
        ax.scatter([p.x.mean for p in front], [p.psnr.mean for p in front], s=90, facecolors="none",
                   edgecolors="k", linewidths=0.9, zorder=4)
    if log_x:
        ax.set_xscale("log")
        _sparse_log_ticks(ax)
    # budget labels: every point when few, else the front's (text layout dominates the drawing time)
    shared = _label_points(ax, pts if len(pts) <= 12 else front_all)
    ax.set_title(panel + (f" ({shared})" if shared else ""), fontsize=9)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("PSNR (dB)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=6, loc="best")


LABEL_GAP_PX = 14   # a label closer than this to one already written (same text) is left out


def _label_points(ax, pts: list[Point]) -> str | None:
    """Write each point's budget beside it, without writing one over another: a label that all the
    points share is returned instead (the panel's title says it once); a label next to one of the same
    text is left out, one next to other labels goes above them; a point near the right edge gets its
    label on its left, inside the axes."""
    labels = {p.label for p in pts}
    if len(labels) == 1 and len(pts) > 1:
        return next(iter(labels))
    ax.autoscale_view()
    (x0, _), (x1, _) = ax.transAxes.transform([(0, 0), (1, 1)])
    placed: list[tuple[str, float, float]] = []
    for p in pts:
        x, y = ax.transData.transform((p.x.mean, p.psnr.mean))
        near = [t for t, u, v in placed if abs(x - u) < LABEL_GAP_PX and abs(y - v) < LABEL_GAP_PX]
        if p.label in near:
            continue
        placed.append((p.label, x, y))
        left = x > x0 + 0.85 * (x1 - x0)
        ax.annotate(p.label, (p.x.mean, p.psnr.mean), fontsize=6, xytext=(-3 if left else 3, 3 + 7 * len(near)),
                    textcoords="offset points", ha="right" if left else "left")
    return None


def compact_number(v: float) -> str:
    """3000 -> "3k", 1500000 -> "1.5M": short tick labels."""
    for div, suffix in ((1e9, "G"), (1e6, "M"), (1e3, "k")):
        if abs(v) >= div:
            return f"{v / div:.3g}{suffix}"
    return f"{v:.3g}"


def _sparse_log_ticks(ax, most: int = 5) -> None:
    """At most ``most`` labelled ticks on a log x axis, compactly written: matplotlib's default
    labels minor ticks too when the range is under a decade, and they run into each other."""
    from matplotlib.ticker import FixedLocator, FuncFormatter, LogLocator, MaxNLocator, NullFormatter

    lo, hi = ax.get_xlim()
    if hi / lo < 10:  # under a decade: evenly spaced round values
        ticks = [t for t in MaxNLocator(nbins=most - 1).tick_values(lo, hi) if lo <= t <= hi and t > 0]
        ax.xaxis.set_major_locator(FixedLocator(ticks))
    else:
        ax.xaxis.set_major_locator(LogLocator(base=10, subs=(1.0, 2.0, 5.0) if hi / lo < 1e3 else (1.0,),
                                              numticks=most + 1))
    ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: compact_number(v)))
    ax.xaxis.set_minor_formatter(NullFormatter())


def panel_name(dataset: str, scene: str | None = None) -> str:
    return f"{dataset_label(dataset)}" if scene is None else f"{dataset_label(dataset)}: {scene}"

