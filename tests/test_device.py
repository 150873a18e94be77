"""The ``device`` setting: resolution and bad input, the plumbing with ``device=cpu`` given
explicitly, and training / evaluation / resume under a check that every tensor is created on the
run's device (tests/device_check.py). The GPU side is in tests/test_device_gpu.py (marked gpu)."""

from __future__ import annotations

import json
import logging

import pytest
import torch
from device_check import StrayTensors, fit_config, only_device, train_save_load

from baselines import create_method
from protocols.results import read_result
from protocols.run import run_experiment
from smgs.data.patterns import pattern_scene
from smgs.device import DeviceError, device_name, resolve_device, restore_generator
from smgs.raster.backends import check_backend
from smgs.train import pattern_config
from smgs.train.trainer import Trainer

CPU = torch.device("cpu")
TINY = ["+experiment=patterns", "grid.methods=[softmax_gs]", "grid.budgets=[cap4]", "grid.seeds=[0]",
        "grid.scenes=[circle4]", "dataset.size=16", "dataset.steps=6", "report=false", "eval.fps_repeats=1",
        "eval.flip=false"]


@pytest.fixture
def two_gpus(monkeypatch):
    """torch believes it sees two CUDA devices (nothing here touches them)."""
    monkeypatch.setattr(torch.cuda, "is_available", lambda: True)
    monkeypatch.setattr(torch.cuda, "device_count", lambda: 2)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)


@pytest.fixture
def no_gpu(monkeypatch):
    monkeypatch.setattr(torch.cuda, "is_available", lambda: False)


# -- resolution and bad input ---------------------------------------------------------------

def test_auto_is_the_first_cuda_device_else_the_cpu(no_gpu):
    assert resolve_device("auto") == CPU and resolve_device(None) == CPU and resolve_device("CPU") == CPU


def test_auto_and_cuda_name_one_device(two_gpus):
    assert resolve_device("auto") == torch.device("cuda", 0)
    assert resolve_device("cuda") == torch.device("cuda", 0)
    assert resolve_device("cuda:1") == torch.device("cuda", 1)
    assert resolve_device(torch.device("cpu")) == CPU


def test_cuda_without_cuda_is_an_error_never_a_cpu_run(no_gpu):
    with pytest.raises(DeviceError, match=r"device=cuda asks for CUDA, but .*use device=cpu") as e:
        resolve_device("cuda")
    if torch.version.cuda is None:
        assert "CPU-only build" in str(e.value)


def test_a_missing_gpu_index_names_the_ones_there(two_gpus):
    with pytest.raises(DeviceError, match=r"device=cuda:3, but torch sees 2 CUDA device\(s\) \(cuda:0\.\.cuda:1\)"):
        resolve_device("cuda:3")


@pytest.mark.parametrize("spec", ["gpu", "gpu:0", "tpu", "cuda:x", "cuda0", ""])
def test_unknown_device_names_are_refused_with_the_choices(spec):
    with pytest.raises(DeviceError, match="unknown device .*; use auto, cpu, cuda or cuda:N") as e:
        resolve_device(spec)
    assert ("a GPU is 'cuda'" in str(e.value)) == spec.startswith("gpu")


def test_backend_of_the_other_kind_of_device_is_refused():
    with pytest.raises(DeviceError, match=r"backend=cuda renders on the CUDA only, but the run's device is cpu; "
                                          r"use backend=auto .* or device=cuda"):
        check_backend("cuda", CPU)
    with pytest.raises(DeviceError, match=r"backend=cpu renders on the CPU only, but the run's device is cuda:0; "
                                          r"use backend=auto .* or device=cpu"):
        check_backend("cpu", torch.device("cuda", 0))
    for backend in ("auto", "reference"):
        check_backend(backend, CPU)
        check_backend(backend, torch.device("cuda", 0))
    check_backend("cpu", CPU)


def test_the_trainer_refuses_bad_devices_before_making_anything(no_gpu):
    scene = pattern_scene("circle4", 8)
    cfg = pattern_config("3dgs", cap=4, steps=2)
    with pytest.raises(DeviceError, match="asks for CUDA"):
        Trainer(scene, cfg, device="cuda")
    cfg.backend = "cuda"
    with pytest.raises(DeviceError, match="backend=cuda renders on the CUDA only"):
        Trainer(scene, cfg, device="cpu")


