"""The procedural scene: deterministic, sharp-edged, points on the surfaces, objects in view."""

from __future__ import annotations

import time

import numpy as np
import pytest
import torch

from smgs.data.procedural import Box, Sphere, make_procedural_scene, make_world, render_view


@pytest.fixture(scope="module")
def scene():
    t0 = time.perf_counter()
    s = make_procedural_scene(seed=0)
    s.meta["_seconds"] = time.perf_counter() - t0
    return s


def test_defaults_split_and_capabilities(scene):
    assert scene.meta["_seconds"] < 10  # about 0.3 s on an idle core
    views = scene.train + scene.test
    assert len(views) == 24 and len(scene.test) == 3
    assert [v.name for v in scene.test] == ["view_000", "view_008", "view_016"]
    assert all(tuple(v.image.shape) == (96, 128, 3) and v.image.dtype == torch.uint8 for v in views)
    assert scene.capabilities == {"sfm_points", "background", "trajectory", "view_dependence"}
    assert len(scene.trajectory) == 48 and scene.meta["split"].startswith("every 8th")


def test_deterministic_per_seed(scene):
    again = make_procedural_scene(seed=0)
    for a, b in zip(scene.train + scene.test, again.train + again.test):
        assert torch.equal(a.image, b.image) and torch.equal(a.camera.viewmat, b.camera.viewmat)
    assert torch.equal(scene.points, again.points) and torch.equal(scene.point_colors, again.point_colors)
    other = make_procedural_scene(n_views=8, seed=1)
    assert not torch.equal(other.points[:100], scene.points[:100])


def test_flat_colours_and_sharp_edges(scene):
    world = make_world(0)
    palette = np.concatenate([ob.colors for ob in world.objects] + [world.background[None]])
    palette = np.round(palette * 255)
    for v in scene.train[:6]:
        img = v.image.numpy().astype(np.float64)
        dist = np.abs(img[:, :, None, :] - palette[None, None]).max(-1).min(-1)
        flat = (dist <= 1).mean()
        assert flat > 0.85  # only pixels a boundary crosses mix colours
        # Boundaries are at most one mixed pixel wide: big jumps between direct neighbours exist,
        # and every mixed pixel touches a flat pixel of each of the colours it mixes.
        jump = np.abs(np.diff(img, axis=1)).max(-1)
        assert (jump > 100).sum() > 20
        mixed = dist > 1
        neighbours_flat = np.zeros_like(mixed)
        neighbours_flat[1:-1, 1:-1] = ~(mixed[:-2, 1:-1] & mixed[2:, 1:-1] & mixed[1:-1, :-2] & mixed[1:-1, 2:])
        assert (mixed[1:-1, 1:-1] <= neighbours_flat[1:-1, 1:-1]).mean() > 0.97


def test_points_lie_on_visible_surfaces(scene):
    world = make_world(0)
    p = scene.points.double().numpy()
    assert p.shape == (3000, 3)
    d = world.distance(p)
    sigma = scene.meta["point_noise"]["position_std"]
    assert np.percentile(d, 99) < 4 * sigma and np.median(d) < 2 * sigma
    c = scene.point_colors.numpy()
    assert c.min() >= 0 and c.max() <= 1
    # Every object contributes points (SfM sees all of them).
    owners = np.argmin(np.stack([ob.distance(p) for ob in world.objects]), 0)
    assert set(owners.tolist()) == set(range(len(world.objects)))


def test_cameras_see_the_objects(scene):
    world = make_world(0)
    solids = [ob for ob in world.objects if isinstance(ob, (Box, Sphere))]
    for v in scene.train + scene.test + [None]:
        cam = v.camera if v is not None else scene.trajectory[5]
        for ob in solids:
            pc = cam.viewmat[:3, :3].double().numpy() @ ob.center + cam.viewmat[:3, 3].double().numpy()
            uv = cam.K.double().numpy() @ pc
            assert pc[2] > 0 and 0 <= uv[0] / uv[2] < cam.width and 0 <= uv[1] / uv[2] < cam.height
        _, ids = render_view(world, cam, supersample=1)
        on_solids = (ids >= 1).mean()  # index 0 is the ground, -1 the background
        assert on_solids > 0.08
        assert len(set(np.unique(ids).tolist()) - {-1, 0}) >= 3  # at least three solids in every view
