"""The Table 1 targets: shapes, four flat colours on black, any resolution, the flat scene."""

import pytest
import torch

from smgs.data.patterns import PATTERNS, QUADRANT_COLORS, make_pattern, pattern_mask, pattern_scene, write_targets


@pytest.mark.parametrize("name", PATTERNS)
def test_four_flat_colours_on_black(name):
    img = make_pattern(name, 64)
    assert img.shape == (64, 64, 3) and img.dtype == torch.uint8
    colours = {tuple(c) for c in img.reshape(-1, 3).tolist()}
    assert colours == {(0, 0, 0), *QUADRANT_COLORS}
    # one colour per quadrant of the shape; corners are black (the shape lies inside the frame)
    h = 32
    assert tuple(img[h - 4, h - 4].tolist()) == QUADRANT_COLORS[0]
    assert tuple(img[h - 4, h + 3].tolist()) == QUADRANT_COLORS[1]
    assert tuple(img[h + 3, h - 4].tolist()) == QUADRANT_COLORS[2]
    assert tuple(img[h + 3, h + 3].tolist()) == QUADRANT_COLORS[3]
    for y, x in ((0, 0), (0, 63), (63, 0), (63, 63)):
        assert img[y, x].eq(0).all()
    # symmetric about both centre lines (by shape, not colour)
    mask = pattern_mask(name, 64, 64)
    assert torch.equal(mask, mask.flip(0)) and torch.equal(mask, mask.flip(1))


def test_shapes_differ_and_scale_with_resolution():
    areas = {n: float(pattern_mask(n, 256, 256).double().mean()) for n in PATTERNS}
    assert abs(areas["circle4"] - 3.14159 * 0.35 ** 2) < 0.005
    assert abs(areas["rect4"] - 4 * 0.36 * 0.24) < 0.005
    assert abs(areas["oval4"] - 3.14159 * 0.42 * 0.26) < 0.005
    for n in PATTERNS:
        small = float(pattern_mask(n, 64, 64).double().mean())
        assert abs(small - areas[n]) < 0.02
    assert make_pattern("oval4", 48, 32).shape == (32, 48, 3)
    with pytest.raises(ValueError, match="unknown pattern"):
        make_pattern("star5")


def test_pattern_scene_contract(tmp_path):
    s = pattern_scene("circle4", 40, 30)
    assert s.flat and s.extent == 1.0 and s.points is None
    assert "view_dependence" not in s.capabilities and "sfm_points" not in s.capabilities
    assert s.train[0] is s.test[0]
    cam = s.train[0].camera
    assert torch.equal(cam.viewmat, torch.eye(4))            # at the origin, looking down +z
    assert torch.allclose(cam.center, torch.zeros(3))
    assert (cam.width, cam.height) == (40, 30) and float(cam.K[0, 0]) == 30.0
    paths = write_targets(tmp_path, 32)
    assert [p.name for p in paths] == [f"{n}.png" for n in PATTERNS] and all(p.stat().st_size > 0 for p in paths)
