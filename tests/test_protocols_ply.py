"""The PLY at the protocol's edges: export at the end of a run and from a run directory, and a PLY
scored by protocols.evaluate_ply exactly as the run that trained it was."""

from __future__ import annotations

import json

import pytest

from protocols import evaluate_ply, export_ply
from protocols.results import read_result
from protocols.run import run_experiment

SCENE = ["dataset.width=32", "dataset.height=24", "dataset.n_views=8", "eval.fps_repeats=1", "eval.flip=false"]
TINY = ["+experiment=smoke", "seeds=1", "protocol.steps=4", "eval.fractions=[1.0]", "report=false",
        "grid.methods=[3dgs,softmax_gs]", *SCENE]


@pytest.fixture(scope="module")
def runs(tmp_path_factory):
    out = tmp_path_factory.mktemp("runs")
    summaries = run_experiment(TINY + [f"out_dir={out}", "export_ply=true"])
    assert [s["status"] for s in summaries] == ["ok", "ok"]
    return out


def _run(out, method, budget="full"):
    return out / "procedural" / "blocks" / method / budget / "seed0"


@pytest.mark.parametrize("method", ["3dgs", "softmax_gs"])
def test_a_pretrained_ply_scores_as_the_run_that_trained_it(runs, method, capsys):
    trained = _run(runs, method)
    ply = trained / "point_cloud.ply"
    assert read_result(trained / "results.json").diagnostics["ply"] == str(ply)
    assert evaluate_ply.main([str(ply), f"out_dir={runs}", "report=false", *SCENE]) == 0
    here = _run(runs, method, "pretrained")
    a, b = read_result(trained / "results.json"), read_result(here / "results.json")
    assert b.status == "ok" and b.method == method and b.budget == "pretrained" and b.preset == a.preset
    assert b.source["kind"] == "pretrained" and b.source["trained_here"] is False
    assert b.source["ply"] == str(ply.resolve()) and b.source["header"]["mode"] == method
    assert b.train_seconds is None and b.steps == 0 and a.train_seconds > 0
    # the same test views, the same 8-bit metrics, the same renders
    assert b.per_view == a.per_view and b.metrics == a.metrics and b.num_gaussians == a.num_gaussians
    pngs = sorted((trained / "renders").rglob("*.png"))   # renders, and the viewer's ground truth and error maps
    assert pngs
    for png in pngs:
        assert (here / png.relative_to(trained)).read_bytes() == png.read_bytes()
    assert b.render_fps > 0
    # a second call finds it done; method= that contradicts the file is refused
    assert evaluate_ply.main([str(ply), f"out_dir={runs}", "report=false", *SCENE]) == 0
    assert "already evaluated" in capsys.readouterr().out
    other = "3dgs" if method == "softmax_gs" else "softmax_gs"
    assert evaluate_ply.main([str(ply), f"out_dir={runs}", f"method={other}", *SCENE]) == 2   # refused: nothing ran
    assert f"holds a {method} model" in capsys.readouterr().err


def test_export_command_writes_the_run_end_file_again(runs, tmp_path, capsys):
    run = _run(runs, "softmax_gs")
    assert export_ply.main([str(run), "--out", str(tmp_path / "again.ply")]) == 0
    assert "step 4" in capsys.readouterr().out
    assert (tmp_path / "again.ply").read_bytes() == (run / "point_cloud.ply").read_bytes()
    assert export_ply.main([str(tmp_path)]) == 2   # refused: nothing to export
    assert "no checkpoint.json" in capsys.readouterr().err


def test_bad_ply_is_refused_before_anything_is_written(runs, tmp_path, capsys):
    (tmp_path / "bad.ply").write_bytes(b"")
    assert evaluate_ply.main([str(tmp_path / "bad.ply"), f"out_dir={tmp_path / 'out'}", *SCENE]) == 2
    assert "bad.ply: empty file" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_scene_is_named_as_smgs_run_names_it(runs, tmp_path, capsys):
    """A dataset given by its folder is its one scene, named after the folder (README's ``smgs evaluate
    point_cloud.ply dataset=colmap dataset.path=/my/capture`` once stopped at "has scenes []"); a
    dataset of several needs scene=, and the message lists them."""
    ply = _run(runs, "3dgs") / "point_cloud.ply"
    cfg = evaluate_ply.evaluation_config(ply, ["dataset=colmap", f"dataset.path={tmp_path / 'capture'}/"])
    assert cfg["scene"] == "capture"
    assert evaluate_ply.main([str(ply), "dataset=mipnerf360", f"out_dir={tmp_path / 'out'}"]) == 2
    err = capsys.readouterr().err
    assert "dataset 'mipnerf360' holds 7 scenes (bicycle, bonsai, counter, garden, kitchen, room, stump): name the one " \
           "the model shows with scene=NAME" in err and "[]" not in err
    assert evaluate_ply.main([str(ply), "+steps=3", f"out_dir={tmp_path / 'out'}"]) == 2
    assert "did you mean protocol.steps=3?" in capsys.readouterr().err
    assert not (tmp_path / "out").exists()


def test_the_report_marks_the_pretrained_row(runs):
    from reports.build import build_report

    ply = _run(runs, "3dgs") / "point_cloud.ply"
    assert evaluate_ply.main([str(ply), f"out_dir={runs}", "report=false", *SCENE]) == 0
    md = build_report(runs, stability="skipped in this test").read_text()
    assert "3D GS (pretrained)" in md and "models read from a PLY (another tool's, or a run's own, exported)" in md
    assert "trained elsewhere" not in md   # the PLY here is this harness's own export
    # the preset's footnote names the trained runs' length, not the evaluation config's 3000 beside it
    assert "[cpu] = the cpu preset (4 steps, images ≤ 400 px wide)" in md and "3000 steps" not in md
    assert json.loads((_run(runs, "3dgs", "pretrained") / "results.json").read_text())["source"]["sha256"]
