"""The ``eval``, ``protocol`` and ``budget`` sections of a cell's config, each one typed value built
once from the resolved config (the method's training section is ``smgs.train.TrainConfig``).

Their values live in one place, the YAML (``configs/config.yaml``, ``configs/protocol/``,
``configs/budget/``, with what each means); the experiments override some. Here are the names and
types, and a default only for a key that some of the YAML files leave out. A key missing, unknown
or of the wrong type is an error naming it (``protocols.validate`` reports it before any cell runs).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from smgs.train.config import from_dict


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
    name: str                                # full, light, mini, 5pct, cap16, mcmc_256, pretrained, ...
    densify_grad_threshold: float | None     # None: MCMC (no gradient threshold)
    cap: int | None
    preset: str | None = None                # its kind where the name is not one (cap16 -> cap)

    @property
    def kind(self) -> str:
        return self.preset or self.name

    @classmethod
    def of(cls, cfg: dict[str, Any]) -> "BudgetConfig":
        return from_dict(cls, cfg.get("budget"), _where="budget")
