"""Cells take turns measuring FPS (on this machine, across sweeps), and the report says when other
cells were running beside a measurement or a training."""

import fcntl

import pytest
import torch

from protocols.fps_slot import LOCK, fps_slot
from protocols.live_cells import live_cell, registry
from protocols.results import RunResult
from reports.tables import mix_notes


def test_cells_measure_one_at_a_time_and_record_the_conditions():
    with fps_slot() as cond:
        assert cond == {"threads": torch.get_num_threads(), "cells_in_parallel": 1}
        with open(registry() / LOCK) as other, pytest.raises(BlockingIOError):
            fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)  # another cell would wait here
    with open(registry() / LOCK) as other:
        fcntl.flock(other, fcntl.LOCK_EX | fcntl.LOCK_NB)  # released after the measurement
    with live_cell("a"), live_cell("b"), fps_slot() as cond:
        pass
    assert cond["cells_in_parallel"] == 2


def test_the_report_notes_fps_and_training_beside_other_cells():
    r = RunResult(method="3dgs", dataset="colmap", scene="fern", budget="full", seed=0, render_fps=10.0,
                  diagnostics={"fps_conditions": {"threads": 1, "cells_in_parallel": 2},
                               "train_conditions": {"threads": 1, "cells_in_parallel": 3}})
    notes = " ".join(mix_notes([r]))
    assert "FPS of 1 run(s) was measured while up to 1 other cell(s)" in notes and "1 thread(s)" in notes
    assert "Train time of 1 run(s) was measured while up to 2 other cell(s), of this or another sweep" in notes
    r.diagnostics["fps_conditions"]["cells_in_parallel"] = 1
    r.diagnostics["train_conditions"]["cells_in_parallel"] = 1
    assert "other cell" not in " ".join(mix_notes([r]))
