"""What every densification strategy is: the interface the trainer calls, and what a step did."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

import torch

from smgs.camera import Camera
from smgs.raster import RenderOutput
from smgs.train.gaussians import Gaussians
from smgs.train.optim import GaussianOptimizer


@dataclass
class RefineEvent:
    """What one refinement step did (0s when nothing happened)."""

    cloned: int = 0
    split: int = 0
    pruned: int = 0
    pruned_transparent: int = 0  # of ``pruned``: opacity under the threshold
    pruned_big: int = 0          # of ``pruned``: too big on screen or in the world (after a reset)
    pruned_big_screen: int = 0   # of ``pruned_big``: too big on screen (``prune_screen_px``)
    reset: bool = False
    capped: int = 0          # candidates dropped because of the cap
    relocated: int = 0       # MCMC: dead Gaussians moved onto live ones
    added: int = 0           # MCMC: Gaussians added by growth

    def changed(self) -> bool:
        return bool(self.cloned or self.split or self.pruned or self.reset or self.relocated or self.added)


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

    def reset_steps(self, steps: int) -> list[int]:
        """The 1-based iterations of a ``steps`` run after which every opacity is reset (an
        evaluation there would score the reset, not the method)."""

    def state_dict(self) -> dict: ...

    def load_state_dict(self, state: dict) -> None: ...
