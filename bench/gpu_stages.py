"""The stages of the GPU check (bench/gpu_check.py), one function each: ``run(ctx) -> dict`` where
``ctx`` says where to write and how big to go, and ``ctx.save(partial)`` leaves what is done so far
in case the stage's deadline cuts it short. Every stage that needs a GPU says so and returns at once
where there is none, except with ``ctx.device == "cpu"`` (the check's own test): then the same code
runs on the CPU with the cpu backend standing in for the CUDA variants, on tiny scenes.

VARIANTS is the hook for renderer variants: each is checked (agreement), timed and counted
(launches, host waits) beside the default. A variant is its environment (what the renderer reads
per call: ``SMGS_CUDA_GLUE``, ``SMGS_CUDA_KERNELS``) and its bench/raster.py backend string.
"""

from __future__ import annotations

import contextlib
import importlib
import importlib.util
import json
import math
import os
import statistics
import subprocess
import sys
import time
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable, Iterator

ROOT = Path(__file__).resolve().parents[1]
BENCH = Path(__file__).resolve().parent
for p in (str(ROOT), str(BENCH)):
    if p not in sys.path:
        sys.path.insert(0, p)

import smgs  # noqa: E402,F401  (before torch: the OpenMP wait policy)

import torch  # noqa: E402


@dataclass(frozen=True)
class Variant:
    """A way of rendering on the GPU that the check verifies and times beside the default."""

    name: str
    env: dict[str, str] = field(default_factory=dict)
    backend: str = "cuda"


VARIANTS: list[Variant] = [
    Variant("default"),
    Variant("lean glue", {"SMGS_CUDA_GLUE": "lean"}),
    Variant("v2 kernels", {"SMGS_CUDA_KERNELS": "v2"}),
    Variant("v2 kernels + lean glue", {"SMGS_CUDA_KERNELS": "v2", "SMGS_CUDA_GLUE": "lean"}),
]
CPU_STANDIN = [Variant("cpu backend (stand-in)", backend="cpu")]

# Inputs of rasterize whose gradients are compared (colours: no SH in the benchmark scenes).
GRAD_KEYS = ("means3d", "quats", "scales", "opacities", "colors", "alpha", "beta", "gamma")
TIMING_SCENES = ("10k_256", "100k_512", "rand_1m_1600x1000")
AGREEMENT_SCENES = ("10k_256", "100k_512")
SMALL_SCENE = "small (vs reference, float64)"
FOX_METHODS = ("3dgs", "softmax_gs")
GSPLAT_ENV = "SMGS_GPU_CHECK_GSPLAT"   # set by bench/gpu_check.py: the background gsplat build's state


@dataclass
class Context:
    out: Path
    device: str = "cuda"            # "cpu": the check's own test (no GPU needed)
    tiny: bool = False              # small scenes and few repeats (the test)
    shared: Path | None = None      # the folder with bench/ and data/fox (../shared or the bundle's)
    save: Callable[[dict], None] = lambda partial: None
    pytest_args: tuple[str, ...] = ()
    ends_at: float = float("inf")   # time.monotonic() of the stage's deadline

    def left(self, margin: float = 10.0) -> float | None:
        """Seconds a child process may take and still leave the stage ``margin`` to collect what it
        did (None: no deadline)."""
        return None if math.isinf(self.ends_at) else max(1.0, self.ends_at - time.monotonic() - margin)


def no_gpu_reason(ctx: Context) -> str | None:
    if ctx.device == "cpu":
        return None
    if not torch.cuda.is_available():
        return ("no CUDA device (torch.cuda.is_available() is False; torch "
                f"{torch.__version__}, CUDA {torch.version.cuda})")
    return None


def variants(ctx: Context) -> list[Variant]:
    return CPU_STANDIN if ctx.device == "cpu" else VARIANTS


@contextlib.contextmanager
def environment(env: dict[str, str]) -> Iterator[None]:
    old = {k: os.environ.get(k) for k in env}
    os.environ.update(env)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


def sync(device: str) -> None:
    if device == "cuda":
        torch.cuda.synchronize()


