"""What makes a stage of the GPU check (bench/gpu_check.py) fail although its process ended well:
each stage's result is read for a failed or errored test, a failed cell, an error, a value that is not
finite, a gross disagreement or a missing figure. ``problems(stage, result, ctx)`` lists them (empty:
the stage is ok); the check then calls the stage "failed" with them as the reason and exits non-zero.

The agreement bounds are for gross errors only (a wrong kernel, not rounding): the exact tolerances
are the tests' (tests/test_raster_cuda.py), which the pytest stages run.
"""

from __future__ import annotations

import math
from typing import Callable

# Gross-disagreement bounds of the agreement stage: images and alpha (absolute), depth (absolute),
# gradients (relative to the input's largest); 20x the float32-vs-float64 tolerances of
# tests/test_raster_cuda.py (2e-5, 2e-4), so rounding never trips them.
AGREE_OUT, AGREE_DEPTH, AGREE_GRAD = 4e-4, 4e-3, 4e-3
# pixels whose n_contrib may differ from the CPU backend's (a reach test on a threshold), as a share
N_CONTRIB_SHARE = 0.01


def _pytest(r: dict, ctx) -> list[str]:
    out = []
    if "tests" not in r:
        return [f"pytest ended without its junit report (exit code {r.get('rc')}): {r.get('summary', '')[-200:]}"]
    bad = r["failures"] + r["errors"]
    if bad:
        out.append(f"{r['failures']} failed, {r['errors']} errors of {r['tests']} tests: "
                   + ", ".join(r.get("failed", [])[:4]) + (" ..." if bad > 4 else ""))
    elif r.get("rc") != 0:
        out.append(f"pytest exit code {r.get('rc')}: {r.get('summary', '')[-200:]}")
    if r["tests"] - r["skipped_tests"] - bad <= 0:
        out.append(f"no test passed ({r['tests']} collected, {r['skipped_tests']} skipped)")
    return out


def _errors(rows: list[dict], what: str) -> list[str]:
    bad = [r for r in rows if r.get("error")]
    if not bad:
        return []
    first = bad[0]
    where = "/".join(str(first.get(k)) for k in ("scene", "variant", "mode") if first.get(k) is not None)
    return [f"{len(bad)} {what} raised: {where}: {first['error'][:200]}"]


def _missing(rows: list[dict], want: set[tuple], keys: tuple[str, ...], what: str) -> list[str]:
    have = {tuple(r.get(k) for k in keys) for r in rows if not r.get("error")}
    gone = sorted(want - have, key=str)
    return [f"{len(gone)} {what} missing, e.g. {'/'.join(map(str, gone[0]))}"] if gone else []


def _expected(ctx) -> tuple[list[str], tuple[str, ...]]:
    from gpu_stages import variants
    from smgs.raster.types import MODES

    return [v.name for v in variants(ctx)], MODES


def _agreement(r: dict, ctx) -> list[str]:
    from gpu_stages import AGREEMENT_SCENES, SMALL_SCENE

    rows = r.get("rows", [])
    names, modes = _expected(ctx)
    out = _errors(rows, "renders") + _missing(
        rows, {(s, v, m) for s in (*AGREEMENT_SCENES, SMALL_SCENE) for v in names for m in modes},
        ("scene", "variant", "mode"), "comparisons")
    for x in rows:
        if x.get("error"):
            continue
        tag = f"{x['scene']}/{x['variant']}/{x['mode']}"
        if not x.get("finite"):
            out.append(f"{tag}: not finite")
        worse = [f"{k} {x[k]:.3g} > {lim:g}" for k, lim in (("rgb", AGREE_OUT), ("alpha", AGREE_OUT),
                                                          ("depth", AGREE_DEPTH), ("grad_rel", AGREE_GRAD))
                 if not x[k] <= lim]   # NaN fails too
        if worse:
            out.append(f"{tag}: " + ", ".join(worse) + (f" ({x.get('grad_worst')})" if "grad" in worse[-1] else ""))
        if x.get("pixels") and x["n_contrib_differ"] > N_CONTRIB_SHARE * x["pixels"]:
            out.append(f"{tag}: n_contrib differs at {x['n_contrib_differ']} of {x['pixels']} pixels")
    return out


