"""The common interface of a method (after nerfbaselines' ``Method`` protocol, ``_types.py``).

What changed from nerfbaselines, and why:

* Set-up is the constructor ``cls(scene, config, name=..., device=..., run=...)`` with a plain
  nested dict ``config`` (the method's own settings, Hydra-free); the registry merges the method's
  fixed settings first and rejects conflicts. ``device`` is the run's ``torch.device`` (already
  resolved and checked, e.g. ``cuda:0`` or ``cpu``): every tensor the method makes lives there, and
  ``load`` maps a checkpoint written on any device onto it. ``run`` is what the protocol asks of
  the run in neutral terms (``RunSettings``: steps, seed, budget, cap, ...); each method maps it
  onto its own settings (None outside a protocol run).
* A method declares what it needs from a scene as data (``SceneNeeds``: required and optional
  scene capabilities, the same names as ``Scene.capabilities``); the registry checks a scene before
  set-up, so "no SfM points" fails with a sentence instead of a KeyError deep inside a method.
* ``render`` returns the renderer's ``RenderOutput`` (torch tensors + stats such as the k_max
  coverage) instead of a dict of numpy arrays; evaluation quantises in one place.
* ``train_step(step)`` runs exactly one step and insists on the step count it has done, so a
  resumed run cannot silently restart its schedules; the harness owns the loop.
* ``save``/``load`` restore everything a resumed run needs (optimiser moments, densification
  statistics, random generators), not just the weights.
* ``describe()`` gives the resolved config, the hyperparameter-set name and the stages the run
  left out (for results.json and the run log); ``parameter_values()`` the learned per-primitive
  values the report summarises (may be empty); ``prepare()`` builds compiled code before the
  harness starts the train clock.
"""

from __future__ import annotations

import copy
import dataclasses
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, ClassVar, Protocol, runtime_checkable

if TYPE_CHECKING:   # types only: naming a method (smgs list methods) imports no torch
    import torch

    from smgs.camera import Camera
    from smgs.data.scene import Scene
    from smgs.raster import RenderOutput

CAPABILITIES: tuple[str, ...] = ("sfm_points", "background", "trajectory", "view_dependence")
"""Scene capabilities a method can ask for (``Scene.capabilities``)."""


@dataclass(frozen=True)
class SceneNeeds:
    """What a method needs from a scene: ``required`` capabilities must be present; ``optional``
    ones are used when present (the method says in ``describe()['plan']`` what it does without
    them)."""

    required: frozenset[str] = frozenset()
    optional: frozenset[str] = frozenset()

    def __post_init__(self) -> None:
        unknown = (set(self.required) | set(self.optional)) - set(CAPABILITIES)
        if unknown:
            raise ValueError(f"unknown scene capabilities {sorted(unknown)}; known: {', '.join(CAPABILITIES)}")

    def check(self, scene: Scene, method: str = "method") -> list[str]:
        """Raise if a required capability is missing; return notes on the missing optional ones."""
        have = scene.capabilities
        missing = sorted(set(self.required) - have)
        if missing:
            raise ValueError(f"{method} needs {', '.join(missing)} from the scene, but scene "
                             f"{scene.name!r} has only {sorted(have) or 'none'}")
        return [f"scene has no {c}" for c in sorted(set(self.optional) - have)]


@dataclass(frozen=True)
class RunSettings:
    """What the protocol asks of one run, in terms every method reads the same way; a method maps
    them onto its own settings (the built-ins: ``baselines.trainer_settings``)."""

    steps: int                       # train_step is called this many times
    seed: int
    budget: str                      # the budget's name: full, light, mini, 5pct, cap16, mcmc_256, ...
    budget_kind: str                 # its kind: full | light | mini | 5pct | cap | mcmc
    grad_threshold: float | None     # the densification gradient threshold that defines it (None: MCMC)
    cap: int | None                  # a hard maximum number of primitives (None: none)
    schedule_steps: int | None       # the run length the protocol's schedules are written for (None: keep the method's)
    backend: str = "auto"            # the renderer backend asked for (auto | cpu | cuda | reference)
    kernels: str | None = None       # its variants asked for (smgs.raster.backends; None: the environment's,
    glue: str | None = None          # else the default): the config's renderer.kernels, renderer.glue

    @property
    def preset(self) -> str:
        """The budget's kind under its earlier name; ``budget_kind`` is the one to read."""
        warnings.warn("RunSettings.preset is RunSettings.budget_kind now", DeprecationWarning, stacklevel=2)
        return self.budget_kind


# What the registry checks a method class for before creating it.
METHOD_FUNCTIONS: tuple[str, ...] = ("train_step", "render", "num_gaussians", "save", "load", "describe",
                                     "parameter_values", "prepare")


