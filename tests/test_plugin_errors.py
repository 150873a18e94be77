"""A plug-in's entry point that cannot be used (a misspelt attribute or module, an object that is not
what its registry takes) stops ``smgs run`` before anything runs, in the one-block form, naming the
entry point, its distribution and the fix: for a scene format, a densification strategy and a
method alike."""

from __future__ import annotations

import textwrap

import pytest

from plugin_dist import install, uninstall
from protocols.run import run_experiment

SOURCE = textwrap.dedent('''
    class Good:
        """No scene format and no strategy: neither a dataclass nor a Strategy."""

        def load(self, request):
            raise AssertionError("never called")
''')

GROUPS = {"dataset": "smgs.datasets", "strategy": "smgs.strategies", "method": "smgs.methods"}
CASES = {   # entry point -> the words that name what is wrong with it
    "hostile:Goood": "of the distribution hostile 0.1: hostile has no 'Goood' (a misspelt name?)",
    "hostle:Good": "of the distribution hostile 0.1: no module 'hostle' is installed (a misspelt module?)",
}


@pytest.fixture
def hostile(tmp_path, monkeypatch):
    def put(kind: str, target: str):
        install(tmp_path / "site", monkeypatch, "hostile", SOURCE, GROUPS[kind], {"bad": target})
    yield put
    uninstall("hostile")


def _run(kind: str, tmp_path):
    args = {"dataset": ["grid.datasets=[bad]", "grid.methods=[3dgs]"],
            "strategy": ["grid.methods=[3dgs]", "+method.train.densify.strategy=bad"],
            "method": ["grid.methods=[bad]"]}[kind]
    with pytest.raises(SystemExit) as e:
        run_experiment([*args, "report=false", "device=cpu", f"out_dir={tmp_path}/runs"])
    assert not (tmp_path / "runs").exists(), "nothing ran"
    return str(e.value)


@pytest.mark.parametrize("kind", ["dataset", "strategy", "method"])
@pytest.mark.parametrize("target", list(CASES))
def test_a_misspelt_entry_point_names_itself_its_distribution_and_the_fix(hostile, tmp_path, kind, target):
    hostile(kind, target)
    msg = _run(kind, tmp_path)
    assert msg.startswith("invalid config, nothing was run:"), msg
    assert f"the entry point bad = {target} (group {GROUPS[kind]}) of the distribution hostile 0.1" in msg
    assert CASES[target] in msg
    assert f'correct it in hostile\'s metadata ([project.entry-points."{GROUPS[kind]}"]' in msg
    assert "pip uninstall hostile" in msg and "Traceback" not in msg


@pytest.mark.parametrize("kind, takes", [
    ("dataset", "a dataclass with load(request) -> Scene"),
    ("strategy", "a dataclass subclassing smgs.train.strategies.Strategy"),
])
def test_an_entry_point_to_what_the_registry_does_not_take_names_it_and_the_fix(hostile, tmp_path, kind, takes):
    hostile(kind, "hostile:Good")
    msg = _run(kind, tmp_path)
    assert msg.startswith("invalid config, nothing was run:"), msg
    assert f"the entry point bad = hostile:Good (group {GROUPS[kind]}) of the distribution hostile 0.1 names " \
           "<class 'hostile.Good'>, which is not " + takes in msg
    assert "point the entry point at one: correct it in hostile's metadata" in msg


def test_the_registry_raises_a_plugin_error_that_is_a_value_error(hostile):
    from smgs.data import registry
    from smgs.plugins import PluginError

    hostile("dataset", "hostile:Goood")
    with pytest.raises(PluginError) as e:
        registry.format_class("bad")
    assert isinstance(e.value, ValueError)
    registry.register("loose", object)
    try:
        with pytest.raises(TypeError) as t:
            registry.format_class("loose")
        assert "'loose' (registered in this process) is <class 'object'>" in str(t.value)
        assert isinstance(t.value, PluginError)
    finally:
        registry.unregister("loose")
