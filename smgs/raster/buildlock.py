"""The lock that serialises the builds of one compiled extension, across processes and hosts.

An ``fcntl.flock`` on a file in the build directory: the operating system releases it when its
owner exits, however it exits, so a build killed midway (Ctrl-C, a killed sweep cell) never blocks
the next one. The file records its owner (pid, host, start time), so a waiting process can say whom
it waits for. torch's own build lock (``<build dir>/lock``, a file that only its creator deletes)
is left behind by a killed build; whoever holds this lock removes it, because every build of this
directory takes this lock first, so a torch lock found while holding it was left by a dead builder.
"""

from __future__ import annotations

import fcntl
import json
import logging
import os
import socket
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

log = logging.getLogger(__name__)

LOCK_FILE = "smgs-build.lock"
TORCH_LOCK_FILE = "lock"      # torch.utils.file_baton.FileBaton of cpp_extension.load


class BuildLockTimeout(TimeoutError):
    """Another process held the build lock longer than the caller agreed to wait."""


@dataclass
class Owner:
    """Who holds (or last held) a build lock."""

    pid: int
    host: str
    since: float        # time.time() when it took the lock
    what: str = ""

    def describe(self) -> str:
        started = time.strftime("%H:%M:%S", time.localtime(self.since))
        return f"pid {self.pid} on {self.host} (building {self.what or 'it'} since {started})"

    @staticmethod
    def read(path: Path) -> "Owner | None":
        try:
            d = json.loads(path.read_text() or "null")
            return Owner(int(d["pid"]), str(d["host"]), float(d["since"]), str(d.get("what", "")))
        except (OSError, ValueError, TypeError, KeyError):
            return None


class BuildLock:
    """``with BuildLock(build_dir, what):`` holds the build of ``build_dir``. Waiting is announced
    through ``say`` with the owner, repeated every ``remind_s``; ``timeout`` (seconds, None = as
    long as the owner lives) raises ``BuildLockTimeout`` naming the owner."""

    def __init__(self, build_dir: Path, what: str, timeout: float | None = None,
                 say: Callable[[str], None] = log.warning, remind_s: float = 60.0, poll_s: float = 0.2) -> None:
        self.dir, self.what, self.timeout, self.say = Path(build_dir), what, timeout, say
        self.remind_s, self.poll_s = remind_s, poll_s
        self.path = self.dir / LOCK_FILE
        self._fd: int | None = None

    def __enter__(self) -> "BuildLock":
        self.dir.mkdir(parents=True, exist_ok=True)
        fd = os.open(self.path, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            self._wait(fd)
        except BaseException:
            os.close(fd)
            raise
        self._fd = fd
        previous = Owner.read(self.path)
        me = Owner(os.getpid(), socket.gethostname(), time.time(), self.what)
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(me.__dict__).encode(), 0)
        self._remove_stale_torch_lock(previous)
        return self

    @property
    def fd(self) -> int | None:
        """The locked file's descriptor while held: a build's child process given it (``pass_fds``)
        holds the lock until it ends too, so a builder killed before its compilers never lets the
        next one into the directory while they still write there."""
        return self._fd

    def __exit__(self, *exc) -> None:
        if self._fd is not None:
            fcntl.flock(self._fd, fcntl.LOCK_UN)
            os.close(self._fd)
            self._fd = None

    def _wait(self, fd: int) -> None:
        start = time.monotonic()
        next_say = start
        while True:
            try:
                fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                return
            except BlockingIOError:
                pass
            now = time.monotonic()
            owner = Owner.read(self.path)
            who = owner.describe() if owner else "another process"
            if self.timeout is not None and now - start >= self.timeout:
                raise BuildLockTimeout(
                    f"waited {now - start:.0f} s for {who} to finish building {self.what} in {self.dir}; "
                    f"the lock ({self.path}) is released when that process ends")
            if now >= next_say:
                self.say(f"waiting for {who} to finish building {self.what} in {self.dir} "
                         f"({now - start:.0f} s so far; the lock is released when that process ends)")
                next_say = now + self.remind_s
            time.sleep(self.poll_s)

    def _remove_stale_torch_lock(self, previous: Owner | None) -> None:
        stale = self.dir / TORCH_LOCK_FILE
        if stale.exists():
            by = f" by {previous.describe()}" if previous else ""
            self.say(f"removing {stale}, left by a killed build{by}")
            stale.unlink(missing_ok=True)
