"""The GPU check: one command that verifies the CUDA backend on a GPU machine and writes what it saw.

    python -m bench.gpu_check --out DIR                   # every stage, at most 8 minutes
    python -m bench.gpu_check --out DIR --stages env,build,syncs

Stages (bench/gpu_stages.py): ``env`` (device, driver, torch, CUDA, commit, gsplat), ``build`` (each
extension built and timed), ``pytest`` (``pytest -m gpu``), ``agreement`` (every renderer variant
against the CPU backend on ../shared/bench and the float64 reference: images, alpha, depth, n_contrib,
every gradient, finiteness), ``timing`` (bench/raster.py's CUDA rows for every mode and variant,
gsplat's ``rasterization`` beside them where importable, synchronised medians, peak memory),
``syncs`` (kernel launches and host waits of one forward and one backward), ``fox`` (3dgs and
softmax_gs trained 3000 steps at the full budget: ms per step, test PSNR, Gaussians) and ``smoke``
(``protocols.run +experiment=smoke device=cuda``).

Each stage runs in its own process with its own deadline (a hang or a broken CUDA context ends only
that stage) and writes ``DIR/stages/<stage>.json`` as it goes; after every stage the report
``DIR/<device>-<date>.md`` and ``.json`` is rewritten from what there is, so a stage cut short leaves
the others' results. gsplat (where importable) builds its CUDA code in a background process while
the first stages run. The bundle of tools/gpu_bundle.py (``.gpu/``: wheels the GPU machine lacks,
the benchmark scenes, fox) is used when present. docs/gpu/README.md has the one command and how to
read the report.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import signal
import subprocess
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
if str(Path(__file__).resolve().parent) not in sys.path:   # gpu_stages, gpu_report, raster
    sys.path.insert(0, str(Path(__file__).resolve().parent))
BUNDLE = ROOT / ".gpu"
GSPLAT_ENV = "SMGS_GPU_CHECK_GSPLAT"   # "built": the timing stage times gsplat beside smgs
ORDER = ("env", "build", "pytest", "agreement", "timing", "syncs", "fox", "smoke")
# seconds each stage may run (the whole check is also cut at --budget)
DEADLINES = {"env": 60, "build": 150, "pytest": 210, "agreement": 90, "timing": 150, "syncs": 60, "fox": 200,
             "smoke": 120}
GSPLAT_BUILD_S = 240


@dataclass
class StageRun:
    name: str
    status: str = "not run"      # ok | failed | timed out | skipped | not run
    seconds: float = 0.0
    note: str = ""
    result: dict | None = None


def setup_environment(shared: Path | None) -> Path | None:
    """The bundle's packages on PYTHONPATH (for this process and its children), no network for
    LPIPS, and the folder holding bench/ and data/fox; returns that folder."""
    site = BUNDLE / "site"
    paths = [str(ROOT)] + ([str(site)] if site.is_dir() else [])
    old = os.environ.get("PYTHONPATH", "")
    os.environ["PYTHONPATH"] = os.pathsep.join(paths + ([old] if old else []))
    for p in reversed(paths):
        if p not in sys.path:
            sys.path.insert(0, p)
    os.environ.setdefault("SMGS_LPIPS_AUTO", "0")
    if shared is None:
        for cand in (ROOT.parent / "shared", BUNDLE / "shared"):
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
    else:
        run.status = "ok"
    return run


def stage_main(args: argparse.Namespace) -> int:
    """Inside a stage's process: run it, saving partial results as it goes."""
    from gpu_stages import STAGES, Context

    out = Path(args.out)
    path = out / "stages" / f"{args.stage}.json"

    def save(result: dict, complete: bool = False) -> None:
        tmp = path.with_suffix(".tmp")
        tmp.write_text(json.dumps({"complete": complete, "result": result}, indent=1, default=str))
        tmp.replace(path)

    ctx = Context(out=out, device=args.device, tiny=args.tiny, shared=args.shared, save=save,
                  pytest_args=tuple(args.pytest_args or ()),
                  ends_at=time.monotonic() + (args.stage_deadline or DEADLINES[args.stage]))
    save(STAGES[args.stage](ctx), complete=True)
    return 0


