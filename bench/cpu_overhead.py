"""What a small CPU render pays beside rendering: the public ``rasterize`` against its compiled passes
called directly, forward + backward, in one process, interleaved call by call.

    python bench/cpu_overhead.py                       # 3dgs at 10k_256, 41 rounds
    python bench/cpu_overhead.py --modes 3dgs softmax_gs --rounds 61 --profile
    python bench/cpu_overhead.py --blocks 16               # totals over 400 calls of each

``kernel alone``: the compiled projection's forward, the compiled renderer's forward and backward
and the projection's backward (csrc/projection_cpu.cpp, csrc/cpu_kernel.cpp) on inputs prepared
once outside the clock (the gathered colours and opacities), with the loss (the image mean) and its
gradient computed as the api's caller computes them: what nothing but rendering would cost. ``rasterize``: the public entry point (input checks, camera,
projection, gathers, autograd, the loss = image mean and its backward). The ratio is the median of
the per-round ratios (a shared machine's load drifts alike for both within a round), in wall time
and in the CPU time of the process's threads (robust to a loaded machine's waits for a core). As
in training, freed image-sized buffers are kept in the heap (``smgs.train.allocator``). ``--profile``
adds torch.profiler's table of one api call's operators and the Python stages of one call.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from smgs.raster import cpu, projection, rasterize  # noqa: E402
from smgs.raster import constants as K  # noqa: E402
from smgs.raster.cpu_build import select_isa  # noqa: E402
from smgs.raster.types import mode_flags  # noqa: E402

import torch  # noqa: E402

sys.path.insert(0, str(Path(__file__).resolve().parent))
from raster import load_scene, to_inputs  # noqa: E402


def _view(cam) -> torch.Tensor:
    """The packed camera the compiled projection reads (as in every tree since the compiled projection)."""
    return projection._packed_view(projection._view(cam, torch.float32, torch.device("cpu")))


def api_call(p, cam, mode):
    leaves = {k: v.clone().requires_grad_(True) for k, v in p.items()}

    def run():
        for v in leaves.values():
            v.grad = None
        out = rasterize(leaves["means3d"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                        cam, alpha=leaves["alpha"], beta=leaves["beta"], gamma=leaves["gamma"], mode=mode,
                        backend="cpu")
        out.rgb.mean().backward()
    return run


def kernel_call(p, cam, mode):
    """The compiled passes alone, on inputs gathered once (the camera does not change)."""
    pm, rm = projection._JIT.module(), cpu.extension()
    gef, soft = mode_flags(mode)
    view = _view(cam)
    near, eps, ext = K.NEAR_PLANE, K.EPS2D, K.SIGMA_EXTENT
    ids = pm.forward(p["means3d"], p["quats"], p["scales"], view, near, eps, ext)[0]
    opac, col = p["opacities"][ids].contiguous(), p["colors"][ids].contiguous()
    al, be, ga = (p[k][ids].contiguous() if on else torch.empty(0) for k, on in (("alpha", gef), ("beta", soft),
                                                                                 ("gamma", soft)))
    W, H, nth = cam.width, cam.height, torch.get_num_threads()
    zeros = torch.zeros(H, W)
    empty = torch.empty(0)

    def run():
        ids_, m2, con, dep, _ = pm.forward(p["means3d"], p["quats"], p["scales"], view, near, eps, ext)
        o = rm.forward(m2, con, opac, col, dep, al, be, ga, empty, empty, W, H, gef, soft, K.DEFAULT_K_MAX, True,
                       1.0, nth, K.T_MIN, False)
        rgb, a, d, reg, cnt, tf, last, pairs, sid, pk, box, toff, tlist, soff, spos, _ = o
        rgb.mean()                                          # the loss, and its gradient, as the api's caller
        g_rgb = torch.full_like(rgb, 1.0 / rgb.numel())
        g = rm.backward(g_rgb, zeros, zeros, empty, a, d, tf, last, sid, pk, box, toff, tlist, soff, spos, empty,
                        m2.shape[0], 3, 0, W, H, gef, soft, K.DEFAULT_K_MAX, True, 1.0, nth, False)
        pm.backward(p["means3d"], p["quats"], p["scales"], view, near, eps, ids_, g[0], g[1], g[4])
    return run


def autograd_call(p, cam, mode):
    """The compiled passes through their autograd Functions, with the gathers and the loss, but
    without ``rasterize``'s checks, camera packing and backend choice."""
    from smgs.raster.cpu import _RasterizeCPU
    from smgs.raster.composite_inputs import composite_settings
    from smgs.raster.projection import _ProjectCPU

    leaves = {k: v.clone().requires_grad_(True) for k, v in p.items()}
    view = _view(cam)
    st = composite_settings(cam.width, cam.height, mode, K.DEFAULT_K_MAX, "solved", 1.0, K.T_MIN)
    gef, soft = mode_flags(mode)

    def run():
        for v in leaves.values():
            v.grad = None
        ids, m2, con, dep, _ = _ProjectCPU.apply(leaves["means3d"], leaves["quats"], leaves["scales"], view,
                                                  K.NEAR_PLANE, K.EPS2D)
        g = lambda k, on=True: leaves[k].index_select(0, ids) if on else None  # noqa: E731
        rgb = _RasterizeCPU.apply(m2, con, g("opacities"), g("colors"), dep, g("alpha", gef), g("beta", soft),
                                  g("gamma", soft), None, None, st)[0]
        rgb.mean().backward()
    return run


