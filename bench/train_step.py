"""Where a training step's time goes, for any method and scene, from the trainer's own timers, and
the same steps of two source trees side by side.

    python bench/train_step.py dataset=colmap dataset.path=../shared/data/fern method=3dgs budget=5pct \\
        protocol=cpu [--start 300] [--steps 100]
    python bench/train_step.py --before /tmp/smgs_before [--chunks 10] [--chunk 10] OVERRIDES...

The cell is composed from the Hydra overrides as ``smgs run`` composes it (one method, dataset,
scene, budget; ``--start`` steps are trained first, untimed: e.g. where SH degree 3 is active at the
cpu preset; then ``--warmup`` more, untimed: the first step of a process loads the compiled kernels,
~0.1 s that a split of 60 steps counted as 1.5 ms of the forward's glue). Then ``--steps`` steps with
``Trainer.profile`` on: each stage's wall time (render forward, loss, backward, optimiser, strategy)
and, inside them, the compiled CPU kernels' (``smgs.raster.kernel_clock``: projection with the SH
colours, compositing, loss, each way), so the split shows the time outside the compiled kernels: the
forward's and the backward's glue.

With ``--before TREE`` each tree trains the cell in its own worker process (the extension cache is
keyed by the sources, so the trees share it) and the workers take turns by chunks of ``--chunk`` steps, which goes
first flipping every round: both see the same load on a shared machine (bench/ab.py says why). Both
start from one state (the after tree trains the first ``--start`` steps, or reads ``--checkpoint``).
The first step of each chunk is untimed (it warms the tree's caches after the other's chunk). Each
process imports its tree's smgs before torch, as every smgs entry point does, so that OpenMP's wait
policy is the one ``smgs run`` trains with (smgs/__init__.py: passive; torch imported first left
OpenMP's threads spinning for milliseconds after each parallel region, on the cores the renderer's
own threads need, which took ~7 ms of a 25 ms step on fern on a quiet 2-core host). At the
end both render the first test view: the largest difference of the two images (0 where the change
keeps the arithmetic; else the float rounding of the changed kernels, grown over the steps).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import statistics
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve()
ROOT = HERE.parents[1]
if str(ROOT) not in sys.path:       # `python bench/train_step.py` from a checkout: its own smgs
    sys.path.insert(0, str(ROOT))


def build(overrides: list[str], device: str = "cpu"):
    """The cell's method, made as ``smgs run`` makes it (protocols of the tree on ``sys.path``)."""
    from hydra import compose, initialize_config_dir

    from baselines.registry import create_method
    from protocols.cell_scene import load_scene_for
    from protocols.run import CONFIG_DIR, plan
    from protocols.run_settings import cell_settings

    with initialize_config_dir(config_dir=CONFIG_DIR, version_base="1.3"):
        payloads = plan(compose(config_name="config", overrides=overrides), overrides)[1]
    if len(payloads) != 1:
        raise SystemExit(f"train_step: the overrides make {len(payloads)} cells; name one method, scene and budget")
    cfg = payloads[0]["config"]
    name, scene, made = cfg["method"]["name"], load_scene_for(cfg), cell_settings(cfg).for_method()
    if isinstance(made, tuple):   # a tree from before the resolved settings (e.g. 698e83b): (config, run)
        return create_method(name, scene, made[0], device=device, run=made[1])
    return create_method(name, scene, device=device, resolved=made)