# -- scenes ----------------------------------------------------------------------------------------

def scene(ctx: Context, name: str):
    """(params, camera) of a bench/raster.py scene; tiny: a random scene of the same recipe."""
    import raster

    if ctx.shared is not None:
        raster.SHARED = ctx.shared / "bench"
    if ctx.tiny:
        sizes = {"10k_256": (300, 48, 32, 1), "100k_512": (600, 64, 48, 2), "rand_1m_1600x1000": (900, 80, 50, 4)}
        return raster.to_inputs(raster.random_scene(*sizes.get(name, (300, 48, 32, 1))))
    return raster.to_inputs(raster.load_scene(name))


# -- env -------------------------------------------------------------------------------------------

def _cmd(*args: str) -> str:
    try:
        return subprocess.run(args, capture_output=True, text=True, timeout=20).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return ""


def gsplat_version() -> str | None:
    try:
        from importlib.metadata import version

        return version("gsplat")
    except Exception:
        return None


def run_env(ctx: Context) -> dict:
    from smgs.env import cpu_model, git_revision

    out = {"python": sys.version.split()[0], "torch": torch.__version__, "cuda": torch.version.cuda,
           "commit": git_revision(), "cpu": cpu_model(), "cpu_count": os.cpu_count(),
           "gsplat": gsplat_version(), "device": ctx.device,
           "bundle": [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p.endswith("site")],
           "nvcc": _cmd("nvcc", "--version").splitlines()[-1:] or None}
    if torch.cuda.is_available():
        props = torch.cuda.get_device_properties(0)
        out.update(gpu=props.name, capability=f"{props.major}.{props.minor}", gpu_mib=props.total_memory // 2**20,
                   driver=_cmd("nvidia-smi", "--query-gpu=driver_version", "--format=csv,noheader") or None)
    else:
        out.update(gpu=None, why_no_gpu=no_gpu_reason(Context(ctx.out)))
    for mod in ("hydra", "omegaconf", "antlr4", "plyfile", "flip_evaluator", "submitit"):
        try:
            importlib.import_module(mod)
            out.setdefault("imports_ok", []).append(mod)
        except Exception as e:   # noqa: BLE001 - recorded
            out.setdefault("imports_missing", []).append(f"{mod}: {type(e).__name__}: {e}")
    return out


# -- build -----------------------------------------------------------------------------------------

# (what, module, t_min): every extension the stages load, the variants for t_min = 0.05 too (the
# tests' non-default threshold, a build of its own), so that no later stage waits for a build
BUILDS = [("default CUDA renderer", "smgs.raster.cuda", None), ("v2 compositing", "smgs.raster.cuda_v2", None),
          ("fused projection", "smgs.raster.projection_cuda", None), ("CPU renderer", "smgs.raster.cpu", None),
          ("CPU projection", "smgs.raster.projection", None),
          ("default CUDA renderer, t_min 0.05", "smgs.raster.cuda", 0.05),
          ("v2 compositing, t_min 0.05", "smgs.raster.cuda_v2", 0.05)]
CPU_BUILDS = ("smgs.raster.cpu", "smgs.raster.projection")
# one build in a process of its own: load (building where the cache has none), print the seconds
BUILD_ONE = """
import importlib, sys, time
name, t_min = sys.argv[1], sys.argv[2]
t0 = time.perf_counter()
mod = importlib.import_module(name)
if name == "smgs.raster.projection":
    if not mod.fused_available():
        sys.exit("the compiled CPU projection is unavailable here")
elif t_min == "default":
    mod.extension()
else:
    mod.extension(float(t_min))
print(round(time.perf_counter() - t0, 1))
"""