def start_gsplat_build(out: Path, device: str) -> subprocess.Popen | None:
    """gsplat's just-in-time CUDA build in the background (about 70 s on 16 cores), into its own
    extension folder, while the first stages run."""
    if device != "cuda":
        return None
    probe = subprocess.run([sys.executable, "-c", "import gsplat"], capture_output=True)
    if probe.returncode != 0:
        return None
    env = {**os.environ, "MAX_JOBS": os.environ.get("MAX_JOBS", "12")}
    if "TORCH_CUDA_ARCH_LIST" not in env:   # this GPU's architecture only: the build takes ~70 s, not minutes
        import torch

        if torch.cuda.is_available():
            env["TORCH_CUDA_ARCH_LIST"] = "%d.%d" % torch.cuda.get_device_capability(0)
    code = ("import time, torch; t=time.perf_counter(); from gsplat.cuda._backend import _C; "
            "print('gsplat build', round(time.perf_counter()-t, 1), 's', _C is not None)")
    log = (out / "logs" / "gsplat_build.log").open("w")
    return subprocess.Popen([sys.executable, "-c", code], cwd=ROOT, env=env, stdout=log, stderr=subprocess.STDOUT)


def device_slug(env: dict | None) -> str:
    name = (env or {}).get("gpu") or "no-gpu"
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, required=True, help="folder for the stage results, logs and the report")
    ap.add_argument("--stages", default=",".join(ORDER), help=f"comma-separated, from {','.join(ORDER)}")
    ap.add_argument("--budget", type=float, default=480.0, help="seconds for the whole check (default 8 min)")
    ap.add_argument("--shared", type=Path, default=None, help="folder with bench/ and data/fox "
                    "(default ../shared, else the bundle's .gpu/shared)")
    ap.add_argument("--report-dir", type=Path, default=ROOT / "docs" / "gpu",
                    help="also write the report here (default docs/gpu of this checkout); '' for --out only")
    ap.add_argument("--device", default="cuda", choices=("cuda", "cpu"),
                    help="cpu: run the stages' code on the CPU (the check's own test)")
    ap.add_argument("--tiny", action="store_true", help="tiny scenes and runs (the check's own test)")
    ap.add_argument("--stage", help=argparse.SUPPRESS)
    ap.add_argument("--stage-deadline", type=float, help=argparse.SUPPRESS)
    ap.add_argument("--pytest-arg", dest="pytest_args", action="append", help="arguments for pytest -m gpu "
                    "instead of the whole tests folder (repeatable)")
    args = ap.parse_args(argv)
    args.out = args.out.resolve()
    args.shared = setup_environment(args.shared)
    if args.stage:
        return stage_main(args)
    return drive(args)


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
    for name in names:
        left = args.budget - (time.perf_counter() - start)
        if left < 5:
            runs[name].status, runs[name].note = "skipped", f"out of time (budget {args.budget:.0f} s)"
            continue
        if name == "timing":
            wait_for_gsplat(gsplat, min(90.0, left - DEADLINES["timing"] / 2))
            left = args.budget - (time.perf_counter() - start)   # the wait came out of the budget
        print(f"gpu_check: {name} (deadline {min(DEADLINES[name], left):.0f} s)", flush=True)
        runs[name] = run_stage(name, args, min(DEADLINES[name], left))
        print(f"gpu_check: {name} {runs[name].status} in {runs[name].seconds} s {runs[name].note}", flush=True)
        write_report(args, runs, date, device_slug((runs.get("env") or StageRun("env")).result), gsplat_status(gsplat))
    if gsplat is not None and gsplat.poll() is None:
        gsplat.kill()
    paths = write_report(args, runs, date, device_slug((runs.get("env") or StageRun("env")).result),
                         gsplat_status(gsplat))
    print("gpu_check: report " + ", ".join(str(p) for p in paths), flush=True)
    return 0 if all(r.status in ("ok", "skipped") for r in runs.values()) else 1


def wait_for_gsplat(proc: subprocess.Popen | None, seconds: float) -> None:
    """Give the background gsplat build up to ``seconds`` to finish before the timing stage; the
    stage times gsplat only if it did (else importing it would build it again under the stage's
    own deadline)."""
    if proc is not None and proc.poll() is None and seconds > 0:
        try:
            proc.wait(timeout=seconds)
        except subprocess.TimeoutExpired:
            pass
    os.environ[GSPLAT_ENV] = "built" if proc is not None and proc.poll() == 0 else "no"


def gsplat_status(proc: subprocess.Popen | None) -> str:
    if proc is None:
        return "not importable here (no gsplat rows)"
    rc = proc.poll()
    return "building" if rc is None else ("built" if rc == 0 else f"build failed (exit code {rc})")


if __name__ == "__main__":
    raise SystemExit(main())
