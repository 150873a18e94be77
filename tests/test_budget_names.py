"""A budget has one name for its kind (``kind``; ``preset`` before) and one home for what the kind
sets (``smgs.train.config.BUDGETS``); the renaming kept every finished result's identity."""

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
    rs = run_settings(cell({"name": "5pct", "cap": None, "densify_grad_threshold": 1e-3}))
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