def run_build(ctx: Context) -> dict:
    """Every extension built (or loaded from the cache) at once, each in its own process, timed."""
    why = no_gpu_reason(ctx) or ("the check runs on the CPU" if ctx.device == "cpu" else None)
    res: dict = {}
    procs = {}
    for what, module, t_min in BUILDS:
        if module not in CPU_BUILDS and why:
            res[what] = {"skipped": why}
            continue
        log = (ctx.out / "logs" / f"build-{module.rsplit('.', 1)[1]}-{t_min or 'default'}.log")
        log.parent.mkdir(parents=True, exist_ok=True)
        procs[what] = (subprocess.Popen([sys.executable, "-c", BUILD_ONE, module, str(t_min or "default")], cwd=ROOT,
                                        stdout=log.open("w"), stderr=subprocess.STDOUT), log, time.perf_counter())
    ends = time.monotonic() + (ctx.left(margin=3.0) or 1e9)
    while procs:
        for what, (proc, log, t0) in list(procs.items()):
            if proc.poll() is None and time.monotonic() < ends:
                continue
            if proc.poll() is None:
                proc.kill()
                proc.wait()
                res[what] = {"error": "cut at the stage's deadline", "seconds": round(time.perf_counter() - t0, 1)}
            elif proc.returncode != 0:
                res[what] = {"error": f"exit code {proc.returncode}: " + log.read_text()[-1500:].strip(),
                             "seconds": round(time.perf_counter() - t0, 1)}
            else:
                res[what] = {"seconds": round(time.perf_counter() - t0, 1)}
            del procs[what]
            ctx.save(res)
        time.sleep(0.2)
    return {what: res[what] for what, _, _ in BUILDS}


# -- pytest -m gpu ---------------------------------------------------------------------------------

# The renderer's GPU tests run first (stage "pytest"); those that train a model or build another
# variant of an extension (a non-default t_min) are marked slow and run after fox ("pytest-train"),
# so that a renderer test never waits for a build or a training run.
GPU_TEST_ORDER = ("test_raster_cuda.py", "test_raster_projection_cuda.py", "test_raster_cuda_v2.py",
                  "test_raster_quad.py", "test_raster_input_checks.py", "test_device_gpu.py")
PYTEST_SELECTION = {"pytest": "gpu and not slow", "pytest-train": "gpu and slow"}
PYTEST_TEST_TIMEOUT = {"pytest": 45, "pytest-train": 120}   # seconds one test may take (pytest-timeout)


def gpu_test_files() -> list[str]:
    marked = sorted(p.name for p in (ROOT / "tests").glob("test_*.py") if "mark.gpu" in p.read_text())
    first = [n for n in GPU_TEST_ORDER if n in marked]
    return [f"tests/{n}" for n in first + [n for n in marked if n not in first]]


def _run_pytest(ctx: Context, stage: str) -> dict:
    """``pytest -m <PYTEST_SELECTION[stage]>`` over the files with GPU tests (or ``ctx.pytest_args``),
    its junit report parsed; cut short by the stage's deadline, what the log shows so far."""
    why = no_gpu_reason(ctx)
    if why:
        return {"skipped": why}
    tag = {"pytest": "gpu", "pytest-train": "train"}[stage]
    xml, log = ctx.out / f"pytest-{tag}.xml", ctx.out / f"pytest-{tag}.log"
    xml.unlink(missing_ok=True)
    args = [sys.executable, "-m", "pytest", "-m", PYTEST_SELECTION[stage], "-v", "-p", "no:cacheprovider",
            f"--junitxml={xml}", *(ctx.pytest_args or gpu_test_files())]
    if importlib.util.find_spec("pytest_timeout"):
        args.append(f"--timeout={PYTEST_TEST_TIMEOUT[stage]}")   # one hung test does not take the whole stage
    t0 = time.perf_counter()
    with log.open("w") as f:
        try:
            rc = subprocess.run(args, cwd=ROOT, stdout=f, stderr=subprocess.STDOUT, timeout=ctx.left()).returncode
        except subprocess.TimeoutExpired:
            rc = "cut at the stage's deadline"
    text = log.read_text()
    res = {"rc": rc, "seconds": round(time.perf_counter() - t0, 1), "selection": PYTEST_SELECTION[stage],
           "summary": (text.strip().splitlines() or [""])[-1],
           "passed_so_far": text.count(" PASSED"), "failed_so_far": text.count(" FAILED") + text.count(" ERROR")}
    if xml.exists() and isinstance(rc, int):
        res.update(junit_summary(xml))
    return res


