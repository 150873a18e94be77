"""Every setting or scene that cannot give a meaningful result stops the sweep before any cell runs,
in the one-block "nothing was run" form naming the key or the file and the fix, instead of failing
in training, after it, or in a traceback; a scaled schedule that degenerates is warned about."""

from __future__ import annotations

import shutil
import struct
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir

from protocols.run import CONFIG_DIR, check_command_line, plan, run_experiment
from protocols.validate import schedule_warning

REPO = Path(__file__).resolve().parents[1]
FERN = REPO.parent / "shared" / "data" / "fern"
needs_fern = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(),
                                reason=f"fixture {FERN} absent (CI keeps ../shared beside the checkout)")
GRID = ["+experiment=smoke", "grid.methods=[gef_only]", "report=false"]
BASE = [*GRID, "dataset.width=32", "dataset.height=24", "dataset.n_views=8"]


def refused(tmp_path: Path, *args: str, base: list[str] = BASE) -> str:
    """The message of a sweep that stops before running anything (and writes nothing)."""
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        run_experiment([*base, f"out_dir={out}", *args])
    assert not out.exists()
    return str(e.value)


@pytest.mark.parametrize("arg,words", [
    ("method.train.optim={means_lr:-0.001}", "optim.means_lr=-0.001: must be a finite number ≥ 0"),
    ("method.train.optim={means_lr:nan}", "optim.means_lr=nan: must be a finite number ≥ 0"),
    ("method.train.optim={sh0_lr:inf}", "optim.sh0_lr=inf: must be a finite number ≥ 0"),
    ("+method.train.gaussians.init_opacity=0", "gaussians.init_opacity=0.0: must be a finite number in (0, 1)"),
    ("+method.train.gaussians.init_opacity=1", "gaussians.init_opacity=1.0: must be a finite number in (0, 1)"),
    ("+method.train.gaussians.max_sh_degree=7", "gaussians.max_sh_degree=7: must be a whole number in [0, 3]"),
    ("protocol.schedule_steps=-1", "protocol.schedule_steps=-1: must be at least 1"),
    ("protocol.test_every=0", "protocol.test_every=0: must be at least 1"),
    ("protocol.max_width=1", "protocol.max_width=1: must be at least 16"),
    ("dataset.width=8", "dataset.width=8: must be a whole number ≥ 16"),
    ("eval.flow=bogus", "eval.flow='bogus': must be one of geometric, opencv, opencv-deepflow"),
    ("eval.lpips_net=vgq", "eval.lpips_net='vgq': must be one of vgg, alex"),
    ("executor.workers=0", "executor.workers=0: must be at least 1"),
    ("executor.kind=bogus", "executor.kind='bogus': must be one of sequential, local, slurm, submitit_local"),
])
def test_a_setting_that_cannot_run_is_refused_naming_the_key(tmp_path, arg, words):
    msg = refused(tmp_path, arg)
    assert msg.startswith("invalid config, nothing was run:\n  ") and words in msg


@pytest.mark.parametrize("arg,words", [
    ("seeds=0", "seeds=0: give the number of seeds, a whole number ≥ 1"),
    ("grid.methods=[]", "grid.methods is empty: the experiment would run nothing"),
    ("grid.budgets=[]", "grid.budgets is empty"),
    ("grid.seeds=[]", "no seed to run for gef_only: grid.seeds is empty"),
    ("grid.methods=[softmax_gz]", "grid.methods=softmax_gz is no method; known methods: 3dgs, gef_only, softmax_gs"),
    ("experiment_name=" + "x" * 300, "is 300 bytes long: a folder name takes at most 255"),
])
def test_a_grid_that_cannot_run_is_refused(tmp_path, arg, words):
    msg = refused(tmp_path, arg)
    assert msg.startswith("invalid config, nothing was run: ") and words in msg


def test_every_view_held_out_of_the_procedural_scene_is_refused(tmp_path):
    msg = refused(tmp_path, "protocol.test_every=1")
    assert msg.startswith("invalid scene, nothing was run:\n  ") and "none left to train on" in msg


def test_a_misspelled_method_on_the_command_line_gets_the_one_block_form(tmp_path):
    assert check_command_line(["+experiment=smoke", "method=softmax_gz"]) == (
        "method=softmax_gz is no method; known methods: 3dgs, gef_only, softmax_gs, softmax_only, stopthepop")
    assert check_command_line(["+experiment=smoke", "method=3dgs"]) is None
    p = subprocess.run([sys.executable, "-m", "protocols.run", "+experiment=smoke", "grid.methods=[softmax_gz]",
                        "report=false", f"out_dir={tmp_path}"], cwd=REPO, capture_output=True, text=True,
                       timeout=180)
    assert p.returncode == 2 and "Traceback" not in p.stderr and "Error executing job" not in p.stderr
    assert p.stderr.strip() == ("error: invalid config, nothing was run: grid.methods=softmax_gz is no method; known "
                                "methods: 3dgs, gef_only, softmax_gs, softmax_only, stopthepop")
    assert not (tmp_path / "_hydra").exists()   # refused before Hydra's run.log


