"""The protocol runner on tiny pattern fits: skip, failure isolation, resume, clear errors."""

import json
import subprocess
import sys
from pathlib import Path

import pytest

from baselines.method import MethodSpec
from baselines.registry import register, unregister
from baselines.splatting import GaussianSplatting
from protocols.results import read_result
from protocols.run import run_experiment
from smgs.metrics.lpips import WEIGHTS_ENV, find_weights

REPO = Path(__file__).resolve().parent.parent

TINY = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
        "dataset.size=16", "dataset.steps=12", "report=false", "eval.fps_repeats=1", "eval.flip=false"]


def tiny(tmp_path, *extra):
    return TINY + [f"out_dir={tmp_path}", *extra]


class Boom(GaussianSplatting):
    def train_step(self, step):
        raise RuntimeError("boom at step %d" % step)


class InterruptOnce(GaussianSplatting):
    calls: list = []
    interrupt_at = 7

    def train_step(self, step):
        InterruptOnce.calls.append(step)
        if step == InterruptOnce.interrupt_at and InterruptOnce.interrupt_at is not None:
            InterruptOnce.interrupt_at = None
            raise KeyboardInterrupt
        return super().train_step(step)


@pytest.fixture
def plugin_methods():
    register(MethodSpec("boom", Boom, {"mode": "3dgs"}))
    register(MethodSpec("interrupt_once", InterruptOnce, {"mode": "3dgs"}))
    yield
    unregister("boom")
    unregister("interrupt_once")


def test_runs_then_skips_finished_cells_and_force_redoes(tmp_path, monkeypatch):
    monkeypatch.delenv(WEIGHTS_ENV, raising=False)   # no LPIPS weights: the metric is missing, with the fix
    s1 = run_experiment(tiny(tmp_path, "grid.methods=[3dgs,softmax_gs]"))
    assert [s["status"] for s in s1] == ["ok", "ok"] and not any(s.get("skipped") for s in s1)
    res = read_result(tmp_path / "patterns/circle4/softmax_gs/cap4/seed0/results.json")
    assert res.status == "ok" and res.steps == 12 and res.num_gaussians == 4
    assert res.per_view["psnr"] and res.curve[-1].step == 12
    assert "lpips" not in res.metrics and res.missing["lpips"] == find_weights("vgg").reason
    assert res.missing["lpips"].startswith(f"no LPIPS weights configured ({WEIGHTS_ENV} is unset): run `python -m")
    s2 = run_experiment(tiny(tmp_path, "grid.methods=[3dgs,softmax_gs]"))
    assert all(s.get("skipped") for s in s2)
    # a changed config is not the same result: it runs again
    s3 = run_experiment(tiny(tmp_path, "grid.methods=[3dgs]", "method.train.k_max=64"))
    assert not s3[0].get("skipped")
    s4 = run_experiment(tiny(tmp_path, "grid.methods=[3dgs]", "method.train.k_max=64", "force=true"))
    assert not s4[0].get("skipped")


def test_a_failing_cell_is_recorded_and_the_others_finish(tmp_path, plugin_methods, capsys):
    s = run_experiment(tiny(tmp_path, "grid.methods=[boom,3dgs]"))
    by = {x["key"].split("/")[2]: x for x in s}
    assert by["boom"]["status"] == "failed" and "boom at step 0" in by["boom"]["error"]
    assert by["3dgs"]["status"] == "ok"
    r = read_result(tmp_path / "patterns/circle4/boom/cap4/seed0/results.json")
    assert r.status == "failed" and "RuntimeError: boom at step 0" in r.error
    log = tmp_path / "patterns/circle4/boom/cap4/seed0/log.txt"
    assert "Traceback" in log.read_text()
    # the summary line names the file that holds the traceback
    assert f"failed: RuntimeError: boom at step 0 (traceback in {log})" in capsys.readouterr().out


