"""The images a run saves for report.html's viewer: ground truth, |error| maps, the popping strip."""

import json

import numpy as np
import torch
from PIL import Image

from protocols.view_images import save_popping_strip, save_view_images, viewer_indices
from smgs.metrics.image import ERROR_MAP_VMAX, abs_error_map


def test_viewer_indices_spread_and_bounded():
    assert viewer_indices(10, 3) == [0, 4, 9]
    assert viewer_indices(2, 5) == [0, 1]
    assert viewer_indices(7, 1) == [0]
    assert viewer_indices(0, 3) == [] and viewer_indices(5, 0) == []


def test_error_map_scale_is_fixed():
    gt = torch.zeros(2, 3, 3)
    pred = gt.clone()
    pred[0, 1] = ERROR_MAP_VMAX          # saturates: white
    pred[1, 0] = ERROR_MAP_VMAX / 3      # a third of the scale: full red only
    m = abs_error_map(pred, gt)
    assert m.dtype == np.uint8 and m.shape == (2, 3, 3)
    assert m[0, 0].tolist() == [0, 0, 0]
    assert m[0, 1].tolist() == [255, 255, 255]
    r, g, b = m[1, 0].tolist()
    assert r >= 250 and g <= 5 and b == 0


def test_error_map_rejects_shape_mismatch():
    try:
        abs_error_map(torch.zeros(2, 2, 3), torch.zeros(3, 2, 3))
    except ValueError as e:
        assert "different shapes" in str(e)
    else:
        raise AssertionError("no error")


def test_save_view_images_writes_same_views_for_any_order(tmp_path):
    names = [f"v{i}.jpg" for i in range(5)]
    gts = [torch.full((4, 6, 3), i / 10) for i in range(5)]
    renders = [g + 0.05 for g in gts]
    saved = save_view_images(tmp_path, names[::-1], renders[::-1], gts[::-1], 2)
    assert saved == ["v0", "v4"]
    gt = np.asarray(Image.open(tmp_path / "gt" / "v4.png"))
    assert gt.shape == (4, 6, 3) and int(gt[0, 0, 0]) == round(0.4 * 255)
    err = np.asarray(Image.open(tmp_path / "error" / "v0.png"))
    assert err.shape == (4, 6, 3) and err[..., 0].min() > 0


def test_popping_strip_tiles_the_worst_pair(tmp_path):
    cams = list(range(12))

    def render(cam):
        return torch.full((8, 400, 3), cam / 20), None

    pairs = [{"i": i, "j": i + 7, "mse": 0.1 * (i == 2) + 0.01} for i in range(5)] + [{"i": 9, "j": 16, "mse": None}]
    info = save_popping_strip(tmp_path, render, cams, pairs, 7)
    assert info["pair"] == [2, 9] and info["frames"] == list(range(2, 10))
    strip = np.asarray(Image.open(tmp_path / "strip.png"))
    assert strip.shape[1] == 8 * info["tile_width"] and info["tile_width"] == 192
    assert json.loads((tmp_path / "strip.json").read_text())["mse"] == info["mse"]
    assert save_popping_strip(tmp_path / "none", render, cams, [{"i": 0, "j": 7, "mse": None}], 7) is None


def test_popping_strip_prefers_the_pair_whose_popped_pixels_cost_most(tmp_path):
    cams = list(range(12))

    def render(cam):
        return torch.full((8, 40, 3), cam / 20), None

    pop = lambda n, se: {"popped": n, "popped_se": se, "rest": 100, "rest_se": 1.0}  # noqa: E731
    pairs = [{"i": 0, "j": 7, "mse": 0.5, "pop": pop(0, 0.0)}, {"i": 1, "j": 8, "mse": 0.1, "pop": pop(3, 2.0)},
             {"i": 2, "j": 9, "mse": 0.1, "pop": pop(9, 0.5)}, {"i": 3, "j": 10, "mse": 0.1, "pop": None}]
    info = save_popping_strip(tmp_path, render, cams, pairs, 7)
    assert info["pair"] == [1, 8] and info["popped_pixels"] == 3 and "popped" in info["why"]
    # without any popped pixel: the highest MSE, as before
    info = save_popping_strip(tmp_path / "b", render, cams, [dict(p, pop=None) for p in pairs], 7)
    assert info["pair"] == [0, 7] and info["popped_pixels"] == 0
