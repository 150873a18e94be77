"""RGBA images in a COLMAP scene: the ground truth is the stored RGB, as 3DGS reads such a scene, and
the scene, the run's plan and the report say that the alpha channel was dropped."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from protocols.results import RunResult
from smgs.data.colmap import load_colmap

FERN = Path(__file__).resolve().parents[1].parent / "shared" / "data" / "fern"
pytestmark = pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(),
                                reason=f"fixture {FERN} absent (CI keeps ../shared beside the checkout)")
RGBA = ("image003.png", "image011.png")


def test_alpha_is_dropped_as_3dgs_does_and_said(tmp_path):
    from PIL import Image

    scene = tmp_path / "fern"
    (scene / "sparse").mkdir(parents=True)
    shutil.copytree(FERN / "sparse" / "0", scene / "sparse" / "0")
    (scene / "images").mkdir()
    for src in sorted((FERN / "images").iterdir()):
        if src.name in RGBA:
            rgb = np.asarray(Image.open(src).convert("RGB"))
            alpha = np.linspace(0, 255, rgb.shape[1], dtype=np.uint8)[None, :].repeat(rgb.shape[0], 0)
            Image.fromarray(np.dstack([rgb, alpha]), "RGBA").save(scene / "images" / src.name)
        else:
            (scene / "images" / src.name).symlink_to(src)
    plain = load_colmap(FERN, images="images")
    s = load_colmap(scene, images="images")
    for a, b in zip(s.train + s.test, plain.train + plain.test):
        assert a.name == b.name and a.rgb.shape == b.rgb.shape and bool((a.rgb == b.rgb).all())
    note = s.meta["alpha_dropped"]
    assert note.startswith("2 of 20 images have an alpha channel (e.g. image003.png); alpha is dropped")
    assert plain.meta["alpha_dropped"] is None

    from types import SimpleNamespace

    from protocols.train_loop import run_plan

    assert f"scene images: {note}" in run_plan({"plan": []}, SimpleNamespace(consistency=False), s)
    from reports.tables import mix_notes

    r = RunResult(method="3dgs", dataset="colmap", scene="fern", budget="full", seed=0, data=dict(s.meta))
    assert f"Scene colmap/fern: {note}." in mix_notes([r])
