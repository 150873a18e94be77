"""A kernel build is never a method's training time: the run builds every compiled kernel it uses
before its train clock starts and records the seconds apart (results.json ``build_seconds``)."""

import time

from protocols.results import read_result
from protocols.run import run_experiment
from smgs.raster import cpu, projection
from smgs.raster.jit import JitExtension
from smgs.train import image_loss

SLOW = 3.0   # seconds each "build" takes here, more than the whole tiny run trains

TINY = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
        "grid.methods=[softmax_gs]", "dataset.size=16", "dataset.steps=12", "report=false",
        "eval.fps_repeats=1", "eval.flip=false"]


def test_kernel_builds_are_kept_out_of_train_time_and_recorded_apart(tmp_path, monkeypatch):
    builds: list[str] = []

    def slow(ext) -> JitExtension:
        """A fresh (unbuilt) holder of the same kernel (on the SIMD path in use) whose build takes
        SLOW seconds longer."""
        jit: JitExtension = ext.jit()

        def build(suffix, defines):
            time.sleep(SLOW)
            builds.append(jit.what)
            return jit.build(suffix, defines)

        return JitExtension(jit.kind, build, jit.precheck, what=jit.what, disable=jit.disable)

    renderer = slow(cpu._JIT)
    monkeypatch.setattr(cpu, "_JIT", renderer)
    monkeypatch.setattr(cpu, "is_available", renderer.is_available)
    monkeypatch.setattr(projection, "_JIT", slow(projection._JIT))
    monkeypatch.setattr(image_loss, "_JIT", slow(image_loss._JIT))

    run_experiment(TINY + [f"out_dir={tmp_path}"])
    res = read_result(tmp_path / "patterns/circle4/softmax_gs/cap4/seed0/results.json")
    assert res.status == "ok", res.error
    assert "renderer backend" in builds and "training-loss kernel" in builds, builds
    assert res.train_seconds < SLOW, res.train_seconds          # no build inside the train clock
    assert all(c.seconds < SLOW for c in res.curve), res.curve  # nor in the error-against-time curve
    assert res.build_seconds is not None and res.build_seconds >= SLOW * len(builds)
