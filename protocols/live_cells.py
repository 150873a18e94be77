"""The cells running on this machine now, of any sweep: what a run's timings shared the cores with.

Each running cell holds a lock on a file of its own in a per-user folder of the machine's temporary
directory (``SMGS_CELLS_DIR`` overrides it); counting the files whose lock is held counts the live
cells, the counting cell included. A file whose lock nobody holds belongs to a process that died and
is removed. Same pattern as the FPS lock (``protocols.fps_slot``): ``flock``, released by the kernel
when the holder exits.
"""

from __future__ import annotations

import contextlib
import fcntl
import os
import tempfile
import uuid
from pathlib import Path
from typing import Iterator

ENV = "SMGS_CELLS_DIR"


def registry() -> Path:
    d = os.environ.get(ENV) or os.path.join(tempfile.gettempdir(), f"smgs-cells-{os.getuid()}")
    path = Path(d)
    path.mkdir(parents=True, exist_ok=True)
    return path


@contextlib.contextmanager
def live_cell(run_dir: Path | str) -> Iterator[None]:
    """Register this process's running cell for the block."""
    name = f"{os.getpid()}-{uuid.uuid4().hex[:12]}"
    tmp, path = registry() / f".{name}.tmp", registry() / f"{name}.cell"
    with open(tmp, "w") as f:
        fcntl.flock(f, fcntl.LOCK_EX)
        f.write(str(run_dir))
        f.flush()
        os.replace(tmp, path)   # counted only once locked: a counter never takes it for a dead cell's
        try:
            yield
        finally:
            path.unlink(missing_ok=True)
            fcntl.flock(f, fcntl.LOCK_UN)


def count_live_cells() -> int:
    """How many cells run on this machine now (at least 1: the caller's own)."""
    n = 0
    for path in registry().glob("*.cell"):
        try:
            with open(path) as f:
                try:
                    fcntl.flock(f, fcntl.LOCK_SH | fcntl.LOCK_NB)
                except BlockingIOError:
                    n += 1   # held: a live cell
                    continue
                path.unlink(missing_ok=True)   # nobody holds it: its process died
        except FileNotFoundError:
            continue   # ended while we looked
    return max(1, n)


class NeighbourLog:
    """The most cells seen running at once over a stretch of work (sampled by ``sample``)."""

    def __init__(self) -> None:
        self.most = count_live_cells()

    def sample(self) -> int:
        now = count_live_cells()
        self.most = max(self.most, now)
        return now
