"""What every render derives from the camera alone (the packed view on the host and on the splats'
device, the fused projection's 25 floats) is made once per camera (``Camera.memo``): it cost each
render ~0.3 ms of small host operations, a quarter of gsplat's whole forward there. The memo lives
on the camera (no global state), follows every change of it, and never travels with it."""

from __future__ import annotations

import copy
import pickle

import pytest
import torch

import smgs.raster.api as api
from smgs import Camera
from smgs.raster import rasterize
from smgs.raster.projection_cuda import camera_floats


def _cam() -> Camera:
    return Camera.look_at([0.1, -0.2, -1.0], [0, 0, 3], [0, -1, 0], 40.0, 42.0, 24, 18)


def test_the_memo_follows_every_change_of_the_camera():
    cam = _cam()
    made = []

    def make():
        made.append(1)
        return len(made)

    assert cam.memo(("k",), make) == 1 and cam.memo(("k",), make) == 1
    assert cam.memo(("other",), make) == 2
    with torch.no_grad():
        cam.K[0, 0] += 1.0                         # a write into K
    assert cam.memo(("k",), make) == 3
    cam.viewmat = cam.viewmat.clone()              # another tensor, the same values
    assert cam.memo(("k",), make) == 4
    cam.width = 30
    assert cam.memo(("k",), make) == 5 and cam.memo(("k",), make) == 5
    cam.viewmat.requires_grad_(True)               # a pose being optimised: never kept
    assert cam.memo(("k",), make) == 6 and cam.memo(("k",), make) == 7


def test_the_memo_is_neither_pickled_nor_shared_by_a_copy():
    cam = _cam()
    floats = camera_floats(cam)
    assert "_memo" in cam.__dict__
    back = pickle.loads(pickle.dumps(cam))
    assert "_memo" not in back.__dict__ and torch.equal(back.viewmat, cam.viewmat)
    twin = copy.copy(cam)
    assert "_memo" not in twin.__dict__
    assert camera_floats(back) == floats
    floats[0] = 99.0                                # the caller's list is its own
    assert camera_floats(cam)[0] != 99.0


def test_a_render_packs_its_camera_once_and_sees_a_change(monkeypatch):
    calls = []
    real = api.host_view
    monkeypatch.setattr(api, "host_view", lambda *a, **k: calls.append(1) or real(*a, **k))
    g = torch.Generator().manual_seed(0)
    n = 30
    means = torch.rand(n, 3, generator=g) - 0.5 + torch.tensor([0.0, 0.0, 3.0])
    args = (means, torch.randn(n, 4, generator=g), 0.05 + 0.1 * torch.rand(n, 3, generator=g),
            0.5 + 0.4 * torch.rand(n, generator=g), torch.rand(n, 3, generator=g))
    cam = _cam()
    first = rasterize(*args, cam, mode="3dgs").rgb
    again = rasterize(*args, cam, mode="3dgs").rgb
    assert len(calls) == 1 and torch.equal(first, again)
    with torch.no_grad():
        cam.viewmat[0, 3] += 0.3                    # the camera moves in place
    moved = rasterize(*args, cam, mode="3dgs").rgb
    assert len(calls) == 2 and not torch.equal(moved, first)
    torch.testing.assert_close(moved, rasterize(*args, Camera(cam.K.clone(), cam.viewmat.clone(), 24, 18),
                                                mode="3dgs").rgb, rtol=0, atol=0)


def test_a_camera_made_non_finite_after_a_render_is_refused():
    """The camera's finiteness is decided once per camera too: a write into it decides again."""
    from smgs.raster.checks import NonFiniteInputError

    g = torch.Generator().manual_seed(1)
    args = (torch.rand(8, 3, generator=g) + torch.tensor([0.0, 0.0, 3.0]), torch.randn(8, 4, generator=g),
            0.1 * torch.ones(8, 3), 0.5 * torch.ones(8), torch.rand(8, 3, generator=g))
    cam = _cam()
    rasterize(*args, cam, mode="3dgs")
    with torch.no_grad():
        cam.viewmat[1, 3] = float("nan")
    with pytest.raises(NonFiniteInputError, match="camera.viewmat has 1 NaN or inf"):
        rasterize(*args, cam, mode="3dgs")
