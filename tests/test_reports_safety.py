"""Report building only removes its own files, escapes what runs recorded, and writes readable files."""

from __future__ import annotations

import json
import os
import stat

import pytest

from protocols.results import RunResult, write_result
from smgs.atomic import atomic_write_text
from reports.build import MANIFEST, build_report

PAYLOAD = "<img src=x onerror=alert(1)> [click](http://evil.example) `code` a|b"


def _tree(root):
    ok = RunResult(method="3dgs", dataset="colmap", scene="fern", budget="full", seed=0, metrics={"psnr": 20.0},
                   preset="cpu<b>x</b>", config={"protocol": {"name": "cpu<b>x</b>", "steps": 5}})
    write_result(root / "ok", ok)
    bad = RunResult(method="softmax_gs", dataset="colmap", scene="fern", budget="full", seed=0, status="failed",
                    error="RuntimeError: " + PAYLOAD)
    write_result(root / "bad", bad)
    return root


def test_a_planted_manifest_deletes_nothing_outside_what_the_report_writes(tmp_path):
    root = _tree(tmp_path / "runs")
    out = root / "report"
    victim_outside = tmp_path / "precious.txt"
    victim_outside.write_text("keep")
    victim_runs = root / "ok" / "results.json"
    victim_inside = out / "notes.md"
    out.mkdir(parents=True)
    victim_inside.write_text("mine")
    stale = out / "tables" / "table9_gone.csv"
    stale.parent.mkdir()
    stale.write_text("old")
    (out / MANIFEST).write_text(json.dumps([str(victim_outside), "../precious.txt", "../ok/results.json",
                                            "notes.md", "tables/../notes.md", "tables/table9_gone.csv"]))
    build_report(root, stability="not here")
    assert victim_outside.read_text() == "keep"
    assert victim_runs.exists() and victim_inside.read_text() == "mine"
    assert not stale.exists()  # a table of an earlier build that this one does not produce


def test_recorded_text_is_escaped_in_report_md(tmp_path):
    md = build_report(_tree(tmp_path / "runs"), stability="not here").read_text()
    assert "<img" not in md and "&lt;img src=x onerror=alert(1)&gt;" in md
    assert "<b>" not in md
    assert "](http://evil.example)" not in md


def test_written_files_honour_the_umask(tmp_path):
    old = os.umask(0o022)
    try:
        atomic_write_text(tmp_path / "a.json", "{}")
        os.umask(0o077)
        atomic_write_text(tmp_path / "b.json", "{}")
    finally:
        os.umask(old)
    assert stat.S_IMODE((tmp_path / "a.json").stat().st_mode) == 0o644
    assert stat.S_IMODE((tmp_path / "b.json").stat().st_mode) == 0o600


def _files(folder):
    return {p.relative_to(folder).as_posix(): p.read_bytes() for p in sorted(folder.rglob("*")) if p.is_file()}


def test_a_failed_build_leaves_the_previous_report_whole(tmp_path, monkeypatch):
    """A full disk midway: the previous report.md, report.html and tables stay as they were (no new
    table beside an old report.md), no temporary folder is left, and the command says so in a line."""
    import errno

    import reports.build as rb

    root = _tree(tmp_path / "runs")
    out = root / "report"
    build_report(root, stability="not here")
    (out / "notes.md").write_text("mine")
    before = _files(out)
    write_result(root / "more", RunResult(method="gef_only", dataset="colmap", scene="flower", budget="full", seed=0,
                                          metrics={"psnr": 21.0}))   # the next build's tables differ
    real, calls = rb.atomic_write_bytes, []

    def full_after_two(path, data):
        calls.append(path)
        if len(calls) > 2:
            raise OSError(errno.ENOSPC, "No space left on device", str(path))
        real(path, data)

    monkeypatch.setattr(rb, "atomic_write_bytes", full_after_two)
    with pytest.raises(OSError, match="No space left on device"):
        build_report(root, stability="not here")
    assert _files(out) == before
    assert sorted(p.name for p in root.iterdir()) == [".report.lock", "bad", "more", "ok", "report"]   # the lock of one_build
    monkeypatch.undo()
    build_report(root, stability="not here")   # and a build that succeeds replaces it, keeping notes.md
    assert (out / "notes.md").read_text() == "mine" and "flower" in (out / "report.md").read_text()


def test_the_builder_reports_a_full_disk_in_one_line(tmp_path, monkeypatch, capsys):
    import errno

    import reports.build as rb

    root = _tree(tmp_path / "runs")

    def full(path, data):
        raise OSError(errno.ENOSPC, "No space left on device", str(path))

    monkeypatch.setattr(rb, "atomic_write_bytes", full)
    assert rb.main([str(root), "--no-stability"]) == 1
    err = capsys.readouterr().err
    assert err.startswith("error: the report was not written ([Errno 28] No space left on device: '")
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1
    assert f"the previous report in {root / 'report'}" in err


def test_long_recorded_strings_are_cut_in_both_report_formats(tmp_path):
    root = tmp_path / "runs"
    huge = "x" * 20_000_000
    write_result(root / "bad", RunResult(method="softmax_gs", dataset="colmap", scene="fern", budget="full", seed=0,
                                         status="failed", error="RuntimeError: " + huge))
    write_result(root / "ok", RunResult(method="3dgs", dataset="colmap", scene="fern", budget="full", seed=0,
                                        metrics={"psnr": 20.0}, render_device="cpu " + "y" * 1_000_000,
                                        versions={"device": "z" * 1_000_000}))
    md = build_report(root, stability="not here")
    html = md.parent / "report.html"
    assert md.stat().st_size < 200_000 and html.stat().st_size < 8_000_000   # plotly.js alone is ~4.6 MB
    assert "x" * 5000 not in html.read_text() and "y" * 5000 not in md.read_text() + html.read_text()
    assert "more characters, in" in html.read_text()


def test_every_recorded_string_is_escaped_in_report_md(tmp_path):
    """Dataset, scene, method, budget, preset, device and version names, metric reasons and errors."""
    from protocols.results import CurvePoint

    p = "<b>x</b>"

    def run(method, **kw):
        return RunResult(method=method, dataset=f"colmap{p}", scene=f"fern{p}", budget=f"full{p}", seed=0,
                         preset=f"cpu{p}", metrics={"psnr": 20.0, "ssim": 0.5, "lpips": 0.3}, lpips_net=f"vgg{p}",
                         missing={"flip": f"no flip{p}"}, num_gaussians=100, train_seconds=10.0, render_fps=5.0,
                         render_device=f"cpu{p}", steps=10, hparams=f"h{p}",
                         curve=[CurvePoint(5, 1.0, 18.0, 50), CurvePoint(10, 2.0, 20.0, 100)],
                         versions={"smgs": f"0.1{p}", "torch": f"2{p}", "backend": f"cpu{p}", "device": f"dev{p}"},
                         config={"protocol": {"name": f"cpu{p}", "steps": 10}},
                         diagnostics={"plan": [f"plan{p}"], "left_out": [f"x{p}: off"]}, **kw)

    root = tmp_path / "runs"
    write_result(root / "a", run("softmax_gs"))
    write_result(root / "b", run(f"3dgs{p}"))
    write_result(root / "c", run(f"gef_only{p}", status="failed", error=f"E{p}"))
    md = build_report(root, stability=f"not here{p}").read_text()
    assert p not in md and "&lt;b&gt;x&lt;/b&gt;" in md
