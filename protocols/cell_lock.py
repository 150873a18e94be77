"""One writer per cell: a file lock in the run folder, held while a process trains, evaluates and
records that cell (docs/runs.md).

The pattern is the FPS lock's (``protocols.fps_slot``): ``flock`` on a file that is never removed,
so the kernel releases the lock when its holder exits, however it exits; a lock left by a process
that died is simply taken by the next one. The file also names its holder (pid, host, start time,
sweep folder) for the message another sweep prints.
"""

from __future__ import annotations

import contextlib
import fcntl
import json
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterator

LOCK = ".cell.lock"
ON_BUSY = ("skip", "wait")


@dataclass
class Holder:
    """Who holds (or last held) a cell's lock, as its lock file says."""

    pid: int | None = None
    host: str = "?"
    since: str = "?"
    out_dir: str = "?"

    def describe(self) -> str:
        who = f"process {self.pid} on {self.host}" if self.pid else "another process"
        return f"{who} (since {self.since}, sweep {self.out_dir})"


def _read_holder(path: Path) -> Holder:
    try:
        d = json.loads(path.read_text() or "{}")
        return Holder(int(d["pid"]), str(d.get("host", "?")), str(d.get("since", "?")), str(d.get("out_dir", "?")))
    except (OSError, ValueError, KeyError, TypeError):
        return Holder()   # being rewritten by its holder, or written by an older smgs


@contextlib.contextmanager
def cell_lock(run_dir: Path, out_dir: str, on_busy: str = "skip",
              note: Callable[[str], None] = print) -> Iterator[Holder | None]:
    """Hold ``run_dir``'s lock for the block. Yields None when this process holds it; with
    ``on_busy="skip"`` and another live process holding it, yields that holder instead (the caller
    leaves the cell alone). ``on_busy="wait"`` waits for the holder to finish, saying so through
    ``note``. ``run_dir`` must exist."""
    if on_busy not in ON_BUSY:
        raise ValueError(f"on_busy={on_busy!r}: must be one of {', '.join(ON_BUSY)}")
    path = run_dir / LOCK
    with open(path, "a+") as f:
        try:
            fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = _read_holder(path)
            if on_busy == "skip":
                yield holder
                return
            note(f"{run_dir}: held by {holder.describe()}; waiting for it to finish")
            fcntl.flock(f, fcntl.LOCK_EX)   # released by its holder's exit, whatever the exit
        previous = _read_holder(path)
        if previous.pid and previous.pid != os.getpid():
            note(f"{run_dir}: lock of {previous.describe()} taken over (that process has ended)")
        f.seek(0)
        f.truncate()
        f.write(json.dumps({"pid": os.getpid(), "host": socket.gethostname(), "out_dir": str(out_dir),
                            "since": time.strftime("%Y-%m-%d %H:%M:%S")}))
        f.flush()
        try:
            yield None
        finally:
            f.seek(0)
            f.truncate()   # a finished holder leaves no name behind
            fcntl.flock(f, fcntl.LOCK_UN)
