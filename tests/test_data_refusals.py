"""Scenes that cannot give a meaningful result are refused by the loaders before a pixel is decoded,
naming the file, the camera, image or frame and the fix: broken intrinsics and poses, an image used
twice (a training view scored as a test view), a split with nothing to train on, images too small
to score. COLMAP cases patch a copy of the LLFF fern model (../shared/data/fern)."""

from __future__ import annotations

import json
import shutil
import struct
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from smgs.data import SceneFormatError, check_scene, load_scene
from smgs.data.colmap import colmap_sources, load_colmap
from smgs.data.procedural import make_procedural_scene
from smgs.data.transforms import load_transforms, transforms_sources

FERN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fern"
needs_fern = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(),
                                reason=f"fixture {FERN} absent (CI keeps ../shared beside the checkout)")

# byte offsets in COLMAP's binary layout (reconstruction_io_binary): the first camera's fx, fy, cx, cy
# (after the count, its id, model id, width and height), the first image's qw, qx, qy, qz, tx
CAMERA0 = {"fx": 32, "fy": 40, "cx": 48, "cy": 56}
IMAGE0 = {"qw": 12, "qx": 20, "qy": 28, "qz": 36, "tx": 44}


def _fern_copy(tmp_path: Path, file: str, **patch: float) -> Path:
    """A copy of fern's model (images linked) with doubles of ``file`` replaced at CAMERA0/IMAGE0."""
    scene = tmp_path / "fern"
    (scene / "sparse").mkdir(parents=True)
    shutil.copytree(FERN / "sparse" / "0", scene / "sparse" / "0")
    (scene / "images").symlink_to(FERN / "images", target_is_directory=True)
    p = scene / "sparse" / "0" / file
    data = bytearray(p.read_bytes())
    offsets = CAMERA0 if file == "cameras.bin" else IMAGE0
    for key, value in patch.items():
        data[offsets[key]:offsets[key] + 8] = struct.pack("<d", value)
    p.write_bytes(bytes(data))
    return scene


def _quat0() -> list[float]:
    data = (FERN / "sparse" / "0" / "images.bin").read_bytes()
    return [struct.unpack_from("<d", data, IMAGE0[k])[0] for k in ("qw", "qx", "qy", "qz")]


@needs_fern
@pytest.mark.parametrize("patch,words", [
    (dict(fx=0.0), "focal length fx = 0"),
    (dict(fx=-407.6, fy=-407.6), "focal length fx = -407.6, fy = -407.6"),
    (dict(fy=float("nan")), "focal length fy = nan"),
    (dict(cx=25200.0), "principal point (cx, cy) = (25200, 189) lies more than one image size outside its 504x378"),
])
def test_broken_colmap_intrinsics_name_the_file_and_camera(tmp_path, patch, words):
    scene = _fern_copy(tmp_path, "cameras.bin", **patch)
    with pytest.raises(SceneFormatError) as e:
        check_scene("colmap", path=scene)
    assert f"{scene / 'sparse' / '0' / 'cameras.bin'}, camera 1" in str(e.value) and words in str(e.value)
    assert "Fix the camera's calibration" in str(e.value)


@needs_fern
@pytest.mark.parametrize("patch,words", [
    (dict(qw=float("nan")), "its pose is not finite"),
    (dict(tx=float("inf")), "its pose is not finite"),
    (dict(qw=0.0, qx=0.0, qy=0.0, qz=0.0), "has length 0, not 1"),
    ({k: 2 * v for k, v in zip(("qw", "qx", "qy", "qz"), _quat0())} if FERN.is_dir() else {}, "has length 2, not 1"),
])
def test_a_pose_that_is_no_rotation_names_the_file_and_image(tmp_path, patch, words):
    scene = _fern_copy(tmp_path, "images.bin", **patch)
    with pytest.raises(SceneFormatError) as e:
        load_colmap(scene)
    msg = str(e.value)
    assert f"{scene / 'sparse' / '0' / 'images.bin'}, image 'image000.png' (id 1)" in msg and words in msg
    assert "colmap image_deleter" in msg


@needs_fern
def test_a_slightly_unnormalised_quaternion_is_normalised_and_said(tmp_path):
    q = _quat0()
    scene = _fern_copy(tmp_path, "images.bin", **{k: 1.004 * v for k, v in zip(("qw", "qx", "qy", "qz"), q)})
    got = colmap_sources(scene, with_points=False).model
    ref = colmap_sources(FERN, with_points=False).model
    assert got.quaternion_note == "1 rotation quaternion(s) of images.bin normalised (length off 1 by up to 0.004)"
    assert ref.quaternion_note is None
    np.testing.assert_allclose(got.images[0].viewmat, ref.images[0].viewmat, rtol=0, atol=1e-12)
    R = got.images[0].viewmat[:3, :3]
    np.testing.assert_allclose(R @ R.T, np.eye(3), atol=1e-12)


