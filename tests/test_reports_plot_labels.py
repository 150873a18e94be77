"""The budget labels of a PSNR-against-FPS / #Gaussians panel never run into one another (a smoke
report's four methods at one budget wrote "full" four times in one spot) nor out of the axes."""

from __future__ import annotations

from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure

from reports.plots import Point, _pareto_panel
from reports.runs import Value


def _panel(pts: list[Point]):
    fig = Figure(figsize=(4, 3), layout="constrained")
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    _pareto_panel(ax, "procedural", pts, "render FPS", True, True)
    fig.canvas.draw()
    r = fig.canvas.get_renderer()
    return ax, [(t.get_text(), t.get_window_extent(r)) for t in ax.texts]


def _point(method: str, budget: str, psnr: float, fps: float) -> Point:
    return Point("procedural", method, budget, "paper", Value(psnr, n=1), Value(fps, n=1))


def test_a_label_every_point_shares_is_said_once_in_the_title():
    ax, texts = _panel([_point(m, "full", 25.0 + 0.01 * i, 40.0 + 0.1 * i)
                        for i, m in enumerate(("3dgs", "gef_only", "softmax_only", "softmax_gs"))])
    assert texts == [] and ax.get_title() == "procedural (full)"


def test_labels_of_close_points_do_not_overlap_and_stay_inside_the_axes():
    pts = [_point("3dgs", "full", 25.0, 40.0), _point("softmax_gs", "5pct", 25.02, 40.2),
           _point("gef_only", "full", 25.01, 40.1), _point("softmax_only", "mini", 20.0, 150.0)]
    ax, texts = _panel(pts)
    assert sorted(t for t, _ in texts) == ["5%", "full", "mini"]   # the second "full" beside the first is left out
    boxes = [b for _, b in texts]
    for i, a in enumerate(boxes):
        for b in boxes[i + 1:]:
            assert not a.overlaps(b), (a, b)
    frame = ax.get_window_extent()
    assert all(frame.x0 <= b.x0 and b.x1 <= frame.x1 for b in boxes)
