"""The screen-space gradient each render mode puts on the splats' 2D means, as 3DGS's densifier
accumulates it (|dL/d means2d| scaled by half the image size), for the same Gaussians.

    python tools/densify_gradients.py [--views N] [--size W H] [--beta-init B ...]

The procedural scene's SfM-initialised Gaussians, the first N training views, an L1 loss per view;
per mode (and, for the softmax modes, per initial β) the median, 90th percentile and mean over
visible splats and the share over the full (2e-4) and 5 % (4e-3) budgets' thresholds. The softmax
term's gradient grows with β, so a mode whose competition scales these gradients clones and splits
more at the same threshold (README: "Softmax-GS on real scenes: β's initial value").
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import smgs  # noqa: E402,F401  (threading policy before torch)
import torch  # noqa: E402

from smgs.raster import MODES  # noqa: E402

THRESHOLDS = (2e-4, 4e-3)   # configs/budget/full.yaml and 5pct.yaml


@dataclass(frozen=True)
class GradStats:
    mode: str
    beta_init: float | None   # None: a mode without softmax
    n: int
    median: float
    p90: float
    mean: float
    over: tuple[float, ...]   # share of splats at or over each of THRESHOLDS

    def row(self) -> str:
        over = " | ".join(f"{100 * x:.1f} %" for x in self.over)
        beta = "–" if self.beta_init is None else f"{self.beta_init:g}"
        return f"| {self.mode} | {beta} | {self.n} | {self.median:.3g} | {self.p90:.3g} | {self.mean:.3g} | {over} |"


def gradient_stats(mode: str, views: int, size: tuple[int, int], seed: int = 0,
                   beta_init: float | None = None) -> GradStats:
    """``beta_init``: the softmax modes' initial β (None: TrainConfig's default)."""
    from smgs.data.datasets import load_scene
    from smgs.train import TrainConfig, from_dict
    from smgs.train.trainer import Trainer

    scene = load_scene("procedural", n_views=24, size=size, test_every=8)
    torch.manual_seed(seed)
    cfg = {"mode": mode, "seed": seed}
    if beta_init is not None:
        cfg["gaussians"] = {"beta": {"init": beta_init}}
    tr = Trainer(scene, from_dict(TrainConfig, cfg), device="cpu")
    vals = []
    for v in scene.train[:views]:
        out = tr.render(v.camera)
        m2 = out.extras["means2d"]
        m2.retain_grad()
        (out.rgb - v.rgb).abs().mean().backward()
        g = (m2.grad * m2.grad.new_tensor([v.camera.width / 2, v.camera.height / 2])).norm(dim=1)
        vals.append(g[out.extras["radii"].reshape(len(g), -1).amax(1) > 0])
        for p in tr.gaussians.params.values():
            p.grad = None
    g = torch.cat(vals)
    beta = float(tr.gaussians.beta[0].detach()) if tr.use_softmax else None
    return GradStats(mode, beta, len(g), float(g.median()), float(g.quantile(0.9)), float(g.mean()),
                     tuple(float((g >= t).float().mean()) for t in THRESHOLDS))


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--size", type=int, nargs=2, default=(128, 96), metavar=("W", "H"))
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--beta-init", type=float, nargs="+", default=None,
                    help="initial β values to compare for the softmax modes (default: the config's)")
    a = ap.parse_args(argv)
    print("| mode | β init | splat-views | median | p90 | mean | " + " | ".join(f"≥ {t:g}" for t in THRESHOLDS) + " |")
    print("|---|--:|--:|--:|--:|--:|" + "--:|" * len(THRESHOLDS))
    for mode in a.modes:
        betas = a.beta_init if a.beta_init and mode in ("softmax_only", "softmax_gs") else [None]
        for b in betas:
            print(gradient_stats(mode, a.views, tuple(a.size), beta_init=b).row(), flush=True)


if __name__ == "__main__":
    main()
