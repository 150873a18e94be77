"""Seconds per training step for each method, split into render (forward), loss, backward,
optimiser and strategy (densification statistics and refinement) shares.

    python -m bench.train [--methods ...] [--steps 50] [--backend auto] [--device auto] [--fit4]

Scenes:
* ``pattern256``: circle4 at 128², 256 Gaussians (a fixed 16×16 layout, no densification);
* ``pattern4``: circle4 at 128², 4 Gaussians (the Table 1 set-up); ×10K steps gives the time of a
  4-Gaussian fit (goal: < 30 s); ``--fit4`` also runs the full 10K-step fit and times it;
* ``scene3d``: a procedural 3D scene (the ``smgs.demo`` blobs rendered by 3DGS from 4 cameras at
  96²) trained from 1000 noisy "SfM" points with SH degree 3 and the 3DGS densification
  (refinement every 25 steps here, capped at +10%, so its cost shows in a short window).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:       # `python bench/train.py` from a checkout
    sys.path.insert(0, str(ROOT))

from smgs.camera import Camera  # noqa: E402  (smgs before torch: it sets the OpenMP wait policy)
from smgs.data.scene import Scene, View, camera_extent  # noqa: E402

import torch  # noqa: E402


def procedural_scene(size: int = 96, n_views: int = 4) -> Scene:
    from smgs.demo import synthetic_gaussians
    from smgs.metrics.image import to_uint8
    from smgs.raster import rasterize

    s = synthetic_gaussians(400, seed=0)
    views = []
    for i in range(n_views):
        a = 2 * math.pi * i / n_views * 0.15 - 0.2
        eye = [3.0 * math.sin(a), -0.3, 3.0 - 3.0 * math.cos(a)]
        cam = Camera.look_at(eye, [0.0, 0.0, 3.0], [0, -1, 0], fx=size, fy=size, width=size, height=size)
        with torch.no_grad():
            out = rasterize(s["means"], s["quats"], s["scales"], s["opacities"], s["colors"], cam, mode="3dgs",
                            background=torch.zeros(3))
        views.append(View(cam, to_uint8(out.rgb.clamp(0, 1)), f"v{i}"))
    # "SfM" points: 1000 noisy samples of the blob centres, grey
    g = torch.Generator().manual_seed(1)
    idx = torch.randint(0, s["means"].shape[0], (1000,), generator=g)
    pts = s["means"][idx] + 0.05 * torch.randn(1000, 3, generator=g)
    return Scene("procedural3d", views, views[:1], camera_extent([v.camera for v in views]), points=pts,
                 point_colors=torch.full((1000, 3), 0.5))


def _config(scene_name: str, method: str, backend: str) -> dict:
    from smgs.train import pattern_config, to_dict

    if scene_name.startswith("pattern"):
        n = 256 if scene_name == "pattern256" else 4
        cfg = to_dict(pattern_config(method, cap=n, steps=10_000))
        if n == 256:
            cfg["gaussians"].update(n_flat=256, flat_spacing=1 / 16, flat_scale=0.03)
            cfg["densify"]["enabled"] = False
    else:
        cfg = {"mode": method, "steps": 30_000,
               "gaussians": {"init": "sfm"},
               "densify": {"budget_kind": "cap", "cap": 1100, "refine_start": 0, "refine_every": 25}}
    cfg["backend"] = backend
    return cfg


def bench(scene: Scene, scene_name: str, method: str, steps: int, warmup: int, backend: str,
          device: torch.device) -> dict:
    """Seconds per step; on a GPU the device is synchronised before and after the timed steps
    (the per-stage shares are host-side times, so there they show launch cost, not GPU time)."""
    from baselines import create_method
    from smgs.metrics.timing import synchronize

    m = create_method(method, scene, _config(scene_name, method, backend), device=device)
    for s in range(warmup):
        m.train_step(s)
    tr = m.trainer
    tr.timings = {k: 0.0 for k in tr.timings}
    tr.profile = True
    synchronize(device)
    t0, c0 = time.perf_counter(), time.process_time()
    for s in range(warmup, warmup + steps):
        m.train_step(s)
    synchronize(device)
    total, cpu = time.perf_counter() - t0, time.process_time() - c0
    shares = {k: v / total for k, v in tr.timings.items()}
    return {"scene": scene_name, "method": method, "gaussians": m.num_gaussians(),
            "sec_per_step": total / steps, "cpu_sec_per_step": cpu / steps,
            **{f"{k}_share": round(v, 3) for k, v in shares.items()}}


def fit4(method: str, backend: str, device: torch.device, steps: int = 10_000) -> tuple[float, float]:
    """Wall and process CPU seconds of a full 4-Gaussian circle4 fit (set-up excluded)."""
    from baselines import create_method
    from smgs.data.patterns import pattern_scene
    from smgs.metrics.timing import synchronize

    m = create_method(method, pattern_scene("circle4", 128), _config("pattern4", method, backend), device=device)
    synchronize(device)
    t0, c0 = time.perf_counter(), time.process_time()
    for s in range(steps):
        m.train_step(s)
    synchronize(device)
    return time.perf_counter() - t0, time.process_time() - c0


def load() -> str:
    return "load average " + " ".join(f"{v:.2f}" for v in os.getloadavg())


def main(argv: list[str] | None = None) -> int:
    from smgs.data.patterns import pattern_scene
    from smgs.raster import resolve_backend
    from smgs.train.trainer import Trainer  # noqa: F401  (import cost outside the timings)

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--methods", nargs="+", default=["3dgs", "gef_only", "softmax_only", "softmax_gs"])
    ap.add_argument("--scenes", nargs="+", default=["pattern4", "pattern256", "scene3d"])
    ap.add_argument("--steps", type=int, default=50)
    ap.add_argument("--warmup", type=int, default=5)
    ap.add_argument("--backend", default="auto")
    ap.add_argument("--device", default="auto", help="auto | cpu | cuda | cuda:N")
    ap.add_argument("--threads", type=int, default=1)
    ap.add_argument("--fit4", action="store_true", help="also time full 10K-step 4-Gaussian fits")
    ap.add_argument("--json", help="write the rows to this file")
    args = ap.parse_args(argv)
    from smgs.device import DeviceError, device_name, resolve_device
    from smgs.raster.backends import check_backend

    try:
        device = resolve_device(args.device)
        check_backend(args.backend, device)
    except DeviceError as e:
        ap.error(str(e))
    torch.set_num_threads(args.threads)
    backend = resolve_backend(args.backend, device, torch.float32)
    print(f"device {device_name(device)}, backend {backend}, torch threads {torch.get_num_threads()}, {args.steps} timed steps "
          f"after {args.warmup} warm-up; {load()} (s/step is wall time, cpu the process CPU time: "
          f"on a shared machine compare cpu, and ratios within one run)")
    scenes = {"pattern4": pattern_scene("circle4", 128), "pattern256": pattern_scene("circle4", 128)}
    if "scene3d" in args.scenes:
        scenes["scene3d"] = procedural_scene()
    rows = []
    hdr = f"{'scene':11s} {'method':13s} {'#GS':>5s} {'s/step':>9s} {'cpu':>9s} {'render':>7s} {'loss':>6s} " \
          f"{'backward':>8s} {'optim':>6s} {'strategy':>8s}"
    print(hdr)
    for sn in args.scenes:
        for meth in args.methods:
            r = bench(scenes[sn], sn, meth, args.steps, args.warmup, args.backend, device)
            r["backend"], r["device"] = backend, device_name(device)
            rows.append(r)
            print(f"{sn:11s} {meth:13s} {r['gaussians']:5d} {r['sec_per_step']:9.5f} {r['cpu_sec_per_step']:9.5f} "
                  f"{r['render_share']:7.1%} "
                  f"{r['loss_share']:6.1%} {r['backward_share']:8.1%} {r['optim_share']:6.1%} "
                  f"{r['strategy_share']:8.1%}", flush=True)
            if sn == "pattern4":
                print(f"{'':11s} -> 10K-step 4-Gaussian fit ≈ {r['sec_per_step'] * 1e4:.1f} s (goal < 30 s)")
    if args.fit4:
        for meth in args.methods:
            secs, cpu = fit4(meth, args.backend, device)
            rows.append({"scene": "fit4_10k", "method": meth, "seconds": secs, "cpu_seconds": cpu,
                         "backend": backend, "device": device_name(device)})
            print(f"10K-step 4-Gaussian circle4 fit, {meth}: {secs:.1f} s wall, {cpu:.1f} s cpu "
                  f"(goal < 30 s; {load()})", flush=True)
    print(load())
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
