"""No setting is silently ignored: a key that nothing reads is refused before anything runs (also
when added with ``+``), naming the nearest key; where two settings compete for an axis of the grid
(``grid.seeds`` and an experiment's ``grid.seeds_of``, ``method=`` and ``grid.methods``), the plan
says which won, or the combination is refused."""

from __future__ import annotations

import pytest
from hydra import compose, initialize_config_dir

from protocols.known_keys import CHECKED_SECTIONS, nearest, unread_keys
from protocols.run import CONFIG_DIR, compose_checked, plan, run_experiment

SMALL = ["dataset.width=32", "dataset.height=24", "dataset.n_views=8", "report=false"]


def refused(tmp_path, *args: str) -> str:
    out = tmp_path / "runs"
    with pytest.raises(SystemExit) as e:
        run_experiment(["+experiment=smoke", *SMALL, f"out_dir={out}", *args])
    assert not out.exists()
    return str(e.value)


@pytest.mark.parametrize("arg", ["+steps=30", "steps=30", "++steps=30"])
def test_a_key_nothing_reads_is_refused_naming_the_nearest(tmp_path, arg):
    """Hydra's own hint for ``steps=30`` is ``+steps=30``, which added a key nothing read: the run
    trained the preset's 300 steps with rc 0 and no word."""
    msg = refused(tmp_path, arg)
    assert msg.startswith("invalid config, nothing was run:\n  ")
    assert f"{arg}: no setting is called steps, so nothing would read it; did you mean protocol.steps=30?" in msg


@pytest.mark.parametrize("arg, near", [("+grid.seed=[0]", "grid.seeds=[0]"), ("+executor.worker=3", "executor.workers=3"),
                                       ("eval.fps_repeat=3", "eval.fps_repeats=3"), ("+step=3", "protocol.steps=3"),
                                       ("+devise=cpu", "device=cpu")])
def test_the_nearest_key_is_beside_it_or_shares_its_name(tmp_path, arg, near):
    assert f"did you mean {near}?" in refused(tmp_path, arg)


@pytest.mark.parametrize("section", CHECKED_SECTIONS)
def test_each_section_left_to_its_type_refuses_an_unknown_key_itself(tmp_path, section):
    """The known-key check leaves a key added below these sections to the section's type (a
    strategy's or a scene format's own keys live there): each must refuse an unknown one."""
    assert "bogus_key" in refused(tmp_path, f"+{section}.bogus_key=1")


def test_the_sections_types_name_the_nearest_key(tmp_path):
    assert "unknown key(s) ['fps_repeat'] (did you mean eval.fps_repeats?)" in refused(tmp_path, "+eval.fps_repeat=3")
    assert "(did you mean dataset.width?)" in refused(tmp_path, "+dataset.widht=40")


def test_known_keys_come_from_the_composed_config_and_its_open_mappings():
    """A key of the config (as another YAML file or helper adds it) is known without a list; a key
    below a mapping the config leaves open ({}: grid.seeds_of, a plugin method's train) is its
    reader's; a config group is no key."""
    base = {"executor": {"slurm": {"account": None}}, "grid": {"seeds_of": {}}, "method": {"name": "x", "train": {}}}
    assert unread_keys(base, ["executor.slurm.account=lab", "+grid.seeds_of.3dgs=[0,1]", "+method.train.anything=1",
                              "dataset=colmap", "+experiment=smoke", "hydra.verbose=true"]) == []
    (msg,) = unread_keys(base, ["executor.slurm.acount=lab"])
    assert "did you mean executor.slurm.account=lab?" in msg
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        assert compose_checked(["+experiment=smoke", "+method.train.densify.strategy=mcmc"]).seed == 0
        with pytest.raises(SystemExit, match=r"method.foo=1: no setting is called method.foo, so nothing would read it "
                                             r"\(settings"):   # nothing near: no guess from another section
            compose_checked(["method.foo=1"])
        with pytest.raises(SystemExit, match=r"added with \+: \+method.train.densify.strategy=mcmc"):
            compose_checked(["method.train.densify.strategy=mcmc"])


def test_nearest_prefers_a_sibling_then_the_same_name():
    known = ["seed", "seeds", "grid.seeds", "protocol.steps", "eval.flip", "executor.workers"]
    assert nearest("grid.seed", known) == "grid.seeds"
    assert nearest("steps", known) == "protocol.steps"
    assert nearest("eval.flop", known) == "eval.flip"
    assert nearest("eval.zzz", known) is None


