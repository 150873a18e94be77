"""The report does not contradict itself: rows "not run" named with their budget, the backend row
filled from the stability battery that ran, left_out holding only what was left out."""

import html
import re

import reports.build
from protocols.train_loop import left_out_of
from reports.build import build_report
from reports.environment import environment_markdown, with_probed
from reports.tables import not_run_note
from reports_tree import make_tree


def test_paper_rows_not_run_name_their_budget():
    note = not_run_note(["3dgs_5pct", "softmax_gs_5pct", "ges", "3dgs", "softmax_gs_mini", "3dcs"],
                        {"3dgs", "softmax_gs"})
    assert "3dgs at budget 5pct" in note and "3dgs at budget full" in note
    assert "softmax_gs at budget mini" in note
    assert "other methods: ges, 3dcs" in note
    assert ", 3dgs," not in note and ": 3dgs," not in note  # never the bare name of a method that ran


def test_environment_names_the_backends_the_stability_battery_rendered_with():
    machine = {"backend": "not probed (the build renders nothing)"}
    md = environment_markdown([], with_probed(machine, ["cpu", "reference"]))
    assert "not probed" not in md and "cpu, reference (rendered by this report's stability battery)" in md
    assert "not probed" in environment_markdown([], machine)


def test_report_html_and_md_name_the_same_backends(tmp_path, monkeypatch):
    rows = [{"case": "c", "mode": "3dgs", "backend": b, "dtype": "float32", "max_abs_err": 0.0,
             "max_grad_rel_err": 0.0, "nonfinite_outputs": 0, "nonfinite_grads": 0} for b in ("cpu", "reference")]
    monkeypatch.setattr(reports.build, "compute_stability", lambda: (rows, None))   # the battery, as it ran
    md = build_report(make_tree(tmp_path / "runs"))
    in_md = re.search(r"^\| backend \| [^|]* \| ([^|]*) \|$", md.read_text(), re.M)[1]
    in_html = re.search(r'<th scope="row">backend</th><td class="txt">[^<]*</td><td class="txt">([^<]*)</td>',
                        (md.parent / "report.html").read_text())[1]
    assert in_md.startswith("cpu, reference") and html.unescape(in_html) == in_md


def test_left_out_holds_only_what_was_left_out():
    plan = ["hyperparameters: 3dgs2023", "densification: off (fixed count)", "scene has no sfm_points",
            "init: 4 identical Gaussians at depth 1", "view consistency: off (eval.consistency=false)"]
    assert left_out_of(plan) == ["densification: off (fixed count)", "scene has no sfm_points",
                                 "view consistency: off (eval.consistency=false)"]


def _label_boxes(xs):
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    from reports.plots import Point, _pareto_panel
    from reports.runs import Value

    fig = Figure(figsize=(4, 3))
    FigureCanvasAgg(fig)
    ax = fig.add_subplot(1, 1, 1)
    pts = [Point("scene", "3dgs", f"b{i}", "paper", Value(20.0 + i, n=1), Value(float(x), n=1)) for i, x in enumerate(xs)]
    _pareto_panel(ax, "scene", pts, "#Gaussians", False, True)
    r = fig.canvas.get_renderer()
    return [t.get_window_extent(r) for t in ax.get_xticklabels(minor=False) + ax.get_xticklabels(minor=True)
            if t.get_text() and t.get_visible() and ax.get_xlim()[0] <= t.get_position()[0] <= ax.get_xlim()[1]]


def test_gaussian_count_ticks_do_not_run_into_each_other():
    for xs in ([2900, 3000, 3050, 3100], [120, 3000, 90000, 2_500_000], [1000, 4000, 9000]):
        boxes = _label_boxes(xs)
        assert len(boxes) >= 2, xs
        boxes.sort(key=lambda b: b.x0)
        for a, b in zip(boxes, boxes[1:]):
            assert a.x1 <= b.x0, (xs, a, b)
