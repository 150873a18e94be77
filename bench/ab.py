"""Two source trees of smgs timed call by call on the same scenes: the before/after table of a change
to the renderer. On a shared machine, separate runs drift by more than such a change (the same
build measured 10-25 % apart minutes later here), so each tree runs in its own worker process
with its own extension cache, and the workers take turns call by call (which goes first flips
every round): both see the same load. Each timed call follows an untimed call of the same tree: an
OpenMP pool keeps spinning on the cores for a while after its work ends, which slowed down
whichever tree ran right after the other's call by up to 30 % on a 2-core machine; the untimed
call absorbs that and leaves the tree's own threads warm, as in a training loop.

    git worktree add /tmp/smgs_before <ref>       # the tree to compare against
    python bench/ab.py --before /tmp/smgs_before [--after .] [--scenes 10k_256 100k_512]

Every call goes through the public ``smgs.raster.rasterize`` (projection included, loss = image
mean), as in bench/raster.py, forward alone and forward + backward, every mode. A tree's extension
is built on its first call into ``<tree>/.ab_ext`` (unless ``--ext-dir`` names caches) and kept
there, so a rerun starts at once. The last column is the largest difference between the two
trees' images: 0 unless the change touches the arithmetic.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

HERE = Path(__file__).resolve()


def worker(tree: str) -> None:
    """Serve timing requests on stdin for the smgs of ``tree``: one JSON request per line, one JSON
    answer per line on the original stdout (anything else printed, e.g. by a build, goes to stderr)."""
    answers = os.fdopen(os.dup(1), "w")
    os.dup2(2, 1)
    sys.stdout = sys.stderr
    sys.path.insert(0, tree)
    import torch

    import smgs  # noqa: F401 - the tree's smgs, imported before bench/raster.py puts ours on the path
    sys.path.insert(0, str(HERE.parent))
    import time

    from raster import load_scene, mode_calls, to_inputs

    calls: dict[tuple[str, str, int], tuple] = {}
    scenes: dict[str, tuple] = {}
    for line in sys.stdin:
        req = json.loads(line)
        key = (req["scene"], req["mode"], req["k_max"])
        if req["scene"] not in scenes:
            scenes[req["scene"]] = to_inputs(load_scene(req["scene"]))
        if key not in calls:
            params, cam = scenes[req["scene"]]
            calls[key] = mode_calls(params, cam, req["mode"], "cpu", req["k_max"])
        fwd, fwd_bwd, _ = calls[key]
        fn = fwd_bwd if req["backward"] else fwd
        fn()  # untimed: absorbs the other tree's spinning threads, warms ours
        t0 = time.perf_counter()
        out = fn()
        ms = 1e3 * (time.perf_counter() - t0)
        if req.get("image"):
            torch.save(out.rgb.detach(), req["image"])
        print(json.dumps({"ms": ms}), file=answers, flush=True)


class Worker:
    """A worker process of ``script`` serving JSON-line requests for the smgs of ``tree`` (bench/ab.py's
    and bench/train_step.py's); ``ext_dir``: its own extension cache (None: the shared one, which is
    keyed by the sources)."""

    def __init__(self, tree: Path, ext_dir: Path | None = None, script: Path = HERE) -> None:
        env = dict(os.environ) if ext_dir is None else dict(os.environ, TORCH_EXTENSIONS_DIR=str(ext_dir))
        self.tree, self.script = tree, script
        self.proc = subprocess.Popen([sys.executable, str(script), "--worker", str(tree)], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, text=True, env=env, cwd=tree)

    def call(self, **req) -> dict:
        self.proc.stdin.write(json.dumps(req) + "\n")
        self.proc.stdin.flush()
        line = self.proc.stdout.readline()
        if not line:
            raise SystemExit(f"{self.script.stem}: the worker of {self.tree} stopped (its error is above)")
        return json.loads(line)

    def close(self) -> None:
        self.proc.stdin.close()
        self.proc.wait()


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--before", type=Path, help="source tree to compare against (required)")
    ap.add_argument("--after", type=Path, default=HERE.parents[1], help="source tree (default: this one)")
    ap.add_argument("--ext-dir", type=Path, nargs=2, default=None, metavar=("BEFORE", "AFTER"),
                    help="extension caches of the two trees (default: <tree>/.ab_ext)")
    ap.add_argument("--scenes", nargs="+", default=["10k_256"])
    ap.add_argument("--modes", nargs="+", default=["3dgs", "gef_only", "softmax_only", "softmax_gs"])
    ap.add_argument("--k-max", type=int, default=128)
    ap.add_argument("--repeats", type=int, default=15)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--worker", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.worker:
        return worker(args.worker)
    if args.before is None:
        ap.error("--before is required: the source tree to compare against")

    import torch

    trees = {"before": args.before.resolve(), "after": args.after.resolve()}
    for name, tree in trees.items():
        if not (tree / "smgs" / "raster").is_dir():
            raise SystemExit(f"ab: --{name} {tree} is not an smgs source tree (no smgs/raster there)")
    caches = dict(zip(trees, args.ext_dir)) if args.ext_dir else {k: t / ".ab_ext" for k, t in trees.items()}
    workers = {k: Worker(trees[k], caches[k]) for k in trees}
    print(f"# before: {trees['before']}\n# after: {trees['after']}")
    print(f"# median of {args.repeats} calls, the two trees alternated, after {args.warmup} warm-up rounds; "
          f"k_max {args.k_max}; load average {' '.join(f'{x:.2f}' for x in os.getloadavg())}; ms")
    print("\n| scene | mode | before fwd / f+b | after fwd / f+b | after / before | max |Δrgb| |")
    print("|---|---|---:|---:|---:|---:|")
    try:
        with tempfile.TemporaryDirectory() as tmp:
            for scene in args.scenes:
                for mode in args.modes:
                    ts = {(k, bw): [] for k in trees for bw in (False, True)}
                    for r in range(args.warmup + args.repeats):
                        for bw in (False, True):
                            for k in (list(trees) if r % 2 else list(trees)[::-1]):
                                ms = workers[k].call(scene=scene, mode=mode, k_max=args.k_max, backward=bw)["ms"]
                                if r >= args.warmup:
                                    ts[(k, bw)].append(ms)
                    imgs = {}
                    for k in trees:
                        path = str(Path(tmp) / f"{k}.pt")
                        workers[k].call(scene=scene, mode=mode, k_max=args.k_max, backward=False, image=path)
                        imgs[k] = torch.load(path)
                    diff = float((imgs["before"] - imgs["after"]).abs().max())
                    m = {key: statistics.median(v) for key, v in ts.items()}
                    print(f"| {scene} | {mode} | {m[('before', False)]:.2f} / {m[('before', True)]:.2f} | "
                          f"{m[('after', False)]:.2f} / {m[('after', True)]:.2f} | "
                          f"{m[('after', False)] / m[('before', False)]:.2f} / "
                          f"{m[('after', True)] / m[('before', True)]:.2f} | {diff:.1e} |", flush=True)
    finally:
        for w in workers.values():
            w.close()
    print(f"\n- load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
