"""The GPU check: one command that verifies the CUDA backend on a GPU machine and writes what it saw.

    python -m bench.gpu_check --out DIR                   # every stage, at most 8 minutes
    python -m bench.gpu_check --out DIR --stages env,build,syncs

Stages (bench/gpu_stages.py), in this order: ``env`` (device, driver, torch, CUDA, commit, gsplat),
``build`` (every extension built at once, each timed), ``pytest`` (the renderer's ``pytest -m gpu``
tests), ``agreement`` (every renderer variant against the CPU backend on ../shared/bench and the
float64 reference: images, alpha, depth, n_contrib, every gradient, finiteness), ``timing``
(bench/raster.py's CUDA rows for every mode and variant, gsplat's ``rasterization`` beside them,
synchronised medians, peak memory), ``syncs`` (kernel launches and host waits of one forward and
one backward), ``fox`` (3dgs and softmax_gs trained 3000 steps at the full budget: ms per step,
test PSNR, Gaussians), ``smoke`` (``protocols.run +experiment=smoke device=cuda``) and
``pytest-train`` (the GPU tests that train or build another variant, marked ``slow``).

Each stage runs in its own process with its own deadline (a hang or a broken CUDA context ends only
that stage) and writes ``DIR/stages/<stage>.json`` as it goes. A stage is judged by its result
(bench/gpu_verdict.py): a non-zero exit, a failed or errored test, a failed cell or a missing figure
makes it "failed" with the reason, and the check exits non-zero unless every stage is "ok". After
every stage the report ``DIR/<device>-<date>.md`` and ``.json`` is rewritten from what there is, so a
stage cut short leaves the others' results; the copy in docs/gpu/ is written only where the check
ran on a GPU. The stages' deadlines add up to the budget (480 s); a stage may also use what the
ones before it left unused. gsplat (where importable) builds its CUDA code in a background process
(``MAX_JOBS`` of half the cores, so that ours builds beside it) while the first stages run. The
bundle of tools/gpu_bundle.py (``.gpu/``: wheels the GPU machine lacks, the benchmark scenes, fox)
is used when present. docs/gpu/README.md has the one command and how to read the report.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(Path(__file__).resolve().parent) not in sys.path:   # gpu_stages, gpu_report, raster
    sys.path.insert(0, str(Path(__file__).resolve().parent))
BUNDLE_ENV = "SMGS_GPU_BUNDLE"   # another bundle folder than .gpu/ (the check's own tests: an empty one)
GSPLAT_ENV = "SMGS_GPU_CHECK_GSPLAT"   # the gsplat build's state as the timing stage is started: "built", ...
ORDER = ("env", "build", "pytest", "agreement", "timing", "syncs", "fox", "smoke", "pytest-train")
BUDGET_S = 480
# Seconds each stage may run, adding up to the budget (tests/test_gpu_check.py holds them to it).
# Estimates for an H200 with 16 cores from the times seen there (../shared/GPU.md): the builds run
# side by side (13-15 s each alone); fox trains 3dgs and softmax_gs for 3000 steps (42 s and 69 s of
# training there); timing includes the wait for gsplat's build, if it is still running.
DEADLINES = {"env": 15, "build": 60, "pytest": 75, "agreement": 30, "timing": 55, "syncs": 20, "fox": 125,
             "smoke": 50, "pytest-train": 50}
GSPLAT_WAIT_S = 20   # at most, out of the timing stage's deadline
GPU_STAGES = set(ORDER) - {"env"}   # what is left out once env has found no GPU


@dataclass
class StageRun:
    name: str
    status: str = "not run"      # ok | failed | timed out | skipped | not run
    seconds: float = 0.0
    note: str = ""
    result: dict | None = None
    problems: list[str] = field(default_factory=list)


def setup_environment(shared: Path | None) -> Path | None:
    """The bundle's packages on PYTHONPATH (for this process and its children), no network for
    LPIPS, and the folder holding bench/ and data/fox; returns that folder."""
    bundle = Path(os.environ.get(BUNDLE_ENV) or ROOT / ".gpu")
    site = bundle / "site"
    paths = [str(ROOT)] + ([str(site)] if site.is_dir() else [])
    old = os.environ.get("PYTHONPATH", "")
    os.environ["PYTHONPATH"] = os.pathsep.join(paths + ([old] if old else []))
    for p in reversed(paths):
        if p not in sys.path:
            sys.path.insert(0, p)
    os.environ.setdefault("SMGS_LPIPS_AUTO", "0")
    if shared is None:
        for cand in (ROOT.parent / "shared", bundle / "shared"):
            if (cand / "bench").is_dir():
                return cand
    return shared


def stage_command(name: str, args: argparse.Namespace, timeout: float) -> list[str]:
    cmd = [sys.executable, "-m", "bench.gpu_check", "--stage", name, "--out", str(args.out), "--device", args.device,
           "--stage-deadline", f"{timeout:.0f}"]
    if args.tiny:
        cmd.append("--tiny")
    if args.shared:
        cmd += ["--shared", str(args.shared)]
    for a in args.pytest_args or ():
        cmd.append(f"--pytest-arg={a}")
    return cmd


def run_stage(name: str, args: argparse.Namespace, timeout: float) -> StageRun:
    """One stage in its own process, killed at ``timeout``; its result file, complete or partial."""
    out = Path(args.out)
    path = out / "stages" / f"{name}.json"
    path.unlink(missing_ok=True)
    log = (out / "logs" / f"{name}.log").open("w")
    t0 = time.perf_counter()
    # its own process group: at the deadline the stage goes with everything it started (pytest,
    # the training runs), so nothing of it keeps the GPU from the next stage
    proc = subprocess.Popen(stage_command(name, args, timeout), cwd=ROOT, stdout=log, stderr=subprocess.STDOUT,
                            start_new_session=True)
    try:
        rc, timed_out = proc.wait(timeout=timeout), False
    except subprocess.TimeoutExpired:
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
        rc, timed_out = None, True
    finally:
        log.close()
    run = StageRun(name, seconds=round(time.perf_counter() - t0, 1))
    saved = json.loads(path.read_text()) if path.exists() else None
    run.result = None if saved is None else saved.get("result")
    if timed_out:
        run.status, run.note = "timed out", f"deadline {timeout:.0f} s" + ("; partial result kept" if saved else "")
    elif rc != 0 or saved is None or not saved.get("complete"):
        tail = (out / "logs" / f"{name}.log").read_text()[-1500:]
        run.status, run.note = "failed", f"exit code {rc}: {tail.strip().splitlines()[-1] if tail.strip() else ''}"
    elif isinstance(run.result, dict) and "skipped" in run.result:
        run.status, run.note = "skipped", str(run.result["skipped"])
    elif saved.get("problems"):   # ran to its end, but its result shows a failure (gpu_verdict)
        run.problems = list(saved["problems"])
        run.status, run.note = "failed", "; ".join(run.problems)
    else:
        run.status = "ok"
    return run


def stage_main(args: argparse.Namespace) -> int:
    """Inside a stage's process: run it, saving partial results as it goes."""
    from gpu_stages import STAGES, Context
    from gpu_verdict import problems

    out = Path(args.out)
    path = out / "stages" / f"{args.stage}.json"

    def save(result: dict, complete: bool = False, found: list[str] | None = None) -> None:
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"complete": complete, "result": result, "problems": found or []}, indent=1,
                                  default=str))
        tmp.replace(path)

    ctx = Context(out=out, device=args.device, tiny=args.tiny, shared=args.shared, save=save,
                  pytest_args=tuple(args.pytest_args or ()),
                  ends_at=time.monotonic() + (args.stage_deadline or DEADLINES[args.stage]))
    result = STAGES[args.stage](ctx)
    save(result, complete=True, found=problems(args.stage, result, ctx))
    return 0


