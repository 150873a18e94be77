"""The runner under reruns and damage: --force and a changed config retrain from step 0, a
checkpoint is never resumed by another config, a bad cell folder fails only its cell."""

import json
from pathlib import Path

import pytest

from counting_method import counting  # noqa: F401 (the fixture)
from protocols.results import read_result
from protocols.run import run_experiment

TINY = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
        "dataset.size=16", "dataset.steps=12", "report=false", "eval.fps_repeats=1", "eval.flip=false"]
RUN = "patterns/circle4/{}/cap4/seed0"


def tiny(tmp_path, *extra):
    return TINY + [f"out_dir={tmp_path}", *extra]


def test_force_and_a_changed_config_train_from_step_0(tmp_path, counting):
    args = tiny(tmp_path, "grid.methods=[counting]")
    run_dir = tmp_path / RUN.format("counting")
    assert run_experiment(args)[0]["status"] == "ok"
    first = read_result(run_dir / "results.json")
    assert counting.calls == list(range(12))
    assert json.loads((run_dir / "checkpoint.json").read_text())["config_hash"] == first.config_hash

    counting.calls.clear()
    assert run_experiment(args + ["force=true"])[0]["status"] == "ok"
    assert counting.calls == list(range(12)), "--force must retrain, not resume the final state"

    counting.calls.clear()
    s = run_experiment(args + ["++method.train.optim={name:3dgs2023+softmaxgs_patterns,means_lr:0.00002}"])
    assert s[0]["status"] == "ok" and counting.calls == list(range(12))
    new = read_result(run_dir / "results.json")
    assert new.config_hash != first.config_hash
    assert new.config["method"]["train"]["optim"]["means_lr"] == 0.00002
    assert "resumed" not in (run_dir / "log.txt").read_text()


def test_a_mid_run_checkpoint_of_another_config_is_discarded(tmp_path, counting):
    args = tiny(tmp_path, "grid.methods=[counting]", "checkpoint_every=5")
    counting.interrupt_at = 7
    with pytest.raises(KeyboardInterrupt):
        run_experiment(args)
    counting.calls.clear()
    assert run_experiment(args + ["++method.train.k_max=64"])[0]["status"] == "ok"
    assert counting.calls == list(range(12))
    log = (tmp_path / RUN.format("counting") / "log.txt").read_text()
    assert "discarded, training from step 0" in log and "resumed" not in log


def test_a_corrupt_checkpoint_names_its_file_and_force_discards_it(tmp_path, counting):
    args = tiny(tmp_path, "grid.methods=[counting]", "checkpoint_every=5")
    counting.interrupt_at = 7
    with pytest.raises(KeyboardInterrupt):
        run_experiment(args)
    ck = tmp_path / RUN.format("counting") / "ckpt-0000005" / "checkpoint.pt"
    ck.write_bytes(b"not a checkpoint")
    s = run_experiment(args)
    assert s[0]["status"] == "failed"
    assert str(ck) in s[0]["error"] and "--force" in s[0]["error"]
    counting.calls.clear()
    assert run_experiment(args + ["force=true"])[0]["status"] == "ok"
    assert counting.calls == list(range(12))


def test_a_file_or_folder_in_the_way_fails_only_its_cell(tmp_path):
    (tmp_path / RUN.format("3dgs")).parent.mkdir(parents=True)
    (tmp_path / RUN.format("3dgs")).write_text("in the way")
    (tmp_path / RUN.format("gef_only") / "results.json").mkdir(parents=True)
    s = run_experiment(tiny(tmp_path, "grid.methods=[3dgs,gef_only,softmax_gs]"))
    by = {x["key"].split("/")[2]: x for x in s}
    assert by["3dgs"]["status"] == "failed" and "is a file where the run's folder should be" in by["3dgs"]["error"]
    assert by["gef_only"]["status"] == "failed" and "is a folder where" in by["gef_only"]["error"]
    assert by["softmax_gs"]["status"] == "ok"


