"""Report building only removes its own files, escapes what runs recorded, and writes readable files."""

from __future__ import annotations

import json
import os
import stat

from protocols.results import RunResult, write_result
from smgs.io.atomic import atomic_write_text
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
