"""The built-in methods' reading of a protocol's ``RunSettings``: steps, seed, budget and backend
become the settings of ``smgs.train.Trainer`` (a TrainConfig dict), the budget its densification
keys, and the protocol's schedule length a scaling of the 3DGS schedule."""

from __future__ import annotations

from typing import Any

from baselines.method import RunSettings, merge_config
from smgs.train.config import DensifyConfig, current_keys, densify_start

SCHEDULE_KEYS = ("refine_start", "refine_stop", "refine_every", "reset_every")


def train_config(config: dict[str, Any], run: RunSettings) -> dict[str, Any]:
    """The TrainConfig dict of a run: the method's ``config`` (its own settings and the dataset's
    overrides), then the run's step count, seed, renderer (backend and variants) and budget."""
    mc = merge_config(config, {})
    densify = current_keys(DensifyConfig, dict(mc.get("densify") or {}))   # its earlier key names as today's
    densify.update(budget_kind=run.budget_kind)
    if run.grad_threshold is not None and "grad_threshold" in strategy_keys(densify):   # MCMC has none
        densify["grad_threshold"] = run.grad_threshold
    if run.cap is not None:
        densify["cap"] = int(run.cap)
    mc.update(steps=run.steps, seed=run.seed, backend=run.backend, kernels=run.kernels, glue=run.glue,
              densify=densify)
    scale_schedule(mc, run.steps, run.schedule_steps)
    return mc


def strategy_keys(densify: dict[str, Any]) -> dict[str, Any]:
    """The keys of the strategy a densify section runs (the one it names, else its budget kind's) with
    the values the section starts from: the strategy's defaults, then its budget kind's."""
    return densify_start(densify.get("budget_kind") or "full", densify.get("strategy"))[1]


def scale_schedule(mc: dict[str, Any], steps: int, schedule_steps: int | None) -> None:
    """Scale the 3DGS schedule (written for ``schedule_steps``, 30K) to a run of ``steps``, as
    gsplat's ``steps_scaler`` does: refinement start/stop/interval, opacity reset and the SH degree
    interval. Unscaled, a 3000-step run would reset every opacity to 0.01 at its last step."""
    if not schedule_steps or steps == int(schedule_steps):
        return
    from smgs.train import TrainConfig

    f = steps / int(schedule_steps)
    d = mc["densify"]
    defaults = strategy_keys(d)   # the strategy's schedule (a budget kind's starting values)
    for k in SCHEDULE_KEYS:
        v = d.get(k, defaults[k])
        if v is not None:
            d[k] = max(1, round(v * f))
    mc["sh_degree_interval"] = max(1, round(mc.get("sh_degree_interval", TrainConfig.sh_degree_interval) * f))
