"""A training step's host waits, counted on the stand-in device (tests/device_mix.py) with the lean
GPU glue: outside the renderer (whose own waits tests/test_raster_syncs.py pins), the default
strategy's step waits once, for the values it reads together after the optimiser step (the loss,
its parts, the parameters' finiteness). Not: a boolean mask per statistic, a read per loss part, a
separate finite check, a copy of the NDC scale. A refinement step and the step that draws a new
view order wait more (they edit the model or draw on the device); they are not counted here.

Also what that one read keeps: a non-finite loss stops the step naming the loss with the parameters
as they were (the optimiser step is cancelled on the device), and the periodic check still names
a group the step made non-finite.
"""

from __future__ import annotations

import pytest
import torch
from device_check import fit_config
from device_mix import OTHER, simulated_gpu

from baselines import create_method
from smgs.data.patterns import pattern_scene
from smgs.data.procedural import make_procedural_scene
from smgs.train import NonFiniteError

TRAIN = "smgs/train/"


def _train_waits(where: list[str]) -> list[str]:
    return [w for w in where if f" {TRAIN}" in w]


@pytest.mark.parametrize("method", ["3dgs", "softmax_gs"])
def test_a_step_waits_once_outside_the_renderer(monkeypatch, method):
    monkeypatch.setenv("SMGS_CUDA_GLUE", "lean")
    scene = make_procedural_scene(n_views=8, size=(24, 16), n_points=150, n_trajectory=0, supersample=1)
    cfg = {"mode": method, "steps": 100, "gaussians": {"init": "sfm"}, "sh_degree_interval": 0,
           "densify": {"refine_start": 1, "refine_every": 4, "reset_every": None}}
    with simulated_gpu(monkeypatch) as mode:
        m = create_method(method, scene, cfg, device=OTHER)
        tr = m.trainer
        counted = 0
        for s in range(7):
            fresh_order = not tr._stack           # the view order is drawn on the device this step
            refines = (s + 1) > 1 and (s + 1) % 4 == 0
            mode.reset()
            m.train_step(s)
            waits = _train_waits(mode.where)
            if fresh_order or refines:
                continue
            assert tr.strategy.grad2d.numel() and tr.strategy.count.sum().cpu() > 0   # statistics kept
            assert len(waits) == 1, "\n".join(waits)
            assert "trainer.py" in waits[0] and "tolist" in waits[0], waits[0]
            counted += 1
    assert counted >= 3


def test_a_non_finite_loss_stops_the_step_and_leaves_the_parameters(monkeypatch):
    scene = pattern_scene("circle4", 12)
    m = create_method("3dgs", scene, fit_config("3dgs"), device="cpu")
    m.train_step(0)
    tr = m.trainer
    before = {k: v.detach().clone() for k, v in tr.gaussians.params.items()}
    monkeypatch.setattr(tr.strategy, "regularizer", lambda it, g: g.params["means"].sum() * float("nan"))
    with pytest.raises(NonFiniteError, match=r"non-finite loss at step 1: loss = nan") as e:
        m.train_step(1)
    assert e.value.group == "loss"
    for k, v in tr.gaussians.params.items():
        assert torch.equal(v.detach(), before[k]), k
    assert tr.step_count == 1