def test_an_interrupted_run_resumes_from_its_checkpoint(tmp_path, plugin_methods):
    InterruptOnce.calls.clear()
    InterruptOnce.interrupt_at = 7
    args = tiny(tmp_path, "grid.methods=[interrupt_once]", "checkpoint_every=5")
    with pytest.raises(KeyboardInterrupt):
        run_experiment(args)
    run_dir = tmp_path / "patterns/circle4/interrupt_once/cap4/seed0"
    assert not (run_dir / "results.json").exists()
    assert json.loads((run_dir / "checkpoint.json").read_text())["dir"] == "ckpt-0000005"
    InterruptOnce.calls.clear()
    s = run_experiment(args)
    assert s[0]["status"] == "ok"
    assert InterruptOnce.calls == list(range(5, 12))  # resumed after step 5, not from 0
    assert "resumed from step 5" in (run_dir / "log.txt").read_text()
    r = read_result(run_dir / "results.json")
    assert r.steps == 12 and [c.step for c in r.curve] == [2, 3, 6, 12]


def test_unknown_method_names_the_registered_ones(tmp_path):
    with pytest.raises(SystemExit, match="invalid config, nothing was run: grid.methods=softmax_gz is no method; "
                                         "known methods: .*softmax_gs"):
        run_experiment(tiny(tmp_path, "grid.methods=[softmax_gz]"))


def test_missing_dataset_names_the_folder_and_skip_records_it(tmp_path):
    args = ["+experiment=full", "grid.methods=[3dgs]", "grid.datasets=[tandt]", f"data_root={tmp_path}/nope",
            f"out_dir={tmp_path}/runs", "report=false"]
    with pytest.raises(SystemExit, match="nope"):
        run_experiment(args)
    s = run_experiment(args + ["on_missing=skip"])
    assert [x["status"] for x in s] == ["skipped", "skipped"]
    r = read_result(tmp_path / "runs/tandt/train/3dgs/full/seed0/results.json")
    assert r.status == "skipped" and "nope" in r.error


