"""The GPU check (bench/gpu_check.py) without a GPU: its stages' code run on the CPU (``--device cpu
--tiny``: the cpu backend stands in for the CUDA variants, tiny scenes), the report written from
what the stages saved, a stage past its deadline or crashing recorded as such while the others'
results stay, a stage whose result shows a failure (a failed test, a failed cell, a missing figure)
failing the check, the GPU stages saying why they skip where there is no GPU (the check then fails
and leaves docs/gpu alone), the plan's deadlines against its budget, and the bundle's size check.
"""

from __future__ import annotations

import ast
import json
import re
import sys
from pathlib import Path
from types import SimpleNamespace

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tools"))

import gpu_check  # noqa: E402
import gpu_stages  # noqa: E402
import gpu_verdict  # noqa: E402

# the file the pytest stages run in place of the GPU tests: one renderer test (gpu) and one late test
# (gpu, slow), each a small real check of the package the stage imports, so a broken install or
# environment in the stage's process fails it
GPU_TESTS = """
import pytest

@pytest.mark.gpu
def test_renders():
    from smgs import MODES
    assert {"3dgs", "softmax_gs"} <= set(MODES)

@pytest.mark.gpu
@pytest.mark.slow
def test_trains():
    from smgs.train.strategies.registry import list_strategies
    assert "default" in list_strategies()
"""


@pytest.fixture(autouse=True)
def _no_bundle_here(tmp_path_factory, monkeypatch):
    """The check puts the bundle of tools/gpu_bundle.py (wheels for the GPU machine's Python) on
    PYTHONPATH and sys.path; where a checkout has one, this session and the tests after it must not
    import from it."""
    monkeypatch.setenv(gpu_check.BUNDLE_ENV, str(tmp_path_factory.mktemp("no_bundle")))
    monkeypatch.setattr(sys, "path", list(sys.path))
    import os

    monkeypatch.setenv("PYTHONPATH", os.environ.get("PYTHONPATH", ""))


def _report(out: Path) -> tuple[str, dict]:
    md = next(out.glob("*.md")).read_text()
    return md, json.loads(next(out.glob("*.json")).read_text())


