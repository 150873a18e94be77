"""Scene formats and benchmark datasets register by name, the way methods do: the built-ins, an
in-process ``register``, and plugins from the entry-point group ``smgs.datasets``; each format is a
dataclass that is its own config (the ``dataset`` section's keys). A format defined in a package
outside smgs/ trains through ``smgs run`` without a change to the repository."""

import json
import os
import subprocess
import sys
import textwrap
from dataclasses import dataclass
from pathlib import Path

import pytest

from smgs.data import SceneRequest, get_dataset, load_scene
from smgs.data import registry
from smgs.data.datasets import DatasetSpec
from smgs.data.images import ResolutionRule
from plugin_dist import install, uninstall

ROOT = Path(__file__).resolve().parents[1]

# A toy scene format as a third party would write it: its own package, its own config (views, size).
PLUGIN = textwrap.dedent('''
    from dataclasses import dataclass
    from typing import ClassVar

    import torch

    from smgs.data.procedural import ring_cameras
    from smgs.data.scene import Scene, View, camera_extent, split_every
    from smgs.ranges import Range


    @dataclass(frozen=True)
    class Stripes:
        """Vertical stripes seen from a ring of cameras; one scene, "stripes"."""
        views: int = 6
        size: int = 24

        SCENES: ClassVar[tuple[str, ...]] = ("stripes",)
        RANGES: ClassVar[dict] = {"views": Range(2, integer=True), "size": Range(16, integer=True)}

        def load(self, request):
            cams = ring_cameras(self.views, self.size, self.size)
            cols = torch.arange(self.size) // 4 % 3
            img = torch.zeros(self.size, self.size, 3, dtype=torch.uint8)
            for c in range(3):
                img[:, :, c] = (cols == c).to(torch.uint8) * 200
            views = [View(cam, img.clone(), f"v{i}") for i, cam in enumerate(cams)]
            train, test = split_every([v.name for v in views], request.test_every)
            return Scene(name=request.scene, train=[views[i] for i in train], test=[views[i] for i in test],
                         extent=camera_extent(cams), meta={"source": "stripes plugin", "views": self.views})
''')


@pytest.fixture
def plugin_dir(tmp_path, monkeypatch):
    """A tiny installed distribution: a package plus a dist-info with an ``smgs.datasets`` entry point."""
    yield install(tmp_path / "site", monkeypatch, "smgs_toy_scenes", PLUGIN, registry.ENTRY_POINT_GROUP,
                  {"stripes": "smgs_toy_scenes:Stripes"})
    uninstall("smgs_toy_scenes")


def test_the_builtins_are_formats_and_benchmark_datasets():
    assert {"colmap", "transforms", "procedural", "pattern", "mipnerf360", "tandt", "deepblending"} <= \
        set(registry.list_names())
    assert registry.format_class("mipnerf360") is registry.format_class("colmap")   # a benchmark's own format
    assert get_dataset("tandt").scenes == ("train", "truck")
    with pytest.raises(ValueError, match="unknown dataset 'colmap'; the built-in benchmark datasets: mipnerf360"):
        get_dataset("colmap")
    with pytest.raises(ValueError, match="unknown scene kind 'nerf'; known: colmap, deepblending"):
        registry.format_class("nerf")


def test_a_format_registered_in_process_loads_and_a_benchmark_in_its_format_finds_its_folder(tmp_path):
    @dataclass(frozen=True)
    class Flat:
        shade: int = 100

        def load(self, request: SceneRequest):
            from smgs.data.patterns import pattern_scene

            s = pattern_scene("rect4", 16)
            s.meta["shade"], s.meta["scene"] = self.shade, request.scene
            return s

    registry.register("flat", Flat)
    bench = DatasetSpec(name="mybench", folders=("mb",), scenes=("a",), format="flat",
                        rules={"paper": {"*": ResolutionRule("paper")}})
    registry.register("mybench", bench)
    try:
        assert load_scene("flat", shade=7).meta["shade"] == 7
        assert load_scene("mybench", "a").meta["scene"] == "a"     # the benchmark's name as kind: its format
        with pytest.raises(ValueError, match="scene format 'flat' takes no size; its settings: shade"):
            load_scene("flat", size=3)
        with pytest.raises(ValueError, match="already registered"):
            registry.register("flat", Flat)
        (tmp_path / "mb" / "a").mkdir(parents=True)
        assert bench.scene_dir(tmp_path, "a") == tmp_path / "mb" / "a"
    finally:
        registry.unregister("flat")
        registry.unregister("mybench")


