"""One scene contract under every format (smgs.data.contract): a plug-in format installed from its own
distribution that breaks each rule in turn is refused after its load and before training, naming
the scene, the view and the rule, never trained and scored (8x8 px views, names twice, no test view,
a 180° or 1e-8° field of view, a pose that is no rotation, a dict for a Scene)."""

from __future__ import annotations

import textwrap

import pytest

from counting_method import counting  # noqa: F401 (the fixture)
from plugin_dist import install, uninstall
from smgs.data import load_scene, registry
from smgs.data.contract import SceneContractError

# A format as a hostile (or careless) third party might write it: its scene breaks the rule `breaks`.
HOSTILE = textwrap.dedent('''
    from dataclasses import dataclass
    from typing import ClassVar

    import torch

    from smgs.data.procedural import ring_cameras
    from smgs.data.scene import Scene, View, camera_extent, split_every


    @dataclass(frozen=True)
    class Hostile:
        breaks: str = ""
        size: int = 24

        SCENES: ClassVar[tuple[str, ...]] = ("hostile",)

        def load(self, request):
            n = 8
            cams = ring_cameras(n, self.size, self.size)
            names = [f"v{i}.png" for i in range(n)]
            if self.breaks == "dot-name":
                names[3] = "./v0.png"
            if self.breaks == "same-stem":
                names[0], names[3] = "a/v.png", "b/v.png"
            for cam in cams:
                if self.breaks == "focal-tiny":
                    cam.K[0, 0] = cam.K[1, 1] = 1e-9
                if self.breaks == "focal-huge":
                    cam.K[0, 0] = cam.K[1, 1] = 1e12
                if self.breaks == "nan-pose":
                    cam.viewmat[0, 3] = float("nan")
                if self.breaks == "scaled-pose":
                    cam.viewmat[:3, :3] *= 2
            views = [View(c, torch.full((self.size, self.size, 3), 100, dtype=torch.uint8), name)
                     for c, name in zip(cams, names)]
            if self.breaks == "image-size":
                views[1].image = torch.zeros(self.size, self.size + 4, 3, dtype=torch.uint8)
            train, test = split_every(names, request.test_every)
            train, test = [views[i] for i in train], [views[i] for i in test]
            if self.breaks == "no-test":
                train, test = train + test, []
            if self.breaks == "test-trains":
                train = train + test
            if self.breaks == "same-stem":
                train, test = [v for v in train if v is not views[3]], test + [views[3]]
            scene = Scene(name=request.scene, train=train, test=test, extent=camera_extent(cams))
            return vars(scene) if self.breaks == "dict" else scene
''')


@pytest.fixture
def hostile(tmp_path, monkeypatch):
    yield install(tmp_path / "site", monkeypatch, "smgs_hostile_scenes", HOSTILE, registry.ENTRY_POINT_GROUP,
                  {"hostile": "smgs_hostile_scenes:Hostile"})
    uninstall("smgs_hostile_scenes")


@pytest.mark.parametrize("breaks,size,words", [
    ("dict", 24, "load returned a dict, not a smgs.data.Scene"),
    ("", 8, "views 'v0.png', 'v1.png', 'v2.png' and 5 more: 8x8 px, under the 16 px a side that a score needs"),
    ("dot-name", 24, "views 'v0.png' and './v0.png' are one name (v0.png)"),
    ("test-trains", 24, "view 'v0.png' is both a training and a test view"),
    ("same-stem", 24, "test views 'a/v.png' and 'b/v.png' would write one render file (renders/v.png)"),
    ("focal-tiny", 24, "views 'v0.png', 'v1.png', 'v2.png' and 5 more: fx = 1e-09 px gives the 24-px width a field "
                       "of view of 180°, outside the 0.5°–170°"),
    ("focal-huge", 24, "fx = 1e+12 px gives the 24-px width a field of view of 1.38e-09°, outside the 0.5°–170°"),
    ("nan-pose", 24, "and 5 more: its pose (viewmat, world-to-camera) holds NaN or infinite values"),
    ("scaled-pose", 24, "its pose's rotation is no rotation (|RᵀR − I| up to 3"),
    ("image-size", 24, "view 'v1.png': its image is 28x24 px but its camera 24x24"),
    ("no-test", 24, "no test view, and the run scores test views"),
])
def test_a_plugin_scene_that_breaks_a_rule_is_refused_naming_it(hostile, breaks, size, words):
    with pytest.raises(SceneContractError) as e:
        load_scene("hostile", breaks=breaks, size=size)
    msg = str(e.value)
    assert words in msg, msg
    assert "scene format smgs_hostile_scenes.Hostile" in msg and "adding-a-scene-format.md#what-the-harness-checks" in msg


def test_a_plugin_scene_that_keeps_the_contract_loads(hostile):
    s = load_scene("hostile")
    assert len(s.train) == 7 and len(s.test) == 1
    assert load_scene("hostile", breaks="no-test", test_every=None).test == []   # nothing to score: none needed


def test_the_runner_refuses_a_scene_without_test_views_before_training(hostile, counting, tmp_path):
    """Before: trained in full, then failed at FPS. Now the cell fails at its load, naming the
    plug-in's scene and distribution, and not one step is trained."""
    from protocols.results import read_result
    from protocols.run import run_experiment

    out = tmp_path / "runs"
    s = run_experiment(["grid.datasets=[hostile]", "grid.methods=[counting]", "+dataset.breaks=no-test",
                        "protocol.steps=3", "protocol.schedule_steps=null", "report=false", "device=cpu",
                        f"out_dir={out}"])
    assert s[0]["status"] == "failed" and counting.calls == []
    err = read_result(out / "hostile/hostile/counting/full/seed0/results.json").error
    assert err.startswith("SceneContractError: hostile scene hostile (scene format 'hostile', plugin "
                          "smgs-hostile-scenes) breaks the scene contract"), err
    assert "no test view" in err


def test_the_builtin_scenes_keep_the_contract():
    from smgs.data.patterns import PATTERNS

    assert len(load_scene("procedural", n_views=8, width=32, height=24).test) == 1
    assert load_scene("pattern", PATTERNS[0], size=16).flat   # its one view trains and is scored
