"""A budget has one name for its kind (``kind``; ``preset`` before) and for its gradient threshold
(``grad_threshold``; ``densify_grad_threshold`` in the budget and ``grow_grad2d`` in the trainer
before), and one home for what the kind sets (``smgs.train.config.BUDGETS``); the renaming kept
every finished result's identity."""

import warnings
from pathlib import Path

import pytest
import yaml

from protocols.run_settings import run_settings
from protocols.sections import BudgetConfig
from smgs.train.config import BUDGETS, budget_threshold

REPO = Path(__file__).resolve().parent.parent
BUDGET_FILES = sorted((REPO / "configs" / "budget").glob("*.yaml"))


@pytest.mark.parametrize("path", BUDGET_FILES, ids=lambda p: p.stem)
def test_a_budget_file_names_a_kind_and_holds_no_threshold(path):
    section = yaml.safe_load(path.read_text())
    assert set(section) <= {"name", "kind", "cap"} and section["name"] == path.stem
    assert BudgetConfig.of({"budget": section}).kind in BUDGETS


# The budget sections as the YAML held them before, and so as finished results were hashed.
EARLIER = {
    "full": {"name": "full", "densify_grad_threshold": 0.0002, "cap": None},
    "5pct": {"name": "5pct", "densify_grad_threshold": 0.004, "cap": None},
    "light": {"name": "light", "densify_grad_threshold": 0.0003, "cap": None},
    "mini": {"name": "mini", "densify_grad_threshold": 0.0005, "cap": None},
    "cap16": {"name": "cap16", "preset": "cap", "densify_grad_threshold": 0.0002, "cap": 16},
    "mcmc_2593000": {"name": "mcmc_2593000", "preset": "mcmc", "densify_grad_threshold": None, "cap": 2593000},
    "pretrained": {"name": "pretrained", "preset": "full", "densify_grad_threshold": 0.0002, "cap": None},
}


@pytest.mark.parametrize("name", EARLIER)
def test_the_identity_of_each_budget_is_what_results_were_hashed_with(name):
    section = yaml.safe_load((REPO / "configs" / "budget" / f"{name}.yaml").read_text())
    assert BudgetConfig.of({"budget": section}).identity() == EARLIER[name]


def cell(budget: dict) -> dict:
    return {"budget": budget, "protocol": {"name": "cpu", "steps": 3000, "resolution": "cpu", "test_every": 8,
                                           "schedule_steps": 30000}, "dataset": {}, "seed": 0}


def test_run_settings_carry_the_kind_and_its_threshold_or_the_override():
    rs = run_settings(cell({"name": "cap16", "kind": "cap", "cap": 16}))
    assert (rs.budget, rs.budget_kind, rs.grad_threshold, rs.cap) == ("cap16", "cap", 2e-4, 16)
    rs = run_settings(cell({"name": "5pct", "cap": None, "grad_threshold": 1e-3}))
    assert (rs.budget_kind, rs.grad_threshold) == ("5pct", 1e-3)
    assert run_settings(cell({"name": "mcmc_4", "kind": "mcmc", "cap": 4})).grad_threshold is None
    with pytest.warns(DeprecationWarning, match="budget_kind"):
        assert rs.preset == "5pct"


def test_the_thresholds_are_the_papers_groups():
    assert [budget_threshold(k) for k in ("full", "light", "mini", "5pct", "cap", "mcmc")] == \
        [2e-4, 3e-4, 5e-4, 4e-3, 2e-4, None]
    with pytest.raises(ValueError, match="unknown budget kind 'huge'"):
        budget_threshold("huge")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match="unknown kind 'cap'.*budget.kind|unknown kind"):
            BudgetConfig.of({"budget": {"name": "cap7", "cap": 7}})


def test_the_densify_section_names_the_kind_budget_kind_and_reads_its_earlier_name():
    """``DensifyConfig.budget_kind`` was ``budget``: a dict with the earlier name (a method config,
    a checkpoint's config) reads as today's, one with both names is refused, and the form a
    finished result was hashed with keeps the earlier name."""
    from smgs.train.config import (DensifyConfig, TrainConfig, current_train_keys, densify_config,
                                   earlier_train_keys, from_dict, to_dict)

    assert from_dict(DensifyConfig, {"budget": "mcmc", "cap": 3}) == densify_config("mcmc", cap=3)
    with pytest.raises(ValueError, match="'budget' is the earlier name of 'budget_kind'"):
        from_dict(TrainConfig, {"densify": {"budget": "full", "budget_kind": "mini"}})
    now = to_dict(from_dict(TrainConfig, {"densify": {"budget_kind": "5pct"}}))
    earlier = earlier_train_keys(now)
    assert earlier["densify"]["budget"] == "5pct" and "budget_kind" not in earlier["densify"]
    assert current_train_keys(earlier) == now and earlier_train_keys(earlier) == earlier


