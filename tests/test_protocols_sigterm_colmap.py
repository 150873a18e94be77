"""SIGTERM during a COLMAP-scene run stops it as on any other scene: pycolmap's import installs glog's
failure-signal handler, which answered SIGTERM with a native stack dump and left no "interrupted"
line in the run's log; the runner's handler is put back after the import."""

from __future__ import annotations

import signal

import pytest
from sigterm_run import REPO, terminate_when_training

FERN = REPO.parent / "shared" / "data" / "fern"


@pytest.mark.skipif(not (FERN / "sparse" / "0").is_dir(), reason=f"fixture {FERN} absent")
def test_sigterm_on_a_fern_run_stops_cleanly(tmp_path):
    pytest.importorskip("pycolmap")
    args = ["dataset=colmap", f"dataset.path={FERN}", "grid.methods=[3dgs]", "protocol.steps=20000",
            "protocol.max_width=64", "checkpoint_every=10", "report=false", "eval.flip=false", f"out_dir={tmp_path}"]
    code, _, err = terminate_when_training(args, "fern/3dgs: step")   # the scene is loaded: pycolmap imported
    assert code == 128 + signal.SIGTERM, err[-2000:]
    assert "stopped by SIGTERM" in err and "*** SIGTERM" not in err and "Aborted at" not in err
    log = tmp_path / "colmap" / "fern" / "3dgs" / "full" / "seed0" / "log.txt"
    assert "interrupted; rerun to resume from the last checkpoint" in log.read_text()
