"""The final checkpoint is written when training ends, before the final evaluation: a run killed
during its metrics, LPIPS, FPS or the consistency frames resumes from it and evaluates again without
training a step (docs/runs.md). The kill is real: SIGTERM (the clean stop) or SIGKILL, sent by the
run to itself at that stage (tests/kill_during_eval.py)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import pytest

from counting_method import counting  # noqa: F401 (the fixture)
from protocols.results import read_result
from protocols.run import run_experiment

REPO = Path(__file__).resolve().parents[1]
ARGS = ["dataset=procedural", "dataset.n_views=10", "dataset.width=32", "dataset.height=24", "grid.methods=[counting]",
        "seeds=1", "protocol.steps=12", "protocol.schedule_steps=null", "checkpoint_every=1000", "eval.fps_repeats=1",
        "eval.flip=false", "eval.fractions=[0.5,1.0]", "report=false", "device=cpu"]
RUN = "procedural/blocks/counting/full/seed0"


def _killed_during(stage: str, sig: str, args: list[str]) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(REPO), str(REPO / "tests")])}
    return subprocess.run([sys.executable, str(REPO / "tests" / "kill_during_eval.py"), stage, sig, *args],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("stage, sig", [
    ("final_metrics", "TERM"), ("consistency", "KILL"),
    pytest.param("measure_render_fps", "KILL", marks=pytest.mark.slow),   # the same path once more
])
def test_a_run_killed_during_its_evaluation_resumes_without_retraining(tmp_path, counting, stage, sig):
    out = tmp_path / "runs"
    args = [*ARGS, f"out_dir={out}", f"eval.consistency={'true' if stage == 'consistency' else 'false'}"]
    done = _killed_during(stage, sig, args)
    expected = 128 + getattr(signal, f"SIG{sig}") if sig == "TERM" else -signal.SIGKILL
    assert done.returncode == expected, done.stdout[-2000:] + done.stderr[-3000:]
    run_dir = out / RUN
    assert not (run_dir / "results.json").exists()
    progress = json.loads((run_dir / json.loads((run_dir / "checkpoint.json").read_text())["dir"]
                           / "progress.json").read_text())
    assert progress["step"] == 12, "the final state is saved before the evaluation"

    assert run_experiment(args)[0]["status"] == "ok"
    assert counting.calls == [], "resumed at the end of training: not one step retrained"
    res = read_result(run_dir / "results.json")
    assert res.steps == 12 and res.train_seconds == pytest.approx(progress["train_seconds"])
    assert [p.step for p in res.curve] == [6, 12]
    assert "resumed from step 12" in (run_dir / "log.txt").read_text()
    ckpts = sorted(p.name for p in run_dir.glob("ckpt-*"))
    assert ckpts == [json.loads((run_dir / "checkpoint.json").read_text())["dir"]] == ["ckpt-0000012"], \
        "the checkpoint it resumed from is the run's final one (not saved again)"
