"""The GPU check (bench/gpu_check.py) without a GPU: its stages' code run on the CPU (``--device cpu
--tiny``: the cpu backend stands in for the CUDA variants, tiny scenes), the report written from
what the stages saved, a stage past its deadline or crashing recorded as such while the others'
results stay, the GPU stages saying why they skip where there is no GPU, and the bundle's size check.
"""

from __future__ import annotations

import json
import sys
from pathlib import Path

import pytest
import torch

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "bench"))
sys.path.insert(0, str(ROOT / "tools"))

import gpu_check  # noqa: E402
import gpu_stages  # noqa: E402


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
    rc = gpu_check.main(["--out", str(tmp_path), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--pytest-arg", "tests/test_raster_cuda.py"])
    md, data = _report(tmp_path)
    st = data["stages"]
    assert rc == 0, {k: (v["status"], v["note"]) for k, v in st.items()}
    assert len(st["timing"]["result"]["rows"]) == 3 * 4
    assert {r["mode"] for r in st["syncs"]["result"]["rows"]} == {"3dgs", "softmax_gs"}
    assert st["pytest"]["result"]["tests"] >= 1
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
    monkeypatch.setitem(gpu_check.DEADLINES, "build", 3)
    rc = gpu_check.main(["--out", str(tmp_path), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--stages", "env,build,pytest,agreement"])
    assert rc == 1
    md, data = _report(tmp_path)
    st = data["stages"]
    assert st["build"]["status"] == "timed out" and "partial result kept" in st["build"]["note"]
    assert st["build"]["result"] == {"default CUDA renderer": {"seconds": 1.5}}
    assert st["build"]["seconds"] < 30
    assert st["pytest"]["status"] == "failed" and "exit code 3" in st["pytest"]["note"] and "boom" in st["pytest"]["note"]
    assert st["env"]["status"] == "ok" and st["agreement"]["status"] == "ok"
    assert "| build | timed out |" in md and "| pytest | failed |" in md


def test_the_whole_budget_skips_what_no_longer_fits(tmp_path):
    rc = gpu_check.main(["--out", str(tmp_path), "--device", "cpu", "--tiny", "--report-dir", "",
                         "--stages", "env,agreement", "--budget", "4"])
    _, data = _report(tmp_path)
    assert rc == 0 and all(v["status"] == "skipped" and "out of time" in v["note"] for v in data["stages"].values())


@pytest.mark.skipif(torch.cuda.is_available(), reason="a GPU is present")
def test_without_a_gpu_the_gpu_stages_say_why(tmp_path):
    ctx = gpu_stages.Context(out=tmp_path)
    for stage in ("agreement", "timing", "syncs", "fox", "smoke"):
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