@pytest.mark.parametrize("overrides, message", [
    (["device=cuda"], "asks for CUDA"),
    (["device=gpu"], "unknown device 'gpu'"),
    (["backend=cuda", "device=cpu"], "backend=cuda renders on the CUDA only"),
])
def test_the_runner_stops_before_writing_any_run_directory(tmp_path, no_gpu, overrides, message):
    with pytest.raises(SystemExit, match=message):
        run_experiment(TINY + [f"out_dir={tmp_path}", *overrides])
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("overrides, message", [
    (["device=cuda:3"], "torch sees 2 CUDA device"),
    (["backend=cpu", "device=cuda"], "backend=cpu renders on the CPU only"),
])
def test_the_runner_refuses_gpu_settings_this_machine_cannot_honour(tmp_path, two_gpus, overrides, message):
    with pytest.raises(SystemExit, match=message):
        run_experiment(TINY + [f"out_dir={tmp_path}", *overrides])
    assert not any(tmp_path.iterdir())


def test_cells_for_a_cluster_are_checked_for_spelling_here_and_for_hardware_on_their_node(no_gpu):
    from protocols.run import check_devices

    cell = {"key": "k", "config": {"device": "cuda", "backend": "auto"}}
    check_devices([cell], "slurm")                    # the GPU is on the node, not here
    with pytest.raises(SystemExit, match="asks for CUDA"):
        check_devices([cell], "local")
    for bad, message in (({"device": "gpu"}, "unknown device 'gpu'"),
                         ({"device": "cuda:1", "backend": "cpu"}, "backend=cpu renders on the CPU only")):
        with pytest.raises(SystemExit, match=message):
            check_devices([{"key": "k", "config": bad}], "slurm")


def test_a_cell_whose_node_lacks_the_device_fails_without_a_run_directory(tmp_path, no_gpu):
    from protocols.cell import run_cell

    s = run_cell({"key": "k", "run_dir": str(tmp_path / "k"), "config": {"device": "cuda", "backend": "auto"}})
    assert s["status"] == "failed" and "DeviceError" in s["error"] and "asks for CUDA" in s["error"]
    assert not (tmp_path / "k").exists()


def test_bench_command_line_refuses_a_bad_device(no_gpu, capsys):
    from bench.train import main as bench_main

    with pytest.raises(SystemExit):
        bench_main(["--device", "gpu"])
    assert "unknown device 'gpu'" in capsys.readouterr().err


# -- plumbing with device=cpu given explicitly ------------------------------------------------

def test_device_cpu_reaches_results_and_the_report_names_it(tmp_path):
    s = run_experiment(TINY + [f"out_dir={tmp_path}", "device=cpu"])
    assert [x["status"] for x in s] == ["ok"]
    res = read_result(tmp_path / "patterns/circle4/softmax_gs/cap4/seed0/results.json")
    name = device_name(CPU)
    assert res.config["device"] == "cpu"          # the resolved device is part of the config hash
    assert res.versions["device"] == name and res.render_device == name and name.startswith("cpu ")
    assert res.diagnostics["peak_memory_kind"].startswith("cpu_peak_rss")
    assert 0 < res.diagnostics["peak_memory_baseline_mb"] <= res.peak_memory_mb
    assert "device: " + name in (tmp_path / "patterns/circle4/softmax_gs/cap4/seed0/log.txt").read_text()


def test_training_bench_takes_the_device(tmp_path):
    from bench.train import main as bench_main

    assert bench_main(["--scenes", "pattern4", "--methods", "3dgs", "--steps", "1", "--warmup", "0",
                       "--device", "cpu", "--json", str(tmp_path / "b.json")]) == 0
    assert json.loads((tmp_path / "b.json").read_text())[0]["device"] == device_name(CPU)


def test_auto_on_a_cpu_machine_is_the_same_cell_as_cpu(tmp_path, no_gpu):
    run_experiment(TINY + [f"out_dir={tmp_path}", "device=cpu"])
    again = run_experiment(TINY + [f"out_dir={tmp_path}", "device=auto"])
    assert again[0].get("skipped")


def test_every_part_of_a_method_gets_the_device():
    m = create_method("softmax_gs", pattern_scene("circle4", 8), fit_config("softmax_gs"), device="cpu")
    tr = m.trainer
    assert m.device == CPU and tr.device == CPU and tr.strategy.device == CPU
    assert tr.gen.device == CPU and tr.strategy.gen.device == CPU
    assert all(p.device == CPU for p in tr.gaussians.params.values())
    assert all(t.device == CPU for t in tr._targets)


# -- every tensor on the run's device ---------------------------------------------------------

def test_the_check_catches_a_tensor_made_without_a_device():
    x = torch.ones(3)
    with pytest.raises(StrayTensors, match=r"aten\.\w+.* -> meta: tests/test_device.py"):
        with only_device(CPU):
            x + torch.zeros(3)          # no device=: on a GPU run this would be a CPU tensor
    with only_device(CPU):
        x + torch.zeros(3, device=CPU)


