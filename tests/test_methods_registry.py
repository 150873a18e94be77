"""The method registry: built-ins, unknown names, fixed settings, scene needs, entry-point plugins."""

import sys
import textwrap

import pytest

from smgs.raster import MODES
import torch

from baselines import (BUILTINS, ENTRY_POINT_GROUP, Method, MethodSpec, SceneNeeds, create_method,
                       get_spec, list_methods, method_class, register, resolve_config, unregister)
from smgs.data.patterns import pattern_scene
from plugin_dist import install, uninstall

PLUGIN = textwrap.dedent('''
    import torch
    from baselines.method import SceneNeeds
    from smgs.raster import RenderOutput, RenderStats

    class ConstantColour:
        """A toy method: one trainable colour for the whole image."""
        needs = SceneNeeds()

        def __init__(self, scene, config=None, *, name=None, device, run=None):
            self.scene, self.config, self.device, self.name, self.run = scene, dict(config or {}), device, name, run
            self.colour = torch.zeros(3, device=device, requires_grad=True)
            self.opt = torch.optim.Adam([self.colour], lr=float(self.config.get("lr", 0.1)))

        def train_step(self, step):
            v = self.scene.train[0]
            loss = ((self.colour - v.rgb.to(self.device)) ** 2).mean()
            self.opt.zero_grad(); loss.backward(); self.opt.step()
            return {"loss": float(loss.detach())}

        def render(self, camera):
            rgb = self.colour.detach().expand(camera.height, camera.width, 3)
            z = torch.zeros(camera.height, camera.width, device=self.device)
            return RenderOutput(rgb, z + 1, z, RenderStats(z.long(), 0, 0))

        def num_gaussians(self):
            return 0

        def save(self, path):
            pass

        def load(self, path):
            pass

        def prepare(self):
            return ""

        def parameter_values(self):
            return {"colour": self.colour.detach()}

        def describe(self):
            r = self.run
            plan = [] if r is None else [f"asked: {r.steps} steps, seed {r.seed}, budget {r.budget} "
                                         f"({r.budget_kind}), cap {r.cap}, schedule {r.schedule_steps}"]
            return {"method": self.name, "config": self.config, "hparams": "toy", "step": 0, "plan": plan}
''')


@pytest.fixture
def plugin(tmp_path, monkeypatch):
    """A tiny installed distribution: a package plus a dist-info with an ``smgs.methods`` entry point."""
    install(tmp_path, monkeypatch, "smgs_toy_plugin", PLUGIN, ENTRY_POINT_GROUP, {"toy": "smgs_toy_plugin:ConstantColour"})
    yield "toy"
    uninstall("smgs_toy_plugin")


def test_builtins_are_one_class_with_a_mode_switch():
    assert {"softmax_gs", "3dgs", "gef_only", "softmax_only"} <= set(list_methods())
    classes = {method_class(n) for n in BUILTINS}
    assert len(classes) == 1
    modes = {n: get_spec(n).fixed["mode"] for n in BUILTINS}
    assert set(modes.values()) == set(MODES)
    assert all(modes[m] == m for m in MODES)
    # StopThePop is 3DGS compositing in each pixel's own depth order
    assert get_spec("stopthepop").fixed == {"mode": "3dgs", "sort": "per_pixel"}
    assert set(BUILTINS) == set(MODES) | {"stopthepop"}
    assert get_spec("softmax_gs").paper_name == "Softmax-GS"


def test_unknown_method_lists_the_registered_ones():
    with pytest.raises(KeyError) as e:
        get_spec("softmax-gs")
    msg = str(e.value)
    assert "softmax-gs" in msg and all(n in msg for n in BUILTINS)


def test_fixed_mode_cannot_be_overridden():
    assert resolve_config("gef_only", {"steps": 5})["mode"] == "gef_only"
    with pytest.raises(ValueError, match="fixes mode"):
        resolve_config("gef_only", {"mode": "softmax_gs"})


def test_scene_needs_are_checked():
    scene = pattern_scene("circle4", 8)
    needs = SceneNeeds(required=frozenset({"sfm_points"}), optional=frozenset({"background"}))
    with pytest.raises(ValueError, match="needs sfm_points"):
        needs.check(scene, "colmap_only")
    assert SceneNeeds(optional=frozenset({"background"})).check(scene) == ["scene has no background"]
    with pytest.raises(ValueError, match="unknown scene capabilities"):
        SceneNeeds(required=frozenset({"lidar"}))