class Session:
    """One method trained step by step, timed with the trainer's profile on."""

    def __init__(self, overrides: list[str], start: int, checkpoint: str | None = None) -> None:
        """The cell's method after ``start`` steps: trained here, or read from ``checkpoint`` where that
        file is there (else written there after training)."""
        import smgs  # noqa: F401 - the tree's smgs before torch: OpenMP's wait policy as smgs run has it
        import torch

        self.m = build(overrides)
        self.tr = self.m.trainer
        if checkpoint and Path(checkpoint).is_file():
            self.tr.load_state_dict(torch.load(checkpoint, weights_only=False))
            if self.tr.step_count != start:
                raise SystemExit(f"train_step: {checkpoint} is at step {self.tr.step_count}, not --start {start}")
        else:
            for s in range(start):
                self.m.train_step(s)
            if checkpoint:
                torch.save(self.tr.state_dict(), checkpoint)
        self.step = start
        self.tr.profile = True

    def clock_compiled_calls(self) -> None:
        """For a tree from before ``smgs.raster.kernel_clock`` (no ``Trainer.kernel_clock``): time its
        compiled calls by wrapping the extension modules' functions (the same names as the clock's),
        so its split shows the time outside them too."""
        import importlib

        self.clock_seconds: dict[str, float] = {}
        calls = {("smgs.raster.cpu", "forward"): "composite fwd", ("smgs.raster.cpu", "backward"): "composite bwd",
                 ("smgs.raster.projection", "forward"): "projection+SH fwd",
                 ("smgs.raster.projection", "backward"): "projection+SH bwd",
                 ("smgs.train.image_loss", "forward"): "loss", ("smgs.train.image_loss", "ray_variance"): "loss"}
        for (mod, fn), name in calls.items():
            ext = importlib.import_module(mod)._JIT.module()
            setattr(ext, fn, self._timed_call(getattr(ext, fn), name))

    def _timed_call(self, f, name: str):
        def timed(*args):
            t0 = time.perf_counter()
            try:
                return f(*args)
            finally:
                self.clock_seconds[name] = self.clock_seconds.get(name, 0.0) + time.perf_counter() - t0
        return timed

    def run(self, n: int, untimed: int = 0) -> dict:
        """``n`` steps, the first ``untimed`` left out of the figures: per-step wall ms, the stages'
        and the kernels' seconds (summed over the timed steps)."""
        for _ in range(untimed):
            self.m.train_step(self.step)
            self.step += 1
        tr = self.tr
        tr.timings = {k: 0.0 for k in tr.timings}
        clock = getattr(tr, "kernel_clock", None)   # a tree from before the kernel clock has none
        if clock is None and not hasattr(self, "clock_seconds"):
            self.clock_compiled_calls()
        if clock is not None:
            clock.seconds = {}
        else:
            self.clock_seconds.clear()
        ms = []
        for _ in range(n):
            t0 = time.perf_counter()
            self.m.train_step(self.step)
            ms.append(1e3 * (time.perf_counter() - t0))
            self.step += 1
        return {"ms": ms, "stages": dict(tr.timings), "kernels": dict(clock.seconds if clock else self.clock_seconds),
                "gaussians": self.m.num_gaussians(), "sh_degree": tr.sh_degree(), "step": self.step}

    def image(self, path: str) -> float:
        """Save the render of the first test view; its PSNR against the view's image."""
        import torch

        from smgs.metrics.image import psnr

        view = self.tr.scene.test[0]
        with torch.no_grad():
            rgb = self.tr.render(view.camera).rgb.detach().cpu()
        torch.save(rgb, path)
        return psnr(rgb.clamp(0, 1), view.rgb)


def split_table(r: dict) -> str:
    """The per-stage split of ``r`` (Session.run) as a markdown table, ms per step."""
    n = len(r["ms"])
    total = sum(r["ms"]) / n
    st = {k: 1e3 * v / n for k, v in r["stages"].items()}
    kn = {k: 1e3 * v / n for k, v in r["kernels"].items()}
    fwd_k = kn.get("projection+SH fwd", 0.0) + kn.get("composite fwd", 0.0)
    bwd_k = kn.get("projection+SH bwd", 0.0) + kn.get("composite bwd", 0.0)
    rows = [("render forward", st["render"]),
            ("  projection + SH colours (kernel)", kn.get("projection+SH fwd")),
            ("  compositing (kernel)", kn.get("composite fwd")),
            ("  glue", st["render"] - fwd_k if kn else None),
            ("loss (kernel, value and gradient)", st["loss"]),
            ("backward", st["backward"]),
            ("  compositing (kernel)", kn.get("composite bwd")),
            ("  projection + SH colours (kernel)", kn.get("projection+SH bwd")),
            ("  glue (autograd, activations, gathers)", st["backward"] - bwd_k if kn else None),
            ("optimiser (fused Adam) and the step's read", st["optim"]),
            ("strategy (densification statistics, refinement)", st["strategy"]),
            ("other (logs, view choice)", total - sum(st.values()))]
    out = ["| stage | ms / step | share |", "|---|--:|--:|"]
    for name, v in rows:
        out.append(f"| {name} | {'n/a' if v is None else f'{v:.2f}'} | "
                   f"{'' if v is None else f'{100 * v / total:.1f} %'} |")
    out.append(f"| **step** | **{total:.2f}** | 100 % |")
    if kn:
        inside = sum(kn.values())
        out.append(f"\ninside the compiled kernels: {inside:.2f} ms ({100 * inside / total:.1f} %); "
                   f"outside: {total - inside:.2f} ms ({100 * (total - inside) / total:.1f} %)")
    return "\n".join(out)


def worker(tree: str) -> None:
    """Serve requests on stdin for the smgs of ``tree``: one JSON request per line, one JSON answer per
    line on the original stdout (anything printed, e.g. by a build, goes to stderr)."""
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    sys.path.insert(0, tree)
    session = None
    for line in sys.stdin:
        req = json.loads(line)
        if req["cmd"] == "init":
            session = Session(req["overrides"], req["start"], req.get("checkpoint"))
            ans = {"gaussians": session.m.num_gaussians()}
        elif req["cmd"] == "run":
            ans = session.run(req["n"], req["untimed"])
        else:
            ans = {"psnr": session.image(req["path"])}
        print(json.dumps(ans), file=answers, flush=True)


