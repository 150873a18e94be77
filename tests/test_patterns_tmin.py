"""The renderer's transmittance threshold ``t_min`` (default: the 3DGS rule, stop before T < 1e-4).

On the 2D patterns it decides whether saturated Softmax-GS splats can compete at all
(docs/table1): two splats at the a = 0.99 clamp leave T = 0.01·0.01, below 1e-4 in float32, so
the 3DGS rule drops the second one even where the softmax would give it the pixel.
"""

import shutil

import pytest
import torch

from smgs.raster import backend_available, rasterize_splats
from smgs.raster import constants as K
from smgs.train import Trainer, from_dict, pattern_config, to_dict
from smgs.data.patterns import pattern_scene

KEYS = ["means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma"]


def two_saturated_splats():
    """Pixel (0, 0) of a 1x1 image: a front splat F (red) 4 px from its centre, a back splat B
    (blue) at its centre, both at the a = 0.99 clamp (wide, opacity 1), 1e-3 apart in depth (the
    softmax acts: β(p_B - p_F) = 1000·0.008 = 8)."""
    return dict(means2d=torch.tensor([[4.5, 0.5], [0.5, 0.5]]), conics=torch.tensor([[1e-3, 0.0, 1e-3]] * 2),
                opacities=torch.tensor([1.0, 1.0]), colors=torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0]]),
                depths=torch.tensor([1.0, 1.001]), alpha=torch.tensor([1.0, 1.0]), beta=torch.tensor([1000.0, 1000.0]),
                gamma=torch.tensor([1.0, 1.0]))


def render(sc, backend, **kw):
    return rasterize_splats(*[sc[k] for k in KEYS], 1, 1, mode="softmax_gs", backend=backend, **kw)


def test_3dgs_rule_drops_a_splat_the_softmax_would_pick():
    sc = two_saturated_splats()
    default = render(sc, "reference").rgb[0, 0]
    off = render(sc, "reference", t_min=0.0).rgb[0, 0]
    assert torch.allclose(default, torch.tensor([0.99, 0.0, 0.0]), atol=1e-6)   # F alone: B is cut
    assert off[2] > 0.9 and off[0] < 0.1                                       # B wins the softmax
    assert render(sc, "reference", t_min=0.0).stats.n_contrib.item() == 2
    assert render(sc, "reference").stats.n_contrib.item() == 1


def test_t_min_is_validated_and_refused_where_not_supported():
    sc = two_saturated_splats()
    with pytest.raises(ValueError, match="t_min must be in"):
        render(sc, "reference", t_min=-1.0)
    if not backend_available("cuda", "cuda"):
        return
    with pytest.raises(ValueError, match="built in"):
        rasterize_splats(*[sc[k].cuda() for k in KEYS], 1, 1, mode="softmax_gs", backend="cuda", t_min=0.0)


@pytest.mark.skipif(shutil.which("c++") is None, reason="no C++ compiler: no cpu backend")
@pytest.mark.parametrize("t_min", [0.0, 0.05])
def test_cpu_matches_reference_at_another_t_min(t_min):
    g = torch.Generator().manual_seed(3)
    n, w, h = 12, 21, 17
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    sig = 2.0 + 4.0 * r(n, 2)
    sc = dict(means2d=r(n, 2) * torch.tensor([w, h]), conics=torch.stack([1 / sig[:, 0] ** 2, torch.zeros(n),
                                                                          1 / sig[:, 1] ** 2], 1),
              opacities=0.9 + 0.1 * r(n), colors=r(n, 3), depths=1 + 0.01 * r(n), alpha=0.5 + 3 * r(n),
              beta=20 * r(n), gamma=3 * r(n))
    outs, grads = [], []
    for backend in ("cpu", "reference"):
        ins = {k: v.clone().requires_grad_(True) for k, v in sc.items()}
        out = rasterize_splats(*[ins[k] for k in KEYS], w, h, mode="softmax_gs", backend=backend, t_min=t_min)
        (out.rgb * torch.linspace(0, 1, out.rgb.numel()).reshape(out.rgb.shape)).sum().backward()
        outs.append(out)
        grads.append({k: v.grad for k, v in ins.items()})
    torch.testing.assert_close(outs[0].rgb, outs[1].rgb, rtol=0, atol=2e-6)
    assert torch.equal(outs[0].stats.n_contrib, outs[1].stats.n_contrib)
    for k in KEYS:
        scale = grads[1][k].abs().max().item() + 1e-8
        assert (grads[0][k] - grads[1][k]).abs().max().item() <= 2e-5 * scale, k
    default = rasterize_splats(*[sc[k] for k in KEYS], w, h, mode="softmax_gs", backend="cpu")
    assert not torch.equal(default.stats.n_contrib, outs[0].stats.n_contrib)   # the value reached the kernel


def test_training_config_reaches_the_renderer():
    scene = pattern_scene("circle4", 12)
    renders = []
    for t_min in (K.T_MIN, 0.85):   # splats of opacity 0.1 at init: T >= 0.9 after one, 0.81 after two
        cfg = to_dict(pattern_config("softmax_gs", cap=4, steps=1))
        cfg.update(backend="reference", t_min=t_min)
        cfg["gaussians"].update(flat_spacing=0.05, flat_scale=0.1)   # overlapping splats
        tr = Trainer(scene, from_dict(type(pattern_config("3dgs", 4)), cfg))
        tr.gaussians.params["sh0"].data.normal_(generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            renders.append(tr.render(scene.train[0].camera))
    assert renders[1].stats.n_contrib.sum() < renders[0].stats.n_contrib.sum()