def test_register_in_process():
    spec = MethodSpec("softmax_gs_k8", "baselines.splatting:GaussianSplatting", {"mode": "softmax_gs", "k_max": 8})
    register(spec)
    try:
        assert "softmax_gs_k8" in list_methods()
        m = create_method("softmax_gs_k8", pattern_scene("circle4", 8), {"steps": 2}, device="cpu")
        assert m.config.k_max == 8 and isinstance(m, Method)
        with pytest.raises(ValueError, match="already registered"):
            register(spec)
    finally:
        unregister("softmax_gs_k8")


def test_entry_point_plugin_is_listed_lazily_and_created(plugin):
    assert plugin in list_methods()
    assert "smgs_toy_plugin" not in sys.modules          # listing does not import the plugin
    scene = pattern_scene("rect4", 8)
    m = create_method(plugin, scene, {"lr": 0.2}, device="cpu")
    assert "smgs_toy_plugin" in sys.modules
    assert isinstance(m, Method) and m.device == torch.device("cpu")   # the constructor got a torch.device
    for s in range(30):
        m.train_step(s)
    out = m.render(scene.test[0].camera)
    torch.testing.assert_close(out.rgb[0, 0], scene.train[0].rgb.mean((0, 1)), atol=0.05, rtol=0)
    assert get_spec(plugin).source.startswith("plugin smgs-toy-plugin")


def test_a_plugin_run_by_the_protocol_gets_neutral_run_settings(plugin, tmp_path):
    """Through ``protocols.run`` a plugin receives its own ``method.train`` config and the
    protocol's steps, seed, budget and cap as ``RunSettings``, never the built-in trainer's keys."""
    import json

    from protocols.run import run_experiment

    s = run_experiment(["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
                        f"grid.methods=[{plugin}]", "dataset.size=16", "dataset.steps=6", "report=false",
                        "eval.fps_repeats=1", "eval.flip=false", f"out_dir={tmp_path}"])
    assert [x["status"] for x in s] == ["ok"], s
    res = json.loads((tmp_path / f"patterns/circle4/{plugin}/cap4/seed0/results.json").read_text())
    assert res["steps"] == 6 and res["hparams"] == "toy"
    assert "asked: 6 steps, seed 0, budget cap4 (cap), cap 4, schedule None" in res["diagnostics"]["plan"]
    assert set(res["diagnostics"]["params"]) == {"colour"}


def test_a_method_missing_part_of_the_contract_is_refused_naming_it():
    class NoRun:
        needs = SceneNeeds()

        def __init__(self, scene, config=None, *, name=None, device):
            raise AssertionError("must not be constructed")

        train_step = render = num_gaussians = save = load = describe = parameter_values = prepare = \
            lambda self, *a: None

    class NoParams(NoRun):
        parameter_values = None

    register(MethodSpec("no_run", NoRun))
    register(MethodSpec("no_params", NoParams))
    try:
        with pytest.raises(TypeError, match=r"'no_run'.*takes no `run` argument.*Adding a method"):
            create_method("no_run", pattern_scene("circle4", 8), {}, device="cpu")
        with pytest.raises(TypeError, match=r"'no_params'.*does not implement Method\.parameter_values"):
            create_method("no_params", pattern_scene("circle4", 8), {}, device="cpu")
    finally:
        unregister("no_run")
        unregister("no_params")


def test_a_method_without_a_device_argument_is_refused_by_name():
    class OldStyle:
        needs = SceneNeeds()

        def __init__(self, scene, config=None, *, name=None):
            raise AssertionError("must not be constructed")

        train_step = render = num_gaussians = save = load = describe = parameter_values = prepare = \
            lambda self, *a: None

    register(MethodSpec("old_style", OldStyle))
    try:
        with pytest.raises(TypeError, match=r"'old_style'.*takes no `device` argument.*Adding a method"):
            create_method("old_style", pattern_scene("circle4", 8), {}, device="cpu")
    finally:
        unregister("old_style")


def test_plugin_cannot_shadow_a_builtin(tmp_path, monkeypatch):
    dist = tmp_path / "evil-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text("Metadata-Version: 2.1\nName: evil\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{ENTRY_POINT_GROUP}]\n3dgs = nowhere:Nothing\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    with pytest.warns(UserWarning, match="shadowed"):
        names = list_methods()
    assert names.count("3dgs") == 1
    assert method_class("3dgs").__name__ == "GaussianSplatting"