def cells(capsys, *overrides: str) -> tuple[list[str], str]:
    """The planned cells (method/budget/seed) and what the plan printed."""
    ov = list(overrides)
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        planned, _ = plan(compose(config_name="config", overrides=ov), ov)
    return [f"{c.method}/{c.budget}/seed{c.seed}" for c in planned], capsys.readouterr().out


def test_grid_seeds_on_the_command_line_replaces_the_experiments_seeds_of_and_says_so(capsys):
    keys, said = cells(capsys, "+experiment=smoke", "grid.methods=[3dgs,gef_only]", "grid.seeds=[0]")
    assert keys == ["3dgs/full/seed0", "gef_only/full/seed0"]
    assert "grid.seeds=[0]: every method runs seeds 0 (instead of the experiment's grid.seeds_of" in said
    keys, said = cells(capsys, "+experiment=smoke", "grid.methods=[3dgs,gef_only]", "grid.seeds=[0]",
                       "grid.seeds_of={3dgs:[1,2]}")
    assert keys == ["3dgs/full/seed1", "3dgs/full/seed2", "gef_only/full/seed0"]
    assert "3dgs, softmax_gs run their grid.seeds_of seeds, the other methods grid.seeds" in said   # merged into smoke's
    keys, said = cells(capsys, "+experiment=smoke", "grid.methods=[3dgs,gef_only]")   # nothing competes: no word
    assert keys == ["3dgs/full/seed0", "3dgs/full/seed1", "3dgs/full/seed2", "gef_only/full/seed0"] and not said


def test_a_key_below_grid_seeds_of_counts_as_giving_it(capsys):
    """``grid.seeds_of.softmax_gs=[0,1]`` beside ``grid.seeds=[0]`` gives both: the per-method seeds
    are kept, not replaced by ``grid.seeds`` as when only ``grid.seeds`` is given."""
    keys, said = cells(capsys, "+experiment=smoke", "grid.methods=[softmax_gs,gef_only]", "grid.seeds=[0]",
                       "grid.seeds_of.softmax_gs=[0,1]")
    assert keys == ["softmax_gs/full/seed0", "softmax_gs/full/seed1", "gef_only/full/seed0"]
    assert "run their grid.seeds_of seeds, the other methods grid.seeds" in said
    with pytest.raises(SystemExit, match=r"seeds=2 and grid\.seeds_of\.softmax_gs=\[1\] disagree"):
        cells(capsys, "+experiment=smoke", "seeds=2", "grid.seeds_of.softmax_gs=[1]")


def test_seeds_n_says_what_it_replaces_and_refuses_a_seed_list_beside_it(capsys):
    keys, said = cells(capsys, "+experiment=smoke", "grid.methods=[3dgs]", "seeds=1")
    assert keys == ["3dgs/full/seed0"] and "seeds=1: running seeds 0 of every method (instead of" in said
    for other in ("grid.seeds=[5]", "grid.seeds_of={3dgs:[1]}"):
        with pytest.raises(SystemExit, match=rf"seeds=2 and {other.split('=')[0]}=.* disagree"):
            cells(capsys, "+experiment=smoke", "seeds=2", other)


def test_a_single_method_budget_or_scene_replaces_the_experiments_list_and_says_so(capsys):
    keys, said = cells(capsys, "+experiment=smoke", "method=gef_only")
    assert keys == ["gef_only/full/seed0"]
    assert "method=gef_only: running gef_only (instead of the experiment's grid.methods [3dgs, gef_only" in said
    keys, said = cells(capsys, "+experiment=smoke", "grid.methods=[gef_only]", "budget=5pct")
    assert keys == ["gef_only/5pct/seed0"] and "budget=5pct: running 5pct (instead of the experiment's grid.budgets [full])" in said
    with pytest.raises(SystemExit, match=r"method=3dgs and grid.methods=\[gef_only\] disagree"):
        cells(capsys, "+experiment=smoke", "method=3dgs", "grid.methods=[gef_only]")
    ov = ["+experiment=budget5", "dataset=tandt", "scene=truck"]
    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        planned, _ = plan(compose(config_name="config", overrides=ov), ov)
    assert {c.scene for c in planned} == {"truck"}