@runtime_checkable
class Method(Protocol):
    """A trainable, renderable scene representation. The harness owns the loop::

        m = create_method("softmax_gs", scene, config, device="auto")
        for step in range(steps):
            logs = m.train_step(step)
        out = m.render(scene.test[0].camera)
    """

    needs: ClassVar[SceneNeeds]
    name: str                        # the registered name it was created under

    def __init__(self, scene: Scene, config: dict[str, Any] | None = None, *, name: str | None = None,
                 device: torch.device, run: RunSettings | None = None) -> None:
        ...

    def prepare(self) -> str:
        """Build or load whatever compiled code training and rendering use (called before the
        train clock starts: a build is never training time); returns a note for the log, e.g. the
        renderer backend ("" when there is nothing to build)."""
        ...

    def train_step(self, step: int) -> dict[str, float]:
        """Run one step; ``step`` = steps already done (0-based). Returns scalars to log."""
        ...

    def render(self, camera: Camera) -> RenderOutput:
        """Render one camera (no gradients)."""
        ...

    def num_gaussians(self) -> int:
        ...

    def save(self, path: str | Path) -> None:
        """Write a checkpoint directory that ``load`` resumes from exactly."""
        ...

    def load(self, path: str | Path) -> None:
        """Restore a checkpoint written by ``save`` (on any device) into this (set-up) method, on
        its own device."""
        ...

    def describe(self) -> dict[str, Any]:
        """{"method", "config", "hparams", "step", "plan": [what the run uses / leaves out]}."""
        ...

    def parameter_values(self) -> dict[str, torch.Tensor]:
        """Learned per-primitive values worth summarising in the report (name -> 1-D tensor);
        {} when there are none."""
        ...


@runtime_checkable
class LeadingSplats(Protocol):
    """Optional, beside ``Method``: a method that can say which of its primitives lead each pixel
    renders with ``RenderOutput.leaders`` filled (``smgs.raster.rasterize(leaders=True)``). The view
    consistency's popping ratio uses it; for a method without it that figure is reported missing."""

    def render_leaders(self, camera: Camera) -> RenderOutput:
        """``render(camera)`` with the leading-splat map (no gradients)."""
        ...


@runtime_checkable
class OpacityResets(Protocol):
    """Optional, beside ``Method``: a method whose schedule resets its primitives' opacities (3DGS
    drops them all to 0.01 and lets training restore them). The harness evaluates the error-against-
    time curve just before such a step, never on it: right after a reset a model renders ~13.6 dB
    (``protocols.train_loop.eval_steps``)."""

    def reset_steps(self, steps: int) -> list[int]:
        """The steps (1-based: ``train_step(s - 1)`` is the one) of a ``steps`` run that end in a reset."""
        ...


@runtime_checkable
class ResolvedSettings(Protocol):
    """Optional, beside ``Method``: the complete settings a run trains with, the method's own
    defaults included. The protocol hashes them into the run's identity, so a result trained under
    earlier defaults (an initial value changed by an update) is retrained, not reported as current.
    They are made once per run: a constructor that takes ``settings=`` is handed the very object
    (``Resolved.settings``) instead of building it again."""

    @classmethod
    def resolved_settings(cls, config: dict[str, Any], run: RunSettings) -> Any:
        """What ``cls(scene, config, run=run)`` trains with: plain data (a dict) or a config
        dataclass (hashed as ``dataclasses.asdict`` gives it)."""
        ...


@dataclass(frozen=True)
class Resolved:
    """A method's settings for one run, worked out once (``baselines.registry.resolve``): ``config``
    its own settings with the name's fixed ones merged, ``run`` what the protocol asks (None outside
    a protocol run), ``settings`` what it trains with (``ResolvedSettings``; None for a method that
    does not say). ``create_method`` builds the method from it without resolving anything again."""

    name: str
    config: dict[str, Any]
    run: RunSettings | None
    settings: Any = None

    def data(self) -> dict[str, Any] | None:
        """``settings`` as plain data (what the result's identity hashes)."""
        s = self.settings
        return dataclasses.asdict(s) if dataclasses.is_dataclass(s) and not isinstance(s, type) else s


def merge_config(base: dict, over: dict) -> dict:
    """Deep merge of nested config dicts (``over`` wins; neither input is modified): how a method's
    settings are layered (the method's, the dataset's, the name's fixed ones)."""
    out = copy.deepcopy(base)
    for k, v in over.items():
        out[k] = merge_config(out[k], v) if isinstance(v, dict) and isinstance(out.get(k), dict) else copy.deepcopy(v)
    return out


@dataclass(frozen=True)
class MethodSpec:
    """A registry entry: a name, the class as a lazily imported "module:Class" string (or the
    class itself), settings fixed for this name (e.g. the render mode) and metadata."""

    name: str
    target: Any
    fixed: dict[str, Any] = field(default_factory=dict)
    paper_name: str | None = None
    description: str = ""
    source: str = "builtin"
