"""The points of the error-against-cost plots: one per method × budget (× preset) and panel.

Real datasets: the Table 2 means (over the scenes every row of a preset ran), so a point is what the
table prints. 2D patterns: one panel per pattern, a point per method × cap, means over seeds.
"""

from __future__ import annotations

from protocols.results import RunResult
from reports.aggregate import Cells, seed_means
from reports.paper import PATTERNS, dataset_rank
from reports.plots import Point, panel_name
from reports.runs import PATTERN_DATASETS
from reports.tables import dataset_means, row_order


def tradeoff_points(runs: list[RunResult], cells: Cells | None = None) -> tuple[list[Point], list[Point]]:
    """(PSNR vs FPS points, PSNR vs #Gaussians points); ``cells``: the runs' results table if made."""
    cells = cells if cells is not None else Cells.of(runs)
    f = cells.frame
    fps: list[Point] = []
    gs: list[Point] = []
    for ds in sorted(set(f.loc[~f["dataset"].isin(PATTERN_DATASETS), "dataset"]), key=dataset_rank):
        dm = dataset_means(cells, ds, ["psnr", "render_fps", "num_gaussians"])
        for (m, b, p), v in sorted(dm.values.items(), key=lambda kv: row_order(kv[0])):
            fps.append(Point(panel_name(ds), m, b, p, v["psnr"], v["render_fps"]))
            gs.append(Point(panel_name(ds), m, b, p, v["psnr"], v["num_gaussians"]))
    fits = cells.rows(f["dataset"].isin(PATTERN_DATASETS) & f["cap"].notna())
    means = seed_means(cells, ["scene", "method", "cap", "preset"], ["psnr", "render_fps", "num_gaussians"], fits)
    order = lambda k: (PATTERNS.index(k[0]) if k[0] in PATTERNS else 99, k[0], k[2], row_order((k[1], "", k[3])))
    for key in sorted(means.keys(), key=order):
        pattern, m, cap, p = key
        psnr = means.get(key, "psnr")
        fps.append(Point(panel_name("patterns", pattern), m, f"cap {cap}", p, psnr, means.get(key, "render_fps")))
        gs.append(Point(panel_name("patterns", pattern), m, f"cap {cap}", p, psnr, means.get(key, "num_gaussians")))
    return fps, gs
