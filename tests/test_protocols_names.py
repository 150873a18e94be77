"""``seed=N`` under an experiment runs seed N; names that become paths stay below the output root."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from baselines.method import MethodSpec
from baselines.registry import register, unregister
from baselines.splatting import GaussianSplatting
from protocols.run import CONFIG_DIR, plan, run_experiment

REPO = Path(__file__).resolve().parent.parent
TINY = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.scenes=[circle4]", "grid.methods=[3dgs]",
        "dataset.size=16", "dataset.steps=4", "report=false", "eval.fps_repeats=1", "eval.flip=false"]


def _plan(args):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return plan(compose(config_name="config", overrides=args), args)


def test_seed_under_an_experiment_runs_that_seed(tmp_path, capsys):
    cells, payloads = _plan(["+experiment=smoke", "seed=3", f"out_dir={tmp_path}"])
    assert {c.seed for c in cells} == {3} and len(cells) == 4   # smoke lists seeds [0], and [0, 1, 2] for two
    assert {p["config"]["seed"] for p in payloads} == {3} and all(p["key"].endswith("/seed3") for p in payloads)
    assert "running seed 3 (instead of the experiment's grid.seeds [0] and grid.seeds_of" in capsys.readouterr().out
    cells, _ = _plan(["+experiment=patterns", "seed=5", "grid.scenes=[circle4]", f"out_dir={tmp_path}"])
    assert {c.seed for c in cells} == {5}                       # patterns lists [0, 1, 2]
    s = run_experiment(TINY + ["seed=2", f"out_dir={tmp_path}"])
    assert [x["key"] for x in s] == ["patterns/circle4/3dgs/cap4/seed2"] and s[0]["status"] == "ok"
    s = run_experiment(TINY + ["seed=4", f"out_dir={tmp_path}"])
    assert not s[0].get("skipped") and s[0]["key"].endswith("/seed4")   # not "finished" as another seed


def test_seed_and_a_disagreeing_grid_seeds_stop_naming_both(tmp_path):
    with pytest.raises(SystemExit, match=r"seed=3 and grid\.seeds=\[0, 1\] disagree"):
        _plan(["+experiment=smoke", "seed=3", "grid.seeds=[0,1]", f"out_dir={tmp_path}"])
    cells, _ = _plan(["+experiment=smoke", "seed=3", "grid.seeds=[3]", f"out_dir={tmp_path}"])
    assert {c.seed for c in cells} == {3}
    with pytest.raises(SystemExit, match=r"seed=-1: must be at least 0"):
        run_experiment(TINY + ["seed=-1", f"out_dir={tmp_path}"])
    with pytest.raises(SystemExit, match=r"seed=3 and seeds=2 disagree"):
        _plan(["+experiment=smoke", "seed=3", "seeds=2", f"out_dir={tmp_path}"])


@pytest.mark.parametrize("name", ["../../x", "..", "a/b", "."])
def test_an_experiment_name_cannot_leave_the_output_root(tmp_path, monkeypatch, name):
    root = tmp_path / "out" / "runs"
    monkeypatch.setenv("SMGS_OUT", str(root))
    with pytest.raises(SystemExit, match=r"experiment_name=.*(one folder name|cannot name a folder)"):
        run_experiment(TINY + [f"experiment_name={name}", "grid.seeds=[0]"])
    assert sorted(p.name for p in tmp_path.iterdir()) == []   # not even the root was made


def test_the_command_line_refuses_it_before_hydra_writes_anything(tmp_path):
    import os

    env = dict(os.environ, SMGS_OUT=str(tmp_path / "a" / "runs"))
    p = subprocess.run([sys.executable, "-m", "protocols.run", "+experiment=smoke", "experiment_name=../../x"],
                       cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert p.returncode == 2 and "experiment_name='../../x' contains '/'" in p.stderr, p.stderr[-2000:]
    assert list(tmp_path.iterdir()) == []


class _Plain(GaussianSplatting):
    pass


def test_scene_method_and_budget_names_cannot_leave_the_output_root(tmp_path):
    fern = tmp_path / "data" / "fern"
    fern.mkdir(parents=True)
    with pytest.raises(SystemExit, match=r"scene='\.\.' cannot name a folder"):
        _plan(["dataset=colmap", f"dataset.path={fern}/..", "grid.methods=[3dgs]", f"out_dir={tmp_path}/runs"])
    with pytest.raises(SystemExit, match=r"budget='\.\./full' contains '/'"):
        _plan(["+experiment=smoke", "grid.budgets=[../full]", f"out_dir={tmp_path}/runs"])
    register(MethodSpec("evil/../../m", _Plain, {"mode": "3dgs"}))
    try:
        with pytest.raises(SystemExit, match=r"method='evil/\.\./\.\./m' contains '/'"):
            _plan(["+experiment=smoke", "grid.methods=[evil/../../m]", f"out_dir={tmp_path}/runs"])
    finally:
        unregister("evil/../../m")
    assert not (tmp_path / "runs").exists()
