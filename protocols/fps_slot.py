"""The conditions of a cell's FPS measurement: parallel cells of one sweep take turns (a file lock
in the sweep's folder), and the result records the threads used and how many cells ran at once,
so a report can say that the other cells may have been training meanwhile."""

from __future__ import annotations

import contextlib
import fcntl
from pathlib import Path
from typing import Iterator

import torch

LOCK = ".fps.lock"


def cells_in_parallel(cfg: dict) -> int:
    ex = cfg.get("executor") or {}
    return max(1, int(ex.get("workers", 1))) if ex.get("kind") == "local" else 1


@contextlib.contextmanager
def fps_slot(cfg: dict) -> Iterator[dict]:
    """Hold the sweep's FPS lock (only when cells run in parallel) while measuring; yields the
    conditions to record in the result's diagnostics."""
    parallel = cells_in_parallel(cfg)
    conditions = {"threads": torch.get_num_threads(), "cells_in_parallel": parallel}
    if parallel == 1:
        yield conditions
        return
    path = Path(cfg["out_dir"]) / LOCK
    path.parent.mkdir(parents=True, exist_ok=True)
    with open(path, "a") as f:
        fcntl.flock(f, fcntl.LOCK_EX)  # released when the file closes, also if the process dies
        try:
            yield conditions
        finally:
            fcntl.flock(f, fcntl.LOCK_UN)
