"""Models of 0, 1 and a handful of Gaussians train: a step, densification (clone, split), pruning,
the opacity reset and MCMC relocation and growth take them without an exception, in every mode and
in StopThePop's per-pixel order, and a model pruned to nothing mid-run goes on training (a
collapsed run must finish and be reported, not crash: docs/studies/fox-collapse.md)."""

from __future__ import annotations

import math

import pytest
import torch

from smgs.data import load_scene
from smgs.train import TrainConfig, from_dict
from smgs.train.gaussians import Gaussians
from smgs.train.trainer import Trainer

STEPS = 8
MODES_SORTS = [("3dgs", "global"), ("gef_only", "global"), ("softmax_only", "global"), ("softmax_gs", "global"),
               ("3dgs", "per_pixel")]


@pytest.fixture(scope="module")
def scene():
    return load_scene("procedural", n_views=4, width=32, height=24)


def _densify(strategy: str, **over) -> dict:
    if strategy == "mcmc":   # relocation and growth every 2 steps (at least one more each), up to 8
        return {"budget_kind": "mcmc", "cap": 8, "refine_start": 1, "refine_every": 2, **over}
    # every Gaussian a candidate (threshold ~0): clones and splits every 2 steps, reset every 5
    return {"budget_kind": "full", "refine_start": 1, "refine_every": 2, "reset_every": 5, "grad_threshold": 1e-12, **over}


def _trainer(scene, mode: str, sort: str, n: int, densify: dict) -> Trainer:
    cfg = from_dict(TrainConfig, {"mode": mode, "sort": sort, "steps": STEPS, "densify": densify})
    g = torch.Generator().manual_seed(n)
    pts = 0.3 * torch.randn(n, 3, generator=g)
    gs = Gaussians.from_points(pts, torch.rand(n, 3, generator=g), cfg.gaussians, scene.extent, 1, device="cpu")
    return Trainer(scene, cfg, gs, device="cpu")


@pytest.mark.parametrize("n", [0, 1, 3])
@pytest.mark.parametrize("strategy", ["default", "mcmc"])
@pytest.mark.parametrize("mode,sort", MODES_SORTS)
def test_zero_one_and_few_gaussians_train(scene, mode, sort, strategy, n):
    tr = _trainer(scene, mode, sort, n, _densify(strategy))
    events = set()
    for s in range(STEPS):
        logs = tr.train_step(s)
        assert math.isfinite(logs["loss"]), (s, logs)
        events |= {k for k in ("cloned", "split", "opacity_reset", "added", "relocated") if logs.get(k)}
    if n == 0:   # nothing to densify from: the model stays empty and renders the background
        assert len(tr.gaussians) == 0
        out = tr.render(scene.test[0].camera)
        assert not out.alpha.any()
    elif strategy == "default":
        assert events & {"cloned", "split"} and "opacity_reset" in events and len(tr.gaussians) > n
    else:
        assert "added" in events and len(tr.gaussians) > n


@pytest.mark.parametrize("mode,sort", MODES_SORTS)
def test_a_model_pruned_to_nothing_goes_on_training(scene, mode, sort):
    """Every Gaussian under the pruning opacity (0.5 > the initial 0.1): the first refinement
    removes them all, says so (pruned as transparent), and the steps after it run on none."""
    tr = _trainer(scene, mode, sort, 5, _densify("default", prune_opacity=0.5, grad_threshold=1.0))
    logs = [tr.train_step(s) for s in range(STEPS)]
    assert logs[1]["pruned"] == logs[1]["pruned_transparent"] == 5 and logs[1]["pruned_big"] == 0
    assert len(tr.gaussians) == 0 and all(math.isfinite(x["loss"]) for x in logs)
    assert logs[-1]["num_gaussians"] == 0.0
