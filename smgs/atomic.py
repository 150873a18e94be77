"""Writing a file so that it appears complete or not at all: the one helper every writer uses.

The data goes to a temporary file in the same folder, is fsynced, and is renamed over the target;
a reader never sees half a file and an interrupted write leaves the previous file intact. The new
file's mode honours the umask, as a plain ``open(path, "w")`` would (mkstemp alone makes 0600).
A temporary file's name says which process made it (``owner_tag``): one left by a process that was
killed midway is removed by the next write of the same file (``remove_stale_temps``).
"""

from __future__ import annotations

import contextlib
import glob
import os
import re
import socket
import tempfile
from pathlib import Path
from typing import BinaryIO, Iterator


@contextlib.contextmanager
def atomic_file(path: Path | str) -> Iterator[BinaryIO]:
    """A binary file to write ``path``'s new content to; it replaces ``path`` when the block ends
    without an error, and is removed otherwise. Parent folders are created."""
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        remove_stale_temps(path)
        fd, tmp = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.{owner_tag()}-", suffix=".tmp")
    except OSError as e:
        raise _naming(e, path) from None
    try:
        os.fchmod(fd, 0o666 & ~umask())
        with os.fdopen(fd, "wb") as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, path)
    except BaseException as e:
        if os.path.exists(tmp):
            os.unlink(tmp)
        if isinstance(e, OSError) and e.filename is None:   # a full disk, an I/O error: say where
            raise _naming(e, path) from None
        raise


def owner_tag() -> str:
    """``<pid>@<host>``: which process on which machine made a temporary file (in its name), so that
    one left by a killed process is known as such (``remove_stale_temps``)."""
    host = re.sub(r"[^A-Za-z0-9-]", "", socket.gethostname().split(".")[0]) or "host"
    return f"{os.getpid()}@{host}"


def remove_stale_temps(path: Path | str) -> list[Path]:
    """Remove the temporary files of ``path`` (``atomic_file``'s) whose writer, a process on this
    machine, no longer lives: what a write killed midway left (a PLY export's may be hundreds of MB).
    Returns those removed; a file it cannot remove is left."""
    path = Path(path)
    pattern = re.compile(re.escape(f".{path.name}.") + r"(\d+)@([A-Za-z0-9-]+)-[^/]*\.tmp")
    host = owner_tag().split("@", 1)[1]
    removed = []
    for p in path.parent.glob(f".{glob.escape(path.name)}.*.tmp"):
        m = pattern.fullmatch(p.name)
        if m and m.group(2) == host and not _alive(int(m.group(1))):
            try:
                p.unlink()
                removed.append(p)
            except OSError:
                pass
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except OSError:   # another user's process: it lives
        return True
    return True


def _naming(e: OSError, path: Path) -> OSError:
    """``e`` with ``path`` as its file name where it names none (ENOSPC from a write or an fsync
    says only "[Errno 28] No space left on device")."""
    if e.filename is not None or e.errno is None:
        return e
    named = OSError(e.errno, e.strerror or str(e), str(path))   # OSError() picks the errno's subclass
    named.__traceback__ = e.__traceback__
    return named


def atomic_write_bytes(path: Path | str, data: bytes) -> None:
    with atomic_file(path) as f:
        f.write(data)


def atomic_write_text(path: Path | str, text: str) -> None:
    atomic_write_bytes(path, text.encode())


def umask() -> int:
    """The process's umask, read without changing it where Linux shows it (no window in which another
    thread would create files under a different mask)."""
    try:
        for line in Path("/proc/self/status").read_text().splitlines():
            if line.startswith("Umask:"):
                return int(line.split()[1], 8)
    except OSError:
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return mask


def replace_dir(new: Path | str, target: Path | str) -> None:
    """Put the folder ``new`` in place of the folder ``target`` (which may not exist) and remove the
    old one. Where the kernel and file system can (Linux ``renameat2`` with ``RENAME_EXCHANGE``)
    the two are swapped in one atomic step; elsewhere ``target`` is first renamed aside, which
    leaves a moment without it, but never a half-written folder in its place. Both must be on
    one file system (``new`` is best made beside ``target``)."""
    import shutil

    new, target = Path(new), Path(target)
    if not target.exists() and not target.is_symlink():
        os.rename(new, target)
        return
    if not target.is_dir() or target.is_symlink():
        raise NotADirectoryError(f"{target} is not a folder; move it away to write the new one there")
    if exchange_dirs(new, target):
        shutil.rmtree(new, ignore_errors=True)   # now holds the old content
        return
    aside = Path(tempfile.mkdtemp(dir=target.parent, prefix=f".{target.name}.old-"))
    try:
        os.rename(target, aside / target.name)
    except OSError:
        aside.rmdir()   # nothing was moved: leave no empty folder behind
        raise
    os.rename(new, target)
    shutil.rmtree(aside, ignore_errors=True)


def exchange_dirs(a: Path | str, b: Path | str) -> bool:
    """Swap two paths atomically (Linux renameat2 RENAME_EXCHANGE); False where that is not there
    (another system, or a file system without it), and nothing was changed."""
    import ctypes

    try:
        fn = ctypes.CDLL(None, use_errno=True).renameat2
    except (OSError, AttributeError):
        return False
    fn.argtypes = [ctypes.c_int, ctypes.c_char_p, ctypes.c_int, ctypes.c_char_p, ctypes.c_uint]
    at_fdcwd, rename_exchange = -100, 2
    return fn(at_fdcwd, os.fsencode(a), at_fdcwd, os.fsencode(b), rename_exchange) == 0
