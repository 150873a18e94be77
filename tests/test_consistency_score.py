"""View-consistency scores: static pairs, popping (3DGS vs Softmax-GS), shared masks, Table 4 rows."""

from __future__ import annotations

import json
import math

import pytest
import torch

from smgs.camera import Camera
from smgs.metrics.consistency import consistency_row, consistency_rows, interpolate_trajectory, score_consistency
from smgs.metrics.image import evaluate_images
from smgs.metrics.result import Missing
from smgs.raster import rasterize

W, H = 96, 72

# Two flat Gaussians in the plane z = 0, overlapping in the middle, red and blue. Orbiting the
# camera about the y axis swaps their depth order when it crosses θ = 0 (paper Fig. 1): vanilla
# compositing switches the overlap from one colour to the other, softmax competition (β 5, γ 1,
# docs/studies/popping.md) blends two coplanar splats independently of their order.
MEANS = torch.tensor([[-0.12, 0.0, 0.0], [0.12, 0.0, 0.0]])
QUATS = torch.tensor([[1.0, 0.0, 0.0, 0.0]] * 2)
SCALES = torch.tensor([[0.3, 0.25, 0.002]] * 2)
OPAC = torch.tensor([0.9, 0.9])
COLORS = torch.tensor([[0.9, 0.2, 0.1], [0.1, 0.3, 0.9]])


def orbit(deg: float) -> Camera:
    th = math.radians(deg)
    return Camera.look_at([2 * math.sin(th), 0.0, -2 * math.cos(th)], [0, 0, 0], [0, -1, 0], 80, 80, W, H)


def splat_render(mode: str):
    def render(cam: Camera):
        out = rasterize(MEANS, QUATS, SCALES, OPAC, COLORS, cam, alpha=torch.ones(2), beta=torch.full((2,), 5.0),
                        gamma=torch.ones(2), mode=mode, backend="auto")
        return out.rgb, out.depth

    return render


@pytest.fixture(scope="module")
def trajectory():
    # 10 frames from -3° to +3°: the order flips between frames 4 and 5. (FLIP dominates the cost:
    # ~20-40 ms per 96×72 map on this machine, so the trajectory is kept short.)
    return interpolate_trajectory([orbit(-3.0), orbit(3.0)], n_between=8)


@pytest.fixture(scope="module")
def short_trajectory():
    return interpolate_trajectory([orbit(-1.0), orbit(1.0)], n_between=3)  # 5 frames


@pytest.mark.parametrize("estimator", ["geometric", "opencv"])
def test_static_pair_scores_zero(estimator):
    cams = [orbit(1.0)] * 9
    res = score_consistency({"3dgs": splat_render("3dgs")}, cams, steps=(7, 1), estimator=estimator, border=8)
    for s in (1, 7):
        sc = res["3dgs"][s]
        assert sc.mse == 0.0 and sc.flip == 0.0 and sc.n_empty == 0, (s, sc.mse, sc.flip)


@pytest.mark.parametrize("estimator", ["geometric", "opencv"])
def test_popping_scores_worse_under_3dgs_than_softmax_gs(trajectory, estimator):
    renders = {"3dgs": splat_render("3dgs"), "softmax_gs": splat_render("softmax_gs")}
    res = score_consistency(renders, trajectory, steps=(7, 1), estimator=estimator, border=8)
    for s in (1, 7):
        v, sm = res["3dgs"][s], res["softmax_gs"][s]
        assert v.mask == sm.mask == "shared:3dgs,softmax_gs"
        assert [p.valid_fraction for p in v.per_pair] == [p.valid_fraction for p in sm.per_pair]
        assert v.mse > 20 * sm.mse, (s, v.mse, sm.mse)
        assert v.flip > 1.5 * sm.flip, (s, v.flip, sm.flip)
    # the pop is at the order flip: the short-range pair (4, 5) carries vanilla's error
    short = {p.i: p.mse for p in res["3dgs"][1].per_pair}
    assert short[4] > 50 * max(m for i, m in short.items() if i != 4)
    soft = {p.i: p.mse for p in res["softmax_gs"][1].per_pair}
    assert soft[4] < 10 * max(m for i, m in soft.items() if i != 4) + 1e-6


def test_shared_mask_and_min_flip_subtraction(short_trajectory):
    trajectory = short_trajectory
    def holed(cam):  # same images, but no depth in a corner: the geometric flow is invalid there
        rgb, depth = splat_render("3dgs")(cam)
        depth = depth.clone()
        depth[:36, :48] = 0
        return rgb, depth

    renders = {"a": splat_render("3dgs"), "b": holed}
    own = score_consistency(renders, trajectory, steps=(1,), border=8, shared_mask=False)
    shared = score_consistency(renders, trajectory, steps=(1,), border=8)
    fa = [p.valid_fraction for p in own["a"][1].per_pair]
    fb = [p.valid_fraction for p in own["b"][1].per_pair]
    assert all(b < a for a, b in zip(fa, fb)) and own["a"][1].mask == "own"
    assert [p.valid_fraction for p in shared["a"][1].per_pair] == fb
    # same images, same mask: the same MSE (FLIP differs a little: its filters see the hole's warp)
    assert shared["a"][1].mse == shared["b"][1].mse
    sub = score_consistency(renders, trajectory, steps=(1,), border=8, flip_min_subtraction=True)
    assert sub["a"][1].flip_name == "flip_minsub"
    for m in "ab":
        assert 0.0 <= sub[m][1].flip < shared[m][1].flip and sub[m][1].mse == shared[m][1].mse
    copies = {"a": renders["a"], "a2": splat_render("3dgs")}  # minus the per-pixel minimum: zero
    sub = score_consistency(copies, trajectory, steps=(1,), border=8, flip_min_subtraction=True)
    assert sub["a"][1].flip == 0.0 == sub["a2"][1].flip
    with pytest.raises(ValueError, match="two methods"):
        score_consistency({"a": renders["a"]}, trajectory, steps=(1,), flip_min_subtraction=True)


