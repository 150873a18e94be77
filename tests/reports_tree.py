"""A results tree for the report tests, written with RunResult + write_result (no committed JSON).

Contents (chosen so each report rule has a case):
- patterns: circle4 × {3dgs, softmax_gs} × caps {4, 16} × seeds {0, 1}, and gef_only cap 4 with one
  seed; 3dgs budgets spelled as the runner writes them (``cap4``, cap in config["budget"]),
  softmax_gs ones as ``cap`` with config["cap"]; rect4 3dgs cap 4 failed.
- mipnerf360: bicycle and garden × {3dgs, softmax_gs} × {full, 5pct}; garden softmax_gs full failed
  (out of memory); bicycle 3dgs 5pct without LPIPS (weights absent); Table 4 consistency on bicycle.
- tandt: train skipped (dataset missing).
- colmap/fern: the cpu preset, 3dgs and softmax_gs at 5pct; the 3dgs run on the reference renderer.
- with ``images=True`` (report.html): the Mip-NeRF360 runs' saved renders, ground truth and |error| maps of
  three views (garden softmax_gs 5pct saved no ground truth: an older run), per-view PSNR, and on bicycle the
  consistency scores per frame pair with a popping strip.

``make_hostile_tree``: runs whose method, preset, scene and error hold HTML and script (escaping).
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from PIL import Image

from protocols.results import CurvePoint, RunResult, write_result

OOM = "RuntimeError: out of memory while allocating 3.2 GiB | at step 1200"
MISSING_DATA = "DatasetMissing: tandt/train not found in data/tandt/train (expected images/ and sparse/0)"
NO_LPIPS = "LPIPS weights not found: run `python -m smgs.metrics.lpips_weights` or set SMGS_LPIPS_WEIGHTS"
VERSIONS = {"smgs": "0.1.0", "torch": "2.13.0+cpu", "numpy": "2.4.6", "python": "3.11.2", "backend": "cpu",
            "device": "cpu", "cpu": "Test CPU @ 2GHz", "git": "abc1234"}


def _curve(final: float, seconds: float, gs: int) -> list[CurvePoint]:
    return [CurvePoint(int(f * 1000), seconds * f, final - 8 * (1 - f) ** 2, int(gs * min(1, 2 * f)))
            for f in (0.1, 0.25, 0.5, 1.0)]


def _ok(method, dataset, scene, budget, seed, psnr, *, gs, seconds=600.0, fps=20.0, preset="paper",
        ssim=0.8, lpips=0.2, **kw) -> RunResult:
    r = RunResult(method=method, dataset=dataset, scene=scene, budget=budget, seed=seed, preset=preset,
                  metrics={"psnr": psnr, "ssim": ssim, "lpips": lpips, "flip": 0.1}, lpips_net="lpips_vgg_v0.1",
                  num_gaussians=gs, train_seconds=seconds, render_fps=fps, render_device="cpu (Test CPU)",
                  steps=3000 if preset == "cpu" else 30000, curve=_curve(psnr, seconds, gs), versions=dict(VERSIONS),
                  **kw)
    r.config = {**r.config, "protocol": {"name": preset, "steps": 3000 if preset == "cpu" else 30000,
                                         "max_width": 400 if preset == "cpu" else None}}
    if method in ("softmax_gs", "softmax_only", "gef_only"):
        params = {}
        if method != "softmax_only":
            params["alpha"] = dict(p05=0.8, p25=1.0, p50=1.4, p75=2.0, p95=4.0, mean=1.7)
        if method != "gef_only":
            params["beta"] = dict(p05=0.5, p25=2.0, p50=5.0, p75=9.0, p95=30.0, mean=7.0)
            params["gamma"] = dict(p05=0.01, p25=0.1, p50=0.5, p75=2.0, p95=10.0, mean=1.5)
        r.diagnostics = {"params": params}
        if method != "gef_only":
            r.diagnostics["frac_within_kmax"] = 0.9 if scene in ("bicycle", "garden") else 0.99
    return r


VIEWS = ("_DSC8679", "_DSC8687", "_DSC8695")


def _png(path: Path, seed: int, size: tuple[int, int] = (48, 32)) -> None:
    rng = np.random.default_rng(seed)
    img = (rng.random((size[1], size[0], 3)) * 255).astype(np.uint8)
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    path.write_bytes(buf.getvalue())


def add_images(run_dir: Path, r: RunResult, gt: bool = True) -> RunResult:
    """The images a run saves (protocols.view_images), on the result before it is written."""
    for k, v in enumerate(VIEWS):
        _png(run_dir / "renders" / f"{v}.png", k + 10 * len(r.method))
        if gt:
            _png(run_dir / "renders" / "gt" / f"{v}.png", k)
            _png(run_dir / "renders" / "error" / f"{v}.png", k + 100)
    r.per_view = {"name": [f"{v}.JPG" for v in VIEWS], "psnr": [r.metrics.get("psnr", 20.0) + 0.5 * k for k in range(3)]}
    if r.consistency:
        r.consistency["scores"] = {"7": {"per_pair": [{"i": i, "j": i + 7, "mse": 0.01 + 0.02 * (i == 5), "flip": 0.03,
                                                       "valid_fraction": 0.8} for i in range(20)]}}
        _png(run_dir / "consistency" / "strip.png", 7, (8 * 24, 16))
        (run_dir / "consistency" / "strip.json").write_text(
            '{"frames": [5, 6, 7, 8, 9, 10, 11, 12], "pair": [5, 12], "mse": 0.03, "step": 7, "why": "worst pair"}')
    return r


def make_tree(root: Path, images: bool = False) -> Path:
    root = Path(root)

    def put(r: RunResult) -> None:
        d = root / r.dataset / r.scene / r.method / r.budget / f"seed{r.seed}"
        if images and r.status == "ok" and r.dataset == "mipnerf360":
            add_images(d, r, gt=(r.scene, r.method, r.budget) != ("garden", "softmax_gs", "5pct"))
        write_result(d, r)

    # Table 1: circle4, two methods, two caps, two seeds
    base = {"3dgs": {4: 18.0, 16: 22.0}, "softmax_gs": {4: 28.5, 16: 32.0}}
    for m, by_cap in base.items():
        for cap, psnr in by_cap.items():
            for seed in (0, 1):
                budget = "cap" if m == "softmax_gs" else f"cap{cap}"
                r = _ok(m, "patterns", "circle4", budget, seed, psnr + 0.2 * seed, gs=cap, seconds=30.0 * cap,
                        fps=200.0 / cap)
                r.config = {"cap": cap} if budget == "cap" else {"budget": {"name": budget, "cap": cap}}
                r.diagnostics["metrics_on_8bit"] = False  # the runner's float-render metrics for fits
                # the budget name "cap" does not tell the caps apart: the directory does
                write_result(root / "patterns" / "circle4" / m / f"cap{cap}" / f"seed{seed}", r)
    put(_ok("gef_only", "patterns", "circle4", "cap4", 0, 24.0, gs=4, seconds=120.0, fps=50.0,
            config={"budget": {"name": "cap4", "cap": 4}}))  # one seed only
    put(RunResult(method="3dgs", dataset="patterns", scene="rect4", budget="cap4", seed=0, status="failed",
                  error="FloatingPointError: loss is nan at step 812", config={"budget": {"cap": 4}},
                  versions=dict(VERSIONS)))

    # Tables 2–5: Mip-NeRF360, two scenes
    psnrs = {("3dgs", "full"): 25.0, ("softmax_gs", "full"): 25.3, ("3dgs", "5pct"): 23.0,
             ("softmax_gs", "5pct"): 24.1}
    for scene, off in (("bicycle", 0.0), ("garden", 2.0)):
        for (m, b), p in psnrs.items():
            if (scene, m, b) == ("garden", "softmax_gs", "full"):
                put(RunResult(method=m, dataset="mipnerf360", scene=scene, budget=b, seed=0, status="failed",
                              error=OOM, versions=dict(VERSIONS)))
                continue
            gs = 4_600_000 if b == "full" else 110_000
            r = _ok(m, "mipnerf360", scene, b, 0, p + off, gs=gs, seconds=2700.0 if b == "full" else 1500.0,
                    fps=50.0 if b == "full" else 150.0, ssim=0.75 + 0.01 * (m == "softmax_gs"),
                    lpips=0.3 - 0.01 * (m == "softmax_gs"))
            if (scene, m, b) == ("bicycle", "3dgs", "5pct"):
                del r.metrics["lpips"]
                r.missing["lpips"] = NO_LPIPS
            if scene == "bicycle" and b == "full":
                r.consistency = {"scene": scene, "method": m, "psnr": p, "mse": 0.016 if m == "softmax_gs" else 0.017,
                                 "flip": 0.031 if m == "softmax_gs" else 0.032, "flip_name": "flip",
                                 "estimator": "geometric", "step": 7, "mask": "per-method",
                                 "pop_ratio": 1.3 if m == "softmax_gs" else 41.0, "popped_fraction": 0.012}
                r.config["eval"] = {"consistency": True}
            put(r)
    put(RunResult(method="softmax_gs", dataset="tandt", scene="train", budget="full", seed=0, status="skipped",
                  error=MISSING_DATA, versions=dict(VERSIONS)))

    # a user COLMAP scene under the cpu preset
    for m, p in (("3dgs", 20.1), ("softmax_gs", 21.3)):
        r = _ok(m, "colmap", "fern", "5pct", 0, p, gs=20_000, seconds=240.0, fps=3.0, preset="cpu")
        if m == "3dgs":   # rendered with the PyTorch reference backend: its row says so
            r.versions["backend"] = "reference"
        put(r)
    return root


# ---- seeds: 3dgs and softmax_gs, three seeds, the procedural scene and fern (cpu preset) ----------------

# PSNR per seed 0, 1, 2. blocks (full): Softmax-GS − 3D GS = 1.0, 1.5, 2.0 per seed (resolved);
# fern (5pct): 0.3, -0.3, 0.9 (inside the noise). tests/test_reports_stats.py does the arithmetic by hand.
SEED_PSNR = {("procedural", "blocks", "full"): {"3dgs": (30.0, 30.4, 29.8), "softmax_gs": (31.0, 31.9, 31.8)},
             ("colmap", "fern", "5pct"): {"3dgs": (20.0, 20.5, 19.5), "softmax_gs": (20.3, 20.2, 20.4)}}


def make_seed_tree(root: Path, seeds: tuple[int, ...] = (0, 1, 2)) -> Path:
    """``SEED_PSNR`` as a runs tree (cpu preset), for the seeds named (a subset of 0, 1, 2)."""
    root = Path(root)
    for (ds, scene, budget), by_method in SEED_PSNR.items():
        for m, psnrs in by_method.items():
            for seed in seeds:
                r = _ok(m, ds, scene, budget, seed, psnrs[seed], gs=3000 + 100 * seed, seconds=60.0 + seed,
                        fps=30.0, preset="cpu", ssim=0.80 + 0.01 * seed, lpips=0.20)
                write_result(root / ds / scene / m / budget / f"seed{seed}", r)
    return root


HOSTILE_METHOD = "<img src=x onerror=window.__pwned=1>"
HOSTILE_PRESET = "</script><script>window.__pwned=2</script>"
HOSTILE_SCENE = "a\"'><b>bold&amp;"
HOSTILE_ERROR = "</td></tr></table><script>window.__pwned=3</script> & <!-- unclosed"


def make_hostile_tree(root: Path) -> Path:
    """Strings from configs, paths and errors that are HTML: report.html must show them as text."""
    root = Path(root)
    for m, preset in ((HOSTILE_METHOD, "paper"), ("3dgs", HOSTILE_PRESET)):
        r = _ok(m, "mipnerf360", HOSTILE_SCENE, "full", 0, 24.0, gs=1000, preset=preset)
        d = root / "mipnerf360" / HOSTILE_SCENE / m / "full" / "seed0"
        add_images(d, r)
        write_result(d, r)
    write_result(root / "mipnerf360" / HOSTILE_SCENE / "softmax_gs" / "full" / "seed0",
                 RunResult(method="softmax_gs", dataset="mipnerf360", scene=HOSTILE_SCENE, budget="full", seed=0,
                           status="failed", error=HOSTILE_ERROR, versions=dict(VERSIONS)))
    return root


# ---- a large tree (bench/report_html.py): the page of a report of hundreds of runs -------------------

def _scene_image(seed: int, w: int, h: int) -> np.ndarray:
    """A smooth synthetic photo: gradients, discs and bars (so renders and error maps look like images)."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / max(w, h)
    img = np.stack([0.3 + 0.4 * x, 0.35 + 0.3 * y, 0.5 - 0.3 * x * y], axis=-1)
    for _ in range(8):
        cx, cy, r = rng.random(), rng.random() * h / w, 0.05 + 0.15 * rng.random()
        img[(x - cx) ** 2 + (y - cy) ** 2 < r * r] = rng.random(3)
    for _ in range(4):
        x0, x1 = sorted(rng.random(2))
        img[:, int(x0 * w):int(x0 * w) + 3] = rng.random(3)
    return img.astype(np.float32)


