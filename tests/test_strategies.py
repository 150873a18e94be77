"""Densification strategies register by name, the way methods do: the built-ins, an in-process
``register``, and plugins from the entry-point group ``smgs.strategies``; each strategy is a
dataclass that is its own config (the ``densify`` section's keys). A strategy defined in a package
outside smgs/ trains through ``smgs run`` without a change to the repository."""

import json
import os
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest
import torch

from plugin_dist import install, uninstall
from smgs.data.patterns import pattern_scene
from smgs.train import TrainConfig, densify_config, from_dict, to_dict
from smgs.train.config import earlier_train_keys
from smgs.train.strategies import (DefaultStrategy, FixedCount, MCMCStrategy, RefineEvent, Strategy, StrategyRun,
                                   registry, start_strategy)
from smgs.train.trainer import Trainer

ROOT = Path(__file__).resolve().parents[1]
RUN = StrategyRun(1.0, "3dgs", 0, torch.device("cpu"))

# A toy strategy as a third party would write it: its own package, its own config (keep, every).
PLUGIN = textwrap.dedent('''
    from dataclasses import dataclass
    from typing import ClassVar

    import torch

    from smgs.ranges import Range
    from smgs.train.strategies import RefineEvent, Strategy


    @dataclass
    class Thinning(Strategy):
        """Keeps the first `keep` initial Gaussians, then drops the last one every `every` steps."""
        strategy: str = "thinning"
        keep: int = 40
        every: int = 2

        RANGES: ClassVar[dict] = {"keep": Range(1, integer=True), "every": Range(1, integer=True)}

        def setup(self, run):
            self.device = run.device
            self.dropped = 0

        def describe(self):
            return [f"densification: thinning to {self.keep}, one fewer every {self.every} steps"]

        @torch.no_grad()
        def initialize(self, g, opt):
            n = len(g)
            opt.keep(torch.arange(n, device=g.means.device) < self.keep)
            return [f"thinning: kept {min(n, self.keep)} of {n}"]

        @torch.no_grad()
        def step_post_backward(self, iteration, g, opt, out, camera, lr_means):
            if iteration % self.every or len(g) < 2:
                return None
            opt.keep(torch.arange(len(g), device=g.means.device) < len(g) - 1)
            self.dropped += 1
            return RefineEvent(pruned=1)

        def state_dict(self):
            return {"kind": self.strategy, "dropped": self.dropped}

        def load_state_dict(self, state):
            self.check_kind(state.get("kind"))
            self.dropped = int(state["dropped"])
''')


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch):
    """A tiny installed distribution: a package plus a dist-info with an ``smgs.strategies`` entry point."""
    yield install(tmp_path / "site", monkeypatch, "smgs_toy_strategy", PLUGIN, registry.ENTRY_POINT_GROUP,
                  {"thinning": "smgs_toy_strategy:Thinning"})
    uninstall("smgs_toy_strategy")


def test_the_builtins_are_strategies_picked_by_name_or_by_the_budget_kind():
    assert {"default", "mcmc"} <= set(registry.list_strategies())
    assert registry.strategy_class("mcmc") is MCMCStrategy
    assert type(densify_config("full")) is DefaultStrategy and type(densify_config("mcmc", cap=8)) is MCMCStrategy
    assert type(densify_config("cap", cap=8, strategy="mcmc")) is MCMCStrategy
    with pytest.raises(ValueError, match=r"unknown densification strategy 'gsplat' \(densify.strategy\); known: "
                                         r"default, mcmc.*docs/adding-a-strategy.md"):
        densify_config("full", strategy="gsplat")


def test_a_section_key_the_strategy_lacks_is_refused_naming_its_keys():
    with pytest.raises(ValueError, match=r"the 'mcmc' strategy has no grad_threshold; its keys: budget_kind, "):
        densify_config("mcmc", cap=8, grad_threshold=1e-3)
    with pytest.raises(ValueError, match=r"unknown key\(s\) \['mcmc_noise_lr'\]"):
        from_dict(TrainConfig, {"densify": {"mcmc_noise_lr": 1.0}})
    with pytest.raises(ValueError, match=r"densify.mcmc_gate_k=-1.0: must be a finite number ≥ 0"):
        from_dict(TrainConfig, {"densify": {"budget_kind": "mcmc", "cap": 4, "mcmc_gate_k": -1}})