def test_table4_row(trajectory, tmp_path):
    render = splat_render("softmax_gs")
    gt = render(orbit(0.5))[0] * 0.9
    views = [(orbit(0.5), gt)]
    row = consistency_row(render, trajectory, scene="toy", method="softmax_gs", test_views=views, border=8)
    expected = evaluate_images([render(orbit(0.5))[0]], [gt], lpips=Missing("-"), flip=False).psnr[0]
    assert row.psnr == pytest.approx(expected)
    assert row.step == 7 and row.mse == row.scores[7].mse and row.flip == row.scores[7].flip
    assert set(row.scores) == {1, 7} and row.estimator == "geometric" and row.flip_name == "flip"
    assert row.scores[7].mask == "own" and row.trajectory["n_frames"] == 10
    blob = json.dumps(row.to_json())
    assert '"flip":' in blob and '"scene": "toy"' in blob
    short = interpolate_trajectory([orbit(-1.0), orbit(1.0)], n_between=3)  # 5 frames: no (i, i+7)
    rows = consistency_rows({"m": render}, short, scene="toy", border=8, steps=(1,))
    assert isinstance(rows["m"].psnr, Missing) and isinstance(rows["m"].mse, Missing)
    assert "no pair at step 7" in rows["m"].mse.reason and not isinstance(rows["m"].scores[1].mse, Missing)
    cams = consistency_rows({"m": render}, trajectory.cameras()[:3], scene="toy", border=8, steps=(1,),
                            table_step=1)["m"]  # a plain camera path works too
    assert cams.trajectory == {"n_frames": 3} and len(cams.scores[1].per_pair) == 2
    traj_path = tmp_path / "trajectory.json"
    trajectory.save(traj_path)
    assert json.loads(traj_path.read_text())["n_between"] == 8


def leader_render(mode: str, backend: str = "reference"):
    def render(cam: Camera):
        return rasterize(MEANS, QUATS, SCALES, OPAC, COLORS, cam, alpha=torch.ones(2), beta=torch.full((2,), 5.0),
                         gamma=torch.ones(2), mode=mode, backend=backend, leaders=True)

    return render


def test_popping_ratio_where_the_leading_splats_swap(trajectory):
    """The pair crosses its depth-order flip: under 3DGS the pixels whose two leading splats swap
    carry the error; under Softmax-GS they cost about what the other pixels cost. Renders without
    the leading-splat map leave the ratio missing, with why."""
    renders = {"3dgs": leader_render("3dgs"), "softmax_gs": leader_render("softmax_gs"),
               "no_map": splat_render("3dgs")}
    res = score_consistency(renders, trajectory, steps=(7, 1), border=8, quantize=False)
    for s in (1, 7):
        v, sm = res["3dgs"][s], res["softmax_gs"][s]
        assert 0 < v.popped_fraction < 0.5 and 0 < sm.popped_fraction < 0.5
        assert v.pop_ratio > 20, (s, v.pop_ratio)
        assert sm.pop_ratio < 5, (s, sm.pop_ratio)
        assert isinstance(res["no_map"][s].pop_ratio, Missing)
        assert "leading-splat map" in res["no_map"][s].pop_ratio.reason
        assert json.loads(json.dumps(v.to_json()))["pop_ratio"] == v.pop_ratio
    # only the pair across the flip (4, 5) has popped pixels at step 1
    popped = {p.i: p.pop.popped for p in res["3dgs"][1].per_pair}
    assert popped[4] > 0 and all(n == 0 for i, n in popped.items() if i != 4)


def test_no_flip_no_popped_pixel(short_trajectory):
    """-1° … +1° of a pair far apart in depth: the leaders never swap; the ratio is missing, said why."""
    far = MEANS.clone()
    far[1, 2] = 0.8

    def render(cam):
        return rasterize(far, QUATS, SCALES, OPAC, COLORS, cam, mode="3dgs", backend="reference", leaders=True)

    sc = score_consistency({"3dgs": render}, short_trajectory, steps=(1,), border=8, quantize=False)["3dgs"][1]
    assert sc.popped_fraction == 0.0
    assert isinstance(sc.pop_ratio, Missing) and "swapped" in sc.pop_ratio.reason


def test_leader_warp_and_swap_by_hand():
    import numpy as np

    from smgs.metrics.consistency.leaders import pair_pop, pooled_ratio, swapped, warp_leaders

    src = np.full((4, 5, 2), -1, dtype=np.int64)
    src[1, 2] = (7, 3)
    flow = np.zeros((4, 5, 2), np.float32)
    flow[..., 0] = 1.0                          # target pixel p shows the source at p + (1, 0)
    warped = warp_leaders(src, flow)
    assert warped[1, 1].tolist() == [7, 3] and warped[1, 2].tolist() == [-1, -1]
    assert (warped[:, 4] == -1).all()           # outside the source
    tgt = np.full((4, 5, 2), -1, dtype=np.int64)
    tgt[1, 1] = (3, 7)
    tgt[2, 2] = (3, 7)
    assert swapped(warped, tgt).sum() == 1 and swapped(warped, tgt)[1, 1]
    se = np.ones((4, 5))
    se[1, 1] = 10.0
    c = pair_pop(se, np.ones((4, 5), bool), src, tgt, flow)
    assert (c.popped, c.rest) == (1, 19)
    ratio, share = pooled_ratio([c, c])
    assert ratio == pytest.approx(10.0) and share == pytest.approx(0.05)