def _degrade(img: np.ndarray, blur: int, noise: float, seed: int) -> np.ndarray:
    out = img.copy()
    for _ in range(blur):  # box blur passes: a worse method is blurrier
        out = (out + np.roll(out, 1, 0) + np.roll(out, -1, 0) + np.roll(out, 1, 1) + np.roll(out, -1, 1)) / 5
    out += np.random.default_rng(seed).normal(0, noise, out.shape)
    return np.clip(out, 0, 1).astype(np.float32)


def make_large_tree(root: Path, size: tuple[int, int] = (240, 160)) -> Path:
    """200 runs: 11 real scenes (Mip-NeRF360, T&T, Deep Blending) × 4 methods × {5pct, full} × seeds {0, 1}
    (176) and 3 patterns × 4 methods × caps {4, 16} (24); each real run saves 3 test views with ground truth
    and |error| maps (the evaluation's own code), the bicycle runs consistency scores and a strip."""
    import torch

    from protocols.view_images import save_view_images

    root = Path(root)
    methods = {"3dgs": (3, 0.03, 0.0), "gef_only": (2, 0.025, 0.4), "softmax_only": (2, 0.02, 0.3),
               "softmax_gs": (1, 0.015, 0.9)}
    scenes = [("mipnerf360", s) for s in ("bicycle", "bonsai", "counter", "garden", "kitchen", "room", "stump")]
    scenes += [("tandt", "train"), ("tandt", "truck"), ("deepblending", "drjohnson"), ("deepblending", "playroom")]
    w, h = size
    n = 0
    for k, (ds, scene) in enumerate(scenes):
        gts = [_scene_image(100 * k + v, w, h) for v in range(3)]
        names = [f"{scene}_{v:03d}.JPG" for v in range(3)]
        for m, (blur, noise, gain) in methods.items():
            for b in ("5pct", "full"):
                for seed in (0, 1):
                    extra = 1.5 if b == "full" else 0.0
                    r = _ok(m, ds, scene, b, seed, 24.0 + gain + extra + 0.1 * seed - 0.3 * k,
                            gs=3_000_000 if b == "full" else 150_000, seconds=2400.0 if b == "full" else 1300.0,
                            fps=60.0 + 20 * blur if b == "full" else 150.0 + 20 * blur)
                    d = root / ds / scene / m / b / f"seed{seed}"
                    renders = [_degrade(g, blur + (b == "5pct"), noise, seed + 7 * v) for v, g in enumerate(gts)]
                    for name, img in zip(names, renders):
                        _png_array(d / "renders" / f"{Path(name).stem}.png", img)
                    save_view_images(d / "renders", names, [torch.from_numpy(x) for x in renders],
                                     [torch.from_numpy(g) for g in gts], 3)
                    r.per_view = {"name": names, "psnr": [r.metrics["psnr"] + 0.3 * v for v in range(3)]}
                    if scene == "bicycle" and seed == 0:
                        pop = np.random.default_rng(blur).random(40)
                        r.consistency = {"scene": scene, "method": m, "psnr": r.metrics["psnr"], "step": 7,
                                         "mse": 0.01 * blur, "flip": 0.02 * blur, "flip_name": "flip",
                                         "estimator": "geometric", "mask": "per-method",
                                         "scores": {"7": {"per_pair": [{"i": i, "j": i + 7, "mse": 0.004 * blur * (1 + 3 * p ** 8)}
                                                                       for i, p in enumerate(pop)]}}}
                        strip = np.concatenate([_degrade(gts[0], blur, noise, i)[:, :96] for i in range(8)], axis=1)
                        _png_array(d / "consistency" / "strip.png", strip)
                        (d / "consistency" / "strip.json").write_text(
                            '{"frames": [3, 4, 5, 6, 7, 8, 9, 10], "pair": [3, 10], "mse": 0.05, "step": 7, '
                            '"why": "the i \\u2192 i+7 pair with the highest warped MSE"}')
                    write_result(d, r)
                    n += 1
    for pattern in ("circle4", "rect4", "oval4"):
        for m, (blur, noise, gain) in methods.items():
            for cap in (4, 16):
                r = _ok(m, "patterns", pattern, f"cap{cap}", 0, 18.0 + 4 * gain + 2 * (cap == 16), gs=cap,
                        seconds=10.0 * cap, fps=200.0 / cap, config={"budget": {"name": f"cap{cap}", "cap": cap}})
                write_result(root / "patterns" / pattern / m / f"cap{cap}" / "seed0", r)
                n += 1
    assert n == 200, n
    return root


def _png_array(path: Path, img: np.ndarray) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    buf = io.BytesIO()
    Image.fromarray((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8)).save(buf, format="PNG")
    path.write_bytes(buf.getvalue())
