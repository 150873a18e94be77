"""Trainer step bookkeeping: the periodic finite check, statistics skipped at a full cap."""

import pytest
import torch

from smgs.data.patterns import pattern_scene
from smgs.train import NonFiniteError, TrainConfig, from_dict, pattern_config, to_dict
from smgs.train.trainer import Trainer


def _trainer(mode="3dgs", cap=4, **over) -> Trainer:
    cfg = to_dict(pattern_config(mode, cap=cap, steps=50))
    cfg.update(over)
    return Trainer(pattern_scene("circle4", 16), from_dict(TrainConfig, cfg), device="cpu")


def test_periodic_finite_check_names_group_step_and_delay():
    tr = _trainer(check_finite_every=4)
    tr.train_step(0)
    with torch.no_grad():           # hidden from the loss: the Gaussian is moved behind the camera
        tr.gaussians.params["means"][0] = torch.tensor([0.0, 0.0, -5.0])
        tr.gaussians.params["alpha"][0] = float("nan")
    tr.train_step(1)
    tr.train_step(2)                # iteration 3: no check
    with pytest.raises(NonFiniteError, match=r"'alpha' at step 3.*every 4 steps.*at step 0 or later") as e:
        tr.train_step(3)            # iteration 4: checked
    assert e.value.group == "alpha" and e.value.step == 3


def test_statistics_skipped_only_while_the_cap_is_full():
    tr = _trainer(cap=4)
    assert len(tr.gaussians) == 4 and not tr.strategy.wants_stats(4)
    tr.train_step(0)
    assert tr.strategy.grad2d.numel() == 0          # nothing accumulated
    tr = _trainer(cap=8)
    tr.train_step(0)
    assert tr.strategy.grad2d.numel() == 4 and tr.strategy.count.sum() > 0
    tr = _trainer(cap=4, densify={"budget_kind": "cap", "cap": 4, "reset_every": 3000})
    assert tr.strategy.wants_stats(4)               # size pruning reads the screen radii


def test_stage_timings_only_when_profiling_and_the_step_is_the_same():
    """``profile`` adds each stage's time and the compiled kernels' (bench/train.py, bench/train_step.py)
    and changes nothing the step computes."""
    quiet, timed = _trainer("softmax_gs"), _trainer("softmax_gs")
    timed.profile = True
    for s in range(3):
        a, b = quiet.train_step(s), timed.train_step(s)
        assert a == b
    assert set(quiet.timings.values()) == {0.0} and quiet.kernel_clock.seconds == {}
    assert set(timed.timings) == {"render", "loss", "backward", "optim", "strategy"}
    assert all(v > 0 for v in timed.timings.values()), timed.timings
    # the compiled kernels inside them (bench/train_step.py's split), each way
    kernels = timed.kernel_clock.seconds
    assert set(kernels) == {"projection+SH fwd", "projection+SH bwd", "composite fwd", "composite bwd", "loss"}
    assert all(v > 0 for v in kernels.values()), kernels
    assert kernels["composite fwd"] + kernels["projection+SH fwd"] < timed.timings["render"]
    assert kernels["composite bwd"] + kernels["projection+SH bwd"] < timed.timings["backward"]
    torch.testing.assert_close(quiet.gaussians.means, timed.gaussians.means, rtol=0, atol=0)


@pytest.mark.parametrize("scope", ["pixel", "patch"])
def test_the_k_max_scope_reaches_the_renderer(monkeypatch, scope):
    """TrainConfig.k_max_scope (docs/kmax-scope.md) is what every render of the trainer uses."""
    import smgs.train.trainer as trainer_mod

    seen = []
    real = trainer_mod.rasterize

    def spy(*a, **kw):
        seen.append((kw.get("k_max"), kw.get("k_max_scope")))
        return real(*a, **kw)

    monkeypatch.setattr(trainer_mod, "rasterize", spy)
    tr = _trainer("softmax_gs", k_max=7, k_max_scope=scope)
    tr.train_step(0)
    tr.render(tr.scene.test[0].camera if tr.scene.test else tr.scene.train[0].camera)
    assert seen and set(seen) == {(7, scope)}
