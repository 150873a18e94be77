"""Renderer throughput: forward and forward+backward from 3D parameters, per scene, mode and backend.

    python bench/raster.py                      # the two benchmark scenes + random scenes, all modes
    python bench/raster.py --scenes 10k_256 --modes 3dgs softmax_gs --repeats 9
    python bench/raster.py --scenes 10k_256 --modes 3dgs --sorts global per_pixel --backends cpu
    python bench/raster.py --scenes 10k_256 --modes 3dgs softmax_gs --backends cpu --leaders
    python bench/raster.py --scenes 100k_512 --modes 3dgs softmax_gs --backends cuda --scopes pixel patch

Everything is timed through ``smgs.raster.rasterize`` (EWA projection and SH in PyTorch, then the
backend), loss = image mean, median over repeats after a warm-up. The modes of a scene and backend
are timed round-robin (one call of each per round), so they share the drift of a shared machine's
load. Columns: forward ms, forward + backward ms, splat-pixel pairs the backend evaluated per second
(forward; pairs / fwd+bwd time), peak resident memory of a forward+backward above the resident set
before it, and each mode's time relative to ``3dgs`` on the same scene and backend (the median of
the per-round ratios). The load average is printed with the table; ratios between modes are more
stable than absolute times. ``--sorts global per_pixel`` adds each mode in the per-pixel order
(rows ``mode/per_pixel``, timed in the same rounds; ×3dgs is then against global ``3dgs``).
``--scopes pixel patch`` adds each softmax mode with k_max in patch scope (rows ``mode@patch``,
docs/kmax-scope.md); "within k_max" is then the pixels whose splats all lie in their tile's first
k_max entries. To compare two source trees of the renderer, see ``bench/ab.py``.

Scenes: the benchmark scenes 10k_256 and 100k_512 (``scene_10k_256.npz``, ``scene_100k_512.npz`` in
the shared data folder beside the checkout), and random scenes made by the same recipe
(``random_scene``) at other sizes (``rand_1m_1600x1000``, 1M splats, only by name). The reference backend is dense (every splat at every
pixel), so it only runs on scenes of at most ``--reference-max-pairs`` splat-pixel pairs.
"""

from __future__ import annotations

import argparse
import math
import os
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

from smgs import Camera  # noqa: E402  (smgs before torch: it sets the OpenMP wait policy)
from smgs.metrics.timing import device_name, track_peak_memory  # noqa: E402
from smgs.raster import MODES, backend_available, mode_flags, rasterize  # noqa: E402
from smgs.raster.projection import project_gaussians  # noqa: E402

import torch  # noqa: E402

SHARED = ROOT.parent / "shared" / "bench"
FILE_SCENES = {"10k_256": "scene_10k_256.npz", "100k_512": "scene_100k_512.npz"}
# name -> (N, width, height, seed)
RANDOM_SCENES = {"rand_1k_64": (1_000, 64, 64, 1), "rand_3k_128": (3_000, 128, 128, 2),
                 "rand_40k_1024x576": (40_000, 1024, 576, 3)}
# by name only (not in the default list): the GPU-sized scene of ../shared/GPU.md and issue 32
LARGE_SCENES = {"rand_1m_1600x1000": (1_000_000, 1600, 1000, 4)}


def random_scene(n: int, width: int, height: int, seed: int) -> dict[str, np.ndarray]:
    """The benchmark scenes' recipe: Gaussians in the frustum of a pinhole camera at the
    origin, z ~ U(2, 6), fx = fy = W, σ_px = 2·exp(N(0, 0.25²)) with per-axis jitter U(0.8, 1.25)
    (3σ radius ≈ 7.6 px at any resolution), random unit quaternions, opacities U(0.3, 0.9), RGB U(0, 1)."""
    rng = np.random.default_rng(seed)
    fx = fy = float(width)
    cx, cy = width / 2, height / 2
    z = rng.uniform(2, 6, n)
    u, v = rng.uniform(0, width, n), rng.uniform(0, height, n)
    means = np.stack([(u - cx) * z / fx, (v - cy) * z / fy, z], 1)
    sig = 2 * np.exp(rng.normal(0, 0.25, n))[:, None] * rng.uniform(0.8, 1.25, (n, 3))
    q = rng.normal(size=(n, 4))
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    K = np.array([[fx, 0, cx], [0, fy, cy], [0, 0, 1]])
    return dict(means=means, scales=sig * z[:, None] / fx, quats_wxyz=q, opacities=rng.uniform(0.3, 0.9, n),
                colors=rng.uniform(0, 1, (n, 3)), K=K, viewmat=np.eye(4), width=width, height=height)