def test_a_checkpoint_written_under_the_earlier_name_resumes(tmp_path):
    import torch

    from baselines.registry import create_method
    from baselines.splatting import CHECKPOINT
    from smgs.data.patterns import pattern_scene
    from smgs.train.config import earlier_train_keys

    scene = pattern_scene("circle4", 8)
    cfg = {"steps": 2, "densify": {"budget_kind": "cap", "cap": 4}}
    a = create_method("3dgs", scene, cfg, device="cpu")
    a.train_step(0)
    a.save(tmp_path / "ck")
    state = torch.load(tmp_path / "ck" / CHECKPOINT, weights_only=True)
    state["trainer"]["config"] = earlier_train_keys(state["trainer"]["config"])   # as it was written then
    assert "budget" in state["trainer"]["config"]["densify"]
    torch.save(state, tmp_path / "ck" / CHECKPOINT)
    b = create_method("3dgs", scene, cfg, device="cpu")
    b.load(tmp_path / "ck")
    assert b.trainer.step_count == a.trainer.step_count == 1


def test_a_result_is_hashed_with_the_earlier_name(monkeypatch):
    """The method's complete settings enter the result's hash with ``densify.budget``, the name
    every finished result was hashed with, so the rename retrains nothing."""
    import protocols.cell as cell_module
    import smgs.identity

    seen = []
    monkeypatch.setattr(smgs.identity, "config_hash", lambda ident: seen.append(ident) or "h")
    c = {**cell({"name": "5pct", "cap": None}), "method": {"name": "3dgs"}}
    cell_module.result_hash(c)
    densify = seen[0]["resolved_settings"]["densify"]
    assert densify["budget"] == "5pct" and "budget_kind" not in densify
    assert densify["grow_grad2d"] == 4e-3 and "grad_threshold" not in densify
    assert seen[0]["budget"]["densify_grad_threshold"] == 4e-3


def test_the_threshold_has_one_name_and_its_earlier_names_still_read():
    """``budget.grad_threshold`` is ``RunSettings.grad_threshold`` is ``densify.grad_threshold``; a
    budget section or a method config written with the earlier name reads as today's (the same
    identity), one giving both names is refused naming them."""
    from smgs.train.config import DensifyConfig, TrainConfig, from_dict

    now = BudgetConfig.of({"budget": {"name": "5pct", "cap": None, "grad_threshold": 1e-3}})
    then = BudgetConfig.of({"budget": {"name": "5pct", "cap": None, "densify_grad_threshold": 1e-3}})
    assert now == then and now.grad_threshold == 1e-3 and now.identity() == then.identity()
    assert run_settings(cell({"name": "5pct", "cap": None, "densify_grad_threshold": 1e-3})).grad_threshold == 1e-3
    with pytest.raises(ValueError, match="'densify_grad_threshold' is the earlier name of 'grad_threshold'"):
        BudgetConfig.of({"budget": {"name": "5pct", "cap": None, "grad_threshold": 1e-3,
                                    "densify_grad_threshold": 1e-3}})
    assert BudgetConfig.of({"budget": {"name": "mcmc_4", "kind": "mcmc", "cap": 4, "grad_threshold": 1e-3}}) \
        .grad_threshold is None    # MCMC refines by opacity: no threshold to set
    assert from_dict(DensifyConfig, {"grow_grad2d": 1e-3}).grad_threshold == 1e-3
    with pytest.raises(ValueError, match="'grow_grad2d' is the earlier name of 'grad_threshold'"):
        from_dict(TrainConfig, {"densify": {"grow_grad2d": 1e-3, "grad_threshold": 1e-3}})


def _plan(overrides: list[str]) -> list[dict]:
    from hydra import compose, initialize_config_dir

    from protocols.run import CONFIG_DIR, plan

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        return plan(compose(config_name="config", overrides=overrides), overrides)[1]


@pytest.mark.parametrize("base, cap, name, kind", [("cap4", 10, "cap10", "cap"), ("mcmc_4", 100, "mcmc_100", "mcmc")])
def test_a_budget_made_on_the_command_line_runs_under_its_own_name(base, cap, name, kind):
    """``budget=cap4 budget.cap=N budget.name=capN`` (docs/usage.md) makes a budget no file holds: its
    cells are composed from the file it started from, with the user's cap, in their own folder."""
    [payload] = _plan(["grid.methods=[3dgs]", f"budget={base}", f"budget.cap={cap}", f"budget.name={name}"])
    assert payload["config"]["budget"] == {"name": name, "kind": kind, "cap": cap}
    assert f"/3dgs/{name}/seed0" in payload["run_dir"]


def test_a_grid_budget_that_no_file_holds_is_refused_with_the_way_to_make_it():
    with pytest.raises(SystemExit, match=r"budget 'cap10' \(grid.budgets\) is no file in configs/budget/.*"
                                         r"budget=cap4 budget.cap=N budget.name=cap10"):
        _plan(["grid.methods=[3dgs]", "grid.budgets=[cap10]"])
