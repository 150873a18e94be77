"""transforms.json loading: the real instant-ngp fox (../shared/data/fox), an exact synthetic check of
the undistortion and of the OpenGL -> OpenCV conversion, Blender-style splits and RGBA, errors."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from smgs.data import MissingImageError, SceneFormatError, DatasetNotFoundError, load_scene
from smgs.data.procedural import _pixel_rays, make_world, render_view, ring_cameras
from smgs.data.transforms import load_transforms

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
FOX = SHARED / "data" / "fox"
needs_fox = pytest.mark.skipif(not (FOX / "transforms.json").is_file(),
                               reason=f"fixture {FOX} absent (CI keeps ../shared beside the checkout)")


def _gl_c2w(cam) -> list[list[float]]:
    c2w = cam.camtoworld.double().numpy().copy()
    c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes
    return c2w.tolist()


# ---------------------------------------------------------------- fox (real capture, distorted)

@pytest.fixture(scope="module")
def fox():
    return load_transforms(FOX, images="images_4")


@needs_fox
def test_fox_split_and_meta(fox):
    names = sorted(f"images/{p.name}" for p in (FOX / "images").glob("*.jpg"))
    assert len(names) == 67
    assert [v.name for v in fox.test] == names[::8]
    assert len(fox.train) == 67 - 9
    m = fox.meta
    assert m["distortion"] == {"k1": 0.0578421, "k2": -0.0805099, "p1": -0.000980296, "p2": 0.00015575}
    assert m["undistortion"].startswith("OpenCV")
    assert m["resampling"] == "jpeg images_4 as shipped" and m["image_size"] == [270, 480]
    assert m["downscale_factor"] == 4.0 and m["instant_ngp_box"] == {"aabb_scale": 4}
    assert fox.points is None and "sfm_points" not in fox.capabilities


@needs_fox
def test_fox_intrinsics_follow_the_quarter_size_images(fox):
    K = fox.test[0].camera.K.double()
    # The undistorted camera (alpha=0: every pixel valid) zooms in by about 1 %: close to fl/4.
    assert K[0, 0].item() == pytest.approx(1375.52 / 4, rel=0.02)
    assert K[1, 1].item() == pytest.approx(1374.49 / 4, rel=0.02)
    assert K[0, 2].item() == pytest.approx(554.558 / 4, abs=1.0)
    assert K[1, 2].item() == pytest.approx(965.268 / 4, abs=1.0)


@needs_fox
def test_fox_cameras_face_the_scene_centre(fox):
    views = fox.train + fox.test
    frames = {f["file_path"].lstrip("./"): np.array(f["transform_matrix"])
              for f in json.loads((FOX / "transforms.json").read_text())["frames"]}
    centres, axes = [], []
    for v in views:
        R = v.camera.viewmat[:3, :3].double().numpy()
        assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-5)
        c = v.camera.center.double().numpy()
        np.testing.assert_allclose(c, frames[v.name][:3, 3], atol=1e-4)
        centres.append(c)
        axes.append(R[2])  # OpenCV +z (viewing direction) in world coordinates
    centres, axes = np.array(centres), np.array(axes)
    # The point nearest to every optical axis, in the least-squares sense.
    A = sum(np.eye(3) - np.outer(a, a) for a in axes)
    b = sum((np.eye(3) - np.outer(a, a)) @ c for a, c in zip(axes, centres))
    focus = np.linalg.solve(A, b)
    to_focus = focus - centres
    to_focus /= np.linalg.norm(to_focus, axis=1, keepdims=True)
    cosines = (to_focus * axes).sum(1)
    assert cosines.min() > 0.95  # every camera looks at the fox, not away from it
    # colmap2nerf makes +z the world up: OpenCV +y (image down) must point down in the world.
    downs = np.array([v.camera.viewmat[1, :3].double().numpy() for v in views])
    assert downs[:, 2].mean() < -0.5


# ------------------------------------------------- exact synthetic check: distortion and poses

DIST = {"k1": -0.12, "k2": 0.02, "p1": 0.001, "p2": -0.0005}


def _distorted_render(world, cam, dist: dict, ss: int = 3) -> np.ndarray:
    """What a camera with this OpenCV distortion sees: each sample of the distorted image looks along
    the ray of its undistorted normalised point (inverted with cv2.undistortPoints to 1e-12)."""
    import cv2

    K = cam.K.double().numpy()
    Kcv = K.copy()
    Kcv[:2, 2] -= 0.5  # OpenCV pixel centres at integers
    d = np.array([dist["k1"], dist["k2"], dist["p1"], dist["p2"]])
    off = (np.arange(ss) + 0.5) / ss
    u = (np.arange(cam.width)[:, None] + off).ravel()
    v = (np.arange(cam.height)[:, None] + off).ravel()
    uu, vv = np.meshgrid(u, v)
    pts = np.stack([uu.ravel() - 0.5, vv.ravel() - 0.5], 1).reshape(-1, 1, 2)
    und = cv2.undistortPoints(pts, Kcv, d, None, None, None,
                              (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)).reshape(-1, 2)
    # The inversion is exact: distorting the result gives the pixel back.
    back, _ = cv2.projectPoints(np.c_[und, np.ones(len(und))], np.zeros(3), np.zeros(3), Kcv, d)
    assert np.abs(back.reshape(-1, 2) - pts.reshape(-1, 2)).max() < 1e-4
    # Rays through the undistorted points: pixel coordinates of a distortion-free camera K.
    o, rd = _pixel_rays(cam, und[:, 0] * K[0, 0] + K[0, 2], und[:, 1] * K[1, 1] + K[1, 2])
    _, _, _, rgb = world.cast(o, rd)
    img = rgb.reshape(cam.height, ss, cam.width, ss, 3).mean((1, 3))
    return np.round(img * 255).astype(np.uint8)


@pytest.fixture(scope="module")
def synthetic_distorted(tmp_path_factory):
    world = make_world(0)
    cams = ring_cameras(8, 160, 120)[:2]
    root = tmp_path_factory.mktemp("distorted")
    (root / "images").mkdir()
    frames = []
    for i, cam in enumerate(cams):
        Image.fromarray(_distorted_render(world, cam, DIST)).save(root / "images" / f"f{i}.png")
        frames.append({"file_path": f"./images/f{i}.png", "transform_matrix": _gl_c2w(cam)})
    K = cams[0].K.double().numpy()
    doc = {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": 160, "h": 120,
           **DIST, "aabb_scale": 2, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(doc))
    return world, cams, root


def test_undistortion_and_pose_conversion_reproduce_the_true_pinhole_view(synthetic_distorted):
    world, cams, root = synthetic_distorted
    scene = load_transforms(root, test_every=None)
    assert len(scene.train) == 2 and scene.test == []
    for view, cam in zip(scene.train, cams):
        # Pose: the OpenGL matrix in the file comes back as the OpenCV camera we rendered with.
        torch.testing.assert_close(view.camera.viewmat, cam.viewmat, atol=1e-5, rtol=0)
        got = view.image.double()
        truth = torch.from_numpy(render_view(world, view.camera)[0]).double()  # pinhole, new K
        raw = torch.from_numpy(np.array(Image.open(root / "images" / Path(view.name).name))).double()
        ignored = torch.from_numpy(render_view(world, cam)[0]).double()       # distortion ignored
        # Misplaced edges show as pixels far off in some channel; resampling blur alone stays below.
        wrong = ((got - truth).abs().amax(-1) > 40)[2:-2, 2:-2].double().mean().item()
        wrong_ignored = ((raw - ignored).abs().amax(-1) > 40)[2:-2, 2:-2].double().mean().item()
        assert wrong < 0.005 and wrong_ignored > 0.02, (wrong, wrong_ignored)
        assert (got - truth).abs().mean().item() < 3.0


def test_distortion_is_refused_when_undistortion_is_off(synthetic_distorted):
    _, _, root = synthetic_distorted
    with pytest.raises(SceneFormatError, match="non-zero distortion"):
        load_transforms(root, undistort=False)


def test_fisheye_is_refused(tmp_path, synthetic_distorted):
    _, _, root = synthetic_distorted
    doc = json.loads((root / "transforms.json").read_text())
    doc["camera_model"] = "OPENCV_FISHEYE"
    for f in doc["frames"]:
        f["file_path"] = str(root / f["file_path"])
    (tmp_path / "transforms.json").write_text(json.dumps(doc))
    with pytest.raises(SceneFormatError, match="OPENCV_FISHEYE"):
        load_transforms(tmp_path)


# ----------------------------------------------------------------- Blender layout, RGBA, errors

def _blender_scene(root: Path) -> None:
    angle = 0.6911112070083618
    for split, n in (("train", 3), ("test", 2)):
        (root / split).mkdir(parents=True)
        frames = []
        for i in range(n):
            rgba = np.zeros((16, 20, 4), dtype=np.uint8)
            rgba[..., 0] = 200
            rgba[:8, :, 3] = 255   # top half opaque red
            rgba[8:, :, 3] = 0     # bottom half transparent
            rgba[8:, :4, 3] = 128  # a half-transparent patch
            Image.fromarray(rgba, "RGBA").save(root / split / f"r_{i}.png")
            a = 2 * math.pi * i / n
            c2w = np.eye(4)
            c2w[:3, 3] = (4 * math.cos(a), 4 * math.sin(a), 1.0)
            frames.append({"file_path": f"./{split}/r_{i}", "transform_matrix": c2w.tolist()})
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle, "frames": frames}))


def test_blender_layout_explicit_split_rgba_and_fov(tmp_path):
    _blender_scene(tmp_path)
    s = load_scene("transforms", path=tmp_path)
    assert [v.name for v in s.train] == ["train/r_0", "train/r_1", "train/r_2"]
    assert [v.name for v in s.test] == ["test/r_0", "test/r_1"]
    assert s.meta["split"].startswith("explicit")
    K = s.train[0].camera.K.double()
    assert K[0, 0].item() == pytest.approx(0.5 * 20 / math.tan(0.5 * 0.6911112070083618))
    assert K[1, 1].item() == pytest.approx(K[0, 0].item())
    assert (K[0, 2].item(), K[1, 2].item()) == (10.0, 8.0)
    img = s.train[0].image
    assert img[0, 10].tolist() == [200, 0, 0]
    assert img[12, 10].tolist() == [255, 255, 255]         # composited on white
    a = 128 / 255
    assert img[12, 1].tolist() == [round(200 * a + 255 * (1 - a)), round(255 * (1 - a)), round(255 * (1 - a))]
    assert s.background.tolist() == [1.0, 1.0, 1.0] and "background" in s.capabilities
    # Identity OpenGL camera-to-world: OpenCV camera looking down world -z, image down = world -y.
    R = s.train[0].camera.viewmat[:3, :3]
    torch.testing.assert_close(R, torch.diag(torch.tensor([1.0, -1.0, -1.0])))


def test_transforms_errors(tmp_path):
    with pytest.raises(DatasetNotFoundError, match="transforms.json"):
        load_transforms(tmp_path)
    (tmp_path / "transforms.json").write_text("{ not json")
    with pytest.raises(SceneFormatError, match="corrupt transforms file"):
        load_transforms(tmp_path)
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": "images/nope.png", "transform_matrix": np.eye(4).tolist()}]}))
    with pytest.raises(MissingImageError, match=str(tmp_path / "images" / "nope.png")):
        load_transforms(tmp_path)
