"""The popping ratio (smgs.metrics.consistency.popping): 1 ± noise without a flip, a pop where the
global order flips, none for the per-pixel order where the geometry decides the order."""

import pytest
import torch

from smgs.metrics.consistency.popping import (POP_METHODS, flip_pair, flip_scenes, orbit_path, popping_ratio,
                                              popping_table)

METHODS = {m.name: m for m in POP_METHODS}


@pytest.fixture(scope="module")
def ratios():
    cams = orbit_path(n_frames=16, width=40, height=30, focal=38.0)
    want = tuple(METHODS[n] for n in ("3dgs", "stopthepop", "softmax_only"))
    res, frames = popping_table(methods=want, cameras=cams, keep_frames=True)
    return {(r.scene, r.method): r for r in res}, frames


def test_the_ratio_is_the_change_at_the_flip_over_the_median_elsewhere():
    assert popping_ratio([1.0, 2.0, 50.0, 3.0], 2) == (25.0, 50.0, 2.0)
    assert popping_ratio([1.0, 2.0, 50.0, 1.0, 3.0], 2) == (50.0 / 1.5, 50.0, 1.5)
    assert popping_ratio([0.0, 0.0, 0.0], 1) == (1.0, 0.0, 0.0)
    with pytest.raises(ValueError, match="not one of"):
        popping_ratio([1.0, 2.0], 2)


def test_each_flip_scene_swaps_its_centres_between_the_middle_frames_and_the_control_never():
    cams = orbit_path(n_frames=10)
    for s in flip_scenes().values():
        assert flip_pair(s, cams) == (4 if s.has_flip else None), s.name
    with pytest.raises(ValueError, match="even"):
        orbit_path(n_frames=9)


def test_no_flip_gives_a_ratio_of_one(ratios):
    res, _ = ratios
    for m in ("3dgs", "stopthepop", "softmax_only"):
        assert res[("control", m)].ratio == pytest.approx(1.0, abs=0.15), m


def test_vanilla_pops_at_every_flip_and_per_pixel_order_removes_only_the_crossing_pop(ratios):
    res, frames = ratios
    for s in ("coplanar_pair", "crossing_30", "coplanar_four", "opaque_pair"):
        assert res[(s, "3dgs")].ratio > 50, s
    # crossing planes: the geometry orders every pixel, so the per-pixel sort does not pop
    assert res[("crossing_30", "stopthepop")].ratio < 2
    # coplanar: equal peak depths leave the per-pixel sort nothing to order by: the global pop stays
    for s in ("coplanar_pair", "coplanar_four", "opaque_pair"):
        assert res[(s, "stopthepop")].ratio == pytest.approx(res[(s, "3dgs")].ratio, rel=1e-6), s
    # and the frames differ between the methods where they should
    k = res[("crossing_30", "3dgs")].flip_index
    assert not torch.allclose(frames[("crossing_30", "3dgs")][k], frames[("crossing_30", "stopthepop")][k])


def test_softmax_competition_removes_the_pair_pops(ratios):
    res, _ = ratios
    for s in ("coplanar_pair", "crossing_30", "opaque_pair"):
        assert res[(s, "softmax_only")].ratio < 3, s
