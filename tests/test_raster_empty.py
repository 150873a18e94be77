"""A view with nothing in it: no Gaussian at all, or every one behind the camera. Every backend and
mode, in both orders (the global depth sort and StopThePop's per-pixel sort), renders the
background with zero alpha and depth, and ``backward()`` succeeds with zero gradients for every
input the mode uses (the trainer's collapsed models and views that miss the model entirely). The
CUDA backend's Python side is covered without a GPU in tests/test_raster_cuda_plumbing.py."""

from __future__ import annotations

import pytest
import torch

from smgs.camera import Camera
from smgs.raster import MODES, mode_flags, rasterize, rasterize_splats
from smgs.train.loss import ray_variance

BG = torch.tensor([0.2, 0.4, 0.6])
CAM = Camera.look_at([0.0, 0.0, -4.0], [0.0, 0.0, 0.0], [0.0, -1.0, 0.0], 30.0, 30.0, 24, 18)


def _model(n: int, behind: bool) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(n)
    means = 0.3 * torch.randn(n, 3, generator=g) + (torch.tensor([0.0, 0.0, -8.0]) if behind else 0.0)
    p = dict(means=means, quats=torch.randn(n, 4, generator=g), scales=torch.full((n, 3), 0.2),
             opacities=torch.full((n,), 0.5), sh=torch.rand(n, 4, 3, generator=g), alpha=torch.ones(n),
             beta=torch.ones(n), gamma=torch.ones(n), reg=torch.rand(n, 2, generator=g))
    return {k: v.requires_grad_(True) for k, v in p.items()}


@pytest.mark.parametrize("n,behind", [(0, False), (3, True)], ids=["no-gaussians", "all-behind"])
@pytest.mark.parametrize("sort", ["global", "per_pixel"])
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_nothing_in_view_renders_the_background_with_zero_gradients(backend, mode, sort, n, behind, request):
    if backend == "cpu":
        request.getfixturevalue("cpu_backend")
    use_gef, use_softmax = mode_flags(mode)
    p = _model(n, behind)
    # the trainer's regulariser sums go with the global sort (the per-pixel kernel has none)
    with_reg = use_softmax and sort == "global"
    out = rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], CAM, alpha=p["alpha"],
                    beta=p["beta"], gamma=p["gamma"], mode=mode, sh_degree=1, background=BG, backend=backend,
                    sort=sort, reg_values=p["reg"] if with_reg else None)
    assert torch.equal(out.rgb, BG.expand(18, 24, 3))
    assert not out.alpha.any() and not out.depth.any() and not out.stats.n_contrib.any()
    with torch.no_grad():   # the leading-splat map (view consistency's popping ratio): none anywhere
        lead = rasterize(p["means"], p["quats"], p["scales"], p["opacities"], p["sh"], CAM, alpha=p["alpha"],
                         beta=p["beta"], gamma=p["gamma"], mode=mode, sh_degree=1, background=BG,
                         backend=backend, sort=sort, leaders=True).leaders
    assert lead.shape == (18, 24, 2) and (lead == -1).all()
    loss = out.rgb.sum() + out.alpha.sum() + out.depth.sum()
    if with_reg:
        assert out.reg.shape == (18, 24, 5)            # Σw, Σw·v, Σw·v² of 2 values
        assert torch.equal(ray_variance(out.reg), torch.zeros(2))
        loss = loss + ray_variance(out.reg).sum()
    loss.backward()
    used = ["means", "quats", "scales", "opacities", "sh"] + (["alpha"] if use_gef else []) \
        + (["beta", "gamma"] if use_softmax else []) + (["reg"] if with_reg else [])
    for k in used:
        assert p[k].grad is not None and p[k].grad.shape == p[k].shape and not p[k].grad.any(), k


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("backend", ["reference", "cpu"])
def test_zero_projected_splats_composite_to_the_background(backend, mode, request):
    """``rasterize_splats`` with N = 0 (what a collapsed model hands the compositor), leaders too."""
    if backend == "cpu":
        request.getfixturevalue("cpu_backend")
    z = lambda *s: torch.zeros(*s, requires_grad=True)  # noqa: E731
    ins = dict(means2d=z(0, 2), conics=z(0, 3), opacities=z(0), colors=z(0, 3), depths=z(0), alpha=z(0),
               beta=z(0), gamma=z(0))
    bg = BG.clone().requires_grad_(True)
    out = rasterize_splats(*ins.values(), 24, 18, mode=mode, background=bg, backend=backend, leaders=True)
    assert torch.equal(out.rgb, BG.expand(18, 24, 3)) and out.stats.pairs_evaluated == 0
    assert (out.leaders == -1).all()
    out.rgb.sum().backward()
    assert torch.equal(bg.grad, torch.full((3,), 18.0 * 24))   # d rgb / d background = T = 1
    for k in ("means2d", "conics", "opacities", "colors", "depths"):
        assert ins[k].grad is not None and ins[k].grad.shape == ins[k].shape, k