def test_the_check_catches_the_strategy_statistics_as_they_were(monkeypatch):
    """The densification statistics before the device was passed (``torch.zeros(n)``): the check
    fails on them, naming the line."""
    from smgs.train.strategies import DefaultStrategy

    def old_reset(self, n):
        self.grad2d = torch.zeros(n)
        self.count = torch.zeros(n)
        self.max_radii = torch.zeros(n)

    monkeypatch.setattr(DefaultStrategy, "_reset_stats", old_reset)
    scene = pattern_scene("circle4", 12)
    with pytest.raises(StrayTensors, match=r"tests/test_device.py:\d+ +self.grad2d = torch.zeros\(n\)"):
        with only_device(CPU):
            m = create_method("3dgs", scene, fit_config("3dgs"), device=CPU)
            for s in range(4):
                m.train_step(s)


@pytest.mark.parametrize("method", ["3dgs", "softmax_gs"])
def test_training_evaluation_and_resume_make_tensors_only_on_the_run_device(tmp_path, method):
    scene = pattern_scene("circle4", 12)
    with only_device(CPU):
        a, b = train_save_load(method, scene, CPU, CPU, tmp_path / "ck", steps=8)
        for s in range(8, 12):
            b.train_step(s)
        out = b.render(scene.test[0].camera)
    for s in range(8, 12):
        a.train_step(s)
    torch.testing.assert_close(out.rgb, a.render(scene.test[0].camera).rgb, rtol=0, atol=0)
    assert b.num_gaussians() != 4      # the fit densified (clone / split paths ran)


def test_a_protocol_cell_trains_evaluates_and_resumes_on_the_run_device(tmp_path, monkeypatch):
    """The runner's whole cell (training with checkpoints, intermediate and final evaluation, FPS,
    peak memory, view consistency, results.json), interrupted and resumed, on the procedural scene
    (SfM init, background, SH): the scene is loaded before the check (data on the host)."""
    import protocols.train_loop as tl
    from hydra import compose, initialize_config_dir

    from protocols.cell import run_cell
    from protocols.cell_scene import load_scene_for
    from protocols.run import CONFIG_DIR, plan

    ov = ["+experiment=smoke", "seeds=1", "grid.methods=[softmax_gs]", "protocol.steps=6", "report=false",
          "eval.fps_repeats=1", "device=cpu", f"out_dir={tmp_path}", "checkpoint_every=3", "dataset.n_views=4",
          "dataset.width=24", "dataset.height=16", "eval.consistency=true", "eval.consistency_max_width=16"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        payload = plan(compose(config_name="config", overrides=ov), ov)[1][0]
    scene = load_scene_for(payload["config"])
    monkeypatch.setattr(tl, "load_scene_for", lambda cfg: scene)
    from baselines.splatting import GaussianSplatting

    calls = {"n": 0}
    real_step = GaussianSplatting.train_step

    def interrupt_at_5(self, step):     # the first run stops in step 5, after the checkpoint at 3
        calls["n"] += 1
        if step == 4 and calls["n"] == 5:
            raise KeyboardInterrupt
        return real_step(self, step)

    monkeypatch.setattr(GaussianSplatting, "train_step", interrupt_at_5)
    with only_device(CPU):
        with pytest.raises(KeyboardInterrupt):
            run_cell(payload)
        s = run_cell(payload)
    assert s["status"] == "ok", s
    run_dir = tmp_path / payload["key"]
    assert "resumed from step 3" in (run_dir / "log.txt").read_text()
    res = json.loads((run_dir / "results.json").read_text())
    assert res["consistency"] and res["config"]["device"] == "cpu"


def test_a_generator_state_from_another_kind_of_device_reseeds_deterministically(caplog):
    scene = pattern_scene("circle4", 8)
    a = create_method("3dgs", scene, fit_config("3dgs"), device=CPU)
    a.train_step(0)
    state = a.trainer.state_dict()
    assert state["gen"]["device_type"] == "cpu" and state["device"] == "cpu"
    state["gen"] = {"device_type": "cuda", "state": torch.arange(16, dtype=torch.uint8)}   # as a GPU run saves it
    state["strategy"]["gen"] = {"device_type": "cuda", "state": torch.arange(16, dtype=torch.uint8)}
    draws = []
    for _ in range(2):
        b = create_method("3dgs", scene, fit_config("3dgs"), device=CPU)
        with caplog.at_level(logging.WARNING):
            b.trainer.load_state_dict(state)
        draws.append(torch.rand(4, generator=b.trainer.gen, device=CPU))
    torch.testing.assert_close(draws[0], draws[1], rtol=0, atol=0)
    assert "random generators cannot carry over between kinds of device" in caplog.text
    # the same kind of device continues the stream exactly
    g, h = torch.Generator(device=CPU).manual_seed(3), torch.Generator(device=CPU)
    assert restore_generator(h, {"device_type": "cpu", "state": g.get_state()}, 0)
    assert torch.equal(torch.rand(3, generator=g), torch.rand(3, generator=h))
