"""The densification-strategy interface and the choice of strategy by config.

A strategy edits a ``Gaussians`` and its ``GaussianOptimizer`` around each training step, as
gsplat's strategies do (``step_pre_backward`` / ``step_post_backward``). The trainer calls, per
1-based ``iteration``:

1. ``step_pre_backward`` after the render, before the loss (e.g. ask for screen-space gradients);
2. ``regularizer``: a term added to the loss (or None);
3. backward and the optimiser step;
4. ``step_post_backward``: statistics, refinement, perturbations; returns what it did.

``DensifyConfig.strategy`` picks one: "default" (3DGS adaptive density control, ``default.py``) or
"mcmc" (3DGS-MCMC, ``mcmc.py``); the interface and ``RefineEvent`` are in ``base.py``.
"""

from __future__ import annotations

import torch

from smgs.train.config import DensifyConfig
from smgs.train.strategies.base import RefineEvent, Strategy
from smgs.train.strategies.default import SIZE_PRUNE_3DGS, SIZE_PRUNE_SOFTMAX_GS, DefaultStrategy
from smgs.train.strategies.mcmc import MCMCStrategy

STRATEGIES = ("default", "mcmc")
__all__ = ["Strategy", "RefineEvent", "DefaultStrategy", "MCMCStrategy", "SIZE_PRUNE_3DGS", "SIZE_PRUNE_SOFTMAX_GS",
           "STRATEGIES", "make_strategy"]


def make_strategy(cfg: DensifyConfig, extent: float, size_prune: float, seed: int = 0, *,
                  device: torch.device | str) -> Strategy:
    """The strategy ``cfg.strategy`` names, on the run's ``device``. ``size_prune`` only matters
    to the default one."""
    if cfg.strategy == "default" or not cfg.enabled:
        return DefaultStrategy(cfg, extent, size_prune, seed=seed, device=device)
    if cfg.strategy == "mcmc":
        return MCMCStrategy(cfg, seed=seed, device=device)
    raise ValueError(f"unknown densification strategy {cfg.strategy!r}; known: {', '.join(STRATEGIES)} "
                     "(densify.strategy)")