def test_a_result_hashes_the_section_in_its_earlier_form_with_every_builtin_key():
    """Before strategies had their own configs the densify section held every key of both: the form a
    finished result was hashed with, which a run of either built-in keeps."""
    for section in (densify_config("full"), densify_config("mcmc", cap=4)):
        earlier = earlier_train_keys(to_dict(TrainConfig(densify=section)))["densify"]
        assert {"grow_grad2d", "percent_dense", "split_n", "reset_value", "mcmc_noise_lr", "mcmc_gate_k"} <= set(earlier)
        assert earlier["strategy"] == section.strategy and "grad_threshold" not in earlier
    assert earlier["grow_grad2d"] == 2e-4 and earlier["reset_every"] is None and earlier["refine_stop"] == 25_000


def test_an_earlier_checkpoints_section_reads_as_its_strategys():
    from smgs.train.config import current_train_keys

    old = earlier_train_keys(to_dict(TrainConfig(densify=densify_config("mcmc", cap=4))))
    assert from_dict(TrainConfig, current_train_keys(old)).densify == densify_config("mcmc", cap=4)


def test_densification_off_runs_no_strategy():
    st = start_strategy(densify_config("mcmc", cap=4, enabled=False), RUN)
    assert type(st) is FixedCount and st.describe() == ["densification: off (fixed count)"]
    st.load_state_dict({"grad2d": torch.zeros(3)})   # a checkpoint of a disabled default strategy


def test_a_strategy_registered_in_process_trains_with_its_own_settings():
    @dataclass
    class Halve(Strategy):
        strategy: str = "halve"
        at: int = 2

        def step_post_backward(self, iteration, g, opt, out, camera, lr_means):
            if iteration != self.at:
                return None
            opt.keep(torch.arange(len(g)) < len(g) // 2)
            return RefineEvent(pruned=len(g))

    registry.register("halve", Halve)
    try:
        cfg = from_dict(TrainConfig, {"mode": "3dgs", "steps": 3, "densify": {"budget_kind": "cap", "cap": 64,
                                                                                "strategy": "halve", "at": 2}})
        assert type(cfg.densify) is Halve and cfg.densify.at == 2
        tr = Trainer(pattern_scene("circle4", 12), cfg, device="cpu")
        assert tr.strategy is not cfg.densify and tr.plan[-3].startswith("densification: halve (budget cap, cap 64)")
        for s in range(3):
            tr.train_step(s)
        assert len(tr.gaussians) == 2
    finally:
        registry.unregister("halve")


def test_what_is_no_strategy_dataclass_is_refused_naming_the_guide():
    registry.register("loose", object)
    try:
        with pytest.raises(TypeError, match="not a dataclass subclassing smgs.train.strategies.Strategy.*"
                                            "docs/adding-a-strategy.md"):
            densify_config("full", strategy="loose")
    finally:
        registry.unregister("loose")


def test_an_entry_point_strategy_is_listed_without_being_imported(plugin_dir, capsys):
    from smgs_cli.main import main

    assert "thinning" in registry.list_strategies() and "smgs_toy_strategy" not in sys.modules
    assert registry.plugin_source("thinning") == "plugin smgs-toy-strategy"
    assert main(["list", "strategies"]) == 0
    out = capsys.readouterr().out
    assert any(line.startswith("thinning") and "+method.train.densify.strategy=thinning (plugin smgs-toy-strategy)"
               in line for line in out.splitlines())
    assert "smgs_toy_strategy" not in sys.modules


def test_a_strategy_from_a_package_outside_smgs_trains_through_smgs_run(plugin_dir, tmp_path):
    """The plugin is installed (on the path, with its entry point); `smgs run` with
    ``+method.train.densify.strategy=thinning`` and its own keys trains with it: the 40 Gaussians it
    keeps, less the one it drops at step 2, and its plan line in the run's log."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(plugin_dir), str(ROOT)])}
    out = tmp_path / "runs"
    cmd = [sys.executable, "-m", "smgs_cli", "run", "dataset=procedural", "dataset.n_views=4", "dataset.width=32",
           "dataset.height=24", "grid.methods=[3dgs]", "seeds=1", "+method.train.densify.strategy=thinning",
           "+method.train.densify.keep=40", "protocol.steps=3", "protocol.schedule_steps=null", "eval.fps_repeats=1",
           "eval.flip=false", "eval.fractions=[1.0]", "report=false", "device=cpu", f"out_dir={out}"]
    done = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    run_dir = out / "procedural/blocks/3dgs/full/seed0"
    res = json.loads((run_dir / "results.json").read_text())
    assert res["status"] == "ok" and res["steps"] == 3 and res["num_gaussians"] == 39
    assert res["config"]["method"]["train"]["densify"] == {"strategy": "thinning", "keep": 40}
    log = (run_dir / "log.txt").read_text()
    assert "plan: densification: thinning to 40, one fewer every 2 steps" in log and "thinning: kept 40 of" in log
