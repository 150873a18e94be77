"""COLMAP loading on the real LLFF fern fixture (../shared/data/fern) and its failure modes."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch

from smgs.data import DatasetNotFoundError, MissingImageError, SceneFormatError, load_scene
from smgs.data.colmap import load_colmap

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
FERN = SHARED / "data" / "fern"
pytestmark = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(),
                                reason=f"fixture {FERN} absent (CI keeps ../shared beside the checkout)")
pycolmap = pytest.importorskip("pycolmap")
NAMES = [f"image{i:03d}.png" for i in range(20)]


@pytest.fixture(scope="module")
def colmap_truth():
    rec = pycolmap.Reconstruction(str(FERN / "sparse" / "0"))
    cam = rec.cameras[1]
    poses = {im.name: np.asarray(im.cam_from_world().matrix()) for im in rec.images.values()}
    return np.asarray(cam.calibration_matrix()), (cam.width, cam.height), poses


@pytest.fixture(scope="module")
def fern():
    return load_colmap(FERN, images="images")


def _tmp_scene(tmp_path: Path, images: str | None = "images") -> Path:
    """A writable copy of fern's model with the image folder linked (never copied into the repo)."""
    scene = tmp_path / "fern"
    (scene / "sparse").mkdir(parents=True)
    shutil.copytree(FERN / "sparse" / "0", scene / "sparse" / "0")
    if images:
        (scene / images).symlink_to(FERN / images, target_is_directory=True)
    return scene


def test_split_every_8th_of_name_sorted(fern):
    assert [v.name for v in fern.test] == ["image000.png", "image008.png", "image016.png"]
    assert len(fern.train) == 17 and len(fern.test) == 3
    assert sorted(v.name for v in fern.train + fern.test) == NAMES
    assert fern.meta["split"].startswith("every 8th of the name-sorted")
    assert fern.meta["n_images"] == 20 and fern.meta["n_test"] == 3


def test_poses_points_and_extent(fern, colmap_truth):
    K, _, poses = colmap_truth
    for v in fern.train + fern.test:
        np.testing.assert_allclose(v.camera.viewmat[:3].double().numpy(), poses[v.name], rtol=0, atol=1e-5)
    assert fern.points.shape == (10091, 3) and fern.point_colors.shape == (10091, 3)
    assert 0 <= fern.point_colors.min() and fern.point_colors.max() <= 1
    assert "sfm_points" in fern.capabilities
    centres = torch.stack([v.camera.center for v in fern.train]).double()
    expect = 1.1 * (centres - centres.mean(0)).norm(dim=1).max().item()
    assert fern.extent == pytest.approx(expect, rel=1e-6)


def _inside_fraction(scene, view) -> float:
    """Fraction of SfM points projecting inside the image (SOURCE.md: 96-99 % per image)."""
    cam = view.camera
    p = scene.points.double() @ cam.viewmat[:3, :3].double().T + cam.viewmat[:3, 3].double()
    uv = p @ cam.K.double().T
    u, v = uv[:, 0] / uv[:, 2], uv[:, 1] / uv[:, 2]
    ok = (p[:, 2] > 0) & (u >= 0) & (u < cam.width) & (v >= 0) & (v < cam.height)
    return ok.double().mean().item()


@pytest.mark.parametrize("kwargs,size", [
    (dict(images="images"), (504, 378)),
    (dict(images="images_2"), (252, 189)),           # the shipped half-size folder
    (dict(images="images", factor=2), (252, 189)),   # our own downscaling
    (dict(rule="cpu"), (400, 300)),                   # cpu preset: max width 400
])
def test_intrinsics_scaled_to_the_loaded_image(colmap_truth, kwargs, size):
    K, (cw, ch), _ = colmap_truth
    s = load_colmap(FERN, **kwargs)
    w, h = size
    expect = K.copy()
    expect[0] *= w / cw
    expect[1] *= h / ch
    for v in s.train + s.test:
        assert (v.camera.width, v.camera.height) == (w, h) and tuple(v.image.shape) == (h, w, 3)
        assert v.image.dtype == torch.uint8
        np.testing.assert_allclose(v.camera.K.double().numpy(), expect, rtol=1e-6)
    assert s.meta["image_size"] == [w, h]
    assert s.meta["downscale_factor"] == pytest.approx(cw / w)
    assert _inside_fraction(s, s.test[0]) > 0.95


def test_shipped_folder_versus_own_downscaling_is_recorded():
    shipped = load_colmap(FERN, images="images_2")
    own = load_colmap(FERN, images="images", factor=2)
    assert shipped.meta["resampling"] == "png images_2 as shipped"
    assert own.meta["resampling"] == "PIL BICUBIC from png images 504x378"
    assert shipped.meta["images_folder"] == "images_2" and own.meta["images_folder"] == "images"
    # Same geometry, different pixels: images_2 is a 2x2 box average, ours is bicubic.
    torch.testing.assert_close(shipped.test[0].camera.K, own.test[0].camera.K)
    a, b = shipped.test[0].image.float(), own.test[0].image.float()
    assert 0 < (a - b).abs().mean() < 10