def _timing(r: dict, ctx) -> list[str]:
    from gpu_stages import TIMING_SCENES

    rows = r.get("rows", [])
    names, modes = _expected(ctx)
    out = _errors(rows, "scenes") + _missing(rows, {(s, v, m) for s in TIMING_SCENES for v in names for m in modes},
                                             ("scene", "variant", "mode"), "rows")
    for x in rows:
        if not x.get("error") and not all(isinstance(x.get(k), (int, float)) and math.isfinite(x[k]) and x[k] > 0
                                          for k in ("fwd_ms", "fb_ms")):
            out.append(f"{x['scene']}/{x['variant']}/{x['mode']}: no time measured")
    if ctx.device == "cuda":
        timed = {x["scene"] for x in rows if x["variant"].startswith("gsplat") and not x.get("error")}
        if timed != set(TIMING_SCENES):
            out.append(f"gsplat not timed on {', '.join(s for s in TIMING_SCENES if s not in timed)}: "
                       f"its build {r.get('gsplat_build') or 'unknown'}")
    return out


def _syncs(r: dict, ctx) -> list[str]:
    names, _ = _expected(ctx)
    rows = r.get("rows", [])
    return _errors(rows, "counts") + _missing(rows, {(v, m) for v in names for m in ("3dgs", "softmax_gs")},
                                              ("variant", "mode"), "counts")


def _runner(r: dict, what: str) -> list[str]:
    return [] if r.get("rc") == 0 else [f"{what} exit code {r.get('rc')}"]


def _fox(r: dict, ctx) -> list[str]:
    from gpu_stages import FOX_METHODS

    out = _runner(r, "protocols.run")
    rows = {x["method"]: x for x in r.get("rows", [])}
    for m in FOX_METHODS:
        x = rows.get(m)
        if x is None:
            out.append(f"{m}: no result")
        elif x.get("status") != "ok":
            out.append(f"{m}: {x.get('status')}: {str(x.get('error') or '')[:200]}")
        elif x.get("psnr") is None or x.get("ms_per_step") is None:
            out.append(f"{m}: no test PSNR or time per step")
    return out


def _smoke(r: dict, ctx) -> list[str]:
    out = _runner(r, "protocols.run")
    if not r.get("cells"):
        out.append("no cell wrote a result")
    elif r.get("ok") != r["cells"]:
        out.append(f"{r['cells'] - (r.get('ok') or 0)} of {r['cells']} cells not ok")
    return out


def _env(r: dict, ctx) -> list[str]:
    out = []
    if ctx.device == "cuda" and not r.get("gpu"):
        out.append(f"no GPU: {r.get('why_no_gpu') or 'no CUDA device'}")
    if r.get("imports_missing"):
        out.append("imports missing: " + "; ".join(r["imports_missing"]))
    return out


def _build(r: dict, ctx) -> list[str]:
    out = [f"{what}: {v['error'][:300]}" for what, v in r.items() if v.get("error")]
    if ctx.device == "cuda":
        out += [f"{what}: not built ({v['skipped']})" for what, v in r.items() if v.get("skipped")]
    return out


JUDGES: dict[str, Callable[[dict, object], list[str]]] = {
    "env": _env, "build": _build, "pytest": _pytest, "agreement": _agreement, "timing": _timing, "syncs": _syncs,
    "fox": _fox, "smoke": _smoke, "pytest-train": _pytest,
}


def problems(stage: str, result: dict, ctx) -> list[str]:
    """Why the finished ``stage``'s ``result`` is a failure (empty: it is not). ``ctx`` is the stage's
    ``gpu_stages.Context`` (its device decides what is expected). A skipped stage has none: the
    check reports it as skipped."""
    if not isinstance(result, dict) or "skipped" in result:
        return []
    return JUDGES[stage](result, ctx)
