"""What a scene was read from, by content: the fingerprint of its input files (images, camera model,
points), which every result records (``inputs`` in results.json) and a cell's identity compares
(``smgs.identity``): a finished cell whose inputs changed on disk is rerun, and seeds trained on
different inputs are not pooled.

A fingerprint is plain data: ``files`` maps each file's name (relative to the files' common folder,
so that two copies of a scene in different places compare equal) to its size and sha256;
``digest`` is a hash of all of them; ``folder`` says where they were read (a location, never
compared). A format that lists no input files (a generated scene, whose config is all of it, or a
plug-in without ``inputs(request)``) gets ``files`` None and a ``note`` saying why.

Hashing is made cheap by a cache: a file's sha256 is kept in ``$XDG_CACHE_HOME/smgs/file-hashes.sqlite``
(default ``~/.cache/smgs``; ``SMGS_HASH_CACHE`` names another file, an empty value turns it off)
under its path, size, modification and change times and inode, so an unchanged file is hashed once
and a file replaced or rewritten in place (which moves its change time, whatever its modification
time says) is hashed again.
"""

from __future__ import annotations

import hashlib
import json
import os
import sqlite3
from pathlib import Path
from typing import Any, Sequence

CACHE_ENV = "SMGS_HASH_CACHE"
CHUNK = 1 << 20


def cache_path() -> Path | None:
    """The hash cache's file (None: off)."""
    given = os.environ.get(CACHE_ENV)
    if given is not None:
        return Path(given) if given.strip() else None
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "smgs" / "file-hashes.sqlite"


def _stamp(st: os.stat_result) -> tuple[int, int, int, int, int]:
    return st.st_size, st.st_mtime_ns, st.st_ctime_ns, st.st_ino, st.st_dev


def _hash_file(path: Path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(CHUNK), b""):
            h.update(block)
    return h.hexdigest()


class _Cache:
    """The sqlite cache of file hashes; every failure (a read-only home, a locked or corrupt
    database) leaves it off for this fingerprint, never the fingerprint undone."""

    def __init__(self, path: Path | None) -> None:
        self.db: sqlite3.Connection | None = None
        if path is None:
            return
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self.db = sqlite3.connect(str(path), timeout=30)
            self.db.execute("CREATE TABLE IF NOT EXISTS hashes (path TEXT PRIMARY KEY, size INTEGER, mtime INTEGER, "
                            "ctime INTEGER, ino INTEGER, dev INTEGER, sha256 TEXT)")
        except (OSError, sqlite3.Error):
            self.close()

    def get(self, path: str, stamp: tuple) -> str | None:
        if self.db is None:
            return None
        try:
            row = self.db.execute("SELECT size, mtime, ctime, ino, dev, sha256 FROM hashes WHERE path = ?",
                                  (path,)).fetchone()
        except sqlite3.Error:
            self.close()
            return None
        return row[5] if row is not None and tuple(row[:5]) == stamp else None

    def put(self, path: str, stamp: tuple, digest: str) -> None:
        if self.db is None:
            return
        try:
            with self.db:
                self.db.execute("INSERT OR REPLACE INTO hashes VALUES (?, ?, ?, ?, ?, ?, ?)", (path, *stamp, digest))
        except sqlite3.Error:
            self.close()

    def close(self) -> None:
        if self.db is not None:
            self.db.close()
        self.db = None


def file_digests(paths: Sequence[Path]) -> list[tuple[int, str]]:
    """(size, sha256) of each file, from the cache where the file is unchanged since it was hashed."""
    cache = _Cache(cache_path())
    out = []
    try:
        for p in paths:
            real = os.path.realpath(p)
            stamp = _stamp(os.stat(real))
            digest = cache.get(real, stamp)
            if digest is None:
                digest = _hash_file(Path(real))
                after = _stamp(os.stat(real))
                if after == stamp:   # not written while it was read: worth keeping
                    cache.put(real, stamp, digest)
            out.append((stamp[0], digest))
    finally:
        cache.close()
    return out


def fingerprint(paths: Sequence[Path | str]) -> dict[str, Any]:
    """The fingerprint of the files ``paths`` (the module's docstring)."""
    paths = [Path(p) for p in dict.fromkeys(os.path.abspath(p) for p in paths)]
    if not paths:
        return {"files": {}, "digest": _digest({}), "folder": None}
    folder = Path(os.path.commonpath([str(p.parent) for p in paths]))
    files = {Path(os.path.relpath(p, folder)).as_posix(): {"size": size, "sha256": digest}
             for p, (size, digest) in zip(paths, file_digests(paths))}
    return {"files": dict(sorted(files.items())), "digest": _digest(files), "folder": str(folder)}


def not_listed(why: str) -> dict[str, Any]:
    """The fingerprint of a scene whose format lists no input files: ``why`` says so."""
    return {"files": None, "digest": None, "note": why}


def _digest(files: dict[str, dict]) -> str:
    blob = json.dumps(sorted((k, v["size"], v["sha256"]) for k, v in files.items())).encode()
    return hashlib.sha256(blob).hexdigest()[:16]