def run_pytest(ctx: Context) -> dict:
    """The renderer's GPU tests (``-m "gpu and not slow"``)."""
    return _run_pytest(ctx, "pytest")


def run_pytest_train(ctx: Context) -> dict:
    """The GPU tests that train or build another variant (``-m "gpu and slow"``)."""
    return _run_pytest(ctx, "pytest-train")


def junit_summary(path: Path) -> dict:
    import xml.etree.ElementTree as ET

    root = ET.parse(path).getroot()
    suites = [root] if root.tag == "testsuite" else list(root)
    count = lambda k: sum(int(s.get(k, 0)) for s in suites)  # noqa: E731
    failed = [f"{c.get('classname')}::{c.get('name')}" for s in suites for c in s
              if c.find("failure") is not None or c.find("error") is not None]
    return {"tests": count("tests"), "failures": count("failures"), "errors": count("errors"),
            "skipped_tests": count("skipped"), "failed": failed[:50]}


# -- agreement -------------------------------------------------------------------------------------

def _render(params, cam, mode, backend, env, device, dtype=torch.float32):
    from smgs.raster import rasterize

    leaves = {k: v.to(device=device, dtype=dtype).clone().requires_grad_(True) for k, v in params.items()}
    with environment(env):
        out = rasterize(leaves["means3d"], leaves["quats"], leaves["scales"], leaves["opacities"], leaves["colors"],
                        cam, alpha=leaves["alpha"], beta=leaves["beta"], gamma=leaves["gamma"], mode=mode,
                        backend=backend)
        g = torch.Generator().manual_seed(3)   # the same weights whatever the dtype
        w = torch.rand(out.rgb.shape, generator=g).to(device=device, dtype=dtype)
        ((out.rgb * w).sum() + out.alpha.sum() + out.depth.mean()).backward()
    host = lambda t: t.detach().to("cpu", torch.float64)  # noqa: E731
    return ({"rgb": host(out.rgb), "alpha": host(out.alpha), "depth": host(out.depth),
             "n_contrib": out.stats.n_contrib.cpu()},
            {k: None if v.grad is None else host(v.grad) for k, v in leaves.items()})


def compare(a, ga, b, gb) -> dict:
    """Largest differences of b against a: outputs absolute, gradients relative to a's largest."""
    res = {k: float((a[k] - b[k]).abs().max()) if a[k].numel() else 0.0 for k in ("rgb", "alpha", "depth")}
    res["n_contrib_differ"] = int((a["n_contrib"] != b["n_contrib"]).sum())
    res["pixels"] = a["n_contrib"].numel()
    res["finite"] = all(bool(torch.isfinite(b[k]).all()) for k in ("rgb", "alpha", "depth")) and all(
        v is None or bool(torch.isfinite(v).all()) for v in gb.values())
    worst, which = 0.0, None
    for k, va in ga.items():
        vb = gb.get(k)
        if va is None or vb is None:
            continue
        rel = float((va - vb).abs().max() / (va.abs().max() + 1e-12))
        if rel >= worst:
            worst, which = rel, k
    res["grad_rel"], res["grad_worst"] = worst, which
    return res


def run_agreement(ctx: Context) -> dict:
    """Each variant against the CPU backend on the benchmark scenes, and against the float64
    reference on a small scene: images, alpha, depth, n_contrib, every 3D input's gradient."""
    import raster
    from smgs.raster import MODES

    why = no_gpu_reason(ctx)
    if why:
        return {"skipped": why}
    dev = ctx.device
    rows = []
    small = raster.to_inputs(raster.random_scene(300 if not ctx.tiny else 60, 64, 48, 5))
    for name in [*AGREEMENT_SCENES, SMALL_SCENE]:
        params, cam = small if name == SMALL_SCENE else scene(ctx, name)
        for mode in MODES:
            if name == SMALL_SCENE:
                a, ga = _render(params, cam, mode, "reference", {}, dev, torch.float64)
            else:
                a, ga = _render(params, cam, mode, "cpu", {}, "cpu")
            for v in variants(ctx):
                try:
                    b, gb = _render(params, cam, mode, v.backend.partition(":")[0], v.env, dev)
                    rows.append({"scene": name, "mode": mode, "variant": v.name, **compare(a, ga, b, gb)})
                except Exception as e:  # noqa: BLE001 - recorded, the other variants still run
                    rows.append({"scene": name, "mode": mode, "variant": v.name, "error": f"{type(e).__name__}: {e}"[:500]})
            ctx.save({"rows": rows})
    return {"rows": rows}


