"""The points of the error-against-cost plots: one per method × budget (× preset) and panel.

Real datasets: the Table 2 means (over the scenes every row of a preset ran), so a point is what the
table prints. 2D patterns: one panel per pattern, a point per method × cap, means over seeds.
"""

from __future__ import annotations

from collections import defaultdict

from protocols.results import RunResult
from reports.paper import PATTERNS, dataset_rank
from reports.plots import Point, panel_name
from reports.runs import aggregate, is_pattern, pattern_cap
from reports.tables import FPS, NUM_GS, PSNR, dataset_means, row_order


def tradeoff_points(runs: list[RunResult]) -> tuple[list[Point], list[Point]]:
    """(PSNR vs FPS points, PSNR vs #Gaussians points)."""
    fps: list[Point] = []
    gs: list[Point] = []
    real = [r for r in runs if not is_pattern(r)]
    for ds in sorted({r.dataset for r in real}, key=dataset_rank):
        dm = dataset_means(ds, real, {"psnr": PSNR, "fps": FPS, "gs": NUM_GS})
        for (m, b, p), v in sorted(dm.values.items(), key=lambda kv: row_order(kv[0])):
            fps.append(Point(panel_name(ds), m, b, p, v["psnr"], v["fps"]))
            gs.append(Point(panel_name(ds), m, b, p, v["psnr"], v["gs"]))
    cells: dict[tuple, list[RunResult]] = defaultdict(list)
    for r in runs:
        if is_pattern(r) and pattern_cap(r) is not None:
            cells[(r.scene, r.method, pattern_cap(r), r.preset)].append(r)
    order = lambda k: (PATTERNS.index(k[0]) if k[0] in PATTERNS else 99, k[0], k[2], row_order((k[1], "", k[3])))
    for (pattern, m, cap, p) in sorted(cells, key=order):
        rs = cells[(pattern, m, cap, p)]
        psnr = aggregate(rs, PSNR)
        fps.append(Point(panel_name("patterns", pattern), m, f"cap {cap}", p, psnr, aggregate(rs, FPS)))
        gs.append(Point(panel_name("patterns", pattern), m, f"cap {cap}", p, psnr, aggregate(rs, NUM_GS)))
    return fps, gs
