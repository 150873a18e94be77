"""Two sweeps on one out_dir: one writer per cell (a lock per run folder), a lock of a dead process
is taken over, and timings record the cells of every sweep that ran beside them."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import pytest

from protocols.cell_lock import LOCK, cell_lock
from protocols.live_cells import count_live_cells, live_cell
from protocols.results import read_result
from protocols.run import run_experiment

REPO = Path(__file__).resolve().parent.parent
TINY = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0]", "grid.scenes=[circle4]",
        "dataset.size=16", "dataset.steps=12", "report=false", "eval.fps_repeats=1", "eval.flip=false",
        "grid.methods=[3dgs]", "checkpoint_every=5"]
RUN = "patterns/circle4/3dgs/cap4/seed0"


def tiny(tmp_path, *extra):
    return TINY + [f"out_dir={tmp_path}", *extra]


# A second sweep, as its own process: trains the same cell and blocks at step 7 (after its step-5
# checkpoint) until the file GO exists, so the test acts while it holds the cell.
_HOLDER = textwrap.dedent("""
    import sys, time
    from pathlib import Path
    from baselines.method import MethodSpec
    from baselines.registry import register
    from baselines.splatting import GaussianSplatting
    from protocols.run import run_experiment

    go, ready = Path(sys.argv[1]), Path(sys.argv[2])

    class Blocking(GaussianSplatting):
        def train_step(self, step):
            if step == 7:
                ready.write_text("at step 7")
                while not go.exists():
                    time.sleep(0.05)
            return super().train_step(step)

    register(MethodSpec("3dgs", Blocking, {"mode": "3dgs"}), overwrite=True)
    print(run_experiment(sys.argv[3:])[0]["status"], flush=True)
""")


def _start_holder(tmp_path, *extra):
    go, ready = tmp_path / "go", tmp_path / "ready"
    p = subprocess.Popen([sys.executable, "-c", _HOLDER, str(go), str(ready), *tiny(tmp_path / "runs", *extra)],
                         cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    deadline = time.monotonic() + 240
    while not ready.exists():
        if p.poll() is not None or time.monotonic() > deadline:
            p.kill()
            pytest.fail("the first sweep did not reach step 7: " + p.communicate()[1][-3000:])
        time.sleep(0.1)
    return p, go


def test_a_second_sweep_leaves_a_cell_that_a_live_sweep_is_writing(tmp_path, capsys):
    """Launched twice by accident, or relaunched with another config while the first still runs:
    the second sweep skips the cell with a message naming the holder; it neither trains it, nor
    removes the first one's checkpoint, nor records a result in its place."""
    holder, go = _start_holder(tmp_path)
    try:
        run_dir = tmp_path / "runs" / RUN
        ckpt = json.loads((run_dir / "checkpoint.json").read_text())["dir"]
        before = sorted(p.name for p in run_dir.glob("ckpt-*"))
        for extra in ([], ["++method.train.k_max=64"]):   # the same command, and another config
            s = run_experiment(tiny(tmp_path / "runs", *extra))
            assert s[0]["status"] == "skipped" and s[0].get("busy"), s
            assert f"process {holder.pid} on" in s[0]["error"] and "on_busy=wait" in s[0]["error"]
            assert not (run_dir / "results.json").exists()
            assert sorted(p.name for p in run_dir.glob("ckpt-*")) == before == [ckpt]
        assert "another process is writing it" in capsys.readouterr().out
    finally:
        go.write_text("go")
        out, err = holder.communicate(timeout=240)
    assert holder.returncode == 0 and out.strip().endswith("ok"), err[-3000:]
    r = read_result(tmp_path / "runs" / RUN / "results.json")
    assert r.status == "ok" and r.steps == 12


def test_on_busy_wait_waits_for_the_holder(tmp_path):
    out = tmp_path / "runs"
    run_dir = out / RUN
    run_dir.mkdir(parents=True)
    release = threading.Event()

    def hold():
        with cell_lock(run_dir, str(out)) as h:
            assert h is None
            release.wait(30)

    t = threading.Thread(target=hold)
    t.start()
    time.sleep(0.2)
    notes = []
    threading.Timer(1.0, release.set).start()
    t0 = time.monotonic()
    with cell_lock(run_dir, str(out), on_busy="wait", note=notes.append) as h:
        waited = time.monotonic() - t0
        assert h is None
    t.join()
    assert waited > 0.5
    assert len(notes) == 1 and f"process {os.getpid()}" in notes[0] and "waiting for it to finish" in notes[0]


def test_a_lock_left_by_a_killed_process_is_taken_over(tmp_path, capsys):
    run_dir = tmp_path / RUN
    run_dir.mkdir(parents=True)
    pid = os.fork()
    if pid == 0:
        try:
            with cell_lock(run_dir, str(tmp_path)):
                os.kill(os.getpid(), signal.SIGKILL)
        finally:
            os._exit(1)
    _, status = os.waitpid(pid, 0)
    assert os.WIFSIGNALED(status)
    assert json.loads((run_dir / LOCK).read_text())["pid"] == pid   # its name is still there
    s = run_experiment(tiny(tmp_path))
    assert s[0]["status"] == "ok" and not s[0].get("busy")
    out = capsys.readouterr().out
    assert f"lock of process {pid} on" in out and "taken over (that process has ended)" in out


def _neighbour(ready_w: int, stop_r: int, stop_w: int) -> int:
    """A forked process that registers a running cell (another sweep's) until ``stop_w`` closes."""
    pid = os.fork()
    if pid == 0:
        try:
            os.close(stop_w)   # else its own copy keeps the pipe open
            with live_cell("another/sweep/cell"):
                os.write(ready_w, b"x")
                os.read(stop_r, 1)
        finally:
            os._exit(0)
    return pid


def test_timings_count_the_cells_of_other_sweeps_running_beside_them(tmp_path):
    ready_r, ready_w = os.pipe()
    stop_r, stop_w = os.pipe()
    pid = _neighbour(ready_w, stop_r, stop_w)
    try:
        os.read(ready_r, 1)
        assert count_live_cells() == 1
        s = run_experiment(tiny(tmp_path))   # a sequential sweep: alone in its own sweep
        assert s[0]["status"] == "ok"
    finally:
        os.close(stop_w)
        os.waitpid(pid, 0)
    d = read_result(tmp_path / RUN / "results.json").diagnostics
    assert d["fps_conditions"]["cells_in_parallel"] == 2
    assert d["train_conditions"]["cells_in_parallel"] == 2


def test_a_dead_process_is_not_counted_as_a_running_cell(tmp_path):
    with live_cell("mine"):
        pid = os.fork()
        if pid == 0:
            try:
                with live_cell("dies"):
                    os.kill(os.getpid(), signal.SIGKILL)
            finally:
                os._exit(1)
        os.waitpid(pid, 0)
        assert count_live_cells() == 1
    assert count_live_cells() == 1   # none: at least the caller's own
