"""Densification on hand-made cases: clone, split, prune, cap, opacity reset, size pruning."""

import torch

from smgs.train import GaussianConfig, densify_config, hparams
from smgs.train.gaussians import PARAM_NAMES, Gaussians, inverse_sigmoid
from smgs.train.optim import GaussianOptimizer
from smgs.train.strategies import SIZE_PRUNE_3DGS, SIZE_PRUNE_SOFTMAX_GS, StrategyRun

EXTENT = 2.0


def _case(scales, opacities, grads, cap=None, size_prune=SIZE_PRUNE_3DGS, **kw):
    n = len(scales)
    pts = torch.arange(n, dtype=torch.float32)[:, None] * torch.tensor([[1.0, 0.0, 0.0]])
    g = Gaussians.from_points(pts, torch.rand(n, 3), GaussianConfig(), EXTENT, sh_degree=0,
                              scales=torch.tensor(scales, dtype=torch.float32)[:, None].expand(n, 3), device="cpu")
    with torch.no_grad():
        g.params["opacities"].copy_(inverse_sigmoid(torch.tensor(opacities)))
    opt = GaussianOptimizer(g, hparams("3dgs2023+softmaxgs_real"), EXTENT, 100)
    cfg = densify_config("cap" if cap else "full", cap=cap, size_prune=size_prune, **kw)
    st = cfg.start(StrategyRun(EXTENT, "3dgs", 0, torch.device("cpu")))
    st._ensure(n)
    st.grad2d = torch.tensor(grads, dtype=torch.float32)
    st.count = torch.ones(n)
    return g, opt, st


def test_clone_split_prune():
    small, big = 0.01 * EXTENT * 0.5, 0.01 * EXTENT * 5       # percent_dense·extent = 0.02
    g, opt, st = _case([small, big, small, small], [0.5, 0.5, 0.001, 0.5], [1e-3, 1e-3, 0.0, 1e-5])
    before = {k: v.detach().clone() for k, v in g.params.items()}
    ev = st.densify_and_prune(g, opt, prune_big=False)
    assert (ev.cloned, ev.split, ev.pruned) == (1, 1, 1)
    # kept: 0 (cloned original), 3 (below threshold); appended: clone of 0, two children of 1
    assert len(g) == 5
    means = g.params["means"].detach()
    torch.testing.assert_close(means[0], before["means"][0])
    torch.testing.assert_close(means[1], before["means"][3])
    torch.testing.assert_close(means[2], before["means"][0])        # the clone: an exact copy
    for k in PARAM_NAMES:
        if k not in ("means", "scales"):
            torch.testing.assert_close(g.params[k].detach()[3:], before[k][[1, 1]])
    # split children: scale / (0.8·2), sampled around the parent
    torch.testing.assert_close(g.scales.detach()[3:], torch.full((2, 3), big / 1.6))
    assert (means[3:] - before["means"][1]).norm(dim=1).max() < 5 * big
    assert not torch.equal(means[3], means[4])
    # statistics restart from zero after a refinement (3DGS)
    assert st.grad2d.shape == (5,) and st.grad2d.eq(0).all() and st.count.eq(0).all()


def test_cap_keeps_the_largest_gradients():
    small = 0.005
    g, opt, st = _case([small] * 4, [0.5] * 4, [3e-4, 9e-4, 5e-4, 1e-5], cap=6)
    ev = st.densify_and_prune(g, opt, prune_big=False)
    assert ev.cloned == 2 and ev.capped == 1 and len(g) == 6
    # clones of Gaussians 1 and 2 (the two largest gradients), appended in index order
    torch.testing.assert_close(g.params["means"].detach()[4:, 0], torch.tensor([1.0, 2.0]))
    g, opt, st = _case([small] * 4, [0.5] * 4, [1.0] * 4, cap=4)
    ev = st.densify_and_prune(g, opt, prune_big=False)
    assert ev.cloned == 0 and ev.capped == 4 and len(g) == 4


