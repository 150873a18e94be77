"""The four built-in methods: few-step fits, save/load/resume, non-finite errors."""

import json

import pytest
import torch

from baselines import create_method
from smgs.data.patterns import pattern_scene
from smgs.train import NonFiniteError, pattern_config, to_dict
from smgs.train.gaussians import PARAM_NAMES

CPU = torch.device("cpu")   # these tests run on the CPU explicitly (tests/test_device.py checks the plumbing)
METHODS = ("3dgs", "gef_only", "softmax_only", "softmax_gs")


def _config(method, steps=40, cap=4, **optim):
    cfg = to_dict(pattern_config(method, cap=cap, steps=steps))
    # faster colour/position rates than the paper's so a few steps show progress at 16x16
    cfg["optim"].update({"sh0_lr": 0.02, "means_lr": 1e-3, **optim})
    # large overlapping splats (not the Table 1 init's σ = 0.05, under a pixel at 16x16)
    cfg["gaussians"].update(flat_spacing=0.05, flat_scale=0.1)
    return cfg


@pytest.mark.parametrize("method", METHODS)
def test_few_step_fit_decreases_loss(method):
    scene = pattern_scene("circle4", 16)
    m = create_method(method, scene, _config(method, alpha_lr=1e-2, beta_lr=1e-2, gamma_lr=1e-2), device=CPU)
    raw0 = {k: v.detach().clone() for k, v in m.trainer.gaussians.params.items()}
    losses = [m.train_step(s)["loss"] for s in range(40)]
    assert sum(losses[-5:]) / 5 < 0.95 * sum(losses[:5]) / 5
    assert m.num_gaussians() == 4
    raw = m.trainer.gaussians.params
    # only the mode's own parameters move
    uses = {"alpha": method in ("gef_only", "softmax_gs"), "beta": method in ("softmax_only", "softmax_gs")}
    for name, used in uses.items():
        assert (not torch.equal(raw[name].detach(), raw0[name])) == used, name
    out = m.render(scene.test[0].camera)
    assert out.rgb.shape == (16, 16, 3) and not out.rgb.requires_grad
    d = m.describe()
    assert d["hparams"] == "3dgs2023+softmaxgs_patterns" and d["config"]["mode"] == method
    assert any("no SfM" in line for line in d["plan"])


@pytest.mark.parametrize("backend", ["cpu", "reference"])   # the re-sorting window's backward, the exact order
def test_stopthepop_trains_with_the_per_pixel_order(backend):
    from smgs.raster import cpu

    if backend == "cpu" and not cpu.is_available():
        pytest.skip(f"cpu backend unavailable: {cpu.unavailable_reason()}")
    scene = pattern_scene("circle4", 12)
    cfg = _config("3dgs", steps=6)
    del cfg["sort"]     # the method fixes it
    cfg["backend"] = backend
    m = create_method("stopthepop", scene, cfg, device=CPU)
    assert m.config.mode == "3dgs" and m.config.sort == "per_pixel"
    losses = [m.train_step(s)["loss"] for s in range(6)]
    assert all(torch.isfinite(torch.tensor(losses)))
    assert not torch.equal(m.trainer.gaussians.params["means"].detach(),
                           create_method("stopthepop", scene, cfg, device=CPU)
                           .trainer.gaussians.params["means"].detach())
    assert m.describe()["config"]["sort"] == "per_pixel"


def test_densification_grows_to_the_cap():
    scene = pattern_scene("rect4", 16)
    cfg = _config("softmax_gs", steps=30, cap=9)
    cfg["densify"].update(refine_start=2, refine_every=5, grad_threshold=1e-6)
    m = create_method("softmax_gs", scene, cfg, device=CPU)
    counts = [m.train_step(s)["num_gaussians"] for s in range(30)]
    assert counts[0] == 4 and max(counts) == 9


def _resume_config():
    cfg = _config("softmax_gs", steps=12, cap=8)
    # exercise densification and an opacity reset inside the resumed stretch
    cfg["densify"].update(refine_start=2, refine_every=3, grad_threshold=1e-6, reset_every=7)
    return cfg


def test_save_load_resume_is_exact(tmp_path):
    scene = pattern_scene("oval4", 12)
    a = create_method("softmax_gs", scene, _resume_config(), device=CPU)
    for s in range(12):
        a.train_step(s)
    b = create_method("softmax_gs", scene, _resume_config(), device=CPU)
    for s in range(5):
        b.train_step(s)
    b.save(tmp_path / "ck")
    manifest = json.loads((tmp_path / "ck" / "checkpoint.json").read_text())
    assert manifest["step"] == 5 and manifest["hparams"] == "3dgs2023+softmaxgs_patterns"
    c = create_method("softmax_gs", scene, _resume_config(), device=CPU)
    c.load(tmp_path / "ck")
    with pytest.raises(ValueError, match="steps are done"):
        c.train_step(0)
    for s in range(5, 12):
        c.train_step(s)
    assert a.num_gaussians() == c.num_gaussians()
    for name in PARAM_NAMES:
        assert torch.equal(a.trainer.gaussians.params[name], c.trainer.gaussians.params[name]), name
    sa, sc = a.trainer.optimizer.state_dict()["groups"], c.trainer.optimizer.state_dict()["groups"]
    for name in sa:
        assert torch.equal(sa[name]["exp_avg_sq"], sc[name]["exp_avg_sq"]), name
    with pytest.raises(ValueError, match="method"):
        create_method("3dgs", scene, _config("3dgs"), device=CPU).load(tmp_path / "ck")


def test_non_finite_parameter_names_group_and_step():
    scene = pattern_scene("circle4", 12)
    m = create_method("softmax_gs", scene, _config("softmax_gs"), device=CPU)
    m.train_step(0)
    with torch.no_grad():
        m.trainer.gaussians.params["beta"][1] = float("nan")
    with pytest.raises(NonFiniteError, match=r"'beta' at step 1") as e:
        m.train_step(1)
    assert e.value.group == "beta" and e.value.step == 1


def test_non_finite_gradient_is_caught_after_the_step():
    scene = pattern_scene("circle4", 12)
    m = create_method("3dgs", scene, _config("3dgs"), device=CPU)
    m.trainer.gaussians.params["scales"].register_hook(lambda g: torch.full_like(g, float("inf")))
    with pytest.raises(NonFiniteError, match=r"'scales' at step 0"):
        m.train_step(0)
