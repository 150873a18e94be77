"""The densification-strategy interface and the choice of strategy by config.

A strategy edits a ``Gaussians`` and its ``GaussianOptimizer`` around each training step, as
gsplat's strategies do (``step_pre_backward`` / ``step_post_backward``). The trainer calls, per
1-based ``iteration``:

1. ``step_pre_backward`` after the render, before the loss (e.g. ask for screen-space gradients);
2. ``regularizer``: a term added to the loss (or None);
3. backward and the optimiser step;
4. ``step_post_backward``: statistics, refinement, perturbations; returns what it did.

``DensifyConfig.strategy`` picks one: "default" (3DGS adaptive density control,
``smgs.train.strategy``) or "mcmc" (3DGS-MCMC, ``smgs.train.mcmc``).
"""

from __future__ import annotations

from typing import Protocol

import torch

from smgs.camera import Camera
from smgs.raster import RenderOutput
from smgs.train.config import DensifyConfig
from smgs.train.gaussians import Gaussians
from smgs.train.optim import GaussianOptimizer
from smgs.train.strategy import DefaultStrategy, RefineEvent

STRATEGIES = ("default", "mcmc")


class Strategy(Protocol):
    """What the trainer needs from a densification strategy."""

    kind: str

    def describe(self) -> list[str]:
        """Lines for the run's plan (what the strategy will do)."""

    def initialize(self, g: Gaussians, opt: GaussianOptimizer) -> list[str]:
        """Adjust the initial Gaussians (e.g. to a cap) before the first step; plan lines."""

    def step_pre_backward(self, iteration: int, g: Gaussians, out: RenderOutput) -> None:
        """After the render of ``iteration``, before its loss."""

    def regularizer(self, iteration: int, g: Gaussians) -> torch.Tensor | None:
        """A term added to the loss of ``iteration``, or None."""

    def step_post_backward(self, iteration: int, g: Gaussians, opt: GaussianOptimizer, out: RenderOutput,
                           camera: Camera, lr_means: float) -> RefineEvent | None:
        """After backward and the optimiser step of ``iteration``; ``lr_means`` is its position
        learning rate. Returns what changed (None when the strategy is idle)."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...


def make_strategy(cfg: DensifyConfig, extent: float, size_prune: float, seed: int = 0, *,
                  device: torch.device | str) -> Strategy:
    """The strategy ``cfg.strategy`` names, on the run's ``device``. ``size_prune`` only matters
    to the default one."""
    if cfg.strategy == "default" or not cfg.enabled:
        return DefaultStrategy(cfg, extent, size_prune, seed=seed, device=device)
    if cfg.strategy == "mcmc":
        from smgs.train.mcmc import MCMCStrategy

        return MCMCStrategy(cfg, seed=seed, device=device)
    raise ValueError(f"unknown densification strategy {cfg.strategy!r}; known: {', '.join(STRATEGIES)} "
                     "(densify.strategy)")
