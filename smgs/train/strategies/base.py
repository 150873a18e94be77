"""What every densification strategy is: a dataclass that is its own config, with the hooks the
trainer calls, and what a step did (docs/adding-a-strategy.md)."""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch

from smgs.camera import Camera
from smgs.ranges import range_problems
from smgs.raster import RenderOutput
from smgs.train.sections import DensifyConfig
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


@dataclass(frozen=True)
class StrategyRun:
    """What a run tells its strategy when it starts: the scene's extent (world units), the render
    mode (3dgs, softmax_gs, ...), the run's seed (a strategy offsets it for its own random stream)
    and the device every tensor of the run lives on."""

    extent: float
    mode: str
    seed: int
    device: torch.device


@dataclass
class Strategy(DensifyConfig):
    """The base of every densification strategy: its fields are the densify section's keys (the
    shared ones of ``DensifyConfig``, then its own, each with a default and, where numeric, a range in
    ``RANGES``), its methods what the trainer calls, per 1-based ``iteration``:

    1. ``step_pre_backward`` after the render, before the loss (e.g. ask for screen-space gradients);
    2. ``regularizer``: a term added to the loss (or None);
    3. backward and the optimiser step;
    4. ``step_post_backward``: statistics, refinement, perturbations; returns what it did.

    The trainer runs a copy made by ``start`` (the config stays plain data), after ``setup`` made its
    state; ``initialize`` may adjust the initial Gaussians. Every hook here does nothing: a strategy
    overrides those it needs. ``state_dict`` goes into checkpoints, tagged with the strategy's name.
    """

    def start(self, run: StrategyRun) -> "Strategy":
        """A copy of this strategy set up for ``run`` (its values checked against ``RANGES``)."""
        problems = range_problems(self, "densify")
        if problems:
            raise ValueError("; ".join(problems))
        running = dataclasses.replace(self)
        running.setup(run)
        return running

    def setup(self, run: StrategyRun) -> None:
        """Make the running state (statistics, generators) on ``run.device``."""

    def describe(self) -> list[str]:
        """Lines for the run's plan (what the strategy will do)."""
        return [f"densification: {self.strategy} (budget {self.budget_kind}{', cap ' + str(self.cap) if self.cap else ''})"]

    def initialize(self, g: Gaussians, opt: GaussianOptimizer) -> list[str]:
        """Adjust the initial Gaussians (e.g. to a cap) before the first step; plan lines."""
        return []

    def step_pre_backward(self, iteration: int, g: Gaussians, out: RenderOutput) -> None:
        """After the render of ``iteration``, before its loss."""

    def regularizer(self, iteration: int, g: Gaussians) -> torch.Tensor | None:
        """A term added to the loss of ``iteration``, or None."""
        return None

    def step_post_backward(self, iteration: int, g: Gaussians, opt: GaussianOptimizer, out: RenderOutput,
                           camera: Camera, lr_means: float) -> RefineEvent | None:
        """After backward and the optimiser step of ``iteration``; ``lr_means`` is its position
        learning rate. Returns what changed (None when the strategy is idle)."""
        return None

    def reset_steps(self, steps: int) -> list[int]:
        """The 1-based iterations of a ``steps`` run after which every opacity is reset (an
        evaluation there would score the reset, not the method)."""
        return []

    def state_dict(self) -> dict:
        return {"kind": self.strategy}

    def load_state_dict(self, state: dict) -> None:
        self.check_kind(state.get("kind"))

    def check_kind(self, kind: str | None) -> None:
        """Refuse a checkpoint's strategy state written by another strategy."""
        if kind != self.strategy:
            raise ValueError(f"checkpoint has the {kind!r} densification strategy's state, this run uses "
                             f"{self.strategy!r} (densify.strategy)")


@dataclass
class FixedCount(Strategy):
    """What runs where densification is off (``densify.enabled=false``): nothing; the count stays as
    it started."""

    def describe(self) -> list[str]:
        return ["densification: off (fixed count)"]

    def load_state_dict(self, state: dict) -> None:
        """Whatever the checkpoint's strategy kept: with densification off nothing reads it."""
