"""The GPU check's report (bench/gpu_check.py): ``<device>-<date>.md`` and ``.json`` from the stages'
results as they stand, written whole each time (a stage cut short shows as such, the others' figures
stay). Every figure the stages measured is in the JSON; the markdown has the tables."""

from __future__ import annotations

import json
import re
from pathlib import Path


def _atomic(path: Path, text: str) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    tmp.write_text(text)
    tmp.replace(path)


def _f(x, nd: int = 2) -> str:
    if x is None:
        return "—"
    if isinstance(x, float):
        return f"{x:.{nd}f}" if abs(x) >= 10 ** -nd or x == 0 else f"{x:.1e}"
    return str(x)


def _table(header: list[str], rows: list[list]) -> list[str]:
    out = ["| " + " | ".join(header) + " |", "|" + "|".join("---" for _ in header) + "|"]
    out += ["| " + " | ".join(_f(c) for c in r) + " |" for r in rows]
    return out + [""]


def _env_lines(env: dict | None) -> list[str]:
    if not env:
        return ["(the env stage did not finish)", ""]
    keys = [("GPU", "gpu"), ("why no GPU", "why_no_gpu"), ("compute capability", "capability"), ("GPU memory MiB", "gpu_mib"), ("driver", "driver"),
            ("torch", "torch"), ("CUDA (torch)", "cuda"), ("nvcc", "nvcc"), ("python", "python"),
            ("commit", "commit"), ("CPU", "cpu"), ("CPU cores", "cpu_count"), ("gsplat", "gsplat"),
            ("bundle on PYTHONPATH", "bundle"), ("imports missing", "imports_missing")]
    return [f"- {label}: {_f(env.get(k))}" for label, k in keys] + [""]


def _section(title: str, run, body) -> list[str]:
    lines = [f"## {title}", ""]
    if run is None:
        return lines + ["Not asked for.", ""]
    if run.status != "ok":
        lines += [f"**{run.status}** ({run.seconds} s) {'' if run.problems else run.note}".rstrip(), ""]
        lines += [f"- {p}" for p in run.problems] + ([""] if run.problems else [])
    if run.result and "skipped" not in run.result:
        lines += body(run.result)
    return lines


def _build(r: dict) -> list[str]:
    return _table(["extension", "seconds", "note"],
                  [[k, v.get("seconds"), v.get("error") or v.get("skipped") or ""] for k, v in r.items()])


def _pytest(r: dict) -> list[str]:
    lines = [f"- `-m \"{r.get('selection', 'gpu')}\"`, exit code {r.get('rc')}, {r.get('seconds')} s: {r.get('tests')} tests, {r.get('failures')} failed, "
             f"{r.get('errors')} errors, {r.get('skipped_tests')} skipped",
             f"- from the log: {r.get('passed_so_far')} passed, {r.get('failed_so_far')} failed or errors "
             "(the counts so far where the stage was cut)", f"- last line: `{r.get('summary', '')[-200:]}`"]
    lines += [f"- failed: `{t}`" for t in r.get("failed", [])]
    return lines + [""]


def _agreement(r: dict) -> list[str]:
    rows = [[x["scene"], x["mode"], x["variant"], x.get("rgb"), x.get("alpha"), x.get("depth"),
             x.get("n_contrib_differ"), x.get("grad_rel"), x.get("grad_worst"), x.get("finite"),
             x.get("error", "")] for x in r.get("rows", [])]
    return ["Largest |Δ| of images, alpha, depth against the CPU backend (benchmark scenes) or the float64 "
            "reference (small scene); pixels whose n_contrib differs; the largest gradient difference over the "
            "3D inputs relative to that input's largest gradient, and which input.", ""] + _table(
        ["scene", "mode", "variant", "rgb", "alpha", "depth", "n_contrib ≠", "grad rel", "worst input", "finite",
         "error"], rows)


def _timing(r: dict) -> list[str]:
    rows = r.get("rows", [])
    base = {(x["scene"], x["mode"]): x for x in rows if x["variant"] == "default"}
    gs = {x["scene"]: x for x in rows if x["variant"].startswith("gsplat")}
    table = []
    for x in rows:
        g = gs.get(x["scene"]) if x["mode"] == "3dgs" and not x["variant"].startswith("gsplat") else None
        d = base.get((x["scene"], x["mode"]))
        table.append([x["scene"], x["variant"], x["mode"], x["fwd_ms"], x["fb_ms"], x["peak_mib"],
                      None if not d else x["fb_ms"] / d["fb_ms"],
                      None if not g else f"{x['fwd_ms'] / g['fwd_ms']:.2f} / {x['fb_ms'] / g['fb_ms']:.2f}"])
    lines = ["ms forward / forward+backward from 3D parameters (loss = image mean), synchronised medians, "
             "every row of a scene interleaved round by round; peak MiB of one forward+backward.", ""]
    lines += _table(["scene", "variant", "mode", "fwd ms", "f+b ms", "peak MiB", "f+b × default",
                     "× gsplat (fwd / f+b)"], table)
    for scene, v in (r.get("vs_gsplat") or {}).items():
        if v:
            lines.append(f"- {scene}: smgs 3dgs against gsplat's image: {v['psnr_db']:.1f} dB PSNR, "
                         f"max |Δ| {v['max_abs']:.3g}")
    return lines + [f"- gsplat: {r.get('gsplat') or 'not importable'}", ""]