def test_a_sweep_with_a_failed_cell_exits_non_zero_saying_how_many(tmp_path):
    import subprocess
    import sys

    blocked = tmp_path / RUN.format("3dgs")
    blocked.parent.mkdir(parents=True)
    blocked.write_text("in the way")
    p = subprocess.run([sys.executable, "-m", "protocols.run", *tiny(tmp_path, "grid.methods=[3dgs]")],
                       cwd=Path(__file__).resolve().parent.parent, capture_output=True, text=True, timeout=300)
    assert p.returncode == 1, p.stderr[-2000:]
    assert "1 of 1 run(s) failed" in p.stderr


@pytest.mark.parametrize("override, words", [
    ("dataset.steps=-5", ["dataset.steps", "-5", "at least 1"]),
    ("dataset.steps=0", ["dataset.steps", "at least 1"]),
    ("dataset.steps=abc", ["dataset.steps", "'abc'", "integer"]),
    ("eval.fps_repeats=x", ["eval.fps_repeats", "integer"]),
    ("++eval.fps_repeat=3", ["EvalConfig at eval", "unknown key(s) ['fps_repeat']", "fps_repeats"]),
    ("~eval.flip", ["EvalConfig at eval", "missing key(s) ['flip']"]),
    ("eval.quantize=maybe", ["eval.quantize='maybe'", "true or false"]),
    ("++protocol.max_widht=300", ["ProtocolConfig at protocol", "unknown key(s) ['max_widht']", "max_width"]),
    ("budget.cap=many", ["budget.cap", "integer"]),
    ("++budget.kind=7", ["budget.kind=7: expected a string"]),
    ("++budget.kind=huge", ["unknown kind 'huge'", "budget.kind", "5pct"]),
    ("++budget.preset=cap", ["BudgetConfig at budget", "unknown key(s) ['preset']"]),
    ("+budget.grad_threshold=high", ["budget.grad_threshold", "number"]),
    ("dataset.train.optim=nosuch", ["nosuch", "hyperparameter set", "3dgs2023"]),
    ("++method.train.k_max=lots", ["k_max", "'lots'", "int"]),
    ("backend=gpu9", ["backend", "gpu9", "reference"]),
    ("eval.popping_ratio=yes", ["eval.popping_ratio", "'yes'", "auto, on, off"]),
])
def test_impossible_settings_stop_the_sweep_before_any_cell_runs(tmp_path, override, words):
    with pytest.raises(SystemExit) as e:
        run_experiment(tiny(tmp_path, "grid.methods=[3dgs]", override))
    for w in words:
        assert w in str(e.value), (w, str(e.value))
    assert not (tmp_path / RUN.format("3dgs")).exists()


def test_protocol_steps_are_checked_too(tmp_path):
    with pytest.raises(SystemExit, match=r"protocol\.steps.*at least 1"):
        run_experiment(["+experiment=smoke", "seeds=1", f"out_dir={tmp_path}", "report=false", "protocol.steps=0"])


def test_sigterm_ends_the_run_cleanly_and_the_log_holds_plain_lines(tmp_path):
    """stderr is a pipe here (as in a log file): whole lines, no carriage returns or cursor codes; a
    SIGTERM mid-training stops with a sentence and exit status 143, the checkpoint kept."""
    import signal

    from sigterm_run import terminate_when_training

    args = tiny(tmp_path, "grid.methods=[3dgs]", "dataset.steps=20000", "checkpoint_every=10")
    code, out, err = terminate_when_training(args, "circle4/3dgs: step")
    assert code == 128 + signal.SIGTERM, err[-2000:]
    assert "stopped by SIGTERM" in err and "resume" in err
    assert "Traceback" not in err and "Fatal" not in err
    assert "\r" not in err + out and "\x1b" not in err + out
    run_dir = tmp_path / RUN.format("3dgs")
    assert "interrupted" in (run_dir / "log.txt").read_text()


def test_a_scene_given_by_its_folder_is_named_after_it(tmp_path):
    from protocols.run import plan
    from hydra import compose, initialize_config_dir
    from protocols.run import CONFIG_DIR

    args = ["dataset=colmap", f"dataset.path={tmp_path}/fern/", "grid.methods=[3dgs]", f"out_dir={tmp_path}/runs"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cells, payloads = plan(compose(config_name="config", overrides=args), args)
    assert [c.scene for c in cells] == ["fern"]
    assert payloads[0]["config"]["scene"] == "fern" and payloads[0]["key"].startswith("colmap/fern/")
