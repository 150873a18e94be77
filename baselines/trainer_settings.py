"""The built-in methods' reading of a protocol's ``RunSettings``: steps, seed, budget and backend
become the settings of ``smgs.train.Trainer`` (a TrainConfig dict), the budget its densification
keys, and the protocol's schedule length a scaling of the 3DGS schedule."""

from __future__ import annotations

from typing import Any

from baselines.method import RunSettings, merge_config
from smgs.train.config import DensifyConfig, current_keys

SCHEDULE_KEYS = ("refine_start", "refine_stop", "refine_every", "reset_every")


def train_config(config: dict[str, Any], run: RunSettings) -> dict[str, Any]:
    """The TrainConfig dict of a run: the method's ``config`` (its own settings and the dataset's
    overrides), then the run's step count, seed, backend and budget."""
    mc = merge_config(config, {})
    densify = current_keys(DensifyConfig, dict(mc.get("densify") or {}))   # its earlier key names as today's
    densify.update(budget_kind=run.budget_kind)
    if run.grad_threshold is not None:   # MCMC budgets have none
        densify["grad_threshold"] = run.grad_threshold
    if run.cap is not None:
        densify["cap"] = int(run.cap)
    mc.update(steps=run.steps, seed=run.seed, backend=run.backend, densify=densify)
    scale_schedule(mc, run.steps, run.schedule_steps)
    return mc


def scale_schedule(mc: dict[str, Any], steps: int, schedule_steps: int | None) -> None:
    """Scale the 3DGS schedule (written for ``schedule_steps``, 30K) to a run of ``steps``, as
    gsplat's ``steps_scaler`` does: refinement start/stop/interval, opacity reset and the SH degree
    interval. Unscaled, a 3000-step run would reset every opacity to 0.01 at its last step."""
    if not schedule_steps or steps == int(schedule_steps):
        return
    from smgs.train import BUDGETS, TrainConfig

    f = steps / int(schedule_steps)
    d = mc["densify"]
    defaults = {**vars(DensifyConfig()), **BUDGETS.get(d.get("budget_kind"), {})}   # the kind's schedule
    for k in SCHEDULE_KEYS:
        v = d.get(k, defaults[k])
        if v is not None:
            d[k] = max(1, round(v * f))
    mc["sh_degree_interval"] = max(1, round(mc.get("sh_degree_interval", TrainConfig.sh_degree_interval) * f))
