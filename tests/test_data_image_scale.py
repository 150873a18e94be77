"""Images must be at their camera's size within the scene's own scale (no 1x1 views), and a scene of
one image is refused clearly (fern and fox fixtures in ../shared/data)."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import pytest
from PIL import Image

from smgs.data import SceneFormatError
from smgs.data.colmap import load_colmap
from smgs.data.images import check_scene_scale
from smgs.data.transforms import load_transforms

SHARED = Path(__file__).resolve().parents[1].parent / "shared"
FERN, FOX = SHARED / "data" / "fern", SHARED / "data" / "fox"
needs_fern = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(), reason=f"fixture {FERN} absent")
needs_fox = pytest.mark.skipif(not (FOX / "transforms.json").is_file(), reason=f"fixture {FOX} absent")


def _fern_copy(tmp_path: Path, folder: str = "images") -> Path:
    """fern's model copied, its images linked one by one (so one can be replaced)."""
    scene = tmp_path / "fern"
    shutil.copytree(FERN / "sparse" / "0", scene / "sparse" / "0")
    (scene / folder).mkdir()
    for p in sorted((FERN / folder).iterdir()):
        (scene / folder / p.name).symlink_to(p)
    return scene


def _replace(path: Path, size: tuple[int, int]) -> None:
    path.unlink()
    Image.new("RGB", size, (90, 120, 60)).save(path)


@needs_fern
@pytest.mark.parametrize("size", [(1, 1), (126, 94), (10, 8)], ids=["1x1", "quarter-thumbnail", "10x8"])
def test_an_image_off_the_scenes_scale_is_refused_naming_it(tmp_path, size):
    """Each of these passes the aspect test at its own size (fern's camera is 504x378): a truncated
    download or a thumbnail would have been scored as a whole test view."""
    scene = _fern_copy(tmp_path)
    _replace(scene / "images" / "image008.png", size)   # a test view (every 8th)
    with pytest.raises(SceneFormatError) as e:
        load_colmap(scene, images="images")
    msg = str(e.value)
    assert f"{scene / 'images' / 'image008.png'} is {size[0]}x{size[1]}, its camera 504x378" in msg
    assert "not at the scene's scale (camera size / 1," in msg and "replace it" in msg


@needs_fern
def test_a_scene_shipped_at_half_size_keeps_loading(tmp_path):
    scene = _fern_copy(tmp_path, "images_2")
    s = load_colmap(scene, images="images_2")
    assert {(v.camera.width, v.camera.height) for v in s.train + s.test} == {(252, 189)}
    _replace(scene / "images_2" / "image003.png", (504, 378))   # a full-size image among the halves
    with pytest.raises(SceneFormatError, match=r"camera size / 2,.*image003\.png is 504x378, its camera 504x378"):
        load_colmap(scene, images="images_2")


@needs_fern
def test_a_colmap_scene_of_one_image_is_refused_clearly(tmp_path):
    pycolmap = pytest.importorskip("pycolmap")
    scene = _fern_copy(tmp_path)
    rec = pycolmap.Reconstruction(str(scene / "sparse" / "0"))
    for image_id in sorted(rec.images)[1:]:
        rec.deregister_frame(rec.images[image_id].frame_id)   # unregistered images are skipped
    rec.write(str(scene / "sparse" / "0"))
    with pytest.raises(SceneFormatError) as e:
        load_colmap(scene, images="images")
    assert str(scene / "sparse" / "0") in str(e.value)
    assert "1 image(s) and none left to train on" in str(e.value) and "at least 2 images" in str(e.value)


@needs_fox
def test_a_1x1_frame_of_a_transforms_scene_is_refused(tmp_path):
    scene = tmp_path / "fox"
    scene.mkdir()
    shutil.copy(FOX / "transforms.json", scene)
    (scene / "images_4").mkdir()
    for p in sorted((FOX / "images_4").iterdir()):
        (scene / "images_4" / p.name).symlink_to(p)
    victim = sorted((scene / "images_4").iterdir())[3]
    _replace(victim, (1, 1))
    with pytest.raises(SceneFormatError, match=rf"camera size / 4,.*{victim} is 1x1, its camera 1080x1920"):
        load_transforms(scene, images="images_4")


def test_a_transforms_scene_of_one_frame_is_refused_clearly(tmp_path):
    Image.new("RGB", (20, 16)).save(tmp_path / "a.png")
    eye = [[1.0, 0, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1]]
    (tmp_path / "transforms.json").write_text(json.dumps(
        {"camera_angle_x": 0.7, "frames": [{"file_path": "a.png", "transform_matrix": eye}]}))
    with pytest.raises(SceneFormatError, match=r"1 image\(s\) and none left to train on.*at least 2 images"):
        load_transforms(tmp_path)


def test_the_scale_rule_takes_the_scenes_own_factor():
    cam = (4946, 3286)
    quarter = [(Path(f"{i}.jpg"), (1237, 822), cam) for i in range(5)]   # mip-NeRF 360's images_4 rounding
    check_scene_scale(quarter)
    check_scene_scale([(Path("a.jpg"), (1080, 1920), (1080, 1920)), (Path("b.jpg"), (1081, 1919), (1080, 1920))])
    with pytest.raises(SceneFormatError, match=r"1 image\(s\).*x\.jpg is 618x411"):
        check_scene_scale(quarter + [(Path("x.jpg"), (618, 411), cam)])
