"""The conditions of a cell's FPS measurement: the cells running on this machine take turns (a file
lock beside the live-cell registry, ``protocols.live_cells``, so cells of different sweeps take
turns too), and the result records the threads used and how many cells were running, this one
included, so a report can say that other cells may have been training meanwhile."""

from __future__ import annotations

import contextlib
import fcntl
from typing import Iterator

import torch

from protocols.live_cells import count_live_cells, registry

LOCK = "fps.lock"


@contextlib.contextmanager
def fps_slot() -> Iterator[dict]:
    """Hold this machine's FPS lock while measuring; yields the conditions to record in the
    result's diagnostics (``cells_in_parallel``: the most cells seen running, before and after)."""
    with open(registry() / LOCK, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)  # released when the file closes, also if the process dies
        try:
            conditions = {"threads": torch.get_num_threads(), "cells_in_parallel": count_live_cells()}
            yield conditions
            conditions["cells_in_parallel"] = max(conditions["cells_in_parallel"], count_live_cells())
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
