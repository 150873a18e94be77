"""The screen-space gradient each render mode puts on the splats' 2D means, as 3DGS's densifier
accumulates it (|dL/d means2d| scaled by half the image size), for the same Gaussians.

    python tools/densify_gradients.py [--views N] [--size W H] [--beta-init B ...] [--gamma-init G]
    python tools/densify_gradients.py --trace STEPS [--modes M ...] [--size W H] [--gamma-init G]

The procedural scene's SfM-initialised Gaussians, the first N training views, an L1 loss per view;
per mode (and, for the softmax modes, per initial β) the median, 90th percentile and mean over
visible splats and the share over the full (2e-4) and 5 % (4e-3) budgets' thresholds. Where splats
at different depths compete (a long depth decay, γ 0.3 per splat size), the softmax term's gradient
grows with β and the densifier clones and splits more at the same threshold; at the default γ (3)
it stays within 5 % of 3DGS's up to β 20 (docs/studies/gamma-init.md).

``--trace STEPS`` follows training instead: each mode trains STEPS steps of the cpu preset's
full-budget schedule (3000 steps, 3DGS's 30K schedule scaled), and at each refinement prints the
statistic the densifier reads (accumulated gradient / views), the training L1 of the last 10 steps,
and what it cloned, split and pruned. It separates a rescaled gradient (larger statistic at the
same residual) from a slower fit (larger residual, hence more splats over the threshold).
"""

from __future__ import annotations

import argparse
import sys
from dataclasses import dataclass
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import smgs  # noqa: E402,F401  (threading policy before torch)
import torch  # noqa: E402

from smgs.raster import MODES, mode_flags  # noqa: E402

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


def _trainer(mc: dict, size: tuple[int, int], beta_init: float | None, gamma_init: float | None) -> tuple:
    """The procedural scene and a Trainer for the TrainConfig dict ``mc`` (mode and seed set), with
    the softmax modes' initial β and γ (per splat size) where given (None: the defaults)."""
    from smgs.data import load_scene
    from smgs.train import TrainConfig, from_dict
    from smgs.train.trainer import Trainer

    scene = load_scene("procedural", n_views=24, width=size[0], height=size[1], test_every=8)
    mc["gaussians"] = {k: {"init": v} for k, v in (("beta", beta_init), ("gamma", gamma_init)) if v is not None}
    torch.manual_seed(mc["seed"])
    return scene, Trainer(scene, from_dict(TrainConfig, mc), device="cpu")


def gradient_stats(mode: str, views: int, size: tuple[int, int], seed: int = 0,
                   beta_init: float | None = None, gamma_init: float | None = None) -> GradStats:
    """``beta_init``, ``gamma_init``: the softmax modes' initial β and γ (per splat size; None:
    TrainConfig's default)."""
    scene, tr = _trainer({"mode": mode, "seed": seed}, size, beta_init, gamma_init)
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


@dataclass(frozen=True)
class RefineRow:
    """One refinement of a traced run: the statistic over the splats seen since the last one."""
    step: int
    n: int                 # Gaussians before the refinement
    median: float
    mean: float
    over: float            # share at or over the threshold
    l1: float              # mean training L1 of the last 10 steps
    beta: float | None     # median β (softmax modes)
    cloned: int
    split: int
    pruned: int

    def row(self, mode: str) -> str:
        beta = "–" if self.beta is None else f"{self.beta:.2f}"
        return (f"| {mode} | {self.step} | {self.n} | {self.median:.3g} | {self.mean:.3g} | {100 * self.over:.1f} % | "
                f"{self.l1:.4f} | {beta} | {self.cloned} | {self.split} | {self.pruned} |")


def refinement_trace(mode: str, steps: int, size: tuple[int, int], seed: int = 0,
                     threshold: float = THRESHOLDS[0], schedule: tuple[int, int] = (3000, 30_000),
                     gamma_init: float | None = None) -> list[RefineRow]:
    """Train ``mode`` for ``steps`` steps of a ``schedule[0]``-step run (3DGS's ``schedule[1]``
    schedule scaled to it) and record every refinement. ``gamma_init``: γ per splat size (None:
    the default)."""
    from baselines.trainer_settings import scale_schedule

    mc = {"mode": mode, "seed": seed, "steps": schedule[0],
          "densify": {"budget_kind": "full", "grad_threshold": threshold}}
    scale_schedule(mc, schedule[0], schedule[1])
    _, tr = _trainer(mc, size, None, gamma_init)
    st, refine = tr.strategy, tr.strategy.densify_and_prune
    rows: list[RefineRow] = []
    l1: list[float] = []

    def traced(g, opt, prune_big):   # read the accumulators the refinement is about to use
        seen = st.count > 0
        gv = (st.grad2d / st.count.clamp_min(1))[seen]
        beta = float(g.beta.detach().median()) if tr.use_softmax else None
        ev = refine(g, opt, prune_big)
        rows.append(RefineRow(tr.step_count + 1, len(seen), float(gv.median()), float(gv.mean()),
                              float((gv >= threshold).float().mean()), sum(l1[-10:]) / max(len(l1[-10:]), 1),
                              beta, ev.cloned, ev.split, ev.pruned))
        return ev

    st.densify_and_prune = traced
    for _ in range(steps):
        l1.append(tr.train_step()["l1"])
    return rows


def main(argv: list[str] | None = None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--views", type=int, default=6)
    ap.add_argument("--size", type=int, nargs=2, default=(128, 96), metavar=("W", "H"))
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--beta-init", type=float, nargs="+", default=None,
                    help="initial β values to compare for the softmax modes (default: the config's)")
    ap.add_argument("--gamma-init", type=float, default=None,
                    help="initial γ per splat size for the softmax modes (default: the config's)")
    ap.add_argument("--trace", type=int, default=None, metavar="STEPS",
                    help="train each mode STEPS steps at the full budget and print every refinement")
    ap.add_argument("--every", type=int, default=50, help="with --trace: print every refinement at a "
                    "multiple of this step (and the first five)")
    a = ap.parse_args(argv)
    if a.trace:
        print("| mode | step | #GS | median | mean | over 2e-4 | train L1 | β | cloned | split | pruned |")
        print("|---|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|")
        for mode in a.modes:
            rows = refinement_trace(mode, a.trace, tuple(a.size), gamma_init=a.gamma_init)
            for i, r in enumerate(rows):
                if i < 5 or r.step % a.every == 0:
                    print(r.row(mode), flush=True)
        return
    print("| mode | β init | splat-views | median | p90 | mean | " + " | ".join(f"≥ {t:g}" for t in THRESHOLDS) + " |")
    print("|---|--:|--:|--:|--:|--:|" + "--:|" * len(THRESHOLDS))
    for mode in a.modes:
        betas = a.beta_init if a.beta_init and mode_flags(mode)[1] else [None]
        for b in betas:
            print(gradient_stats(mode, a.views, tuple(a.size), beta_init=b, gamma_init=a.gamma_init).row(), flush=True)


if __name__ == "__main__":
    main()