def test_dataset_rules_pick_folders(tmp_path):
    """A Mip-NeRF360-shaped data root (links to fern): the rules choose folder and resampling."""
    root = tmp_path / "data"
    scene = root / "mipnerf360" / "bonsai"  # indoor: 3DGS uses images_2
    scene.mkdir(parents=True)
    for f in ("images", "images_2", "sparse"):
        (scene / f).symlink_to(FERN / f, target_is_directory=True)
    r3 = load_scene("mipnerf360", "bonsai", data_root=root, rule="3dgs")
    assert (r3.meta["images_folder"], r3.meta["resampling"]) == ("images_2", "png images_2 as shipped")
    assert r3.meta["downscale_factor"] == 2.0 and r3.meta["dataset"] == "mipnerf360"
    rg = load_scene("mipnerf360", "bonsai", data_root=root, rule="gsplat")
    assert rg.meta["resampling"].startswith("PIL BICUBIC from png images") and rg.meta["downscale_factor"] == 2.0
    rp = load_scene("mipnerf360", "bonsai", data_root=root, rule="paper")  # 504 < 1600: native, not upsampled
    assert rp.meta["image_size"] == [504, 378] and rp.meta["rule"] == "paper"
    rc = load_scene("mipnerf360", "bonsai", data_root=root, rule="cpu")
    assert rc.meta["image_size"] == [400, 300] and "NOT the paper protocol" in rc.meta["rule_label"]
    # The cpu preset starts from the smallest shipped folder still wide enough (252 < 400 here).
    assert rc.meta["images_folder"] == "images"


def test_missing_dataset_names_the_folders_and_layout(tmp_path):
    with pytest.raises(DatasetNotFoundError) as e:
        load_scene("tandt", "truck", data_root=tmp_path)
    assert str(tmp_path / "tandt" / "truck") in str(e.value) and "sparse/0" in str(e.value)
    with pytest.raises(DatasetNotFoundError, match="does not exist"):
        load_colmap(tmp_path / "nowhere")
    with pytest.raises(ValueError, match="unknown mipnerf360 scene"):
        load_scene("mipnerf360", "lego", data_root=tmp_path)


def test_missing_model(tmp_path):
    scene = _tmp_scene(tmp_path)
    (scene / "sparse" / "0" / "images.bin").unlink()
    with pytest.raises(SceneFormatError, match=r"incomplete: missing images\.bin") as e:
        load_colmap(scene)
    assert str(scene / "sparse" / "0") in str(e.value)
    shutil.rmtree(scene / "sparse")
    with pytest.raises(SceneFormatError, match="no COLMAP model") as e:
        load_colmap(scene)
    assert "sparse/0" in str(e.value)


@pytest.mark.parametrize("victim", ["cameras.bin", "images.bin", "points3D.bin"])
def test_corrupt_model_file(tmp_path, victim):
    scene = _tmp_scene(tmp_path)
    rng = np.random.default_rng(0)
    (scene / "sparse" / "0" / victim).write_bytes(rng.integers(0, 256, 300, dtype=np.uint8).tobytes())
    with pytest.raises(SceneFormatError, match="corrupt COLMAP model") as e:
        load_colmap(scene)
    assert str(scene / "sparse" / "0") in str(e.value)


@pytest.mark.parametrize("victim", ["cameras.bin", "images.bin", "points3D.bin"])
def test_truncated_model_file(tmp_path, victim):
    """A partial copy: pycolmap itself would read a cut cameras.bin without complaint."""
    scene = _tmp_scene(tmp_path)
    p = scene / "sparse" / "0" / victim
    data = p.read_bytes()
    p.write_bytes(data[:len(data) - 3])
    with pytest.raises(SceneFormatError, match="corrupt COLMAP model") as e:
        load_colmap(scene)
    assert str(scene / "sparse" / "0") in str(e.value)


def test_missing_image(tmp_path):
    scene = _tmp_scene(tmp_path, images=None)
    (scene / "images").mkdir()
    for n in NAMES:
        if n != "image011.png":
            (scene / "images" / n).symlink_to(FERN / "images" / n)
    with pytest.raises(MissingImageError) as e:
        load_colmap(scene)
    assert str(scene / "images" / "image011.png") in str(e.value)


def test_unsupported_camera_model(tmp_path):
    scene = _tmp_scene(tmp_path)
    rec = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    cam = rec.cameras[1]
    cam.model = pycolmap.CameraModelId.OPENCV
    cam.params = [407.6, 407.6, 252.0, 189.0, 0.02, 0.0, 0.0, 0.0]
    rec.write(str(scene / "sparse" / "0"))
    with pytest.raises(SceneFormatError, match="OPENCV") as e:
        load_colmap(scene)
    assert "image_undistorter" in str(e.value) and "PINHOLE" in str(e.value)


def test_image_of_the_wrong_aspect_is_refused(tmp_path):
    from PIL import Image

    scene = _tmp_scene(tmp_path, images=None)
    (scene / "images").mkdir()
    for n in NAMES:
        (scene / "images" / n).symlink_to(FERN / "images" / n)
    (scene / "images" / "image003.png").unlink()
    Image.new("RGB", (378, 504)).save(scene / "images" / "image003.png")  # rotated
    with pytest.raises(SceneFormatError, match="image003.png is 378x504 but its camera is 504x378"):
        load_colmap(scene)
