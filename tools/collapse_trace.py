"""Where a model's Gaussians go: a training run of the harness's set-up, traced refinement by
refinement (docs/studies/fox-collapse.md).

    python tools/collapse_trace.py SCENE [--mode M] [--budget 5pct] [--steps 3000] [--width 400]
        [--schedule-steps 30000] [--refine-every N] [--reset-every N] [--prune-screen-px PX]
        [--size-prune X] [--init random|auto] [--n-random N] [--every 100] [--json out.json]

SCENE is a transforms.json scene (a folder or the file), loaded as the cpu preset loads it (images
at most ``--width`` px wide). The TrainConfig is the one ``protocols.run`` builds for the method and
budget (``baselines.trainer_settings``: the 3DGS 30K schedule scaled to ``--steps`` by
``--schedule-steps``); ``--refine-every`` / ``--reset-every`` then replace the scaled interval
(e.g. 100, 3DGS's own, in a 3000-step run). Every ``--every`` steps and at each opacity reset it
prints the count, what refinement cloned, split and pruned since the last row (pruned as
transparent or as too big), the share of Gaussians under the pruning opacity, and the training L1;
at the end the test views' PSNR (float renders) and their mean alpha.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent.parent))

import smgs  # noqa: E402,F401  (threading policy before torch)
import torch  # noqa: E402


def build(args: argparse.Namespace):
    from baselines.method import RunSettings
    from baselines.trainer_settings import train_config
    from smgs.data import load_scene
    from smgs.train import TrainConfig, from_dict
    from smgs.train.config import budget_threshold
    from smgs.train.trainer import Trainer

    scene = load_scene("transforms", path=args.scene, rule="cpu", max_width=args.width, test_every=8)
    grad = budget_threshold(args.budget)   # the kind's threshold, from its one home (BUDGETS)
    run = RunSettings(steps=args.steps, seed=args.seed, budget=args.budget, budget_kind=args.budget,
                      grad_threshold=grad, cap=None, schedule_steps=args.schedule_steps)
    mc = train_config({"mode": args.mode, "k_max": 128, "optim": "3dgs2023+softmaxgs_real",
                       "gaussians": {"init": args.init, "n_random": args.n_random}}, run)
    for key, v in (("refine_every", args.refine_every), ("reset_every", args.reset_every),
                   ("prune_screen_px", args.prune_screen_px), ("size_prune", args.size_prune)):
        if v is not None:
            mc["densify"][key] = v
    cfg = from_dict(TrainConfig, mc)
    return scene, Trainer(scene, cfg, device="cpu")


@torch.no_grad()
def evaluate(trainer, scene) -> tuple[float, float]:
    from smgs.metrics.image import psnr

    ps, cover = [], []
    for v in scene.test:
        out = trainer.render(v.camera)
        ps.append(float(psnr(out.rgb.clamp(0, 1), v.rgb)))
        cover.append(float(out.alpha.mean()))
    return sum(ps) / len(ps), sum(cover) / len(cover)


def main(argv: list[str] | None = None) -> dict:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("scene")
    ap.add_argument("--mode", default="3dgs")
    ap.add_argument("--budget", default="5pct", choices=("5pct", "mini", "light", "full"))
    ap.add_argument("--steps", type=int, default=3000)
    ap.add_argument("--schedule-steps", type=int, default=30000)
    ap.add_argument("--width", type=int, default=400)
    ap.add_argument("--refine-every", type=int)
    ap.add_argument("--reset-every", type=int)
    ap.add_argument("--prune-screen-px", type=float,
                    help="prune by screen size after a reset (the rule 3DGS's code names: 20 px; default off)")
    ap.add_argument("--size-prune", type=float, help="world size limit x extent (3dgs 0.1, softmax modes 0.4)")
    ap.add_argument("--init", default="auto", choices=("auto", "random", "sfm"))
    ap.add_argument("--n-random", type=int, default=100_000, help="random points where the scene has no SfM points")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--every", type=int, default=100)
    ap.add_argument("--json")
    args = ap.parse_args(argv)

    scene, tr = build(args)
    d = tr.cfg.densify
    big = {"screen": 0, "world": 0}
    strat = tr.strategy
    original = strat.densify_and_prune

    def traced(g, opt, prune_big):   # which size rule fires, on the rows refinement starts from
        if prune_big and len(g):
            with torch.no_grad():
                keep = g.opacities >= d.prune_opacity
                px = math.inf if d.prune_screen_px is None else d.prune_screen_px
                screen = (strat.max_radii > px) & keep
                world = (g.scales.max(dim=1).values > strat.size_limit * strat.extent) & keep & ~screen
                big["screen"] += int(screen.sum())
                big["world"] += int(world.sum())
        return original(g, opt, prune_big)

    strat.densify_and_prune = traced
    print(f"# {args.mode} {args.budget} steps {args.steps} (schedule of {args.schedule_steps}), "
          f"{scene.train[0].camera.width}x{scene.train[0].camera.height}, {len(scene.train)} train views; "
          f"refine {d.refine_start}-{d.refine_stop} every {d.refine_every}, reset every {d.reset_every}, "
          f"grad {d.grad_threshold:g}; init {len(tr.gaussians)}", flush=True)
    print("| step | #GS | cloned | split | pruned transparent | pruned big | of which > px on screen | "
          "of which only > world size | under 0.005 | L1 | s |")
    print("|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|--:|")
    acc = dict(cloned=0, split=0, pruned_transparent=0, pruned_big=0)
    tot = dict(acc)
    l1s: list[float] = []
    rows, peak, peak_step = [], len(tr.gaussians), 0
    t0 = time.perf_counter()
    for step in range(args.steps):
        logs = tr.train_step(step)
        it = step + 1
        l1s.append(logs["l1"])
        for k in acc:
            acc[k] += int(logs.get(k, 0))
            tot[k] += int(logs.get(k, 0))
        n = len(tr.gaussians)
        if n > peak:
            peak, peak_step = n, it
        reset = bool(logs.get("opacity_reset"))
        if it % args.every == 0 or reset or it == args.steps or n == 0:
            under = float((tr.gaussians.opacities < d.prune_opacity).float().mean()) if n else math.nan
            row = dict(step=it, n=n, **acc, big_screen=big["screen"], big_world=big["world"], under=under,
                       l1=sum(l1s[-10:]) / len(l1s[-10:]), seconds=time.perf_counter() - t0, reset=reset)
            rows.append(row)
            print(f"| {it}{' (reset)' if reset else ''} | {n} | {acc['cloned']} | {acc['split']} | "
                  f"{acc['pruned_transparent']} | {acc['pruned_big']} | {big['screen']} | {big['world']} | "
                  f"{100 * under:.0f} % | {row['l1']:.4f} | {row['seconds']:.0f} |", flush=True)
            acc = {k: 0 for k in acc}
            big = {"screen": 0, "world": 0}
    test_psnr, coverage = evaluate(tr, scene)
    out = dict(args=vars(args), rows=rows, peak=peak, peak_step=peak_step, final=len(tr.gaussians),
               totals=tot, test_psnr=test_psnr, test_mean_alpha=coverage,
               train_seconds=time.perf_counter() - t0)
    print(f"final {len(tr.gaussians)} Gaussians (peak {peak} at step {peak_step}); totals {tot}; "
          f"test PSNR {test_psnr:.2f} dB (float), mean test alpha {coverage:.3f}", flush=True)
    if args.json:
        Path(args.json).write_text(json.dumps(out, indent=1))
    return out


if __name__ == "__main__":
    main()
