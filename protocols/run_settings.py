"""From a cell's config to what a method is created with: its own settings (``method_settings``)
and the protocol's neutral ``RunSettings`` (steps, seed, budget, cap, schedule length, backend),
which each method maps onto its own keys."""

from __future__ import annotations

from typing import Any

from baselines.method import RunSettings
from baselines.registry import merge_config
from protocols.sections import BudgetConfig, ProtocolConfig


def method_settings(cfg: dict) -> dict[str, Any]:
    """The method's ``train`` settings with the dataset's overrides for its methods (e.g. the
    2D-pattern set-up) merged on top."""
    return merge_config(cfg["method"].get("train") or {}, cfg["dataset"].get("train") or {})


def run_settings(cfg: dict) -> RunSettings:
    """The cell's steps (a dataset with its own step count keeps its own schedule), seed, budget
    and renderer backend."""
    budget, protocol = BudgetConfig.of(cfg), ProtocolConfig.of(cfg)
    own_steps = cfg["dataset"].get("steps")
    return RunSettings(steps=int(own_steps or protocol.steps), seed=int(cfg["seed"]), budget=budget.name,
                       budget_kind=str(budget.kind), grad_threshold=budget.grad_threshold, cap=budget.cap,
                       schedule_steps=None if own_steps else protocol.schedule_steps,
                       backend=cfg.get("backend", "auto"))
