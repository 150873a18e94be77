"""Split rule, resolution rules as data, and the ``load_scene`` entry point."""

from __future__ import annotations

import pytest

from smgs.data import (DATA_ROOT_ENV, DatasetNotFoundError, ResolutionRule, get_dataset, load_scene,
                       resolve_data_root, split_every)
from smgs.data.formats import with_trajectory
from smgs.data.registry import BUILTIN_DATASETS


def test_split_is_on_name_sorted_order():
    names = ["c.png", "a.png", "b.png", "j.png", "d.png", "e.png", "f.png", "g.png", "h.png", "i.png"]
    train, test = split_every(names, 8)
    assert sorted(names[i] for i in test) == ["a.png", "i.png"]  # sorted positions 0 and 8
    assert len(train) == 8 and set(train).isdisjoint(test)
    assert split_every(names, None) == (sorted(range(10), key=lambda i: names[i]), [])


@pytest.mark.parametrize("rule,src,out", [
    (ResolutionRule(max_width=1600), (4946, 3286), (1600, 1063)),     # 3DGS -r -1 on bicycle
    (ResolutionRule(max_width=1600), (1601, 1000), (1600, 999)),      # 3DGS's float division gives 1599
    (ResolutionRule(max_width=1600), (979, 546), (979, 546)),         # never upsampled
    (ResolutionRule(factor=4), (4946, 3286), (1237, 822)),            # rounded half up
    (ResolutionRule(factor=2, max_width=400), (1080, 1920), (400, 711)),
])
def test_target_size(rule, src, out):
    assert rule.target_size(*src) == out


def test_protocol_rules_are_data():
    mip = get_dataset("mipnerf360")
    assert mip.scenes == ("bicycle", "bonsai", "counter", "garden", "kitchen", "room", "stump")
    assert {s for s in mip.scenes if mip.group_of(s) == "indoor"} == {"bonsai", "counter", "kitchen", "room"}
    assert mip.rule("3dgs", "bicycle").images == "images_4" and mip.rule("3dgs", "room").images == "images_2"
    assert mip.rule("paper", "garden").images == "images" and mip.rule("paper", "garden").max_width == 1600
    assert mip.rule("gsplat", "kitchen").factor == 2 and mip.rule("gsplat", "stump").factor == 4
    assert get_dataset("tandt").scenes == ("train", "truck") and get_dataset("tandt").folders[0] == "tandt"
    db = get_dataset("deepblending")
    assert db.folders[0] == "db" and db.rule("paper", "playroom").max_width is None  # native
    for spec in map(get_dataset, BUILTIN_DATASETS):
        assert "NOT the paper protocol" in spec.rule("cpu", spec.scenes[0]).label
    with pytest.raises(ValueError, match="no resolution rule 'fast'"):
        mip.rule("fast", "bicycle")


def test_data_root_errors(tmp_path, monkeypatch):
    monkeypatch.delenv(DATA_ROOT_ENV, raising=False)
    with pytest.raises(DatasetNotFoundError, match=DATA_ROOT_ENV):
        resolve_data_root(None)
    monkeypatch.setenv(DATA_ROOT_ENV, str(tmp_path))
    assert resolve_data_root(None) == tmp_path
    with pytest.raises(DatasetNotFoundError) as e:
        load_scene("deepblending", scene="playroom")
    msg = str(e.value)
    assert str(tmp_path / "db" / "playroom") in msg and str(tmp_path / "tandt_db" / "db" / "playroom") in msg
    assert "sparse/0" in msg


def test_load_scene_entry_point():
    s = load_scene("procedural", n_views=16, width=48, height=32, seed=3, trajectory_between=5)
    assert len(s.train) + len(s.test) == 16 and s.train[0].camera.width == 48
    assert len(s.trajectory) == 48 and "trajectory" not in s.meta   # a scene's own trajectory is kept
    s.trajectory = None
    with_trajectory(s, 5)
    assert s.trajectory is not None and len(s.trajectory) == 7  # 2 test views, 5 frames between
    assert "frames between consecutive test cameras" in s.meta["trajectory"]
    with pytest.raises(ValueError, match="unknown scene kind 'nerf'"):
        load_scene("nerf")
    with pytest.raises(ValueError, match="needs the scene's folder: add dataset.path="):
        load_scene("colmap")
    with pytest.raises(ValueError, match="needs a scene"):
        load_scene("tandt")
    with pytest.raises(ValueError, match="scene format 'procedural' takes no size; its settings: n_views, width"):
        load_scene("procedural", size=(48, 32))
