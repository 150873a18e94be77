"""Gaussians: activations, initial values, γ scaling; config dicts and presets."""

import dataclasses
import math

import pytest
import torch

from smgs.train import (BUDGETS, HPARAMS, GaussianConfig, ParamInit, TrainConfig, densify_config,
                        from_dict, hparams, pattern_config, to_dict)
from smgs.train.gaussians import Gaussians, flat_layout, knn_scale


def _gaussians(cfg=None, extent=4.0, n=5):
    pts = torch.randn(n, 3)
    return Gaussians.from_points(pts, torch.rand(n, 3), cfg or GaussianConfig(), extent, sh_degree=3, device="cpu")


def test_default_activations_and_initial_values():
    g = _gaussians(extent=4.0)
    # α = 1 is the plain Gaussian (vanilla 3DGS); β = 1; γ = 3 per splat size: γ_world = 3/σ_i.
    torch.testing.assert_close(g.alpha, torch.ones(5))
    torch.testing.assert_close(g.beta, torch.ones(5))
    torch.testing.assert_close(g.gamma, 3.0 / g.scales.mean(1))
    torch.testing.assert_close(g.gamma_rel, 12.0 / g.scales.mean(1))  # stored relative to the extent
    g = _gaussians(GaussianConfig(gamma=ParamInit(1.0), gamma_unit="extent"), extent=4.0)
    torch.testing.assert_close(g.gamma_rel, torch.ones(5))
    torch.testing.assert_close(g.gamma, torch.full((5,), 0.25))     # γ_world = γ / extent
    torch.testing.assert_close(g.opacities, torch.full((5,), 0.1))
    torch.testing.assert_close(g.scales, torch.exp(g.params["scales"]))
    assert g.params["shN"].shape == (5, 15, 3)
    # exp activations: the raw values are logs, so Adam steps are ratios
    torch.testing.assert_close(g.params["beta"], torch.zeros(5))
    assert g.params["quats"][:, 0].eq(1).all() and g.params["quats"][:, 1:].eq(0).all()


def test_gamma_is_scale_aware():
    """Scaling a scene (positions and extent) by k leaves γ·|Δd| unchanged."""
    pts, cols = torch.randn(6, 3), torch.rand(6, 3)
    for unit in ("splat", "extent"):
        cfg = GaussianConfig(gamma_unit=unit)
        for k in (0.5, 3.0):
            g1 = Gaussians.from_points(pts, cols, cfg, 2.0, sh_degree=0, device="cpu")
            gk = Gaussians.from_points(pts * k, cols, cfg, 2.0 * k, sh_degree=0, device="cpu")
            dd = 0.3
            torch.testing.assert_close(g1.gamma * dd, gk.gamma * (dd * k))


def test_gamma_splat_unit_follows_the_splat_size():
    """Decay length = initial splat size / gamma.init, for each Gaussian; softplus inverts too."""
    scales = torch.tensor([[0.1] * 3, [0.4] * 3])
    for act in ("exp", "softplus"):
        cfg = GaussianConfig(gamma=ParamInit(2.0, act))
        g = Gaussians.from_points(torch.zeros(2, 3), torch.rand(2, 3), cfg, 5.0, sh_degree=0,
                                  scales=scales, device="cpu")
        torch.testing.assert_close(g.gamma, torch.tensor([20.0, 5.0]))
    with pytest.raises(ValueError, match="gamma_unit"):
        Gaussians.from_points(torch.zeros(1, 3), torch.rand(1, 3), GaussianConfig(gamma_unit="x"), 1.0,
                              sh_degree=0, device="cpu")
    pg = pattern_config("softmax_gs", 4).gaussians          # Table 1 unchanged: γ_rel = 1
    assert (pg.gamma_unit, pg.gamma.init) == ("extent", 1.0)
    import yaml
    from pathlib import Path
    ds = yaml.safe_load((Path(__file__).parents[1] / "configs/dataset/patterns.yaml").read_text())
    pg = from_dict(GaussianConfig, ds["train"]["gaussians"])  # the runner's Table 1 path too
    assert (pg.gamma_unit, pg.gamma.init) == ("extent", 1.0)


def test_softplus_activation_and_colour_init():
    cfg = GaussianConfig(alpha=ParamInit(2.5, "softplus"), beta=ParamInit(0.3, "softplus"))
    g = _gaussians(cfg)
    torch.testing.assert_close(g.alpha, torch.full((5,), 2.5))
    torch.testing.assert_close(g.beta, torch.full((5,), 0.3))
    cols = torch.tensor([[0.0, 0.5, 1.0]])
    g = Gaussians.from_points(torch.zeros(1, 3), cols, GaussianConfig(), 1.0, sh_degree=0, device="cpu")
    from smgs.raster.sh import SH_C0
    torch.testing.assert_close(SH_C0 * g.params["sh0"][:, 0] + 0.5, cols)
    with pytest.raises(ValueError, match="must be > 0"):
        _gaussians(GaussianConfig(beta=ParamInit(0.0)))


