"""A finished cell under reruns: a rerun with another config or --force works beside it and replaces
it only when complete (docs/runs.md); an interrupted, failed or half-swapped rerun leaves a folder
that agrees with itself; a results file of a newer smgs is never rewritten."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml

from counting_method import counting  # noqa: F401 (the fixture)
from protocols.ply import export_run
from protocols.results import find_results, read_result
from protocols.run import run_experiment

TINY = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
        "dataset.size=16", "dataset.steps=12", "report=false", "eval.fps_repeats=1", "eval.flip=false",
        "grid.methods=[counting]", "checkpoint_every=5"]
RUN = "patterns/circle4/counting/cap4/seed0"
OTHER = "++method.train.k_max=64"


def _state(run_dir: Path, export: bool = True) -> dict:
    """What must agree: the result, the checkpoint in force, the config, the model export hands out."""
    ptr = json.loads((run_dir / "checkpoint.json").read_text())
    return {"results": (run_dir / "results.json").read_text(), "pointer": ptr,
            "ckpts": sorted(p.name for p in run_dir.glob("ckpt-*")), "config": (run_dir / "config.yaml").read_text(),
            "step": export_run(run_dir, run_dir.parents[4] / "m.ply")[1] if export else None}


def _consistent(run_dir: Path) -> str:
    r = read_result(run_dir / "results.json")
    assert r.status == "ok"
    assert json.loads((run_dir / "checkpoint.json").read_text())["config_hash"] == r.config_hash
    assert yaml.safe_load((run_dir / "config.yaml").read_text()) == r.config
    assert [p.name for p in run_dir.parent.iterdir()] == [run_dir.name], "a hidden folder was left beside it"
    return r.config_hash


def run(tmp_path, *extra):
    return run_experiment(TINY + [f"out_dir={tmp_path}", *extra])


@pytest.mark.parametrize("rerun", [[OTHER], ["force=true"]], ids=["changed-config", "force"])
def test_an_interrupted_rerun_leaves_the_finished_cell_whole(tmp_path, counting, rerun):
    run_dir = tmp_path / RUN
    assert run(tmp_path)[0]["status"] == "ok"
    before = _state(run_dir)
    counting.calls.clear()
    counting.interrupt_at = 7   # after the rerun's checkpoint of step 5
    with pytest.raises(KeyboardInterrupt):
        run(tmp_path, *rerun)
    assert _state(run_dir) == before, "the finished model, its result and config must survive"
    assert export_run(run_dir)[1:] == (12, "ok")
    assert find_results(tmp_path) == [run_dir / "results.json"]

    counting.calls.clear()
    s = run(tmp_path)   # the original command: truly finished before
    assert s[0].get("skipped") and counting.calls == []
    s = run(tmp_path, *rerun)   # the rerun again: resumes its own progress (--force starts over)
    assert s[0]["status"] == "ok" and not s[0].get("skipped")
    assert counting.calls == (list(range(12)) if "force=true" in rerun else list(range(5, 12)))
    new = _consistent(run_dir)
    assert (new == json.loads(before["results"])["config_hash"]) == ("force=true" in rerun)
    assert export_run(run_dir)[1] == 12
    assert "works in" in (run_dir / "log.txt").read_text()


def test_a_failed_rerun_keeps_the_finished_cell(tmp_path, counting):
    run_dir = tmp_path / RUN
    assert run(tmp_path)[0]["status"] == "ok"
    before = _state(run_dir)
    counting.fail_at = 3
    s = run(tmp_path, OTHER)
    assert s[0]["status"] == "failed" and "diverged on purpose" in s[0]["error"]
    assert f"in {run_dir} is kept" in s[0]["error"] and ".seed0.rerun" in s[0]["log"]
    assert _state(run_dir) == before
    counting.calls.clear()
    assert run(tmp_path)[0].get("skipped") and counting.calls == []


def test_a_rerun_stopped_at_its_swap_is_completed_by_the_next_run(tmp_path, counting, monkeypatch):
    """Stopped before the exchange: the finished cell is in place and the rerun's complete folder
    beside it, which the rerun's next run swaps in without training. Stopped after it: the rerun's
    cell is in place and the earlier one whole beside it, which that config's next run swaps back."""
    run_dir = tmp_path / RUN
    assert run(tmp_path)[0]["status"] == "ok"
    first = _state(run_dir)

    def stop(*a, **k):
        raise KeyboardInterrupt

    with monkeypatch.context() as m:
        m.setattr("protocols.cell.swap_in", stop)
        with pytest.raises(KeyboardInterrupt):
            run(tmp_path, OTHER)
    assert _state(run_dir) == first
    counting.calls.clear()
    assert run(tmp_path, OTHER)[0]["status"] == "ok" and counting.calls == []
    second = _state(run_dir)
    assert _consistent(run_dir) != json.loads(first["results"])["config_hash"]

    import os

    real_rename = os.rename

    def stop_after_exchange(src, dst):
        if ".old-" in str(dst):
            raise KeyboardInterrupt
        return real_rename(src, dst)

    counting.calls.clear()
    with monkeypatch.context() as m:
        m.setattr(os, "rename", stop_after_exchange)
        with pytest.raises(KeyboardInterrupt):
            run(tmp_path)   # the first config again: trains beside, stopped right after the exchange
    assert counting.calls == list(range(12))
    assert run(tmp_path)[0].get("skipped")
    counting.calls.clear()
    assert run(tmp_path, OTHER)[0]["status"] == "ok" and counting.calls == []   # swapped back
    assert _state(run_dir) == second
    _consistent(run_dir)


