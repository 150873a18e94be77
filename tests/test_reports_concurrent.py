"""Two builds of one report (two sweeps on one folder ending together): the report built last holds
every result; what killed builds and exports left behind is removed by the next one."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import reports.build as build
from protocols.results import read_result, write_result

sys.path.insert(0, str(Path(__file__).parent))
from reports_tree import make_seed_tree  # noqa: E402

REPO = Path(__file__).resolve().parent.parent


def test_the_last_report_holds_every_result(tmp_path, monkeypatch, capsys):
    """Sweep A builds its report and has read the results when sweep B swaps in its last result and
    builds its own, which ends first; A's report, switched in last, must not be the stale one. The
    order is forced: A is held right after reading; B runs until it has read the results too or
    waits for A's build (then A goes on)."""
    root = make_seed_tree(tmp_path / "runs")
    a_read, a_go, b_read = threading.Event(), threading.Event(), threading.Event()
    real = build.load_runs

    def load_runs(*args):
        loaded = real(*args)
        if threading.current_thread().name == "A":
            a_read.set()
            a_go.wait(120)
        else:
            b_read.set()
        return loaded

    monkeypatch.setattr(build, "load_runs", load_runs)
    errors = []

    def sweep(name):
        try:
            build.build_report(root, stability="x")
        except BaseException as e:  # noqa: BLE001 (reported below)
            errors.append((name, e))

    a = threading.Thread(target=sweep, args=("A",), name="A")
    a.start()
    assert a_read.wait(120)
    extra = read_result(root / "procedural/blocks/3dgs/full/seed0/results.json")
    extra.seed = 7
    write_result(root / "procedural/blocks/3dgs/full/seed7", extra)   # B's last result
    b = threading.Thread(target=sweep, args=("B",), name="B")
    b.start()
    waiting = ""
    while not (b_read.is_set() or "another build of" in waiting):   # old code: B reads; now: B waits for A
        waiting += capsys.readouterr().err
        time.sleep(0.05)
    if b_read.is_set():
        b.join(120)
    a_go.set()
    a.join(120)
    b.join(120)
    assert not errors, errors
    md = (root / "report" / "report.md").read_text()
    assert "13 results (13 ok)" in md, md[:400]


def _killed_midway(code: str, *args: str) -> None:
    p = subprocess.run([sys.executable, "-c", textwrap.dedent(code), *args], cwd=REPO, capture_output=True, text=True,
                       env={**os.environ, "PYTHONPATH": str(REPO)}, timeout=600)
    assert p.returncode == -signal.SIGKILL, p.stderr[-3000:]


def test_a_killed_build_leaves_nothing_the_next_one_keeps(tmp_path):
    root = make_seed_tree(tmp_path / "runs")
    build.build_report(root, stability="x")
    _killed_midway("""
        import os, signal, sys
        import reports.build as b
        real = b.atomic_write_text
        def write(path, text):
            real(path, text[: len(text) // 2])
            os.kill(os.getpid(), signal.SIGKILL)
        b.atomic_write_text = write
        b.build_report(sys.argv[1], stability="x")
    """, str(root))
    assert [p.name for p in root.glob(".report.building-*")], "the kill left no half-built folder to test with"
    build.build_report(root, stability="x")
    assert sorted(p.name for p in root.glob(".report*")) == [".report.lock"]


def test_a_killed_export_leaves_no_temporary_file(tmp_path):
    from protocols.ply import export_run

    run_dir = tmp_path / "run"
    _killed_midway("""
        import os, signal, sys
        from pathlib import Path
        from smgs.atomic import atomic_file
        with atomic_file(Path(sys.argv[1]) / "point_cloud.ply") as f:
            f.write(b"x" * 4096)
            os.kill(os.getpid(), signal.SIGKILL)
    """, str(run_dir))
    left = list(run_dir.glob(".point_cloud.ply.*.tmp"))
    assert left, "the kill left no temporary file to test with"
    _trained_checkpoint(run_dir)
    assert export_run(run_dir)[1] == 2
    assert (run_dir / "point_cloud.ply").is_file() and not list(run_dir.glob(".point_cloud.ply.*.tmp"))


def _trained_checkpoint(run_dir: Path) -> None:
    """A run folder with a checkpoint of two steps, as a run saves it."""
    import json

    from baselines import create_method
    from smgs.data.patterns import pattern_scene
    from smgs.train import pattern_config, to_dict

    m = create_method("3dgs", pattern_scene("circle4", 12), to_dict(pattern_config("3dgs", cap=4, steps=2)), device="cpu")
    for s in range(2):
        m.train_step(s)
    m.save(run_dir / "ckpt-0000002")
    (run_dir / "checkpoint.json").write_text(json.dumps({"dir": "ckpt-0000002", "config_hash": "x"}))
