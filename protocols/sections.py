"""The ``eval``, ``protocol`` and ``budget`` sections of a cell's config, each one typed value built
once from the resolved config (the method's training section is ``smgs.train.TrainConfig``).

Their values live in one place, the YAML (``configs/config.yaml``, ``configs/protocol/``,
``configs/budget/``, with what each means); the experiments override some. A budget's YAML names its
kind; what the kind sets (its gradient threshold) lives in ``smgs.train.config.BUDGETS``. Here are the names and
types, and a default only for a key that some of the YAML files leave out. A key missing, unknown
or of the wrong type is an error naming it (``protocols.validate`` reports it before any cell runs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any, ClassVar

from smgs.train.config import BUDGETS, budget_threshold, from_dict


@dataclass(frozen=True)
class EvalConfig:
    fractions: list[float]           # intermediate test-view PSNR at these fractions of the steps
    quantize: bool                   # metrics on 8-bit renders (3DGS's PNG round trip)
    lpips_net: str
    lpips_input: str                 # "3dgs" | "lpips" (smgs.metrics.lpips)
    lpips_weights: str | None
    flip: bool
    fps_repeats: int
    fps_warmup: int
    save_renders: bool
    viewer_views: int
    consistency: bool                # Table 4 metrics
    flow: str                        # "geometric" | "opencv"
    consistency_max_width: int | None
    popping_ratio: str = "auto"      # auto | on | off: Table 4's Pop7 (leading-splat maps of the video)

    @classmethod
    def of(cls, cfg: dict[str, Any]) -> "EvalConfig":
        """The ``eval`` section of a resolved run config."""
        return from_dict(cls, cfg.get("eval"), _where="eval")


@dataclass(frozen=True)
class ProtocolConfig:
    name: str                        # paper | cpu
    steps: int
    resolution: str                  # the resolution rule (smgs.data.rules)
    test_every: int                  # every n-th image (name-sorted) is a test view
    schedule_steps: int | None       # the run length the 3DGS schedule is written for; None: not scaled
    max_width: int | None = None     # only a reduced preset caps the image width

    @classmethod
    def of(cls, cfg: dict[str, Any]) -> "ProtocolConfig":
        return from_dict(cls, cfg.get("protocol"), _where="protocol")


@dataclass(frozen=True)
class BudgetConfig:
    """A budget: its name (a folder of every run), its kind (what densification it sets,
    ``smgs.train.config.BUDGETS``) and its cap. ``grad_threshold``, the densification gradient
    threshold that defines it, is the kind's unless the section gives one (``+budget.grad_threshold=X``;
    ``densify_grad_threshold`` is its earlier name); None for MCMC, which has none."""

    name: str                                # full, light, mini, 5pct, cap16, mcmc_256, pretrained, ...
    cap: int | None
    kind: str | None = None                  # full | light | mini | 5pct | cap | mcmc; None: the name
    grad_threshold: float | None = None      # None: the kind's (smgs.train.config.BUDGETS)

    RENAMED: ClassVar[dict[str, str]] = {"densify_grad_threshold": "grad_threshold"}

    def __post_init__(self) -> None:
        kind = self.kind or self.name
        if kind not in BUDGETS:
            raise ValueError(f"budget {self.name!r}: unknown kind {kind!r} (budget.kind); known: {', '.join(BUDGETS)}")
        object.__setattr__(self, "kind", kind)
        own = budget_threshold(kind)
        object.__setattr__(self, "grad_threshold", own if self.grad_threshold is None or own is None
                           else float(self.grad_threshold))

    @classmethod
    def of(cls, cfg: dict[str, Any]) -> "BudgetConfig":
        return from_dict(cls, cfg.get("budget"), _where="budget")

    def identity(self) -> dict[str, Any]:
        """What defines the budget's result, in the form results were hashed with before the kind had
        its one name (``preset`` in the YAML then), the threshold its one home and its one name
        (``densify_grad_threshold`` then): renaming them kept every finished result valid."""
        out: dict[str, Any] = {"name": self.name, "densify_grad_threshold": self.grad_threshold, "cap": self.cap}
        if self.kind != self.name:
            out["preset"] = self.kind
        return out