def interleaved(fns: dict, rounds: int, warmup: int = 3) -> dict[str, list[float]]:
    for _ in range(warmup):
        for f in fns.values():
            f()
    ts = {k: [] for k in fns}
    cpu_ts = {k: [] for k in fns}
    for r in range(rounds):
        order = list(fns.items()) if r % 2 == 0 else list(fns.items())[::-1]
        for k, f in order:
            c0, t0 = time.process_time(), time.perf_counter()
            f()
            ts[k].append(1e3 * (time.perf_counter() - t0))
            cpu_ts[k].append(1e3 * (time.process_time() - c0))
    return ts, cpu_ts


def blocks(fns: dict, n_blocks: int, per_block: int = 25) -> dict[str, tuple[float, float]]:
    """(CPU ms, wall ms) per call of each function over ``n_blocks`` blocks of ``per_block`` calls,
    the functions taking turns block by block (which goes first flips every block): totals over
    hundreds of calls, steadier on a loaded machine than per-call medians."""
    import resource

    def cpu_s() -> float:
        r = resource.getrusage(resource.RUSAGE_SELF)
        return r.ru_utime + r.ru_stime

    for f in fns.values():
        for _ in range(3):
            f()
    tot = {k: [0.0, 0.0] for k in fns}
    for b in range(n_blocks):
        for k, f in (list(fns.items()) if b % 2 == 0 else list(fns.items())[::-1]):
            c0, t0 = cpu_s(), time.perf_counter()
            for _ in range(per_block):
                f()
            tot[k][0] += cpu_s() - c0
            tot[k][1] += time.perf_counter() - t0
    n = n_blocks * per_block
    return {k: (1e3 * c / n, 1e3 * w / n) for k, (c, w) in tot.items()}


def profile_api(run) -> None:
    from torch.profiler import ProfilerActivity, profile

    with profile(activities=[ProfilerActivity.CPU]) as prof:
        for _ in range(5):
            run()
    print(prof.key_averages().table(sort_by="self_cpu_time_total", row_limit=25))
    import cProfile
    import pstats

    pr = cProfile.Profile()
    pr.enable()
    for _ in range(20):
        run()
    pr.disable()
    pstats.Stats(pr).sort_stats("tottime").print_stats(25)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scene", default="10k_256")
    ap.add_argument("--modes", nargs="+", default=["3dgs"])
    ap.add_argument("--rounds", type=int, default=41)
    ap.add_argument("--profile", action="store_true")
    ap.add_argument("--blocks", type=int, default=0, help="instead of per-call rounds: N blocks of 25 calls "
                    "of each, CPU time (getrusage) and wall time per call from the totals")
    ap.add_argument("--no-keep-freed-buffers", action="store_true",
                    help="leave glibc's malloc thresholds as they are (the trainer raises them, "
                         "smgs.train.allocator: freed image-sized buffers are reused instead of re-faulted)")
    args = ap.parse_args(argv)
    if not args.no_keep_freed_buffers:
        from smgs.train.allocator import keep_freed_buffers

        keep_freed_buffers()
    p, cam = to_inputs(load_scene(args.scene))
    import os

    from smgs.env import cpu_model

    print(f"cpu {cpu_model()}, isa {select_isa()}, "
          f"{torch.get_num_threads()} threads, load {os.getloadavg()[0]:.1f}")
    if args.blocks:
        print("| scene | mode | kernel alone CPU / wall ms | rasterize CPU / wall ms | ratio CPU | ratio wall |")
        print("|---|---|--:|--:|--:|--:|")
        for mode in args.modes:
            r = blocks({"kernel": kernel_call(p, cam, mode), "api": api_call(p, cam, mode)}, args.blocks)
            (kc, kw), (ac, aw) = r["kernel"], r["api"]
            print(f"| {args.scene} | {mode} | {kc:.2f} / {kw:.2f} | {ac:.2f} / {aw:.2f} | {ac / kc:.3f} | "
                  f"{aw / kw:.3f} |", flush=True)
        return 0
    print("wall ms (median) / CPU ms of the process's threads (median), and each one's ratio to the kernel alone "
          "(median of per-round ratios)")
    print("| scene | mode | kernel alone | + autograd, gathers, loss | rasterize | ratio autograd | ratio rasterize |")
    print("|---|---|--:|--:|--:|--:|--:|")
    for mode in args.modes:
        fns = {"kernel": kernel_call(p, cam, mode), "autograd": autograd_call(p, cam, mode),
               "api": api_call(p, cam, mode)}
        ts, cs = interleaved(fns, args.rounds)
        med = lambda d, k: statistics.median(d[k])  # noqa: E731
        rat = lambda d, k: statistics.median(a / b for a, b in zip(d[k], d["kernel"]))  # noqa: E731
        cell = lambda k: f"{med(ts, k):.2f} / {med(cs, k):.2f}"  # noqa: E731
        print(f"| {args.scene} | {mode} | {cell('kernel')} | {cell('autograd')} | {cell('api')} "
              f"| {rat(ts, 'autograd'):.3f} / {rat(cs, 'autograd'):.3f} | {rat(ts, 'api'):.3f} / {rat(cs, 'api'):.3f} |",
              flush=True)
        if args.profile:
            profile_api(fns["api"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