def test_a_format_that_is_no_dataclass_with_load_is_refused_naming_the_guide():
    class NotAConfig:
        def load(self, request):
            raise AssertionError("never loaded")

    registry.register("bad", NotAConfig)
    try:
        with pytest.raises(TypeError, match=r"'bad'.*not a dataclass with load\(request\).*adding-a-scene-format"):
            registry.format_class("bad")
    finally:
        registry.unregister("bad")


def test_an_entry_point_format_is_listed_without_being_imported(plugin_dir):
    assert "stripes" in registry.list_names()
    assert "smgs_toy_scenes" not in sys.modules
    assert registry.plugin_source("stripes") == "plugin smgs-toy-scenes"
    s = load_scene("stripes", views=4)
    assert "smgs_toy_scenes" in sys.modules and len(s.train) + len(s.test) == 4


def test_smgs_list_datasets_lists_a_plugin_format_with_its_distribution(plugin_dir, capsys):
    from smgs_cli.main import main

    assert main(["list", "datasets"]) == 0
    lines = {line.split()[0]: line for line in capsys.readouterr().out.splitlines()}
    assert "grid.datasets=[stripes] (plugin smgs-toy-scenes)" in lines["stripes"]
    assert "colmap" in lines and "plugin" not in lines   # configs/dataset/plugin.yaml is the runner's, not listed


def test_a_dataset_section_is_the_formats_config_and_a_wrong_key_is_refused_naming_it(plugin_dir, tmp_path):
    from protocols.run import run_experiment

    base = ["grid.datasets=[stripes]", "grid.methods=[3dgs]", "report=false", f"out_dir={tmp_path}/runs"]
    with pytest.raises(SystemExit, match=r"dataset.views=1: must be a whole number ≥ 2"):
        run_experiment([*base, "+dataset.views=1"])
    with pytest.raises(SystemExit, match=r"Stripes at dataset: unknown key\(s\) \['colour'\]; known: \['size', 'views'\]"):
        run_experiment([*base, "+dataset.colour=red"])
    assert not (tmp_path / "runs").exists()


def test_a_scene_format_from_a_package_outside_smgs_trains_through_smgs_run(plugin_dir, tmp_path):
    """The plugin is installed (on the path, with its entry point); `smgs run grid.datasets=[stripes]`
    composes its dataset section from configs/dataset/plugin.yaml, trains and records the result."""
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(plugin_dir), str(ROOT)])}
    out = tmp_path / "runs"
    cmd = [sys.executable, "-m", "smgs_cli", "run", "grid.datasets=[stripes]", "grid.methods=[3dgs]", "seeds=1",
           "+dataset.views=5", "protocol.steps=3", "protocol.schedule_steps=null", "eval.fps_repeats=1",
           "eval.flip=false", "eval.fractions=[1.0]", "report=false", "device=cpu", f"out_dir={out}"]
    done = subprocess.run(cmd, env=env, cwd=tmp_path, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stdout + done.stderr
    res = json.loads((out / "stripes/stripes/3dgs/full/seed0/results.json").read_text())
    assert res["status"] == "ok" and res["steps"] == 3 and (res["dataset"], res["scene"]) == ("stripes", "stripes")
    assert res["config"]["dataset"] == {"name": "stripes", "kind": "stripes", "scenes": None, "views": 5}
    assert res["data"]["source"] == "stripes plugin" and res["data"]["views"] == 5


def test_dataset_on_the_command_line_names_a_plugin_without_a_file_the_way_to_run_it(plugin_dir):
    from protocols.run import check_command_line

    assert check_command_line(["dataset=stripes"]) == (
        "dataset=stripes is a plugin scene format or dataset without a file in configs/dataset/: run it with "
        "grid.datasets=[stripes] (its settings as +dataset.KEY=VALUE)")
    assert check_command_line(["dataset=nowhere"]).startswith("dataset=nowhere is no dataset; known: colmap, ")
    assert check_command_line(["grid.datasets=[stripes]", "+dataset.path=/data/x"]) is None   # a plugin's own key


def test_smgs_list_datasets_names_a_plugin_and_not_the_runners_stand_in(plugin_dir, capsys):
    from smgs_cli.listing import main

    assert main(["datasets"]) == 0
    lines = capsys.readouterr().out.splitlines()
    names = [line.split()[0] for line in lines]
    assert "plugin" not in names and {"colmap", "mipnerf360", "procedural", "stripes"} <= set(names)
    assert any(line.startswith("stripes") and "grid.datasets=[stripes] (plugin smgs-toy-scenes)" in line
               for line in lines)
