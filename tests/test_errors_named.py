"""Errors name the file they are about (and the frame): NaN in a transforms.json pose, a full disk."""

from __future__ import annotations

import errno
import json
import os

import numpy as np
import pytest
from PIL import Image

from protocols.run import run_experiment
from smgs.data import SceneFormatError
from smgs.data.transforms import load_transforms
from smgs.atomic import atomic_write_text


def _scene(root, n=3):
    frames = []
    for i in range(n):
        Image.new("RGB", (20, 16), (10 * i, 0, 0)).save(root / f"f{i}.png")
        c2w = np.eye(4)
        c2w[:3, 3] = (i, 0.0, 4.0)
        frames.append({"file_path": f"f{i}.png", "transform_matrix": c2w.tolist()})
    return frames


def test_nan_in_a_translation_names_the_file_and_the_frame(tmp_path):
    frames = _scene(tmp_path)
    frames[2]["transform_matrix"][1][3] = float("nan")
    (tmp_path / "transforms.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames}))
    with pytest.raises(SceneFormatError) as e:
        load_transforms(tmp_path)
    msg = str(e.value)
    assert f"{tmp_path / 'transforms.json'} frame 2 ('f2.png')" in msg
    assert "1 non-finite value(s) in its translation (at row, column (1, 3))" in msg


def test_a_blender_split_file_is_named_with_its_own_frame_index(tmp_path):
    frames = _scene(tmp_path, 4)
    frames[3]["transform_matrix"][0][0] = float("inf")
    (tmp_path / "transforms_train.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames[:2]}))
    (tmp_path / "transforms_test.json").write_text(json.dumps({"camera_angle_x": 0.7, "frames": frames[2:]}))
    with pytest.raises(SceneFormatError, match=r"transforms_test\.json frame 1 \('f3\.png'\).*in its rotation"):
        load_transforms(tmp_path)


def _disk_full(monkeypatch):
    def full(fd):
        raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
    monkeypatch.setattr(os, "fsync", full)   # where a full disk shows: a write flushed to it


def test_a_full_disk_names_the_file_it_could_not_write(tmp_path, monkeypatch):
    atomic_write_text(tmp_path / "a.json", "old")
    _disk_full(monkeypatch)
    with pytest.raises(OSError) as e:
        atomic_write_text(tmp_path / "a.json", "new")
    assert e.value.errno == errno.ENOSPC and str(tmp_path / "a.json") in str(e.value)
    monkeypatch.undo()
    assert (tmp_path / "a.json").read_text() == "old" and os.listdir(tmp_path) == ["a.json"]


def test_a_sweep_on_a_full_disk_says_which_file(tmp_path, monkeypatch):
    _disk_full(monkeypatch)
    s = run_experiment(["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
                        "grid.methods=[3dgs]", "dataset.size=16", "dataset.steps=4", "report=false",
                        f"out_dir={tmp_path}"])
    run_dir = tmp_path / "patterns/circle4/3dgs/cap4/seed0"
    assert s[0]["status"] == "failed"
    assert f"No space left on device: '{run_dir / 'config.yaml'}'" in s[0]["error"]
    assert f"not recorded in {run_dir}" in s[0]["error"] and str(run_dir / "results.json") in s[0]["error"]
