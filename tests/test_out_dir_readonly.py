"""An ``out_dir`` that cannot be written is refused in one block before anything runs (before Hydra
writes its log there), even when every cell in it is finished, naming the folder, why, and what can
be done; and what it says can be done works: the report of its finished cells built elsewhere.

Root writes read-only folders, so as root the commands run without CAP_DAC_OVERRIDE (setpriv), as a
user would."""

from __future__ import annotations

import os
import shutil
import stat
import subprocess
import sys
from pathlib import Path

import pytest

from protocols.run import run_experiment

REPO = Path(__file__).resolve().parents[1]
ARGS = ["dataset=procedural", "dataset.n_views=6", "dataset.width=24", "dataset.height=16", "grid.methods=[3dgs]",
        "seeds=1", "protocol.steps=2", "protocol.schedule_steps=null", "eval.fps_repeats=1", "eval.flip=false",
        "eval.consistency=false", "eval.fractions=[1.0]", "report=false", "device=cpu"]


def _as_a_user() -> list[str]:
    """The command prefix under which read-only means read-only (empty when not root)."""
    if os.geteuid() != 0:
        return []
    setpriv = shutil.which("setpriv")
    drop = [setpriv, "--bounding-set", "-dac_override,-dac_read_search", "--inh-caps",
            "-dac_override,-dac_read_search"] if setpriv else None
    if drop is None or subprocess.run([*drop, "true"], capture_output=True).returncode != 0:
        pytest.skip("running as root, and setpriv cannot drop CAP_DAC_OVERRIDE here: a read-only folder is writable")
    return drop


def _read_only(root: Path, writable: bool = False) -> None:
    for d, dirs, files in os.walk(root):
        for p in [d, *(os.path.join(d, f) for f in files)]:
            mode = os.stat(p).st_mode
            os.chmod(p, mode | stat.S_IWUSR if writable else mode & ~(stat.S_IWUSR | stat.S_IWGRP | stat.S_IWOTH))


def _smgs(prefix: list[str], *args: str) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    return subprocess.run([*prefix, sys.executable, "-m", "smgs_cli", *args], cwd=REPO, env=env, capture_output=True,
                          text=True, timeout=600)


def test_a_read_only_out_dir_of_finished_cells_is_refused_in_one_block_naming_what_works(tmp_path):
    prefix = _as_a_user()
    out = tmp_path / "runs"
    assert run_experiment([*ARGS, f"out_dir={out}"])[0]["status"] == "ok"
    _read_only(out)
    try:
        done = _smgs(prefix, "run", *ARGS, f"out_dir={out}")
        assert done.returncode == 2, done.stderr[-3000:]
        assert done.stderr.startswith(f"error: nothing was run: out_dir={out} cannot be written (Permission denied in "
                                      f"{out}): smgs run writes there even when every cell is finished"), done.stderr
        assert done.stderr.count("\n") == 1 and "Traceback" not in done.stderr
        assert f"smgs report {out} --out DIR" in done.stderr
        report = tmp_path / "elsewhere"
        built = _smgs(prefix, "report", str(out), "--out", str(report))   # what the message says works
        assert built.returncode == 0, built.stderr[-3000:]
        assert (report / "report.md").is_file() and "procedural" in (report / "report.md").read_text()
    finally:
        _read_only(out, writable=True)


def test_an_out_dir_that_cannot_be_made_is_refused_too(tmp_path):
    prefix = _as_a_user()
    parent = tmp_path / "ro"
    parent.mkdir()
    _read_only(parent)
    try:
        done = _smgs(prefix, "run", *ARGS, f"out_dir={parent}/runs")
        assert done.returncode == 2, done.stderr[-3000:]
        assert f"error: nothing was run: out_dir={parent}/runs cannot be written (Permission denied in {parent})" \
            in done.stderr and "Traceback" not in done.stderr and "smgs report" not in done.stderr
    finally:
        _read_only(parent, writable=True)
