"""Optimiser groups, learning rates and the position schedule; row edits keep Adam state aligned."""

import math

import torch

from smgs.train import GaussianConfig, expon_lr, hparams
from smgs.train.gaussians import PARAM_NAMES, Gaussians
from smgs.train.optim import GaussianOptimizer
from smgs.train.trainer import trainable_groups


def _setup(n=4, extent=3.0, steps=1000, names=PARAM_NAMES, hp="3dgs2023+softmaxgs_real"):
    g = Gaussians.from_points(torch.randn(n, 3), torch.rand(n, 3), GaussianConfig(), extent, sh_degree=1, device="cpu")
    return g, GaussianOptimizer(g, hparams(hp), extent, steps, names)


def test_group_learning_rates():
    g, opt = _setup(extent=3.0)
    assert math.isclose(opt.lr("means"), 1.6e-4 * 3.0)      # × scene extent
    expect = {"scales": 5e-3, "quats": 1e-3, "opacities": 0.05, "sh0": 2.5e-3, "shN": 2.5e-3 / 20,
              "alpha": 8e-4, "beta": 8e-3, "gamma": 4e-4}
    for k, v in expect.items():
        assert math.isclose(opt.lr(k), v), k
    assert opt.opt.defaults["eps"] == 1e-15
    _, opt_p = _setup(hp="3dgs2023+softmaxgs_patterns")
    assert (opt_p.lr("alpha"), opt_p.lr("beta"), opt_p.lr("gamma")) == (3e-4, 3e-4, 2e-4)


def test_position_schedule_is_log_linear():
    assert math.isclose(expon_lr(0, 1e-2, 1e-4, 100), 1e-2)
    assert math.isclose(expon_lr(50, 1e-2, 1e-4, 100), 1e-3)      # geometric midpoint
    assert math.isclose(expon_lr(100, 1e-2, 1e-4, 100), 1e-4)
    assert math.isclose(expon_lr(500, 1e-2, 1e-4, 100), 1e-4)      # held after max_steps
    g, opt = _setup(extent=2.0, steps=1000)
    # the real-scene set pins 30K steps (3DGS position_lr_max_steps); patterns use the run length
    assert math.isclose(opt.update_lr(15_000), 2.0 * math.sqrt(1.6e-4 * 1.6e-6))
    g, opt = _setup(extent=2.0, steps=1000, hp="3dgs2023+softmaxgs_patterns")
    assert math.isclose(opt.update_lr(1000), 2.0 * 1.6e-6)
    assert math.isclose(opt.lr("means"), 2.0 * 1.6e-6)


def test_trainable_groups_follow_the_mode():
    assert {"alpha", "beta", "gamma"}.isdisjoint(trainable_groups("3dgs", 3))
    assert "alpha" in trainable_groups("gef_only", 3) and "beta" not in trainable_groups("gef_only", 3)
    assert {"beta", "gamma"} <= set(trainable_groups("softmax_only", 3))
    assert "alpha" not in trainable_groups("softmax_only", 3)
    assert {"alpha", "beta", "gamma"} <= set(trainable_groups("softmax_gs", 0))
    assert "shN" not in trainable_groups("softmax_gs", 0)


def test_append_keep_reset_keep_adam_moments_aligned():
    g, opt = _setup(n=3)
    for p in g.params.values():
        p.grad = torch.ones_like(p)
    opt.step()
    before = {n: opt.opt.state[g.params[n]]["exp_avg"].clone() for n in PARAM_NAMES}
    extra = {n: g.params[n].detach()[:2].clone() for n in PARAM_NAMES}
    opt.append(extra)
    assert len(g) == 5
    for n in PARAM_NAMES:
        st = opt.opt.state[g.params[n]]
        assert opt.opt.param_groups[opt.names.index(n)]["params"][0] is g.params[n]
        torch.testing.assert_close(st["exp_avg"][:3], before[n])
        assert st["exp_avg"][3:].eq(0).all() and st["exp_avg_sq"][3:].eq(0).all()
    mask = torch.tensor([True, False, True, True, False])
    opt.keep(mask)
    assert len(g) == 3
    torch.testing.assert_close(opt.opt.state[g.params["means"]]["exp_avg"][:2], before["means"][[0, 2]])
    opt.reset("opacities", torch.zeros(3))
    assert g.params["opacities"].eq(0).all()
    assert opt.opt.state[g.params["opacities"]]["exp_avg"].eq(0).all()
    # the optimiser still steps every (new) tensor
    for p in g.params.values():
        p.grad = torch.ones_like(p)
    old = g.params["means"].detach().clone()
    opt.step()
    assert not torch.equal(old, g.params["means"].detach())


def test_step_matches_torch_adam_per_group():
    """All groups in one foreach update (small models) or torch's fused Adam (large ones, switched
    here mid-run) = torch's Adam group by group, including a group that has no gradient on some
    steps (its state and step count stay put)."""
    g, opt = _setup(n=5)
    ref_params = {n: g.params[n].detach().clone().requires_grad_(True) for n in opt.names}
    ref = torch.optim.Adam([{"params": [ref_params[n]], "lr": opt.lr(n)} for n in opt.names],
                           betas=opt.cfg.betas, eps=opt.cfg.eps)
    gen = torch.Generator().manual_seed(3)
    for it in range(6):
        opt.FOREACH_MAX_NUMEL = 1 << 16 if it < 3 else 0
        for n in opt.names:
            grad = None if (n == "shN" and it % 2 == 0) else torch.randn(g.params[n].shape, generator=gen)
            g.params[n].grad = grad
            ref_params[n].grad = None if grad is None else grad.clone()
        opt.step()
        ref.step()
        for n in opt.names:
            torch.testing.assert_close(g.params[n].detach(), ref_params[n].detach(), rtol=1e-6, atol=1e-7)
    assert float(opt.opt.state[g.params["shN"]]["step"]) == 3 and float(opt.opt.state[g.params["means"]]["step"]) == 6


def test_large_cpu_models_take_torchs_fused_kernel_to_the_bit():
    """Above FOREACH_MAX_NUMEL on the CPU, the optimiser calls torch's fused Adam kernel per group
    itself (without torch.optim's per-group Python): the parameters, moments and step counts are
    torch.optim.Adam(fused=True)'s to the bit, with a group that has no gradient on some steps and a
    skipped step (a non-finite loss)."""
    g, opt = _setup(n=300)
    opt.FOREACH_MAX_NUMEL = 0
    ref_params = {n: g.params[n].detach().clone().requires_grad_(True) for n in opt.names}
    ref = torch.optim.Adam([{"params": [ref_params[n]], "lr": opt.lr(n)} for n in opt.names],
                           betas=opt.cfg.betas, eps=opt.cfg.eps, fused=True)
    gen = torch.Generator().manual_seed(5)
    for it in range(6):
        for n in opt.names:
            grad = None if (n == "shN" and it % 2 == 0) else torch.randn(g.params[n].shape, generator=gen)
            g.params[n].grad = grad
            ref_params[n].grad = None if grad is None else grad.clone()
        skip = it == 4
        opt.step(skip=torch.tensor(skip))
        if not skip:
            ref.step()
        for n in opt.names:
            assert torch.equal(g.params[n].detach(), ref_params[n].detach()), (it, n)
            mine, theirs = opt.opt.state[g.params[n]], ref.state[ref_params[n]]
            assert set(mine) == set(theirs), n
            for k in theirs:
                assert torch.equal(mine[k], theirs[k]) and mine[k].dtype == theirs[k].dtype, (it, n, k)
    assert float(opt.opt.state[g.params["means"]]["step"]) == 5