def load_scene(name: str) -> dict[str, np.ndarray]:
    if name in FILE_SCENES:
        path = SHARED / FILE_SCENES[name]
        with np.load(path) as z:
            return {k: z[k] for k in z.files}
    if name not in RANDOM_SCENES and name not in LARGE_SCENES:
        raise SystemExit(f"unknown scene {name!r}; known: {', '.join([*FILE_SCENES, *RANDOM_SCENES, *LARGE_SCENES])}")
    return random_scene(*{**RANDOM_SCENES, **LARGE_SCENES}[name])


def to_inputs(sc: dict[str, np.ndarray], seed: int = 0) -> tuple[dict[str, torch.Tensor], Camera]:
    """Float32 leaf tensors; α, β, γ drawn around typical trained values (α log-uniform in
    [0.8, 1.25] so GEF images stay comparable, β ~ U(0, 10), γ ~ U(0, 2))."""
    n = sc["means"].shape[0]
    g = torch.Generator().manual_seed(seed)
    t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
    p = dict(means3d=t(sc["means"]), quats=t(sc["quats_wxyz"]), scales=t(sc["scales"]),
             opacities=t(sc["opacities"]).reshape(-1), colors=t(sc["colors"]),
             alpha=torch.exp(math.log(1.25) * (2 * torch.rand(n, generator=g) - 1)),
             beta=10 * torch.rand(n, generator=g), gamma=2 * torch.rand(n, generator=g))
    cam = Camera(t(sc["K"]), t(sc["viewmat"]), int(sc["width"]), int(sc["height"]))
    return p, cam


def median_ms(fn, repeats: int, warmup: int) -> float:
    for _ in range(warmup):
        fn()
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * statistics.median(ts)


def _rss_bytes() -> int:
    try:
        with open("/proc/self/statm") as f:
            return int(f.read().split()[1]) * os.sysconf("SC_PAGE_SIZE")
    except OSError:
        return 0


def interleaved_ms(fns: dict[str, Callable[[], object]], repeats: int, warmup: int) -> dict[str, list[float]]:
    """Times of each function in ms, called round-robin (one call of each per round), so that every
    function sees the same drift of a shared machine's load and ratios between them stay fair."""
    for _ in range(warmup):
        for fn in fns.values():
            fn()
    ts: dict[str, list[float]] = {k: [] for k in fns}
    for _ in range(repeats):
        for k, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            ts[k].append(1e3 * (time.perf_counter() - t0))
    return ts


def ratio_to(ts: dict[str, list[float]], key: str, base: str) -> float:
    """Median over rounds of the per-round ratio ts[key] / ts[base]."""
    return statistics.median(a / b for a, b in zip(ts[key], ts[base]))