# The background build: torch first (the architecture of this GPU only: ~70 s instead of minutes),
# then gsplat, whose CUDA code builds on first use; exit 3 where gsplat is not importable.
GSPLAT_BUILD = """
import os, sys, time
t = time.perf_counter()
import torch
if "TORCH_CUDA_ARCH_LIST" not in os.environ and torch.cuda.is_available():
    os.environ["TORCH_CUDA_ARCH_LIST"] = "%d.%d" % torch.cuda.get_device_capability(0)
try:
    import gsplat
except Exception as e:
    print("gsplat is not importable:", type(e).__name__, e)
    sys.exit(3)
from gsplat.cuda._backend import _C
print("gsplat build", round(time.perf_counter() - t, 1), "s", _C is not None)
sys.exit(0 if _C is not None else 4)
"""
GSPLAT_NOT_IMPORTABLE = 3


def start_gsplat_build(out: Path, device: str) -> subprocess.Popen | None:
    """gsplat's just-in-time CUDA build in a background process (about 70 s on 16 cores), started
    at once (nothing here waits for it), with half the cores (``MAX_JOBS``) so that our own builds
    run beside it."""
    if device != "cuda":
        return None
    env = {**os.environ, "MAX_JOBS": os.environ.get("MAX_JOBS", str(max(1, (os.cpu_count() or 2) // 2)))}
    log = (out / "logs" / "gsplat_build.log").open("w")
    return subprocess.Popen([sys.executable, "-c", GSPLAT_BUILD], cwd=ROOT, env=env, stdout=log,
                            stderr=subprocess.STDOUT)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="folder for the stage results, logs and the report")
    ap.add_argument("--stages", default=",".join(ORDER), help=f"comma-separated, from {','.join(ORDER)}")
    ap.add_argument("--budget", type=float, default=float(BUDGET_S),
                    help=f"seconds for the whole check (default {BUDGET_S}: the stages' deadlines)")
    ap.add_argument("--shared", type=Path, default=None, help="folder with bench/ and data/fox "
                    "(default ../shared, else the bundle's .gpu/shared)")
    ap.add_argument("--report-dir", type=Path, default=ROOT / "docs" / "gpu",
                    help="also write the report here (default docs/gpu of this checkout); '' for --out only")
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"),
                    help="cpu: run the stages' code on the CPU (the check's own test)")
    ap.add_argument("--tiny", action="store_true", help="tiny scenes and runs (the check's own test)")
    ap.add_argument("--stage", help=argparse.SUPPRESS)
    ap.add_argument("--stage-deadline", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--pytest-arg", dest="pytest_args", action="append", help="test files (or other pytest "
                    "arguments) for the pytest stages instead of their own selection (repeatable)")
    args = ap.parse_args(argv)
    args.out = args.out.resolve()
    args.shared = setup_environment(args.shared)
    if args.stage:
        return stage_main(args)
    return drive(args)


def stage_timeout(name: str, later: list[str], left: float) -> float:
    """Seconds for stage ``name``: its own deadline, plus what the stages before it left unused
    beyond the deadlines of the ``later`` ones, within the ``left`` of the budget."""
    reserved = sum(DEADLINES[n] for n in later)
    return max(0.0, min(left, max(DEADLINES[name], left - reserved)))


def drive(args: argparse.Namespace) -> int:
    from gpu_report import write_report

    names = [s for s in args.stages.split(",") if s]
    unknown = set(names) - set(ORDER)
    if unknown:
        raise SystemExit(f"unknown stage(s) {sorted(unknown)}; choose from {', '.join(ORDER)}")
    for sub in ("stages", "logs"):
        (args.out / sub).mkdir(parents=True, exist_ok=True)
    start = time.perf_counter()
    date = dt.date.today().isoformat()
    gsplat = start_gsplat_build(args.out, args.device)
    runs = {n: StageRun(n) for n in names}
    no_gpu = None
    for i, name in enumerate(names):
        left = args.budget - (time.perf_counter() - start)
        if no_gpu and name in GPU_STAGES:
            runs[name].status, runs[name].note = "skipped", no_gpu
            continue
        if left < 5:
            runs[name].status, runs[name].note = "skipped", f"out of time (budget {args.budget:.0f} s)"
            continue
        timeout = stage_timeout(name, names[i + 1:], left)
        if name == "timing":   # the wait for gsplat comes out of the stage's own time
            timeout -= wait_for_gsplat(gsplat, min(GSPLAT_WAIT_S, timeout / 3))
        print(f"gpu_check: {name} (deadline {timeout:.0f} s)", flush=True)
        runs[name] = run_stage(name, args, timeout)
        print(f"gpu_check: {name} {runs[name].status} in {runs[name].seconds} s {runs[name].note}", flush=True)
        if name == "env" and args.device == "cuda" and not (runs[name].result or {}).get("gpu"):
            no_gpu = "no GPU (the env stage says why)"
        write_report(args, runs, date, gsplat_status(gsplat))
    if gsplat is not None and gsplat.poll() is None:
        gsplat.kill()
    paths = write_report(args, runs, date, gsplat_status(gsplat))
    print("gpu_check: report " + ", ".join(str(p) for p in paths), flush=True)
    bad = [r for r in runs.values() if r.status != "ok"]
    for r in bad:
        print(f"gpu_check: {r.name} {r.status}: {r.note}", flush=True)
    print(f"gpu_check: {'FAILED' if bad else 'passed'}: {len(runs) - len(bad)} of {len(runs)} stages ok", flush=True)
    return 1 if bad else 0


def wait_for_gsplat(proc: subprocess.Popen | None, seconds: float) -> float:
    """Give the background gsplat build up to ``seconds`` to finish before the timing stage, which
    times gsplat only if it did (else importing it would build it again under the stage's own
    deadline); tells the stage the build's state (``GSPLAT_ENV``); returns the seconds waited."""
    t0 = time.perf_counter()
    if proc is not None and proc.poll() is None and seconds > 0:
        try:
            proc.wait(timeout=seconds)
        except subprocess.TimeoutExpired:
            pass
    os.environ[GSPLAT_ENV] = gsplat_status(proc)
    return time.perf_counter() - t0


def gsplat_status(proc: subprocess.Popen | None) -> str:
    if proc is None:
        return "not started (the check runs on the CPU)"
    rc = proc.poll()
    if rc == GSPLAT_NOT_IMPORTABLE:
        return "not importable (not installed, nor in the bundle: docs/gpu/README.md)"
    return {None: "still building", 0: "built"}.get(rc, f"build failed (exit code {rc}; logs/gsplat_build.log)")


if __name__ == "__main__":
    raise SystemExit(main())