def _syncs(r: dict) -> list[str]:
    rows = []
    for x in r.get("rows", []):
        f, b = x["forward"], x["backward"]
        rows.append([x["variant"], x["mode"], f["launches"], f.get("kernels"), f["syncs"], f["sync_warnings"],
                     b["launches"], b.get("kernels"), b["syncs"], b["sync_warnings"]])
    return ["One forward and one backward at 10k_256 (after a warm-up call): kernel launches and synchronising "
            "CUDA runtime calls seen by torch.profiler, and the warnings of torch.cuda.set_sync_debug_mode('warn').",
            ""] + _table(["variant", "mode", "fwd launches", "fwd kernels", "fwd syncs", "fwd sync warnings",
                          "bwd launches", "bwd kernels", "bwd syncs", "bwd sync warnings"], rows)


def _fox(r: dict) -> list[str]:
    rows = [[x["method"], x.get("scene"), x["status"], x["steps"], x["train_s"], x["ms_per_step"], x["psnr"],
             x["gaussians"], x.get("fps"), x.get("peak_mib"), x.get("backend")] for x in r.get("rows", [])]
    return [f"- runner exit code {r.get('rc')}, {r.get('seconds')} s", ""] + _table(
        ["method", "scene", "status", "steps", "train s", "ms / step", "test PSNR", "Gaussians", "render FPS",
         "peak MiB", "backend"], rows) + (
        [f"```\n{r['tail']}\n```", ""] if r.get("tail") else [])


def _smoke(r: dict) -> list[str]:
    return [f"- exit code {r.get('rc')}, {r.get('seconds')} s, {r.get('ok')} of {r.get('cells')} cells ok", ""] + (
        [f"```\n{r['tail']}\n```", ""] if r.get("tail") else [])


SECTIONS = [("Build", "build", _build), ("pytest -m gpu: the renderer's tests", "pytest", _pytest),
            ("Agreement (CUDA against the CPU backend and the reference)", "agreement", _agreement),
            ("Timing (and gsplat beside it)", "timing", _timing), ("Kernel launches and host waits", "syncs", _syncs),
            ("Training fox (transforms.json, full budget, 3000 steps, cpu preset)", "fox", _fox),
            ("Smoke experiment", "smoke", _smoke),
            ("pytest -m 'gpu and slow': training and variant builds", "pytest-train", _pytest)]


def render_markdown(runs: dict, date: str, gsplat: str, command: str) -> str:
    env_run = runs.get("env")
    env = env_run.result if env_run else None
    lines = [f"# GPU check: {(env or {}).get('gpu') or 'no GPU'}, {date}", "",
             f"Written by `{command}` (bench/gpu_check.py; docs/gpu/README.md says how to read it).", ""]
    lines += _env_lines(env)
    lines += [f"**Verdict: {verdict(runs)}.** A stage is ok only where its process ended in time and its result "
              "shows no failed test, failed cell or missing figure (bench/gpu_verdict.py).", ""]
    lines += ["## Stages", ""] + _table(["stage", "status", "seconds", "note"],
                                          [[r.name, r.status, r.seconds, r.note[:300]] for r in runs.values()])
    lines += [f"gsplat build: {gsplat}", ""]
    for title, key, body in SECTIONS:
        lines += _section(title, runs.get(key), body)
    return "\n".join(lines)


def device_slug(env: dict | None) -> str:
    name = (env or {}).get("gpu") or "no-gpu"
    return re.sub(r"[^a-z0-9]+", "-", name.lower()).strip("-")


def write_report(args, runs: dict, date: str, gsplat: str) -> list[Path]:
    """Write ``<gpu>-<date>.md`` and ``.json`` into ``args.out``, and into ``args.report_dir`` (the
    checkout's record, docs/gpu/) only where the env stage found a GPU: a run without one leaves
    nothing there."""
    env = getattr(runs.get("env"), "result", None)   # None: env not run
    command = "python -m bench.gpu_check --out " + str(args.out.name)
    md = render_markdown(runs, date, gsplat, command)
    data = {"date": date, "gsplat_build": gsplat, "budget_s": args.budget, "verdict": verdict(runs),
            "stages": {n: {"status": r.status, "seconds": r.seconds, "note": r.note, "problems": r.problems,
                           "result": r.result} for n, r in runs.items()}}
    paths = []
    on_gpu = bool((env or {}).get("gpu"))
    dirs = [args.out] + ([Path(args.report_dir)] if on_gpu and str(args.report_dir or "") not in ("", ".") else [])
    for d in dirs:
        for suffix, text in ((".md", md), (".json", json.dumps(data, indent=1, default=str))):
            p = Path(d) / f"{device_slug(env)}-{date}{suffix}"
            _atomic(p, text + "\n")
            paths.append(p)
    return paths


def verdict(runs: dict) -> str:
    """"passed" where every stage is ok, else "failed" with the stages that are not."""
    bad = [f"{r.name} {r.status}" for r in runs.values() if r.status != "ok"]
    return "passed" if not bad else "failed: " + ", ".join(bad)