# -- timing ----------------------------------------------------------------------------------------

def _gsplat_calls(params, cam, device):
    """gsplat's rasterization (packed=False) on the same scene, its camera prepared on the device
    outside the clock; (forward, forward+backward) closures, or None where gsplat is missing."""
    if os.environ.get(GSPLAT_ENV) != "built":   # bench/gpu_check.py built it, or not
        return None
    try:
        import gsplat
    except Exception:
        return None
    p = {k: v.to(device) for k, v in params.items()}
    leaves = {k: v.clone().requires_grad_(True) for k, v in p.items()}
    viewmat, K = cam.viewmat.to(device)[None], cam.K.to(device)[None]

    def call(q):
        rgb, _, _ = gsplat.rasterization(q["means3d"], q["quats"], q["scales"], q["opacities"], q["colors"], viewmat,
                                         K, cam.width, cam.height, packed=False)
        return rgb[0]

    def fwd():
        with torch.no_grad():
            out = call(p)
        torch.cuda.synchronize()
        return out

    def fwd_bwd():
        for v in leaves.values():
            v.grad = None
        out = call(leaves)
        out.mean().backward()
        torch.cuda.synchronize()
        return out
    return fwd, fwd_bwd


def _timed_rows(ctx, name, params, cam, modes, repeats) -> list[dict]:
    """bench/raster.py's calls for each variant and mode, and gsplat's, interleaved round by round."""
    import raster
    from smgs.metrics.timing import track_peak_memory

    dev = "cpu" if ctx.device == "cpu" else "cuda"
    calls = {}
    for v in variants(ctx):
        for mode in modes:
            fwd, fb, _ = raster.mode_calls(params, cam, mode, v.backend, 128)
            calls[(v.name, mode)] = (_with_env(fwd, v.env), _with_env(fb, v.env))
    gs = _gsplat_calls(params, cam, dev) if dev == "cuda" else None
    if gs is not None:
        calls[("gsplat 1.5.3 rasterization" if gsplat_version() == "1.5.3" else f"gsplat {gsplat_version()}",
               "3dgs")] = gs
    t_f = raster.interleaved_ms({k: c[0] for k, c in calls.items()}, repeats, 2)
    t_fb = raster.interleaved_ms({k: c[1] for k, c in calls.items()}, repeats, 2)
    rows = []
    for k, (_, fb) in calls.items():
        base = raster._rss_bytes() if dev == "cpu" else 0   # the CPU's peak is of the whole process
        with track_peak_memory(torch.device(dev)) as pm:
            fb()
        rows.append({"scene": name, "variant": k[0], "mode": k[1], "fwd_ms": statistics.median(t_f[k]),
                     "fb_ms": statistics.median(t_fb[k]), "peak_mib": max(0, (pm.bytes or 0) - base) / 2**20,
                     "peak_kind": pm.kind})
    return rows


def _with_env(fn, env):
    def call():
        with environment(env):
            return fn()
    return call


def image_vs_gsplat(params, cam) -> dict | None:
    """PSNR and largest difference of smgs 3dgs (default) against gsplat's image."""
    gs = _gsplat_calls(params, cam, "cuda")
    if gs is None:
        return None
    import raster

    ours = raster.mode_calls(params, cam, "3dgs", "cuda", 128)[0]().rgb.float()
    theirs = gs[0]().float()
    mse = float(((ours - theirs) ** 2).mean())
    return {"psnr_db": 10 * math.log10(1.0 / mse) if mse > 0 else float("inf"),
            "max_abs": float((ours - theirs).abs().max())}


