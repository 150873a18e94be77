"""Two PLYs of one scene evaluated into one experiment: the second never replaces the first's
evaluation unless asked to (--force), gets a cell of its own with a budget name, and nothing of a
cell is removed before its lock is held."""

from __future__ import annotations

import json
import threading

import pytest

from protocols import evaluate_ply
from protocols.cell_lock import cell_lock
from protocols.results import read_result
from protocols.run import run_experiment

SCENE = ["dataset.width=32", "dataset.height=24", "dataset.n_views=8", "eval.fps_repeats=1", "eval.flip=false",
         "eval.consistency=false", "eval.save_renders=false"]
TINY = ["+experiment=smoke", "seeds=1", "eval.fractions=[1.0]", "report=false", "grid.methods=[3dgs]",
        "export_ply=true", *SCENE]


@pytest.fixture(scope="module")
def plys(tmp_path_factory):
    """Two models of the procedural scene (4 and 2 steps), as PLYs named as 3DGS names them."""
    out = []
    for steps in (4, 2):
        runs = tmp_path_factory.mktemp(f"trained{steps}")
        assert run_experiment(TINY + [f"out_dir={runs}", f"protocol.steps={steps}"])[0]["status"] == "ok"
        out.append(runs / "procedural/blocks/3dgs/full/seed0/point_cloud.ply")
    return out


def _evaluate(ply, out, *extra) -> int:
    return evaluate_ply.main([str(ply), f"out_dir={out}", "report=false", *SCENE, *extra])


def test_a_second_ply_does_not_replace_the_first(plys, tmp_path, capsys):
    a, b = plys
    cell = tmp_path / "procedural/blocks/3dgs/pretrained/seed0"
    assert _evaluate(a, tmp_path) == 0
    first = (cell / "results.json").read_text()
    pointer = (cell / "checkpoint.json").read_text()
    capsys.readouterr()
    assert _evaluate(b, tmp_path) == 1
    err = capsys.readouterr().err
    assert f"holds the evaluation of {a.resolve()}" in err and str(b) in err and "nothing was changed" in err
    assert "budget.name=pretrained-seed0" in err and "--force" in err
    assert (cell / "results.json").read_text() == first and (cell / "checkpoint.json").read_text() == pointer
    assert (cell / json.loads(pointer)["dir"]).is_dir()

    # its own cell, beside the first; both in the report
    assert _evaluate(b, tmp_path, "budget.name=pretrained-b") == 0
    other = read_result(tmp_path / "procedural/blocks/3dgs/pretrained-b/seed0/results.json")
    assert other.source["sha256"] != read_result(cell / "results.json").source["sha256"]
    from reports.build import build_report

    md = build_report(tmp_path, stability="skipped in this test").read_text()
    assert "3D GS (pretrained)" in md and "3D GS (pretrained-b)" in md

    # --force replaces it
    assert _evaluate(b, tmp_path, "--force") == 0
    assert read_result(cell / "results.json").source["ply"] == str(b.resolve())


def test_nothing_of_a_cell_is_removed_before_its_lock_is_held(plys, tmp_path, capsys):
    a, b = plys
    cell = tmp_path / "procedural/blocks/3dgs/pretrained/seed0"
    assert _evaluate(a, tmp_path) == 0
    before = sorted(p.name for p in cell.iterdir())
    held, release = threading.Event(), threading.Event()

    def hold():
        with cell_lock(cell, str(tmp_path)):
            held.set()
            release.wait(60)

    t = threading.Thread(target=hold)
    t.start()
    try:
        assert held.wait(30)
        assert _evaluate(b, tmp_path, "--force") == 1   # skipped: another process writes the cell
        assert "which is writing this cell" in capsys.readouterr().err
        assert sorted(p.name for p in cell.iterdir()) == before
        assert read_result(cell / "results.json").source["ply"] == str(a.resolve())
    finally:
        release.set()
        t.join()


def test_a_cell_holds_one_kind_of_result(plys, tmp_path, capsys):
    """``smgs evaluate model.ply budget.name=full`` into the cell of a trained run replaced it (its
    steps, curve and checkpoint gone, a 0-step evaluation in their place); ``smgs run`` into a cell
    holding an evaluation took it for a changed config and replaced it. Both are refused, naming
    both and the fix; --force replaces."""
    import shutil

    a, _ = plys
    trained = tmp_path / "trained"
    shutil.copytree(a.parents[5], trained)
    cell = trained / "procedural/blocks/3dgs/full/seed0"
    before = {p.name: p.read_bytes() for p in cell.iterdir() if p.is_file()}
    capsys.readouterr()
    assert _evaluate(a, trained, "budget.name=full") == 1
    err = capsys.readouterr().err
    assert f"{cell} holds a trained run (3dgs, 4 steps, config " in err and f"the evaluation of {a.resolve()}" in err
    assert "nothing was changed" in err and "budget.name=pretrained" in err and "--force" in err
    assert {p.name: p.read_bytes() for p in cell.iterdir() if p.is_file()} == before

    evaluated = tmp_path / "evaluated"
    assert _evaluate(a, evaluated, "budget.name=full") == 0
    cell = evaluated / "procedural/blocks/3dgs/full/seed0"
    first = (cell / "results.json").read_text()
    s = run_experiment(TINY + [f"out_dir={evaluated}", "protocol.steps=2"])
    assert s[0]["status"] == "failed"
    assert f"{cell} holds the evaluation of {a.resolve()}" in s[0]["error"] and "nothing was changed" in s[0]["error"]
    assert "--force" in s[0]["error"] and (cell / "results.json").read_text() == first
    s = run_experiment(TINY + [f"out_dir={evaluated}", "protocol.steps=2", "force=true"])
    assert s[0]["status"] == "ok" and read_result(cell / "results.json").steps == 2