def load() -> str:
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def ab(before: Path, after: Path, overrides: list[str], start: int, chunks: int, chunk: int,
       checkpoint: str | None) -> None:
    """Both trees alternated by chunks; medians of the per-step times, the image difference. Both
    start from one state: the after tree trains the first ``start`` steps (or reads ``checkpoint``)
    and writes it, the before tree reads it."""
    import torch

    trees = {"before": before.resolve(), "after": after.resolve()}
    for name, tree in trees.items():
        if not (tree / "smgs" / "train").is_dir():
            raise SystemExit(f"train_step: --{name} {tree} is not an smgs source tree (no smgs/train there)")
    sys.path.insert(0, str(HERE.parent))
    from ab import Worker   # bench/ab.py's worker process, serving this script

    workers = {k: Worker(t, script=HERE) for k, t in trees.items()}
    print(f"# before: {trees['before']}\n# after: {trees['after']}\n# {' '.join(overrides)}; "
          f"{start} steps first, then {chunks} rounds of {chunk} steps per tree (the first of each untimed)")
    print(f"# load average at the start: {load()}")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            state = checkpoint or f"{tmp}/start.pt"
            for k in ("after", "before"):
                n = workers[k].call(cmd="init", overrides=overrides, start=start, checkpoint=state)["gaussians"]
                print(f"# {k}: {n} Gaussians at step {start}", flush=True)
        ms = {k: [] for k in trees}
        last = {}
        for r in range(chunks):
            for k in (list(trees) if r % 2 else list(trees)[::-1]):
                res = workers[k].call(cmd="run", n=chunk - 1, untimed=1)
                ms[k] += res["ms"]
                last[k] = res
        with tempfile.TemporaryDirectory() as tmp:
            imgs, quality = {}, {}
            for k, w in workers.items():
                quality[k] = w.call(cmd="image", path=f"{tmp}/{k}.pt")["psnr"]
                imgs[k] = torch.load(f"{tmp}/{k}.pt")
        diff = float((imgs["before"] - imgs["after"]).abs().max())
        mse = float(((imgs["before"] - imgs["after"]) ** 2).mean())
    finally:
        for w in workers.values():
            w.close()
    med = {k: statistics.median(v) for k, v in ms.items()}
    q = {k: statistics.quantiles(v, n=4) for k, v in ms.items()}
    print("\n| tree | ms / step (median) | quartiles | Gaussians at the end | SH degree | test view 0 PSNR |\n"
          "|---|--:|--:|--:|--:|--:|")
    for k in trees:
        print(f"| {k} | {med[k]:.1f} | {q[k][0]:.1f} – {q[k][2]:.1f} | {last[k]['gaussians']} | "
              f"{last[k]['sh_degree']} | {quality[k]:.2f} dB |")
    between = "identical" if mse == 0 else f"{10 * math.log10(1 / mse):.1f} dB PSNR between them"
    print(f"\nafter / before: {med['after'] / med['before']:.2f}; steps {start} to {last['after']['step']}; the "
          f"first test view's renders: largest |Δ| {diff:.2e}, {between}; load average at the end: {load()}")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("overrides", nargs="*", help="Hydra overrides of the cell, as for smgs run")
    ap.add_argument("--start", type=int, default=0, help="steps trained first, untimed")
    ap.add_argument("--steps", type=int, default=50, help="timed steps (one tree)")
    ap.add_argument("--warmup", type=int, default=1,
                    help="steps after --start trained untimed before the split's timed ones (the first loads "
                         "the compiled kernels: ~0.1 s, which counted as the forward's glue)")
    ap.add_argument("--before", type=Path, help="a source tree to compare against, alternated by chunks")
    ap.add_argument("--after", type=Path, default=ROOT, help="the other tree (default: this one)")
    ap.add_argument("--chunks", type=int, default=10)
    ap.add_argument("--chunk", type=int, default=10, help="steps per tree per round (the first untimed)")
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's)")
    ap.add_argument("--checkpoint", help="the state after --start steps: read where the file is there, else "
                                         "written there (the trees start from it alike)")
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        worker(args.worker)
        return 0
    if args.threads:   # before torch starts (and in the workers, which inherit it)
        os.environ["OMP_NUM_THREADS"] = str(args.threads)
    if args.before is not None:
        ab(args.before, args.after, args.overrides, args.start, args.chunks, args.chunk, args.checkpoint)
        return 0
    import smgs  # noqa: F401 - before torch (Session says why)
    import torch

    from smgs.env import cpu_model

    if args.threads:
        torch.set_num_threads(args.threads)
    s = Session(args.overrides, args.start, args.checkpoint)
    r = s.run(args.steps, untimed=args.warmup)
    from smgs.raster.cpu_build import isa_in_use

    print(f"# {' '.join(args.overrides)}\n# steps {r['step'] - args.steps}-{r['step']}, {r['gaussians']} Gaussians at the end, "
          f"SH degree {r['sh_degree']}; {cpu_model()}, {isa_in_use()} path, {torch.get_num_threads()} threads; "
          f"load average {load()}\n")
    print(split_table(r))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
