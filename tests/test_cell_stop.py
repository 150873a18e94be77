"""A stop request (a SLURM job's time-limit warning or SIGTERM, protocols.cell_stop) waits for the
end of the training step it came in, saves that step's checkpoint, then acts; the next run resumes
from that step. Outside the train loop it acts at once."""

import json

import pytest
from hydra import compose, initialize_config_dir

from baselines.method import MethodSpec
from baselines.registry import register, unregister
from baselines.splatting import GaussianSplatting
from protocols.cell import run_cell
from protocols.cell_stop import StopRequests
from protocols.run import CONFIG_DIR, plan, run_experiment

ARGS = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
        "grid.methods=[asking]", "dataset.size=16", "dataset.steps=12", "report=false", "eval.fps_repeats=1",
        "eval.flip=false", "checkpoint_every=1000"]
STOPS = StopRequests()


class Asking(GaussianSplatting):
    """Asks to stop in the middle of step 4, as a signal landing there would."""

    def train_step(self, step):
        out = super().train_step(step)
        if step == 4:
            STOPS.request("a test's request", _stop)
        return out


def _stop():
    raise KeyboardInterrupt


@pytest.fixture
def asking():
    register(MethodSpec("asking", Asking, {"mode": "3dgs"}))
    yield
    unregister("asking")


def test_a_request_saves_its_steps_checkpoint_then_acts_and_the_rerun_resumes_there(tmp_path, asking):
    args = ARGS + [f"out_dir={tmp_path}"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        _, (payload,) = plan(compose(config_name="config", overrides=args), args)
    with pytest.raises(KeyboardInterrupt):
        run_cell(payload, stops=STOPS)
    run = tmp_path / "patterns/circle4/asking/cap4/seed0"
    assert json.loads((run / "checkpoint.json").read_text())["dir"] == "ckpt-0000005"   # after step 4, the 5th
    assert "step 5: stopping for a test's request; checkpoint saved" in (run / "log.txt").read_text()
    assert run_experiment(args)[0]["status"] == "ok"
    assert "resumed from step 5" in (run / "log.txt").read_text()


def test_outside_the_loop_a_request_acts_at_once_and_a_late_one_when_it_ends():
    stops, acted = StopRequests(), []
    stops.request("now", lambda: acted.append("now"))
    stops.begin()
    stops.request("late", lambda: acted.append("late"))
    stops.request("second", lambda: acted.append("second"))   # the first one wins
    assert acted == ["now"]
    stops.end()
    assert acted == ["now", "late"] and stops.take() is None


def test_a_request_after_the_last_steps_look_acts_once_the_final_checkpoint_is_saved(tmp_path, monkeypatch):
    """A signal landing after the loop's last look (here: in its progress bar's last update) acts
    when the loop ends, and the trained state is saved first: the rerun evaluates without retraining."""
    import protocols.train_loop as loop

    args = [a for a in ARGS if not a.startswith("grid.methods=")] + ["grid.methods=[3dgs]", f"out_dir={tmp_path}"]
    stops, real = StopRequests(), loop.progress_bar

    def progress_bar(total, *a, **kw):
        bar = real(total, *a, **kw)
        update = bar.update

        def late(n=1):
            update(n)
            if bar.n == total and kw.get("unit", "step") == "step":   # the training's bar, at its last step
                stops.request("a late request", _stop)

        bar.update = late
        return bar

    monkeypatch.setattr(loop, "progress_bar", progress_bar)
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        _, (payload,) = plan(compose(config_name="config", overrides=args), args)
    with pytest.raises(KeyboardInterrupt):
        run_cell(payload, stops=stops)
    run = tmp_path / "patterns/circle4/3dgs/cap4/seed0"
    assert json.loads((run / "checkpoint.json").read_text())["dir"] == "ckpt-0000012", "the final state is saved"
    monkeypatch.setattr(loop, "progress_bar", real)
    assert run_experiment(args)[0]["status"] == "ok"
    assert "resumed from step 12" in (run / "log.txt").read_text()