def run_timing(ctx: Context) -> dict:
    from smgs.raster import MODES

    why = no_gpu_reason(ctx)
    if why:
        return {"skipped": why}
    res: dict = {"rows": [], "vs_gsplat": {}, "gsplat": gsplat_version(), "gsplat_build": os.environ.get(GSPLAT_ENV)}
    for name in TIMING_SCENES:
        try:
            params, cam = scene(ctx, name)
            repeats = 3 if ctx.tiny else (5 if name.startswith("rand_1m") else 10)
            res["rows"] += _timed_rows(ctx, name, params, cam, MODES, repeats)
            if ctx.device == "cuda":
                res["vs_gsplat"][name] = image_vs_gsplat(params, cam)
        except Exception as e:  # noqa: BLE001 - recorded, the next scene still runs
            res["rows"].append({"scene": name, "variant": "", "mode": "", "error": f"{type(e).__name__}: {e}"[:500]})
        if ctx.device == "cuda":
            torch.cuda.empty_cache()
        ctx.save(res)
    return res


# -- launches and host waits -----------------------------------------------------------------------

SYNC_EVENTS = ("cudaStreamSynchronize", "cudaDeviceSynchronize", "cudaEventSynchronize", "cudaMemcpy")
LAUNCH_EVENTS = ("cudaLaunchKernel", "cuLaunchKernel", "cudaLaunchKernelExC", "cuLaunchKernelEx")


def count_calls(fn, device: str) -> dict:
    """Kernel launches and synchronising runtime calls of ``fn()`` (torch.profiler), and the
    warnings of torch.cuda.set_sync_debug_mode("warn") (a CUDA device only)."""
    from torch.profiler import ProfilerActivity, profile

    acts = [ProfilerActivity.CPU] + ([ProfilerActivity.CUDA] if device == "cuda" else [])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        if device == "cuda":
            torch.cuda.set_sync_debug_mode("warn")
        try:
            with profile(activities=acts) as prof:
                fn()
        finally:
            if device == "cuda":
                torch.cuda.set_sync_debug_mode("default")
        sync(device)
    events = list(prof.events())
    names = [e.name for e in events]
    return {"launches": sum(n in LAUNCH_EVENTS for n in names),
            "kernels": sum(str(getattr(e, "device_type", "")).endswith("CUDA") for e in events),
            "syncs": sum(n.startswith(SYNC_EVENTS) and "Async" not in n for n in names),
            "memcpy_async": sum(n == "cudaMemcpyAsync" for n in names),
            "sync_warnings": sum("synchroniz" in str(w.message).lower() for w in caught) if device == "cuda" else None,
            "aten_ops": sum(n.startswith("aten::") for n in names)}