def test_knn_scale_and_flat_layout():
    pts = torch.tensor([[0.0, 0, 0], [1, 0, 0], [0, 2, 0], [0, 0, 3]])
    s = knn_scale(pts)
    expect0 = math.sqrt((1 + 4 + 9) / 3)
    assert abs(float(s[0]) - expect0) < 1e-5
    p = flat_layout(4, depth=1.0, spacing=0.1)
    assert torch.allclose(p[:, 2], torch.ones(4))
    assert torch.allclose(p[:, :2].mean(0), torch.zeros(2), atol=1e-7)
    d = torch.cdist(p, p) + torch.eye(4)
    assert torch.isclose(d.min(), torch.tensor(0.1))


def test_hparam_sets_are_named_and_distinct():
    real, pat = hparams("3dgs2023+softmaxgs_real"), hparams("3dgs2023+softmaxgs_patterns")
    assert (real.alpha_lr, real.beta_lr, real.gamma_lr) == (8e-4, 8e-3, 4e-4)
    assert (pat.alpha_lr, pat.beta_lr, pat.gamma_lr) == (3e-4, 3e-4, 2e-4)
    for h in (real, pat):     # 3DGS 2023 release
        assert (h.means_lr, h.means_lr_final, h.opacities_lr, h.scales_lr, h.quats_lr, h.eps) == \
            (1.6e-4, 1.6e-6, 0.05, 5e-3, 1e-3, 1e-15)
        assert h.sh0_lr == 2.5e-3 and math.isclose(h.shN_lr, 2.5e-3 / 20)
    assert set(HPARAMS) == {real.name, pat.name}
    with pytest.raises(ValueError, match="known"):
        hparams("nope")


def test_budget_presets():
    assert {k: v.get("grad_threshold") for k, v in BUDGETS.items()} == \
        {"full": 2e-4, "light": 3e-4, "mini": 5e-4, "5pct": 4e-3, "cap": 2e-4, "mcmc": None}
    assert BUDGETS["mcmc"]["strategy"] == "mcmc" and densify_config("full").strategy == "default"
    assert densify_config("cap", cap=16).cap == 16
    with pytest.raises(ValueError, match="cap"):
        densify_config("cap")
    with pytest.raises(ValueError, match="unknown budget"):
        densify_config("huge")


def test_config_from_dict_roundtrip_and_errors():
    cfg = pattern_config("gef_only", cap=16, steps=100, seed=3)
    again = from_dict(TrainConfig, to_dict(cfg))
    assert again == cfg
    c = from_dict(TrainConfig, {"mode": "3dgs", "optim": "3dgs2023+softmaxgs_patterns",
                                "densify": {"budget_kind": "mini"}, "gaussians": {"beta": {"init": 5}}})
    assert c.optim.beta_lr == 3e-4 and c.densify.grad_threshold == 5e-4
    assert c.gaussians.beta.init == 5.0 and isinstance(c.gaussians.beta.init, float)
    with pytest.raises(ValueError, match="unknown key"):
        from_dict(TrainConfig, {"loss": {"lamda_dssim": 0.1}})


def test_presets_apply_to_their_section_at_any_depth_and_alone():
    """A section with a preset (optim by name, densify by budget kind) is built from that preset first
    wherever it is built, also on its own; the renderer's constants are the trainer's defaults."""
    from smgs.raster import constants as K
    from smgs.train.config import DensifyConfig, OptimConfig

    assert from_dict(OptimConfig, {"name": "3dgs2023+softmaxgs_patterns", "beta_lr": 1e-3}) == \
        dataclasses.replace(HPARAMS["3dgs2023+softmaxgs_patterns"], beta_lr=1e-3)
    assert from_dict(DensifyConfig, {"budget_kind": "5pct", "cap": 7}) == densify_config("5pct", cap=7)
    assert from_dict(TrainConfig, {"densify": "light"}).densify == densify_config("light")
    with pytest.raises(ValueError, match="budget 'cap' needs cap"):
        from_dict(TrainConfig, {"densify": {"budget_kind": "cap"}})
    with pytest.raises(TypeError, match=r"densify\.cap='many': expected an int"):
        from_dict(TrainConfig, {"densify": {"budget_kind": "cap", "cap": "many"}})
    assert (TrainConfig().k_max, TrainConfig().t_min) == (K.DEFAULT_K_MAX, K.T_MIN)


def test_random_init_stays_inside_the_ring_of_cameras():
    """Without SfM points the cube of random points is 3DGS's (±1.3 world units for a camera
    extent of ~4.9): on a ring of cameras it lies well inside the ring. Read as ±1.3 extents it
    reached past the cameras and left points right in front of every lens (fox learned nothing)."""
    from smgs.data.procedural import make_procedural_scene
    from smgs.train.trainer import Trainer

    scene = make_procedural_scene(n_views=8, size=(32, 24), n_points=10)
    cfg = dataclasses.replace(TrainConfig(mode="3dgs", steps=1),
                              gaussians=GaussianConfig(init="random", n_random=2000))
    pts = Trainer(scene, cfg, device="cpu").gaussians.means.detach().double()
    centres = torch.stack([v.camera.center.double() for v in scene.train])
    nearest = torch.cdist(pts, centres).min().item()
    ring = (centres - centres.mean(0)).norm(dim=1).min().item()
    assert nearest > 0.5 * ring, (nearest, ring)
