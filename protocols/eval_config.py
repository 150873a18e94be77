"""The ``eval`` section of an experiment config as one typed value, built once per run.

Its default values live in one place, ``configs/config.yaml`` (with what each means); the
experiments override some. Here are the names and types: a key missing, unknown or of the wrong
type is an error naming it (``protocols.validate`` reports it before any cell runs).
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

    @classmethod
    def of(cls, cfg: dict[str, Any]) -> "EvalConfig":
        """The ``eval`` section of a resolved run config."""
        return from_dict(cls, cfg.get("eval"), _where="eval")