def run_syncs(ctx: Context) -> dict:
    """One forward and one backward of 3dgs and softmax_gs at 10k_256 per variant."""
    from smgs.raster import rasterize

    why = no_gpu_reason(ctx)
    if why:
        return {"skipped": why}
    params, cam = scene(ctx, "10k_256")
    dev = ctx.device
    rows = []
    for v in variants(ctx):
        for mode in ("3dgs", "softmax_gs"):
            leaves = {k: t.to(dev).clone().requires_grad_(True) for k, t in params.items()}
            with environment(v.env):
                def fwd():
                    return rasterize(leaves["means3d"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                     leaves["colors"], cam, alpha=leaves["alpha"], beta=leaves["beta"],
                                     gamma=leaves["gamma"], mode=mode, backend=v.backend.partition(":")[0])
                fwd().rgb.mean().backward()            # warm: builds, caches, allocator
                box = {}
                f = count_calls(lambda: box.setdefault("out", fwd()), dev)
                b = count_calls(lambda: box["out"].rgb.mean().backward(), dev)
            rows.append({"variant": v.name, "mode": mode, "forward": f, "backward": b})
            ctx.save({"rows": rows})
    return {"rows": rows}


# -- training (fox) and the smoke experiment -------------------------------------------------------

def protocol_command(ctx: Context, which: str, out_dir: Path) -> list[str]:
    base = [sys.executable, "-m", "protocols.run", f"out_dir={out_dir}", f"device={ctx.device}"]
    methods = f"grid.methods=[{','.join(FOX_METHODS)}]"
    if which == "fox" and not ctx.tiny:
        fox = (ctx.shared or ROOT.parent / "shared") / "data" / "fox"
        # the final evaluation only, without FLIP: the figures the stage reports, in its deadline
        return base + ["dataset=transforms", f"dataset.path={fox}", methods, "budget=full", "protocol.steps=3000",
                       "report=false", "eval.fractions=[1.0]", "eval.flip=false"]
    if which == "fox":   # the test: the same runner and results on a tiny procedural scene
        return base + ["+experiment=smoke", methods, "protocol.steps=2", "report=false",
                       "dataset.n_views=4", "dataset.width=24", "dataset.height=16", "eval.fps_repeats=1",
                       "eval.flip=false", "eval.fractions=[1.0]"]
    return base + ["+experiment=smoke"] + (["protocol.steps=2", "dataset.n_views=4", "dataset.width=24",
                                            "dataset.height=16", "grid.methods=[3dgs]", "report=false"]
                                           if ctx.tiny else [])


def _run_protocol(ctx: Context, which: str) -> tuple[dict, Path]:
    out_dir = ctx.out / which
    env = {**os.environ, "SMGS_LPIPS_AUTO": "0"}
    t0 = time.perf_counter()
    log = ctx.out / f"{which}.log"
    with log.open("w") as f:
        try:
            rc = subprocess.run(protocol_command(ctx, which, out_dir), cwd=ROOT, env=env, stdout=f,
                                stderr=subprocess.STDOUT, timeout=ctx.left()).returncode
        except subprocess.TimeoutExpired:   # the cells that finished are read all the same
            rc = "cut at the stage's deadline"
    text = log.read_text()
    return {"rc": rc, "seconds": round(time.perf_counter() - t0, 1),
            "tail": text.strip()[-600:] if rc != 0 else ""}, out_dir


def run_fox(ctx: Context) -> dict:
    """fox (transforms.json), FOX_METHODS, full budget, 3000 steps, cpu preset: ms per step, test PSNR,
    Gaussians (from each run's results.json)."""
    from protocols.results import read_result

    why = no_gpu_reason(ctx)
    if why:
        return {"skipped": why}
    res, out_dir = _run_protocol(ctx, "fox")
    rows = []
    for path in sorted(out_dir.rglob("results.json")):
        r = read_result(path)
        rows.append({"method": r.method, "scene": r.scene, "status": r.status, "steps": r.steps, "train_s": r.train_seconds,
                     "ms_per_step": 1e3 * r.train_seconds / r.steps if r.steps and r.train_seconds else None,
                     "psnr": r.metrics.get("psnr"), "gaussians": r.num_gaussians, "fps": r.render_fps,
                     "peak_mib": r.peak_memory_mb, "error": r.error,
                     "device": r.versions.get("device"), "backend": r.versions.get("backend")})
    return {**res, "rows": rows}


def run_smoke(ctx: Context) -> dict:
    """``python -m protocols.run +experiment=smoke device=cuda``: its return code and the cells' status."""
    why = no_gpu_reason(ctx)
    if why:
        return {"skipped": why}
    res, out_dir = _run_protocol(ctx, "smoke")
    statuses = [json.loads(p.read_text()).get("status") for p in sorted(out_dir.rglob("results.json"))]
    return {**res, "cells": len(statuses), "ok": statuses.count("ok")}


STAGES: dict[str, Callable[[Context], dict]] = {
    "env": run_env, "build": run_build, "pytest": run_pytest, "agreement": run_agreement, "timing": run_timing,
    "syncs": run_syncs, "fox": run_fox, "smoke": run_smoke, "pytest-train": run_pytest_train,
}
