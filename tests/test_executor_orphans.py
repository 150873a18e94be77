"""A local-executor sweep killed with SIGKILL (which it cannot pass on) takes its workers with it:
each stops its cell as on SIGTERM and exits, instead of holding its memory forever."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

REPO = Path(__file__).resolve().parent.parent

# The sweep as a script file: spawned workers import it again, and so register the method too.
DRIVER = textwrap.dedent("""
    import os, sys, time
    from pathlib import Path
    from baselines.method import MethodSpec
    from baselines.registry import register
    from baselines.splatting import GaussianSplatting

    class Stuck(GaussianSplatting):
        def train_step(self, step):
            if step == 2:
                Path(os.environ["SMGS_TEST_PIDS"], str(os.getpid())).write_text("in its cell")
                while True:
                    time.sleep(0.05)
            return super().train_step(step)

    register(MethodSpec("stuck", Stuck, {"mode": "3dgs"}), overwrite=True)

    if __name__ == "__main__":
        from protocols.run import run_experiment
        run_experiment(sys.argv[1:])
""")


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    try:   # a zombie (exited, not yet reaped by its new parent) has ended too
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False


def test_workers_end_with_a_killed_sweep(tmp_path):
    (tmp_path / "driver.py").write_text(DRIVER)
    pids = tmp_path / "pids"
    pids.mkdir()
    args = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.seeds=[0,1]", "grid.scenes=[circle4]",
            "grid.methods=[stuck]", "dataset.size=16", "dataset.steps=12", "report=false", "checkpoint_every=1",
            "executor.kind=local", "executor.workers=2", f"out_dir={tmp_path / 'runs'}"]
    sweep = subprocess.Popen([sys.executable, str(tmp_path / "driver.py"), *args], cwd=REPO,
                             env={**os.environ, "PYTHONPATH": str(REPO), "SMGS_TEST_PIDS": str(pids)},
                             stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    workers: list[int] = []
    try:
        deadline = time.monotonic() + 300
        while len(workers) < 2:
            assert sweep.poll() is None and time.monotonic() < deadline, sweep.communicate()[1][-3000:]
            workers = [int(p.name) for p in pids.iterdir()]
            time.sleep(0.1)
        sweep.kill()
        sweep.wait()
        deadline = time.monotonic() + 30
        while any(_alive(w) for w in workers) and time.monotonic() < deadline:
            time.sleep(0.2)
        assert not [w for w in workers if _alive(w)], "workers outlived their killed sweep"
        for seed in (0, 1):   # each stopped its cell as on SIGTERM: the log says so, the checkpoint stays
            run = tmp_path / "runs" / f"patterns/circle4/stuck/cap4/seed{seed}"
            assert "interrupted; rerun to resume" in (run / "log.txt").read_text()
            assert (run / "checkpoint.json").is_file()
    finally:
        if sweep.poll() is None:
            sweep.kill()
        for w in workers:
            if _alive(w):
                os.kill(w, signal.SIGKILL)
