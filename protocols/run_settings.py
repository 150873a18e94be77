"""From a cell's config to what a method is created with: its own settings (``method_settings``)
and the protocol's neutral ``RunSettings`` (steps, seed, budget, cap, schedule length, backend),
which each method maps onto its own keys."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from baselines.method import Resolved, RunSettings, merge_config
from baselines.registry import resolve
from protocols.sections import BudgetConfig, ProtocolConfig
from smgs.raster.backends import Renderer


def asked_renderer(cfg: dict) -> Renderer:
    """The renderer a cell's config asks for: ``backend`` and the ``renderer`` section's variants."""
    section = cfg.get("renderer") or {}
    return Renderer(str(cfg.get("backend", "auto")), section.get("kernels"), section.get("glue"))


def method_settings(cfg: dict) -> dict[str, Any]:
    """The method's ``train`` settings with the dataset's overrides for its methods (e.g. the
    2D-pattern set-up) merged on top."""
    return merge_config(cfg["method"].get("train") or {}, cfg["dataset"].get("train") or {})


def run_settings(cfg: dict) -> RunSettings:
    """The cell's steps (a dataset with its own step count keeps its own schedule), seed, budget
    and renderer (``backend`` and the ``renderer`` section's variants)."""
    budget, protocol = BudgetConfig.of(cfg), ProtocolConfig.of(cfg)
    own_steps = cfg["dataset"].get("steps")
    renderer = asked_renderer(cfg)
    return RunSettings(steps=int(own_steps or protocol.steps), seed=int(cfg["seed"]), budget=budget.name,
                       budget_kind=str(budget.kind), grad_threshold=budget.grad_threshold, cap=budget.cap,
                       schedule_steps=None if own_steps else protocol.schedule_steps,
                       backend=renderer.backend, kernels=renderer.kernels, glue=renderer.glue)


@dataclass(frozen=True)
class CellSettings:
    """What a cell's method is created with, worked out once per cell (the runner makes it when it
    plans the cell; ``protocols.validate``, the identity of its result, ``protocols.cell.result_key``, and
    the method, ``protocols.ply.make_method``, all read it). ``method``: the method's settings resolved
    (``baselines.registry.resolve``: its config, the RunSettings and the complete settings it trains
    with, a TrainConfig for the built-ins), None where they could not be made. ``run``: the
    RunSettings, also where the method refused them. ``error``: why they could not be made from the
    config; raised where the method is built, so the cell fails with it."""

    method: Resolved | None
    run: RunSettings | None
    error: Exception | None = None

    @property
    def resolved(self) -> dict[str, Any] | None:
        """The method's complete settings as plain data (None for a method that gives none or a
        config it refuses)."""
        return self.method.data() if self.method is not None else None

    def for_method(self) -> Resolved:
        """The resolved settings to create the method with, or the error."""
        if self.error is not None:
            raise self.error
        return self.method


def cell_settings(cfg: dict) -> CellSettings:
    """A cell's ``CellSettings``. A config that cannot be resolved is recorded, not raised: its cell
    fails in training, with the error, as one that fails any other way."""
    try:
        method, run = method_settings(cfg), run_settings(cfg)
    except (KeyError, ImportError, TypeError, ValueError) as e:
        return CellSettings(None, None, e)
    try:
        return CellSettings(resolve(cfg["method"]["name"], method, run), run)
    except (KeyError, ImportError, TypeError, ValueError) as e:   # the method refuses these settings
        return CellSettings(None, run, e)