def mode_calls(params, cam, mode, backend, k_max, sort="global", leaders=False, scope="pixel"):
    """(forward, forward+backward) closures of one mode, each returning the render output.
    ``backend`` "cuda:v2" is the cuda backend through the opt-in kernels (docs/cuda.md)."""
    backend, _, kernels = backend.partition(":")
    dev = torch.device("cuda" if backend == "cuda" else "cpu")
    params = {k: v.to(dev) for k, v in params.items()}
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}
    sync = torch.cuda.synchronize if dev.type == "cuda" else (lambda: None)  # time finished work

    # sort only where it is not the default: bench/ab.py runs this file against older trees too
    extra = {} if sort == "global" else {"sort": sort}
    if leaders:
        extra["leaders"] = True
    if scope != "pixel":
        extra["k_max_scope"] = scope
    if kernels:
        try:   # the variant in the renderer's registry; a tree from before it took the keyword
            from smgs.raster import Renderer
            backend = Renderer(backend, kernels=kernels)
        except ImportError:
            extra["cuda_kernels"] = kernels

    def call(p):
        return rasterize(p["means3d"], p["quats"], p["scales"], p["opacities"], p["colors"], cam,
                         alpha=p["alpha"], beta=p["beta"], gamma=p["gamma"], mode=mode, k_max=k_max,
                         backend=backend, **extra)

    def fwd():
        with torch.no_grad():
            out = call(params)
        sync()
        return out

    def fwd_bwd():
        for v in leaves.values():
            v.grad = None
        out = call(leaves)
        out.rgb.mean().backward()
        sync()
        return out

    return fwd, fwd_bwd, dev


def bench_modes(params, cam, modes, backend, k_max, repeats, warmup) -> dict[str, dict]:
    """Every mode on one scene and backend: forward and forward+backward times (modes interleaved
    round by round), pairs, peak memory, and ratios to ``3dgs`` as medians of per-round ratios."""
    # a label is a mode, or mode/sort for a sort other than global, @scope for a k_max scope other
    # than pixel, +leaders with the leading-splat map
    def parts(label):
        base, lead = label.removesuffix("+leaders"), label.endswith("+leaders")
        base, _, scope = base.partition("@")
        return base.partition("/")[0], base.partition("/")[2] or "global", lead, scope or "pixel"

    calls = {}
    for m in modes:
        mode, sort, lead, scope = parts(m)
        calls[m] = mode_calls(params, cam, mode, backend, k_max, sort, lead, scope)
    res: dict[str, dict] = {}
    for m, (fwd, _, _dev) in calls.items():
        out = fwd()
        res[m] = dict(pairs=out.stats.pairs_evaluated, contrib=out.stats.contributions,
                      within=out.stats.frac_within_kmax)
    t_f = interleaved_ms({m: c[0] for m, c in calls.items()}, repeats, warmup)
    t_fb = interleaved_ms({m: c[1] for m, c in calls.items()}, repeats, warmup)
    for m, (_, fwd_bwd, dev) in calls.items():
        base = _rss_bytes() if dev.type == "cpu" else 0   # cuda: peak allocated by torch
        with track_peak_memory(dev) as pm:
            fwd_bwd()
        peak = max(0, pm.bytes - base) if pm.kind in ("cpu_peak_rss_vmhwm_reset", "cuda_max_memory_allocated") \
            else float("nan")
        res[m].update(fwd_ms=statistics.median(t_f[m]), fb_ms=statistics.median(t_fb[m]), peak_mib=peak / 2**20,
                      ratio=None if "3dgs" not in calls else (ratio_to(t_f, m, "3dgs"), ratio_to(t_fb, m, "3dgs")))
    return res