def test_the_users_files_in_a_cell_survive_a_rerun(tmp_path, counting):
    run_dir = tmp_path / RUN
    assert run(tmp_path)[0]["status"] == "ok"
    (run_dir / "notes.txt").write_text("mine")
    (run_dir / "mine").mkdir()
    (run_dir / "mine" / "a.txt").write_text("also mine")
    assert run(tmp_path, OTHER)[0]["status"] == "ok"
    assert (run_dir / "notes.txt").read_text() == "mine" and (run_dir / "mine" / "a.txt").read_text() == "also mine"
    _consistent(run_dir)


@pytest.mark.parametrize("extra", [[], [OTHER], ["force=true"]], ids=["same", "changed-config", "force"])
def test_a_results_file_of_a_newer_smgs_is_left_as_it_is(tmp_path, counting, extra):
    run_dir = tmp_path / RUN
    assert run(tmp_path)[0]["status"] == "ok"
    d = json.loads((run_dir / "results.json").read_text())
    d.update(schema=2, written_by_the_future={"x": 1})
    (run_dir / "results.json").write_text(json.dumps(d))
    before = _state(run_dir, export=False)
    counting.calls.clear()
    s = run(tmp_path, *extra)
    assert s[0]["status"] == "failed" and "results schema 2" in s[0]["error"] and "upgrade smgs" in s[0]["error"]
    assert str(run_dir / "results.json") in s[0]["error"]
    assert counting.calls == [] and _state(run_dir, export=False) == before
    assert [p.name for p in run_dir.parent.iterdir()] == ["seed0"]
    from reports.runs import load_runs

    assert [(p, "upgrade smgs" in why) for p, why in load_runs(tmp_path).unreadable] == [(run_dir / "results.json", True)]


def test_unknown_fields_of_a_newer_smgs_are_kept(tmp_path, counting):
    run_dir = tmp_path / RUN
    assert run(tmp_path)[0]["status"] == "ok"
    d = json.loads((run_dir / "results.json").read_text())
    d["written_by_the_future"] = {"x": 1}
    (run_dir / "results.json").write_text(json.dumps(d))
    before = (run_dir / "results.json").read_text()
    counting.calls.clear()
    assert run(tmp_path)[0].get("skipped") and counting.calls == []
    assert (run_dir / "results.json").read_text() == before
    r = read_result(run_dir / "results.json")
    assert r.other_fields == {"written_by_the_future": {"x": 1}}
    from protocols.results import write_result

    write_result(tmp_path / "copy", r)
    assert json.loads((tmp_path / "copy" / "results.json").read_text())["written_by_the_future"] == {"x": 1}