def test_the_check_runs_its_stages_on_the_cpu_and_reports_them(tmp_path):
    rc = gpu_check.main(["--out", str(tmp_path), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--stages", "env,agreement"])
    assert rc == 0
    md, data = _report(tmp_path)
    assert data["stages"]["env"]["status"] == "ok" and data["stages"]["agreement"]["status"] == "ok"
    assert data["stages"]["env"]["result"]["torch"] == torch.__version__
    rows = data["stages"]["agreement"]["result"]["rows"]
    assert {r["mode"] for r in rows} == {"3dgs", "gef_only", "softmax_only", "softmax_gs"}
    ref = [r for r in rows if r["scene"].startswith("small")]
    assert ref and all(r["finite"] and r["rgb"] < 1e-5 and r["grad_rel"] < 1e-4 for r in ref), ref
    assert "| env | ok |" in md and "## Agreement" in md and "small (vs reference, float64)" in md


@pytest.mark.slow
def test_every_stage_runs_on_the_cpu(tmp_path):
    """Timing, launch counting, pytest, the fox runner (a tiny procedural run in its place) and the
    smoke experiment, through the same code as on a GPU."""
    tests = tmp_path / "gpu_tests" / "test_stand_in.py"
    tests.parent.mkdir()
    tests.write_text(GPU_TESTS)
    rc = gpu_check.main(["--out", str(tmp_path / "out"), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--pytest-arg", str(tests)])
    md, data = _report(tmp_path / "out")
    st = data["stages"]
    assert rc == 0, {k: (v["status"], v["note"]) for k, v in st.items()}
    assert len(st["timing"]["result"]["rows"]) == 3 * 4
    assert {r["mode"] for r in st["syncs"]["result"]["rows"]} == {"3dgs", "softmax_gs"}
    assert st["pytest"]["result"]["tests"] == 1 and st["pytest-train"]["result"]["tests"] == 1
    assert {r["method"] for r in st["fox"]["result"]["rows"]} == {"3dgs", "softmax_gs"}
    assert st["smoke"]["result"]["rc"] == 0 and st["smoke"]["result"]["ok"] >= 1


def test_a_stage_past_its_deadline_or_crashing_leaves_the_others(tmp_path, monkeypatch):
    """build saves a partial result and hangs (killed at its deadline, the partial result kept);
    pytest crashes; env and agreement run for real before and after them."""
    real = gpu_check.stage_command
    hang = ("import json, sys, time, pathlib; p = pathlib.Path(sys.argv[1]) / 'stages' / 'build.json'; "
            "p.write_text(json.dumps({'complete': False, 'result': {'default CUDA renderer': {'seconds': 1.5}}})); "
            "time.sleep(60)")

    def command(name, args, timeout):
        if name == "build":
            return [sys.executable, "-c", hang, str(args.out)]
        if name == "pytest":
            return [sys.executable, "-c", "import sys; print('boom'); sys.exit(3)"]
        return real(name, args, timeout)

    monkeypatch.setattr(gpu_check, "stage_command", command)
    deadlines = {"env": 20, "build": 3, "pytest": 20, "agreement": 60}
    for k, v in deadlines.items():
        monkeypatch.setitem(gpu_check.DEADLINES, k, v)
    rc = gpu_check.main(["--out", str(tmp_path), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--stages", ",".join(deadlines), "--budget", str(sum(deadlines.values()))])
    assert rc == 1
    md, data = _report(tmp_path)
    st = data["stages"]
    assert st["build"]["status"] == "timed out" and "partial result kept" in st["build"]["note"]
    assert st["build"]["result"] == {"default CUDA renderer": {"seconds": 1.5}}
    assert st["build"]["seconds"] < 30
    assert st["pytest"]["status"] == "failed" and "exit code 3" in st["pytest"]["note"] and "boom" in st["pytest"]["note"]
    assert st["env"]["status"] == "ok" and st["agreement"]["status"] == "ok"
    assert "| build | timed out |" in md and "| pytest | failed |" in md


def test_a_failed_test_fails_its_stage_and_the_check(tmp_path):
    """pytest ends (exit code 1) with one test failed: the stage is "failed", naming the test, and the
    check exits non-zero (it used to say "ok" for any pytest that ended)."""
    tests = tmp_path / "gpu_tests" / "test_on_purpose.py"
    tests.parent.mkdir()
    tests.write_text(GPU_TESTS + "\n\n@pytest.mark.gpu\ndef test_fails_on_purpose():\n    assert 1 == 2\n")
    rc = gpu_check.main(["--out", str(tmp_path / "out"), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--stages", "pytest", "--pytest-arg", str(tests)])
    md, data = _report(tmp_path / "out")
    st = data["stages"]["pytest"]
    assert rc == 1 and st["status"] == "failed", st
    assert st["result"]["tests"] == 2 and st["result"]["failures"] == 1     # the slow one is not selected
    assert "1 failed, 0 errors of 2 tests" in st["note"] and "test_fails_on_purpose" in st["note"]
    assert "Verdict: failed: pytest failed" in md


def _ctx(device="cuda"):
    return SimpleNamespace(device=device, tiny=True)


def test_a_finished_stage_is_judged_by_its_result():
    """What each stage's result must show; every case here ended with exit code 0 before."""
    p = gpu_verdict.problems
    assert p("smoke", {"rc": 0, "cells": 8, "ok": 8}, _ctx()) == []
    assert p("smoke", {"rc": 0, "cells": 8, "ok": 7}, _ctx()) == ["1 of 8 cells not ok"]
    assert p("smoke", {"rc": 1, "cells": 0, "ok": 0}, _ctx()) == ["protocols.run exit code 1",
                                                                  "no cell wrote a result"]
    fox = {"rc": 0, "rows": [{"method": "3dgs", "status": "ok", "psnr": 20.8, "ms_per_step": 14.0},
                             {"method": "softmax_gs", "status": "failed", "error": "collapsed"}]}
    assert p("fox", fox, _ctx()) == ["softmax_gs: failed: collapsed"]
    assert p("fox", {"rc": 0, "rows": fox["rows"][:1]}, _ctx()) == ["softmax_gs: no result"]
    junit = {"rc": 0, "tests": 3, "failures": 0, "errors": 0, "skipped_tests": 3, "failed": []}
    assert p("pytest", junit, _ctx()) == ["no test passed (3 collected, 3 skipped)"]
    assert p("pytest-train", {"rc": "cut at the stage's deadline", "summary": "x"}, _ctx())[0].startswith(
        "pytest ended without its junit report")
    built = {"default CUDA renderer": {"seconds": 14.0}, "v2 compositing": {"error": "exit code 1: nvcc: boom"},
             "fused projection": {"skipped": "no CUDA device"}}
    assert p("build", built, _ctx()) == ["v2 compositing: exit code 1: nvcc: boom",
                                         "fused projection: not built (no CUDA device)"]
    assert p("build", built, _ctx("cpu")) == ["v2 compositing: exit code 1: nvcc: boom"]
    assert p("env", {"gpu": None, "why_no_gpu": "no CUDA device (x)"}, _ctx()) == ["no GPU: no CUDA device (x)"]
    assert p("timing", {"skipped": "no CUDA device"}, _ctx()) == []   # reported as skipped, not ok


def _rows(variants, modes, **fields):
    return [{"variant": v, "mode": m, **fields} for v in variants for m in modes]


def test_agreement_timing_and_counts_fail_on_a_bad_or_missing_figure():
    from smgs.raster.types import MODES

    names = [v.name for v in gpu_stages.VARIANTS]
    good = dict(rgb=1e-6, alpha=1e-6, depth=1e-5, grad_rel=1e-5, grad_worst="means3d", finite=True,
                n_contrib_differ=2, pixels=65536)
    rows = [{"scene": s, **r} for s in (*gpu_stages.AGREEMENT_SCENES, gpu_stages.SMALL_SCENE)
            for r in _rows(names, MODES, **good)]
    assert gpu_verdict.problems("agreement", {"rows": rows}, _ctx()) == []
    rows[0] = {**rows[0], "finite": False, "rgb": float("nan")}
    rows[1] = {**rows[1], "n_contrib_differ": 5000}
    del rows[-1]
    found = gpu_verdict.problems("agreement", {"rows": rows}, _ctx())
    assert found[0].startswith("1 comparisons missing, e.g. small (vs reference, float64)/v2 kernels + lean glue/")
    assert any("not finite" in f for f in found) and any("rgb nan > 0.0004" in f for f in found)
    assert any("n_contrib differs at 5000 of 65536 pixels" in f for f in found)

    timed = [{"scene": s, **r} for s in gpu_stages.TIMING_SCENES for r in _rows(names, MODES, fwd_ms=2.0, fb_ms=4.0)]
    gs = [{"scene": s, "variant": "gsplat 1.5.3 rasterization", "mode": "3dgs", "fwd_ms": 0.5, "fb_ms": 1.4}
          for s in gpu_stages.TIMING_SCENES]
    assert gpu_verdict.problems("timing", {"rows": timed + gs}, _ctx()) == []
    assert gpu_verdict.problems("timing", {"rows": timed, "gsplat_build": "still building"}, _ctx()) == [
        "gsplat not timed on 10k_256, 100k_512, rand_1m_1600x1000: its build still building"]
    timed[3] = {**timed[3], "fb_ms": float("nan")}
    assert gpu_verdict.problems("timing", {"rows": timed + gs}, _ctx()) == ["10k_256/default/softmax_gs: no time measured"]

    counts = _rows(names, ("3dgs", "softmax_gs"), forward={}, backward={})
    assert gpu_verdict.problems("syncs", {"rows": counts}, _ctx()) == []
    assert gpu_verdict.problems("syncs", {"rows": counts[1:]}, _ctx()) == ["1 counts missing, e.g. default/3dgs"]


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")
def test_without_a_gpu_the_check_fails_saying_why_and_leaves_docs_gpu_alone(tmp_path):
    docs = tmp_path / "docs_gpu"
    rc = gpu_check.main(["--out", str(tmp_path / "out"), "--report-dir", str(docs)])
    md, data = _report(tmp_path / "out")
    st = data["stages"]
    assert rc == 1 and st["env"]["status"] == "failed" and "no GPU: no CUDA device" in st["env"]["note"]
    assert all(v["status"] == "skipped" for k, v in st.items() if k != "env")
    assert not docs.exists()


def test_the_plan_fits_its_budget():
    """The stages' deadlines add up to the default budget (8 minutes on the GPU machine), the wait
    for gsplat comes out of the timing stage's own, and a stage that takes every second it is given
    (its own deadline plus what the ones before it left) never takes a later stage's share."""
    assert list(gpu_check.DEADLINES) == list(gpu_check.ORDER)
    assert sum(gpu_check.DEADLINES.values()) == gpu_check.BUDGET_S == 480
    assert gpu_check.GSPLAT_WAIT_S < gpu_check.DEADLINES["timing"] / 2
    order = gpu_check.ORDER
    assert order.index("pytest") < order.index("agreement") and order.index("fox") < order.index("smoke")
    assert order.index("fox") < order.index("pytest-train")
    for used in (1.0, 0.5, 0.0):        # each stage takes this share of its deadline, then all of its time
        left = float(gpu_check.BUDGET_S)
        for i, name in enumerate(order):
            given = gpu_check.stage_timeout(name, list(order[i + 1:]), left)
            assert given >= gpu_check.DEADLINES[name] - 1e-9, (name, given)
            left -= given if i == len(order) - 1 else used * gpu_check.DEADLINES[name]
        assert left >= -1e-9


def test_the_renderer_gpu_tests_neither_train_nor_build_a_variant():
    """The pytest stage runs ``-m "gpu and not slow"``: no test it selects may train a model or ask
    for a non-default t_min (a build of its own); those are marked slow and run after fox."""
    assert gpu_stages.PYTEST_SELECTION == {"pytest": "gpu and not slow", "pytest-train": "gpu and slow"}
    bad = re.compile(r"t_min\s*=\s*[0-9.]|run_experiment\(|create_method\(|train_save_load\(|bench_main\(|Trainer\(")
    seen = 0
    for rel in gpu_stages.gpu_test_files():
        src = (ROOT / rel).read_text()
        tree = ast.parse(src)
        marks = " ".join(ast.get_source_segment(src, n) for n in tree.body if isinstance(n, ast.Assign)
                         and any(getattr(t, "id", "") == "pytestmark" for t in n.targets))
        for fn in (n for n in tree.body if isinstance(n, ast.FunctionDef) and n.name.startswith("test_")):
            own = marks + " ".join(ast.get_source_segment(src, d) for d in fn.decorator_list)
            if "slow" in own or "gpu" not in own + ("gpu" if "marks=pytest.mark.gpu" in src else ""):
                continue
            seen += 1
            body = ast.get_source_segment(src, fn)
            assert not bad.search(body), f"{rel}::{fn.name} trains or builds a variant: mark it slow"
    assert seen > 40


def test_gsplat_builds_beside_ours_on_half_the_cores(tmp_path, monkeypatch):
    seen = {}

    class Popen:
        def __init__(self, cmd, env, **kw):
            seen.update(cmd=cmd, env=env)

    monkeypatch.setattr(gpu_check.subprocess, "Popen", Popen)
    monkeypatch.delenv("MAX_JOBS", raising=False)
    monkeypatch.setattr(gpu_check.os, "cpu_count", lambda: 16)
    (tmp_path / "logs").mkdir()
    assert gpu_check.start_gsplat_build(tmp_path, "cpu") is None
    gpu_check.start_gsplat_build(tmp_path, "cuda")
    assert seen["env"]["MAX_JOBS"] == "8" and seen["cmd"][-1] == gpu_check.GSPLAT_BUILD


def test_the_whole_budget_skips_what_no_longer_fits(tmp_path):
    rc = gpu_check.main(["--out", str(tmp_path), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--stages", "env,agreement", "--budget", "4"])
    _, data = _report(tmp_path)
    assert rc == 1 and all(v["status"] == "skipped" and "out of time" in v["note"] for v in data["stages"].values())


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")
def test_without_a_gpu_the_gpu_stages_say_why(tmp_path):
    ctx = gpu_stages.Context(out=tmp_path)
    for stage in ("pytest", "agreement", "timing", "syncs", "fox", "smoke", "pytest-train"):
        assert "no CUDA device" in gpu_stages.STAGES[stage](ctx)["skipped"]
    built = gpu_stages.run_build(ctx)
    assert "no CUDA device" in built["default CUDA renderer"]["skipped"] and "seconds" in built["CPU renderer"]


def test_the_bundle_refuses_more_than_travels_with_the_checkout(tmp_path):
    import gpu_bundle

    (tmp_path / "a").mkdir()
    (tmp_path / "a" / "f").write_bytes(b"0" * (2 * 2**20))
    assert gpu_bundle.check_size([tmp_path / "a"], limit_mib=3) == pytest.approx(2.0)
    with pytest.raises(SystemExit, match=r"2\.0 MiB \(a 2\.0 MiB\), over the 1 MiB"):
        gpu_bundle.check_size([tmp_path / "a"], limit_mib=1)
    flags = gpu_bundle.target_flags("3.12")
    assert flags[:2] == ["--python-version", "3.12"] and "--only-binary=:all:" in flags