@needs_fern
def test_a_folder_that_is_no_scene_is_refused_before_any_cell_runs(tmp_path):
    msg = refused(tmp_path, "dataset=colmap", f"dataset.path={FERN / 'images'}", base=GRID)
    assert msg.startswith(f"invalid scene, nothing was run:\n  dataset.path={FERN / 'images'}: no COLMAP model in")
    assert msg.endswith(f"(did you mean dataset.path={FERN}?)")
    msg = refused(tmp_path, "dataset=transforms", f"dataset.path={FERN}", base=GRID)
    assert "no transforms.json" in msg


@needs_fern
def test_a_scene_with_broken_intrinsics_is_refused_before_any_cell_runs(tmp_path):
    scene = tmp_path / "fern"
    shutil.copytree(FERN / "sparse", scene / "sparse")
    (scene / "images").symlink_to(FERN / "images", target_is_directory=True)
    cams = scene / "sparse" / "0" / "cameras.bin"
    data = bytearray(cams.read_bytes())
    data[32:48] = struct.pack("<dd", 0.0, 0.0)       # the first camera's fx, fy (COLMAP's binary layout)
    cams.write_bytes(bytes(data))
    msg = refused(tmp_path, "dataset=colmap", f"dataset.path={scene}", "on_missing=skip", base=GRID)
    assert msg.startswith("invalid scene, nothing was run:") and f"{cams}, camera 1: focal length fx = 0, fy = 0" in msg


def test_missing_data_advice_fits_what_is_missing(tmp_path):
    """on_missing=skip is the advice only when some scene is there: with none, it would run nothing."""
    root = tmp_path / "data"
    args = ["+experiment=full", "protocol=cpu", "grid.methods=[3dgs]", "grid.datasets=[tandt]", "report=false",
            f"data_root={root}"]
    root.mkdir()
    msg = refused(tmp_path, *args, base=[])
    assert msg.startswith("missing data, nothing was run (no scene of the experiment is there: put the data where")
    assert "on_missing=skip" not in msg and str(root / "tandt" / "train") in msg and str(root / "tandt" / "truck") in msg
    if (FERN / "sparse" / "0").is_dir():
        (root / "tandt").mkdir()
        (root / "tandt" / "train").symlink_to(FERN, target_is_directory=True)
        msg = refused(tmp_path, *args, base=[])
        assert msg.startswith("missing data, nothing was run (set on_missing=skip to run the scenes that are there)")
        assert str(root / "tandt" / "truck") in msg and "'train' not found" not in msg


def _configs(*overrides: str) -> list[dict]:
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        _, payloads = plan(compose(config_name="config", overrides=list(overrides)), list(overrides))
    return [p["config"] for p in payloads]


def test_a_schedule_squeezed_into_a_short_run_is_warned_about():
    short = _configs("+experiment=smoke", "grid.methods=[3dgs]", "seeds=1", "protocol.schedule_steps=30000")[0]
    w = schedule_warning(short)
    assert w.startswith("protocol.steps=300 scales the 3DGS schedule (written for protocol.schedule_steps=30000) "
                        "by 0.01: it refines every 1 step(s) and resets every opacity to 0.01 every 30 steps (they "
                        "need about 92 to climb back)")
    assert "protocol.schedule_steps=null" in w
    assert schedule_warning(_configs("+experiment=smoke", "grid.methods=[3dgs]", "seeds=1")[0]) is None   # unscaled
    assert schedule_warning(_configs("grid.methods=[3dgs]")[0]) is None             # the cpu preset's 3000 steps
    mcmc = _configs("+experiment=mcmc", "grid.methods=[3dgs]", "grid.scenes=[garden]", "grid.budgets=[mcmc_256]",
                    "protocol.steps=300")[0]
    assert "refines every 1 step(s), so" in schedule_warning(mcmc)                  # MCMC: no reset to warn about


def test_the_warning_is_printed_before_the_run(tmp_path, capsys):
    s = run_experiment([*BASE, f"out_dir={tmp_path}", "protocol.steps=4", "protocol.schedule_steps=30000",
                        "eval.fps_repeats=1", "eval.flip=false", "eval.fractions=[1.0]"])
    assert s[0]["status"] == "ok"
    out = capsys.readouterr().out
    assert "warning: protocol.steps=4 scales the 3DGS schedule" in out
    assert out.index("warning: protocol.steps=4") < out.index("experiment smoke: 1 run(s)")