def projection_ms(params, cam, repeats, warmup):
    leaves = {k: v.clone().requires_grad_(True) for k, v in params.items()}

    def f():
        with torch.no_grad():
            project_gaussians(params["means3d"], params["quats"], params["scales"], cam)

    def fb():
        pr = project_gaussians(leaves["means3d"], leaves["quats"], leaves["scales"], cam)
        (pr.means2d.sum() + pr.conics.sum() + pr.depths.sum()).backward()

    return median_ms(f, repeats, warmup), median_ms(fb, repeats, warmup)


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--scenes", nargs="+", default=["10k_256", "100k_512", *RANDOM_SCENES])
    ap.add_argument("--modes", nargs="+", default=list(MODES), choices=MODES)
    ap.add_argument("--backends", nargs="+", default=["cpu", "cuda", "reference"],
                    help="cpu, cuda, reference, or cuda:v2 (the cuda backend through the opt-in kernels, "
                         "docs/cuda.md)")
    ap.add_argument("--sorts", nargs="+", default=["global"], choices=["global", "per_pixel"])
    ap.add_argument("--leaders", action="store_true",
                    help="also each mode with the leading-splat map (rasterize(leaders=True), Table 4's Pop7)")
    ap.add_argument("--k-max", type=int, default=128)
    ap.add_argument("--scopes", nargs="+", default=["pixel"], choices=["pixel", "patch"],
                    help="k_max scopes of the softmax modes (docs/kmax-scope.md); rows mode@patch")
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--warmup", type=int, default=1)
    ap.add_argument("--reference-max-pairs", type=float, default=5e6)
    args = ap.parse_args(argv)

    from smgs.raster import cpu_build   # here, not at the top: bench/ab.py imports this file into older trees

    print(f"# smgs renderer benchmark: {device_name('cpu')}, CPU SIMD path {cpu_build.isa_in_use()} "
          f"(${cpu_build.ISA_ENV}), torch {torch.__version__}, k_max {args.k_max} "
          f"(scopes {', '.join(args.scopes)}), "
          f"median of {args.repeats} after {args.warmup} warm-up")
    print(f"load average before: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")
    rows, notes = [], []
    for name in args.scenes:
        params, cam = to_inputs(load_scene(name))
        n = params["means3d"].shape[0]
        pf, pfb = projection_ms(params, cam, args.repeats, args.warmup)
        notes.append(f"{name}: projection alone {pf:.1f} ms forward, {pfb:.1f} ms forward+backward")
        for backend in args.backends:
            base = backend.partition(":")[0]
            if not backend_available(base, "cuda" if base == "cuda" else "cpu", torch.float32):
                notes.append(f"{name}: backend {backend} unavailable here")
                continue
            if backend == "reference" and n * cam.width * cam.height > args.reference_max_pairs:
                continue
            reps = args.repeats if backend != "reference" else max(1, min(args.repeats, 3))
            labels = [(m if s == "global" else f"{m}/{s}") + ("" if sc == "pixel" else f"@{sc}")
                      for sc in args.scopes for s in args.sorts for m in args.modes
                      if sc == "pixel" or mode_flags(m)[1]]   # the scope changes softmax modes only
            if backend == "cuda":   # the default kernels: no per-pixel order (cuda:v2 has one)
                labels = [m for m in labels if "/" not in m]
            if args.leaders and backend != "cuda":   # (the default cuda kernels composite them on host copies)
                labels += [f"{m}+leaders" for m in labels]
            res = bench_modes(params, cam, labels, backend, args.k_max, reps, args.warmup)
            for mode, r in res.items():
                print(f"  {name} {mode} {backend}: {r['fwd_ms']:.1f} / {r['fb_ms']:.1f} ms", file=sys.stderr,
                      flush=True)
                rows.append((name, n, mode, backend, r, r["ratio"]))
    print()
    print("| scene | N | mode | backend | fwd ms | fwd+bwd ms | fwd Mpairs/s | f+b Mpairs/s | peak MiB (f+b) "
          "| ×3dgs fwd | ×3dgs f+b | within k_max |")
    print("|---|---:|---|---|---:|---:|---:|---:|---:|---:|---:|---:|")
    for name, n, mode, backend, r, ratio in rows:
        rf, rfb = ("–", "–") if ratio is None else (f"{ratio[0]:.2f}", f"{ratio[1]:.2f}")
        print(f"| {name} | {n:,} | {mode} | {backend} | {r['fwd_ms']:.1f} | {r['fb_ms']:.1f} | "
              f"{r['pairs'] / r['fwd_ms'] / 1e3:.0f} | {r['pairs'] / r['fb_ms'] / 1e3:.0f} | {r['peak_mib']:.0f} | "
              f"{rf} | {rfb} | {r['within']:.2f} |")
    print()
    for s in notes:
        print(f"- {s}")
    print(f"- load average after: {' '.join(f'{x:.2f}' for x in os.getloadavg())}")


if __name__ == "__main__":
    main()
