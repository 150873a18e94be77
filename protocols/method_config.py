"""A cell's training settings for the built-in trainer: the method's, the dataset's and the
protocol's (steps, budget, seed, schedule) merged into one TrainConfig dict."""

from __future__ import annotations

from typing import Any


def method_config(cfg: dict) -> dict[str, Any]:
    """The TrainConfig dict of a cell: the method's settings, then the dataset's overrides (e.g.
    the 2D-pattern set-up), then the protocol's step count, the budget and the seed."""
    from baselines.registry import merge_config

    mc = merge_config(cfg["method"].get("train") or {}, cfg["dataset"].get("train") or {})
    budget = cfg["budget"]
    densify = dict(mc.get("densify") or {})
    densify.update(budget=budget.get("preset", budget["name"]))
    if budget.get("densify_grad_threshold") is not None:   # MCMC budgets have none
        densify["grow_grad2d"] = budget["densify_grad_threshold"]
    if budget.get("cap") is not None:
        densify["cap"] = int(budget["cap"])
    own_steps = cfg["dataset"].get("steps")    # a dataset with its own step count has its own schedule
    steps = int(own_steps or cfg["protocol"]["steps"])
    mc.update(steps=steps, seed=int(cfg["seed"]), backend=cfg.get("backend", "auto"), densify=densify)
    if not own_steps:
        scale_schedule(mc, steps, cfg["protocol"].get("schedule_steps"))
    return mc


SCHEDULE_KEYS = ("refine_start", "refine_stop", "refine_every", "reset_every")


def scale_schedule(mc: dict[str, Any], steps: int, schedule_steps: int | None) -> None:
    """Scale the 3DGS schedule (written for ``schedule_steps``, 30K) to a run of ``steps``, as
    gsplat's ``steps_scaler`` does: refinement start/stop/interval, opacity reset and the SH degree
    interval. Unscaled, a 3000-step run would reset every opacity to 0.01 at its last step."""
    if not schedule_steps or steps == int(schedule_steps):
        return
    from smgs.train import BUDGETS, DensifyConfig, TrainConfig

    f = steps / int(schedule_steps)
    d = mc["densify"]
    defaults = {**vars(DensifyConfig()), **BUDGETS.get(d.get("budget"), {})}   # the preset's schedule
    for k in SCHEDULE_KEYS:
        v = d.get(k, defaults[k])
        if v is not None:
            d[k] = max(1, round(v * f))
    mc["sh_degree_interval"] = max(1, round(mc.get("sh_degree_interval", TrainConfig.sh_degree_interval) * f))
