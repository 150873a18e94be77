"""An experiment's grid on the user's own scene: ``+experiment=X dataset=Y dataset.path=...`` runs X's
methods, budgets and seeds on that one scene (docs/usage.md, "Your own scene"), and the ways to get
it wrong stop with what to add."""

import json
import subprocess
import sys
from pathlib import Path

import pytest
from hydra import compose, initialize_config_dir
from PIL import Image

from protocols.run import CONFIG_DIR, check_command_line, plan, run_experiment
from smgs.data.procedural import make_world, render_view, ring_cameras

REPO = Path(__file__).resolve().parent.parent


def planned(overrides):
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        cells, payloads = plan(compose(config_name="config", overrides=overrides), overrides)
    return cells, payloads


def test_an_experiments_grid_runs_on_the_scene_given_by_its_folder(tmp_path):
    scene = tmp_path / "my_capture"
    args = ["+experiment=budget5", "dataset=colmap", f"dataset.path={scene}", "protocol=cpu"]
    cells, payloads = planned(args)
    assert [(c.method, c.dataset, c.scene, c.budget, c.seed) for c in cells] == [
        ("3dgs", "colmap", "my_capture", "5pct", 0), ("softmax_gs", "colmap", "my_capture", "5pct", 0)]
    assert all(p["config"]["dataset"]["path"] == str(scene) for p in payloads)
    assert all(p["config"]["experiment_name"] == "budget5" for p in payloads)


def test_an_experiment_that_names_scenes_takes_the_folders_scene_instead(tmp_path):
    cells, _ = planned(["+experiment=consistency", "dataset=transforms", f"dataset.path={tmp_path / 'fox'}"])
    assert {c.scene for c in cells} == {"fox"} and {c.method for c in cells} == {"3dgs", "stopthepop", "softmax_gs"}


def test_grid_keys_given_as_well_win(tmp_path):
    cells, _ = planned(["+experiment=budget5", "dataset=mipnerf360", "grid.datasets=[tandt]", "grid.scenes=[truck]"])
    assert {(c.dataset, c.scene) for c in cells} == {("tandt", "truck")}
    cells, _ = planned(["+experiment=budget5", "dataset=tandt"])
    assert {(c.dataset, c.scene) for c in cells} == {("tandt", "train"), ("tandt", "truck")}


def test_a_dataset_kind_without_its_folder_says_to_add_dataset_path():
    with pytest.raises(SystemExit, match=r"needs the scene's folder: add dataset.path=/path/to/scene"):
        planned(["+experiment=budget5", "dataset=colmap"])


def test_dataset_path_without_a_dataset_kind_is_refused_before_hydra():
    assert check_command_line(["+experiment=budget5", "dataset.path=/x"]).startswith(
        "dataset.path names a scene folder")
    assert check_command_line(["+experiment=budget5", "dataset=colmap", "dataset.path=/x"]) is None
    p = subprocess.run([sys.executable, "-m", "protocols.run", "+experiment=budget5", "dataset.path=/x"],
                       cwd=REPO, capture_output=True, text=True, timeout=120)
    assert p.returncode == 2 and "add dataset=colmap" in p.stderr and "not in struct" not in p.stderr


@pytest.mark.slow  # two short trainings with their evaluation: about a minute on 2 cores
def test_the_experiment_runs_on_a_transforms_scene_end_to_end(tmp_path):
    """budget5's two methods on a transforms.json folder, a few steps each."""
    folder = tmp_path / "scene"
    (folder / "images").mkdir(parents=True)
    world, cams, frames = make_world(0), ring_cameras(10, 48, 36), []
    for i, cam in enumerate(cams):
        Image.fromarray(render_view(world, cam)[0]).save(folder / "images" / f"v{i:02d}.png")
        c2w = cam.camtoworld.double().numpy().copy()
        c2w[:3, 1:3] *= -1  # OpenCV -> OpenGL camera axes, as transforms.json has them
        frames.append({"file_path": f"images/v{i:02d}.png", "transform_matrix": c2w.tolist()})
    K = cams[0].K.double().numpy()
    (folder / "transforms.json").write_text(json.dumps(
        {"fl_x": K[0, 0], "fl_y": K[1, 1], "cx": K[0, 2], "cy": K[1, 2], "w": 48, "h": 36, "frames": frames}))
    s = run_experiment(["+experiment=budget5", "dataset=transforms", f"dataset.path={folder}", "protocol=cpu",
                        "protocol.steps=4", f"out_dir={tmp_path / 'runs'}", "report=false", "eval.fps_repeats=1",
                        "eval.flip=false"])
    assert [(x["key"], x["status"]) for x in s] == [
        ("transforms/scene/3dgs/5pct/seed0", "ok"), ("transforms/scene/softmax_gs/5pct/seed0", "ok")]