@needs_fern
def test_an_image_listed_twice_in_a_colmap_model_is_refused(tmp_path):
    scene = _fern_copy(tmp_path, "images.bin")
    p = scene / "sparse" / "0" / "images.bin"
    p.write_bytes(p.read_bytes().replace(b"image008.png\0", b"image001.png\0"))
    with pytest.raises(SceneFormatError) as e:
        check_scene("colmap", path=scene)
    assert f"{p} lists 1 image name(s) more than once: image001.png (image ids 2, 9)" in str(e.value)
    assert "both a training and a test view" in str(e.value)


@needs_fern
def test_an_image_listed_twice_under_another_spelling_is_refused(tmp_path):
    """``./image010.png`` beside ``image010.png`` in images.txt is one file as two views (the copy
    became a test view while the original trained)."""
    import pycolmap

    scene = tmp_path / "fern"
    (scene / "sparse" / "0").mkdir(parents=True)
    (scene / "images").symlink_to(FERN / "images", target_is_directory=True)
    pycolmap.Reconstruction(str(FERN / "sparse" / "0")).write_text(str(scene / "sparse" / "0"))
    p = scene / "sparse" / "0" / "images.txt"
    p.write_text(p.read_text().replace(" image008.png\n", " ./image010.png\n"))
    with pytest.raises(SceneFormatError) as e:
        check_scene("colmap", path=scene)
    assert (f"{p} lists 1 image name(s) more than once: image010.png (also as ./image010.png) (image ids 9, 11)"
            in str(e.value)), str(e.value)


@needs_fern
@pytest.mark.parametrize("focal,angle", [(1e-9, "180°"), (1e12, "2.89e-08°")])
def test_a_focal_length_outside_any_field_of_view_names_the_file_and_camera(tmp_path, focal, angle):
    """A focal length of 1e-9 px (a ~180° view) trained a collapsed model; one of 1e12 px failed at step 0
    as a NonFiniteError naming neither file nor key. Both are refused up front, naming both."""
    scene = _fern_copy(tmp_path, "cameras.bin", fx=focal, fy=focal)
    with pytest.raises(SceneFormatError) as e:
        check_scene("colmap", path=scene)
    msg = str(e.value)
    assert f"{scene / 'sparse' / '0' / 'cameras.bin'}, camera 1: fx = {focal:g} px gives the 504-px width a field " \
           f"of view of {angle}, outside the 0.5°–170° a pinhole camera may have here" in msg, msg

    from protocols.run import run_experiment

    with pytest.raises(SystemExit) as stop:   # the runner: before anything runs, naming dataset.path too
        run_experiment(["dataset=colmap", f"dataset.path={scene}", "grid.methods=[3dgs]", "report=false",
                        f"out_dir={tmp_path / 'runs'}"])
    assert str(stop.value).startswith(f"invalid scene, nothing was run:\n  dataset.path={scene}: {scene}")
    assert "field of view" in str(stop.value) and not (tmp_path / "runs").exists()


@needs_fern
@pytest.mark.parametrize("max_width,size", [(1, "1x1"), (8, "8x6"), (20, "20x15")])
def test_images_too_small_to_score_are_refused(max_width, size):
    with pytest.raises(SceneFormatError, match=f"the images are {size} px after the resolution rule") as e:
        check_scene("colmap", path=FERN, rule="cpu", max_width=max_width)
    assert "under the 16 px a side" in str(e.value) and "protocol.max_width" in str(e.value)
    assert check_scene("colmap", path=FERN, rule="cpu", max_width=22) is None   # 22x16


@needs_fern
def test_a_hold_out_of_every_image_is_refused_before_loading():
    with pytest.raises(SceneFormatError, match=r"20 image\(s\) and none left to train on.*protocol\.test_every"):
        check_scene("colmap", path=FERN, test_every=1)


def test_the_procedural_scene_with_every_view_held_out_is_refused():
    with pytest.raises(SceneFormatError, match=r"procedural scene \(dataset.n_views=8\): 8 image\(s\) and none left"):
        make_procedural_scene(n_views=8, size=(32, 24), test_every=1)
    with pytest.raises(SceneFormatError, match="none left to train on"):
        check_scene("procedural", n_views=8, test_every=1)


# ---------------------------------------------------------------- transforms.json

