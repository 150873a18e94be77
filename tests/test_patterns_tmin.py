"""The renderer's transmittance threshold ``t_min`` (default: the 3DGS rule, stop before T < 1e-4).

The stop applies to vanilla steps only: inside the softmax head a later splat can take the pixel,
and with the stop saturated Softmax-GS splats could not compete at all on the 2D patterns
(docs/table1). Two splats at the a = 0.99 clamp leave T = 0.01·0.01 = 1e-4, which float32 rounds
to 9.99998e-5; tested without slack (as 3DGS does), the second splat is dropped in float32 and
kept in float64 (constants.T_STOP_SLACK).
"""

import shutil

import pytest
import torch

from smgs.raster import backend_available, rasterize_splats
from smgs.raster import constants as K
from smgs.train import Trainer, from_dict, pattern_config, to_dict
from smgs.data.patterns import pattern_scene

# every SIMD path of the compiled CPU kernels this host runs (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("cpu_isa")

KEYS = ["means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma"]


def saturated_splats(n: int = 2, dtype=torch.float32):
    """Pixel (0, 0) of a 1x1 image: a front splat F (red) 4 px from its centre, then back splats B
    (blue, then green) at their centres, all at the a = 0.99 clamp (wide, opacity 1), 1e-3 apart in
    depth (the softmax acts: β(p_B - p_F) = 1000·0.008 = 8)."""
    sc = dict(means2d=torch.tensor([[4.5, 0.5], [0.5, 0.5], [0.5, 0.5]]), conics=torch.tensor([[1e-3, 0.0, 1e-3]] * 3),
              opacities=torch.tensor([1.0, 1.0, 1.0]),
              colors=torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, 1.0, 0.0]]),
              depths=torch.tensor([1.0, 1.001, 1.002]), alpha=torch.ones(3), beta=torch.full((3,), 1000.0),
              gamma=torch.ones(3))
    return {k: v[:n].to(dtype) for k, v in sc.items()}


def render(sc, backend, mode="softmax_gs", **kw):
    return rasterize_splats(*[sc[k] for k in KEYS], 1, 1, mode=mode, backend=backend, **kw)


def backends():
    return ["reference"] + (["cpu"] if backend_available("cpu", "cpu") else [])


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("mode", ["3dgs", "gef_only"])
def test_two_saturated_splats_are_composited_in_float32_as_in_float64(dtype, mode):
    """T = 0.01·0.01 is exactly 1e-4, not below it: vanilla compositing keeps the second splat in
    float32 as in float64 and stops at the third; the test without slack drops it in float32 only."""
    for backend in backends() if dtype == torch.float32 else ["reference"]:
        assert render(saturated_splats(2, dtype), backend, mode).stats.n_contrib.item() == 2, backend
        assert render(saturated_splats(3, dtype), backend, mode).stats.n_contrib.item() == 2, backend
    a = torch.tensor(K.ALPHA_MAX, dtype=dtype)
    unslacked_drop = bool((1 - a) * (1 - a) < K.T_MIN)
    assert unslacked_drop == (dtype == torch.float32)   # the rounding the slack absorbs


def test_softmax_head_is_exempt_from_the_stop_and_the_vanilla_tail_is_not():
    """Three saturated splats: in the softmax head the back ones win the pixel (B, then B and G
    share it at equal p) although T is below 1e-4 before G; with k_max = 2, G is a vanilla step
    and the 3DGS stop drops it."""
    sc = saturated_splats(3)
    for backend in backends():
        out = render(sc, backend)
        assert out.stats.n_contrib.item() == 3, backend
        assert out.rgb[0, 0, 1] > 0.4 and out.rgb[0, 0, 2] > 0.4 and out.rgb[0, 0, 0] < 0.1, backend
        tail = render(sc, backend, k_max=2)
        assert tail.stats.n_contrib.item() == 2, backend
        assert tail.rgb[0, 0, 1] == 0 and tail.rgb[0, 0, 2] > 0.9, backend
        assert render(sc, backend, k_max=2, t_min=0.0).rgb[0, 0, 1] > 0, backend


def test_t_min_is_validated_and_refused_where_not_supported():
    sc = saturated_splats()
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
        out = rasterize_splats(*[ins[k] for k in KEYS], w, h, mode="softmax_gs", backend=backend, t_min=t_min,
                               k_max=3)   # the stop applies past the softmax head
        (out.rgb * torch.linspace(0, 1, out.rgb.numel()).reshape(out.rgb.shape)).sum().backward()
        outs.append(out)
        grads.append({k: v.grad for k, v in ins.items()})
    torch.testing.assert_close(outs[0].rgb, outs[1].rgb, rtol=0, atol=2e-6)
    assert torch.equal(outs[0].stats.n_contrib, outs[1].stats.n_contrib)
    for k in KEYS:
        scale = grads[1][k].abs().max().item() + 1e-8
        assert (grads[0][k] - grads[1][k]).abs().max().item() <= 2e-5 * scale, k
    default = rasterize_splats(*[sc[k] for k in KEYS], w, h, mode="softmax_gs", backend="cpu", k_max=3)
    assert not torch.equal(default.stats.n_contrib, outs[0].stats.n_contrib)   # the value reached the kernel


def test_training_config_reaches_the_renderer():
    scene = pattern_scene("circle4", 12)
    renders = []
    for t_min in (K.T_MIN, 0.85):   # splats of opacity 0.1 at init: T >= 0.9 after one, 0.81 after two
        cfg = to_dict(pattern_config("gef_only", cap=4, steps=1))   # vanilla steps: the stop applies
        cfg.update(backend="reference", t_min=t_min)
        cfg["gaussians"].update(flat_spacing=0.05, flat_scale=0.1)   # overlapping splats
        tr = Trainer(scene, from_dict(type(pattern_config("3dgs", 4)), cfg), device="cpu")
        tr.gaussians.params["sh0"].data.normal_(generator=torch.Generator().manual_seed(0))
        with torch.no_grad():
            renders.append(tr.render(scene.train[0].camera))
    assert renders[1].stats.n_contrib.sum() < renders[0].stats.n_contrib.sum()
