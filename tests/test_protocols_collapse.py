"""A run whose model collapses, or that has only a handful of Gaussians, finishes (rc 0) through
every stage: training, evaluation, FPS, view consistency, PLY export and the report. A collapse is
said when it happens (log.txt), recorded (results.json diagnostics["collapse"]) and marks the
report's row with a footnote naming what happened and its likely cause."""

from __future__ import annotations

import csv
import json

import pytest

from protocols.collapse import EMPTY_VIEW_ALPHA
from protocols.results import read_result
from protocols.run import run_experiment
from smgs.io.ply import read_ply

# The procedural scene, tiny; the 3DGS schedule scaled to 6 steps refines from step 2 on
SCENE = ["+experiment=smoke", "seed=0", "dataset.width=32", "dataset.height=24", "dataset.n_views=16", "protocol.steps=6",
         "protocol.schedule_steps=30000", "eval.fractions=[0.5,1.0]", "eval.fps_repeats=1", "eval.flip=false",
         "eval.consistency=true", "eval.consistency_max_width=32", "export_ply=true", "checkpoint_every=3"]


def _run_dir(out, method):
    return out / "procedural" / "blocks" / method / "full" / "seed0"


@pytest.fixture(scope="module")
def collapsed(tmp_path_factory):
    """Every Gaussian under the pruning opacity (0.5 > the initial 0.1): the first refinement prunes
    them all; the run goes on with none."""
    out = tmp_path_factory.mktemp("collapsed")
    s = run_experiment(SCENE + [f"out_dir={out}", "grid.methods=[3dgs,softmax_gs]",
                                "+method.train.densify.prune_opacity=0.5"])
    return out, s


def test_a_run_pruned_to_nothing_finishes_and_says_so(collapsed):
    out, summaries = collapsed
    assert [s["status"] for s in summaries] == ["ok", "ok"]
    for method in ("3dgs", "softmax_gs"):
        d = _run_dir(out, method)
        r = read_result(d / "results.json")
        c = r.diagnostics["collapse"]
        assert r.status == "ok" and r.num_gaussians == 0 and c["final_gaussians"] == 0
        assert c["collapsed"] and c["peak_gaussians"] > 0 and c["fell_under_threshold_at"] == 2
        assert c["pruned_transparent"] == c["pruned"] >= c["peak_gaussians"]   # with what it cloned and split
        assert c["empty_views"] == sorted(r.per_view["name"]) and c["min_view_alpha"] == 0.0
        assert c["what"].startswith(f"ended with 0 of its peak {c['peak_gaussians']} Gaussians")
        assert "pruned as transparent" in c["likely_cause"]
        assert r.consistency and r.render_fps > 0 and r.metrics["psnr"] > 0
        assert len(read_ply(d / "point_cloud.ply")) == 0
        log = (d / "log.txt").read_text()
        assert "step 2: 0 Gaussians left" in log and "the model is collapsing" in log
        assert "collapse: ended with 0 of its peak" in log


def test_the_report_marks_collapsed_rows_with_the_cause(collapsed):
    out, _ = collapsed
    md = (out / "report" / "report.md").read_text()
    assert md.count("3D GS [cpu] [collapsed]") >= 1 and "Softmax-GS [cpu] [collapsed]" in md
    assert "procedural/blocks seed 0: ended with 0 of its peak" in md and "likely cause: Gaussians pruned as" in md
    html = (out / "report" / "report.html").read_text()
    assert "[collapsed]" in html and "likely cause" in html
    notes = [row["row_notes"] for f in (out / "report").rglob("*.csv") for row in csv.DictReader(f.open()) if "row_notes" in row]
    assert any("ended with 0 of its peak" in n for n in notes)


@pytest.mark.parametrize("n", [1, 3])
def test_a_handful_of_gaussians_goes_through_every_stage(tmp_path, n):
    """n random Gaussians, no densification: evaluation, FPS, consistency, PLY export and the report.
    Such a model covers little of the image: the views it leaves (almost) empty are reported."""
    s = run_experiment(SCENE + [f"out_dir={tmp_path}", "grid.methods=[softmax_gs]", "+method.train.gaussians.init=random",
                                f"+method.train.gaussians.n_random={n}", "+method.train.densify.enabled=false"])
    assert [x["status"] for x in s] == ["ok"]
    d = _run_dir(tmp_path, "softmax_gs")
    r = read_result(d / "results.json")
    c = r.diagnostics["collapse"]
    assert r.num_gaussians == n == c["peak_gaussians"] == c["final_gaussians"] and len(read_ply(d / "point_cloud.ply")) == n
    assert r.consistency and r.render_fps > 0 and (tmp_path / "report" / "report.md").exists()
    assert c["collapsed"] == bool(c["empty_views"])     # the count never fell: only empty views can flag it
    if c["empty_views"]:
        assert c["min_view_alpha"] < EMPTY_VIEW_ALPHA and "render (almost) empty" in c["what"]
        assert c["likely_cause"].startswith("the model does not cover those views")


def _watched(events: list[dict], start: int = 1000, plan: tuple[str, ...] = ()) -> tuple[dict, list[str]]:
    """A CollapseWatch fed ``events`` (one step each, the count following them), then assessed."""
    import logging

    from protocols.collapse import CollapseWatch

    class Sink(logging.Handler):
        def __init__(self):
            super().__init__()
            self.lines = []

        def emit(self, record):
            self.lines.append(record.getMessage())

    log, sink = logging.getLogger("test.collapse"), Sink()
    log.addHandler(sink)
    w, n = CollapseWatch.start(start), start
    for i, e in enumerate(events, 1):
        n += e.get("cloned", 0) + e.get("split", 0) - e.get("pruned", 0)
        w.step(i, n, e, log)
    out = w.assess(n, {"a": 0.5}, list(plan), 4e-3, log)
    log.removeHandler(sink)
    return out, sink.lines


def test_the_cause_names_the_rule_that_took_the_gaussians():
    screen, lines = _watched([{"pruned": 980, "pruned_big": 900, "pruned_big_screen": 900, "pruned_transparent": 80,
                               "opacity_reset": 1}], plan=("init: 1000 random points (no SfM)",))
    assert screen["collapsed"] and screen["final_gaussians"] == 20 and screen["fell_under_threshold_at"] == 1
    assert screen["likely_cause"].startswith("Gaussians pruned as too big on screen (900 of 980 pruned")
    assert "random points" in screen["likely_cause"] and "docs/studies/fox-collapse.md" in screen["likely_cause"]
    assert lines[0].startswith("step 1: 20 Gaussians left, 2.0 % of the peak 1000 (step 0)")
    world, _ = _watched([{"pruned": 980, "pruned_big": 900, "pruned_transparent": 80}])
    assert world["likely_cause"].startswith("Gaussians pruned as too big in the world (900 of 980")
    assert "random points" not in world["likely_cause"]
    clear, _ = _watched([{"pruned": 980, "pruned_transparent": 980}, {"cloned": 5}])
    assert clear["likely_cause"].startswith("Gaussians pruned as transparent (980 of 980 pruned, 0 opacity reset(s))")
    kept, lines = _watched([{"pruned": 960, "pruned_transparent": 960}, {"cloned": 960}])
    assert not kept["collapsed"] and kept["fell_under_threshold_at"] == 1 and len(lines) == 1   # fell, then grew back


def test_a_resumed_run_keeps_its_collapse_history():
    from protocols.collapse import CollapseWatch

    w = CollapseWatch.start(500)
    w.totals["pruned"], w.fell_at, w.resets = 490, 30, 2
    again = CollapseWatch.start(10)
    again.restore(w.to_json())
    assert again == w