def _transforms(root: Path, n: int = 4, size=(24, 16), **cam) -> Path:
    frames = []
    for i in range(n):
        Image.new("RGB", size, (40 * i, 0, 0)).save(root / f"f{i}.png")
        c2w = np.eye(4)
        c2w[:3, 3] = (0.3 * i, 0.0, 4.0)
        frames.append({"file_path": f"f{i}.png", "transform_matrix": c2w.tolist()})
    d = {"fl_x": 20.0, "fl_y": 20.0, **cam, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(d))
    return root / "transforms.json"


@pytest.mark.parametrize("cam,words", [
    (dict(fl_x=0.0), "focal length fx = 0"),
    (dict(fl_x=float("nan")), "fl_x = nan is not a finite number"),
    (dict(fl_x=-20.0, fl_y=-20.0), "focal length fx = -20, fy = -20"),
    (dict(k1=float("nan")), "k1 = nan is not a finite number"),
    (dict(cx=500.0), "principal point (cx, cy) = (500, 8) lies more than one image size outside its 24x16 image"),
])
def test_broken_transforms_intrinsics_name_the_file_and_frame(tmp_path, cam, words):
    f = _transforms(tmp_path, **cam)
    with pytest.raises(SceneFormatError) as e:
        load_transforms(tmp_path)
    assert f"{f} frame 0 ('f0.png')" in str(e.value) and words in str(e.value)


@pytest.mark.parametrize("cam", [dict(fl_x=1e12, fl_y=1e12), dict(fl_x=1e-9, fl_y=1e-9), dict(fl_y=0.01)])
def test_a_transforms_focal_length_outside_any_field_of_view_names_the_file_frame_and_keys(tmp_path, cam):
    f = _transforms(tmp_path, **cam)
    with pytest.raises(SceneFormatError) as e:
        transforms_sources(tmp_path)
    assert f"{f} frame 0 ('f0.png') (fl_x, fl_y, cx, cy): f" in str(e.value)
    assert "outside the 0.5°–170° a pinhole camera may have here" in str(e.value)


@pytest.mark.parametrize("angle", [0.0, -0.5, 3.2])
def test_a_field_of_view_that_is_no_angle_is_refused_not_a_division_by_zero(tmp_path, angle):
    f = _transforms(tmp_path)
    d = json.loads(f.read_text())
    del d["fl_x"], d["fl_y"]
    d["camera_angle_x"] = angle
    f.write_text(json.dumps(d))
    with pytest.raises(SceneFormatError, match=rf"frame 0 \('f0.png'\): camera_angle_x = {angle:g} is no field of view"):
        load_transforms(tmp_path)


def test_a_frame_listed_twice_is_refused(tmp_path):
    f = _transforms(tmp_path, n=9)
    d = json.loads(f.read_text())
    d["frames"][8]["file_path"] = "./f1.png"      # the same file under another spelling
    f.write_text(json.dumps(d))
    with pytest.raises(SceneFormatError) as e:
        transforms_sources(tmp_path)
    assert f"{f} frame 1 ('f1.png') and {f} frame 8 ('./f1.png') use the same image {tmp_path / 'f1.png'}" in str(e.value)


def test_a_blender_test_frame_that_also_trains_is_refused(tmp_path):
    f = _transforms(tmp_path, n=4)
    frames = json.loads(f.read_text())["frames"]
    f.unlink()
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames[:3]}))
    (tmp_path / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames[2:]}))
    with pytest.raises(SceneFormatError, match=r"transforms_train\.json frame 2 \('f2\.png'\) and .*"
                                               r"transforms_test\.json frame 0 \('f2\.png'\) use the same image"):
        load_transforms(tmp_path)


def test_a_name_in_both_split_lists_is_refused(tmp_path):
    f = _transforms(tmp_path, n=4)
    d = json.loads(f.read_text())
    d["train_filenames"], d["test_filenames"] = ["f0.png", "f1.png", "f2.png"], ["f2.png", "f3.png"]
    f.write_text(json.dumps(d))
    with pytest.raises(SceneFormatError, match=r"1 image\(s\) in both train_filenames and test_filenames \(f2\.png\)"):
        load_transforms(tmp_path)
    d["train_filenames"] = ["f0.png", "f1.png"]
    f.write_text(json.dumps(d))
    s = load_transforms(tmp_path)
    assert [v.name for v in s.train] == ["f0.png", "f1.png"] and [v.name for v in s.test] == ["f2.png", "f3.png"]


def test_transforms_images_too_small_are_refused(tmp_path):
    _transforms(tmp_path, size=(24, 16))
    with pytest.raises(SceneFormatError, match="the images are 12x8 px after the resolution rule"):
        load_scene("transforms", path=tmp_path, max_width=12)
    assert len(load_scene("transforms", path=tmp_path, rule="native").train) == 3