def test_size_pruning_threshold_relative_to_extent():
    # a Gaussian of 0.2 × extent: pruned by 3DGS's 0.1, kept by Softmax-GS's 0.4
    s = 0.2 * EXTENT
    for thr, left in ((SIZE_PRUNE_3DGS, 1), (SIZE_PRUNE_SOFTMAX_GS, 2)):
        g, opt, st = _case([0.001, s], [0.5, 0.5], [0.0, 0.0], size_prune=thr)
        st.densify_and_prune(g, opt, prune_big=True)
        assert len(g) == left
    # screen-size pruning: off by default (3DGS as released never applies its 20 px rule) ...
    g, opt, st = _case([0.001, 0.001], [0.5, 0.5], [0.0, 0.0])
    st.max_radii = torch.tensor([5.0, 25.0])
    ev = st.densify_and_prune(g, opt, prune_big=True)
    assert len(g) == 2 and ev.pruned == 0
    # ... and where it is asked for (> 20 px), only after the first reset, counted as too big
    g, opt, st = _case([0.001, 0.001], [0.5, 0.5], [0.0, 0.0], prune_screen_px=20.0)
    st.max_radii = torch.tensor([5.0, 25.0])
    st.densify_and_prune(g, opt, prune_big=False)
    assert len(g) == 2
    st.max_radii = torch.tensor([5.0, 25.0])
    ev = st.densify_and_prune(g, opt, prune_big=True)
    assert len(g) == 1 and ev.pruned == ev.pruned_big == ev.pruned_big_screen == 1 and ev.pruned_transparent == 0


def test_schedule_and_opacity_reset():
    g, opt, st = _case([0.001, 0.001], [0.5, 0.001], [0.0, 0.0], refine_start=2, refine_every=3,
                       reset_every=6, refine_stop=10)
    for p in g.params.values():
        p.grad = torch.ones_like(p)
    opt.step()
    events = {it: st.step(it, g, opt) for it in range(1, 13)}
    refined = [it for it, e in events.items() if e.pruned or e.cloned or e.split]
    assert refined == [3]           # the transparent Gaussian goes at the first refinement
    assert [it for it, e in events.items() if e.reset] == [6]       # not 12: past refine_stop
    assert not st.active(10) and st.active(9)
    torch.testing.assert_close(g.opacities.detach(), torch.full((1,), 0.01))
    assert opt.opt.state[g.params["opacities"]]["exp_avg"].eq(0).all()


def test_accumulate_uses_ndc_gradients_and_visible_ids():
    g, opt, st = _case([0.001] * 3, [0.5] * 3, [0.0] * 3)
    st._reset_stats(3)
    ids = torch.tensor([0, 2])
    grad = torch.tensor([[1.0, 0.0], [0.0, 2.0]])            # pixels
    radii = torch.tensor([[3.0, 4.0], [2.0, 2.0]])
    st.accumulate(3, ids, grad, radii, width=32, height=16)
    torch.testing.assert_close(st.grad2d, torch.tensor([16.0, 0.0, 16.0]))   # × W/2, × H/2
    torch.testing.assert_close(st.count, torch.tensor([1.0, 0.0, 1.0]))
    torch.testing.assert_close(st.max_radii, torch.tensor([4.0, 0.0, 2.0]))
    # a culled row of the dense projection (radius 0 on an axis) adds nothing; the largest radius is
    # the larger axis, as a reduction over the two would give
    st.accumulate(3, torch.tensor([0, 1, 2]), torch.tensor([[1.0, 0.0], [5.0, 5.0], [0.0, 1.0]]),
                  torch.tensor([[5.0, 0.0], [0.0, 0.0], [1.0, 6.0]]), width=32, height=16)
    torch.testing.assert_close(st.grad2d, torch.tensor([16.0, 0.0, 24.0]))
    torch.testing.assert_close(st.count, torch.tensor([1.0, 0.0, 2.0]))
    torch.testing.assert_close(st.max_radii, torch.tensor([5.0, 0.0, 6.0]))
