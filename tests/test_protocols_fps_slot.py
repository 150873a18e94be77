"""Parallel cells take turns measuring FPS, and the report says when cells ran side by side."""

import fcntl

import pytest
import torch

from protocols.fps_slot import LOCK, fps_slot
from protocols.results import RunResult
from reports.tables import mix_notes


def test_parallel_cells_measure_one_at_a_time_and_record_the_conditions(tmp_path):
    cfg = {"executor": {"kind": "local", "workers": 2}, "out_dir": str(tmp_path)}
    with fps_slot(cfg) as cond:
        assert cond == {"threads": torch.get_num_threads(), "cells_in_parallel": 2}
        with open(tmp_path / LOCK) as other, pytest.raises(BlockingIOError):
            fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another cell would wait here
    with open(tmp_path / LOCK) as other:
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released after the measurement
    with fps_slot({"executor": {"kind": "sequential", "workers": 2}, "out_dir": str(tmp_path)}) as cond:
        assert cond["cells_in_parallel"] == 1


def test_the_report_notes_fps_measured_beside_other_cells():
    r = RunResult(method="3dgs", dataset="colmap", scene="fern", budget="full", seed=0, render_fps=10.0,
                  diagnostics={"fps_conditions": {"threads": 1, "cells_in_parallel": 2}})
    notes = " ".join(mix_notes([r]))
    assert "1 other cell(s)" in notes and "1 thread(s)" in notes
    r.diagnostics["fps_conditions"]["cells_in_parallel"] = 1
    assert "other cell" not in " ".join(mix_notes([r]))