def test_config_typo_is_a_clear_error_on_the_command_line():
    p = subprocess.run([sys.executable, "-m", "protocols.run", "+experiment=smoke", "protocol.stpes=5"],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2
    assert "protocol.stpes=5: no setting is called protocol.stpes" in p.stderr and "did you mean protocol.steps=5?" in p.stderr


def test_consistency_row_and_trajectory_recorded(tmp_path):
    s = run_experiment(["+experiment=smoke", "seeds=1", f"out_dir={tmp_path}", "report=false", "grid.methods=[softmax_gs]",
                        "protocol.steps=5", "dataset.width=96", "dataset.height=72", "dataset.n_views=10",
                        "eval.consistency=true", "eval.fps_repeats=1", "eval.flip=false"])
    assert s[0]["status"] == "ok"
    run = tmp_path / "procedural/blocks/softmax_gs/full/seed0"
    r = read_result(run / "results.json")
    c = r.consistency
    assert c["step"] == 7 and c["estimator"] == "geometric" and c["mask"] == "per-method"
    assert c["mse"] >= 0 and "psnr" in c  # 96x72: the 20 px border still leaves valid pixels
    # the popping ratio from the leading-splat maps: a share of popped pixels, a ratio or why not
    assert 0.0 <= c["popped_fraction"] < 1.0
    assert isinstance(c["pop_ratio"], float) or "swapped" in c["pop_ratio"]["missing"]
    assert json.loads((run / "trajectory.json").read_text())
    assert r.diagnostics["metrics_on_8bit"] is True
    assert r.lpips_net.endswith("3dgs-input")
    assert set(r.diagnostics["params"]) == {"alpha", "beta", "gamma"}
    # the viewer's images (report.html): ground truth and |error| map of a few test views, the popping strip
    gts = sorted(p.name for p in (run / "renders" / "gt").glob("*.png"))
    n_test = len(list((run / "renders").glob("*.png")))
    assert n_test >= 2 and len(gts) == min(3, n_test) and gts == sorted(p.name for p in (run / "renders" / "error").glob("*.png"))
    assert all((run / "renders" / g).is_file() for g in gts)
    strip = json.loads((run / "consistency" / "strip.json").read_text())
    assert len(strip["frames"]) == 8 and (run / "consistency" / "strip.png").is_file()


def test_smoke_experiment_end_to_end_with_report(tmp_path):
    """The README's main command, with fewer steps and smaller images (the full one takes minutes)."""
    s = run_experiment(["+experiment=smoke", f"out_dir={tmp_path}", "protocol.steps=8", "dataset.width=64",
                        "dataset.height=48", "dataset.n_views=10", "eval.fps_repeats=1"])
    # the compared pair at seeds 0, 1, 2 (grid.seeds_of), the two ablations at seed 0
    assert sorted(x["key"].split("/", 2)[2] for x in s) == sorted(
        [f"{m}/full/seed{i}" for m in ("3dgs", "softmax_gs") for i in range(3)]
        + ["gef_only/full/seed0", "softmax_only/full/seed0"])
    assert [x["status"] for x in s] == ["ok"] * 8
    report = (tmp_path / "report" / "report.md").read_text()
    for name in ("3D GS", "Sharp edge only", "Softmax only", "Softmax-GS", "[cpu]"):
        assert name in report
    assert "n = 3 per value" in report and "Softmax-GS − 3D GS [cpu]" in report  # spread, paired difference
    assert (tmp_path / "report" / "tables" / "table5_paired.csv").exists()


def test_seeds_n_and_per_method_seeds():
    from hydra import compose, initialize_config_dir

    from protocols.run import CONFIG_DIR, plan

    def keys(*ov: str) -> list[str]:
        with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
            cells, payloads = plan(compose(config_name="config", overrides=list(ov)), list(ov))
        assert all(p["config"]["seeds"] is None for p in payloads)  # not part of a cell's identity
        return [c.key.split("/", 2)[2] for c in cells]

    smoke = keys("+experiment=smoke", "grid.methods=[3dgs,gef_only]")
    assert smoke == ["3dgs/full/seed0", "3dgs/full/seed1", "3dgs/full/seed2", "gef_only/full/seed0"]
    assert keys("+experiment=smoke", "grid.methods=[3dgs,gef_only]", "seeds=2") == [
        "3dgs/full/seed0", "3dgs/full/seed1", "gef_only/full/seed0", "gef_only/full/seed1"]
    assert keys("grid.seeds=[4,7]") == ["softmax_gs/full/seed4", "softmax_gs/full/seed7"]
    for bad in ("seeds=0", "seeds=[0,1]"):
        with pytest.raises(SystemExit, match="invalid config, nothing was run: seeds=.*whole number"):
            keys(bad)


def test_the_popping_ratio_is_left_out_with_why_where_its_maps_are_not_made():
    """eval.popping_ratio: auto renders the leading-splat maps where the renderer makes them (not on
    a CUDA device but with the opt-in kernels), on forces them, off never; a method without
    render_leaders is named."""
    from types import SimpleNamespace

    import torch

    from protocols.train_loop import _no_popping_ratio as why
    from smgs.raster import Renderer

    _no_popping_ratio = lambda m, e, d: why(m, e, d, Renderer(kernels="default"))  # noqa: E731

    class WithMaps:
        name = "m"

        def render_leaders(self, camera):
            raise AssertionError("not called here")

    class Without:
        name = "plugin"

    ev = lambda v: SimpleNamespace(popping_ratio=v)  # noqa: E731
    cpu, cuda = torch.device("cpu"), torch.device("cuda:0")
    assert _no_popping_ratio(WithMaps(), ev("auto"), cpu) == ""
    assert "renderer cuda (kernels default, glue verified) has no leading-splat kernel" in \
        _no_popping_ratio(WithMaps(), ev("auto"), cuda)
    assert why(WithMaps(), ev("auto"), cuda, Renderer(kernels="v2")) == ""
    assert _no_popping_ratio(WithMaps(), ev("on"), cuda) == ""
    assert _no_popping_ratio(WithMaps(), ev("off"), cpu) == "eval.popping_ratio=off"
    assert "'plugin'" in _no_popping_ratio(Without(), ev("on"), cpu)
