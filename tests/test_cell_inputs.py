"""A cell records the fingerprint of what it read (smgs.data.fingerprint: each image, the camera model
and the points by name, size and sha256) and compares it: a finished cell whose scene changed on
disk is rerun, saying why, instead of "skipped (finished before)"; seeds trained on different
inputs, or on two copies of a scene that differ, are not pooled, and the footnote names the file.
Runs are tiny: the fern (COLMAP) and fox (transforms.json) scenes of ../shared/data at 64 px, 2 steps."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from counting_method import counting  # noqa: F401 (the fixture)
from protocols.results import read_result
from protocols.run import run_experiment
from reports.runs import config_difference
from smgs.data import fingerprint

DATA = Path(__file__).resolve().parents[1].parent / "shared" / "data"
FERN, FOX = DATA / "fern", DATA / "fox"
pytestmark = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir() or not FOX.is_dir(),
                                reason=f"fixtures {FERN}, {FOX} absent (CI keeps ../shared beside the checkout)")
TINY = ["grid.methods=[counting]", "protocol.steps=2", "protocol.schedule_steps=null", "eval.fractions=[1.0]",
        "eval.fps_repeats=1", "eval.flip=false", "eval.save_renders=false", "report=false", "device=cpu",
        "protocol.max_width=64"]


@pytest.fixture(autouse=True)
def _own_hash_cache(tmp_path, monkeypatch):
    monkeypatch.setenv(fingerprint.CACHE_ENV, str(tmp_path / "hashes.sqlite"))


def _fern(where: Path) -> Path:
    """A copy of fern: its model and its images (copied: the test changes one)."""
    shutil.copytree(FERN / "sparse", where / "sparse")
    shutil.copytree(FERN / "images", where / "images")
    for p in where.rglob("*"):
        p.chmod(0o755 if p.is_dir() else 0o644)
    return where


def _repaint(image: Path) -> None:
    """The image replaced on disk under its name: other pixels, the same size of picture."""
    px = np.asarray(Image.open(image).convert("RGB")).copy()
    px[:40, :40] = 255 - px[:40, :40]
    image.unlink()
    Image.fromarray(px).save(image)


def run(out: Path, scene: Path, *extra: str) -> dict:
    return run_experiment(["dataset=colmap", f"dataset.path={scene}", f"out_dir={out}", *TINY, *extra])[0]


def test_a_scene_changed_on_disk_reruns_its_finished_cell_saying_why(tmp_path, counting, capsys):
    scene = _fern(tmp_path / "fern")
    out = tmp_path / "runs"
    assert run(out, scene)["status"] == "ok"
    res = out / "colmap/fern/counting/full/seed0/results.json"
    inputs = read_result(res).inputs
    assert {"sparse/0/cameras.bin", "sparse/0/images.bin", "sparse/0/points3D.bin",
            "images/image003.png"} <= set(inputs["files"]) and inputs["folder"] == str(scene)
    assert inputs["files"]["images/image003.png"]["size"] == (scene / "images/image003.png").stat().st_size
    counting.calls.clear()
    assert run(out, scene).get("skipped") and counting.calls == []

    _repaint(scene / "images" / "image003.png")
    capsys.readouterr()
    s = run(out, scene)
    assert s["status"] == "ok" and not s.get("skipped") and counting.calls == [0, 1]
    why = "the inputs changed since it was computed: images/image003.png (changed)"
    assert s["rerun"] == why and f"colmap/fern/counting/full/seed0: rerun: {why}" in capsys.readouterr().out
    assert why in (res.parent / "log.txt").read_text()
    assert read_result(res).inputs["files"]["images/image003.png"] != inputs["files"]["images/image003.png"]
    counting.calls.clear()
    assert run(out, scene).get("skipped") and counting.calls == []


def test_seeds_trained_on_different_inputs_are_not_pooled(tmp_path, counting):
    """Two seeds on one scene, its image replaced between them; and seeds on two copies of fern in
    different folders (dataset.path is where, not what): pooled when the copies agree, not when one
    differs."""
    scene = _fern(tmp_path / "a" / "fern")
    out = tmp_path / "runs"
    assert run(out, scene, "seed=0")["status"] == "ok"
    _repaint(scene / "images" / "image010.png")
    assert run(out, scene, "seed=1")["status"] == "ok"
    runs = [read_result(out / f"colmap/fern/counting/full/seed{i}/results.json") for i in (0, 1)]
    why = config_difference(runs)
    assert why.startswith("seeds trained on different inputs, not pooled: images/image010.png (seed 0: sha256 "), why
    assert why.endswith("(rerun them on one copy of the scene)")

    same = _fern(tmp_path / "b" / "fern")
    shutil.copy2(scene / "images" / "image010.png", same / "images" / "image010.png")
    other = tmp_path / "other"
    assert run(other, same, "seed=0")["status"] == "ok"
    copy = read_result(other / "colmap/fern/counting/full/seed0/results.json")
    assert copy.config["dataset"]["path"] != runs[1].config["dataset"]["path"]
    assert config_difference([runs[1], _as_seed(copy, 2)]) is None
    assert config_difference([runs[0], _as_seed(copy, 2)]).startswith("seeds trained on different inputs")
    old = _as_seed(copy, 3)
    old.inputs = {}   # written before inputs were recorded: not compared on them
    assert config_difference([runs[0], old]) is None


def _as_seed(r, seed: int):
    r.seed, r.config = seed, {**r.config, "seed": seed}
    return r


def test_a_transforms_scene_and_a_generated_one_are_fingerprinted(tmp_path, counting):
    out = tmp_path / "runs"
    s = run_experiment(["dataset=transforms", f"dataset.path={FOX}", "+dataset.images=images_4", f"out_dir={out}",
                        *TINY])[0]
    assert s["status"] == "ok"
    files = read_result(out / "transforms/fox/counting/full/seed0/results.json").inputs["files"]
    assert "transforms.json" in files and "images_4/0001.jpg" in files and len(files) == 68
    s = run_experiment(["+experiment=smoke", "grid.seeds_of={}", "dataset.width=32", "dataset.height=24",
                        "dataset.n_views=8", f"out_dir={out}", *TINY])[0]
    assert s["status"] == "ok"
    assert read_result(out / "procedural/blocks/counting/full/seed0/results.json").inputs["files"] == {}


def test_a_file_is_hashed_once_until_it_changes(tmp_path, monkeypatch):
    f = tmp_path / "a.bin"
    f.write_bytes(b"x" * 100)
    hashed = []
    real = fingerprint._hash_file
    monkeypatch.setattr(fingerprint, "_hash_file", lambda p: hashed.append(p) or real(p))
    first = fingerprint.fingerprint([f])
    assert fingerprint.fingerprint([f]) == first and len(hashed) == 1
    f.write_bytes(b"y" * 100)   # rewritten in place, same size
    again = fingerprint.fingerprint([f])
    assert len(hashed) == 2 and again["files"]["a.bin"]["sha256"] != first["files"]["a.bin"]["sha256"]
    monkeypatch.setenv(fingerprint.CACHE_ENV, "")   # off: hashed every time, the same answer
    assert fingerprint.fingerprint([f]) == again and len(hashed) == 3
