"""One archive over HTTP into a partial file, resumed where an earlier try stopped (HTTP Range).

``<name>.part`` holds the bytes received so far and ``<name>.part.json`` the URL, the full size and
the server's validator (ETag or Last-Modified) they belong to. A resumed request sends ``Range`` and
``If-Range``: a server whose file changed answers with the whole new file, which starts over; a part
of another URL or size is never continued. The caller renames the part to its final name only once
it is complete and checked.
"""

from __future__ import annotations

import errno
import json
import re
import urllib.error
import urllib.request
from dataclasses import dataclass
from http.client import HTTPException, HTTPResponse
from pathlib import Path

from smgs.atomic import atomic_write_text
from smgs.version import __version__
from smgs.data.download.errors import DiskSpaceError, NetworkError, RemoteChangedError

CHUNK = 1 << 20
TIMEOUT_S = 60.0
USER_AGENT = f"smgs-download/{__version__}"


@dataclass
class Remote:
    """An answered request: the archive's full size (None where the server does not say), the byte
    the body starts at, and the open response (None when the part is already complete)."""

    url: str
    total: int | None
    offset: int
    response: HTTPResponse | None
    validator: str | None
    short_at: int | None = None   # where an earlier try of this size ended short
    manual: str = ""              # how to fetch it by hand (the end of a misreported size's message)

    @property
    def remaining(self) -> int | None:
        return None if self.total is None else self.total - self.offset

    def close(self) -> None:
        if self.response is not None:
            self.response.close()


def sidecar(part: Path) -> Path:
    return part.with_name(part.name + ".json")


def _earlier(part: Path, url: str) -> tuple[int, dict]:
    """Bytes of an earlier try of ``url`` to continue from, and what was recorded about them; a part
    of another URL, or without its record, is discarded."""
    try:
        meta = json.loads(sidecar(part).read_text())
    except (OSError, ValueError):
        meta = {}
    if part.is_file() and meta.get("url") == url:
        return part.stat().st_size, meta
    part.unlink(missing_ok=True)
    return 0, {}


def _total(resp: HTTPResponse, offset: int) -> int | None:
    """The full size: from Content-Range on a 206, else Content-Length."""
    rng = resp.headers.get("Content-Range")
    if rng:
        m = re.match(r"bytes (\d+)-\d+/(\d+|\*)", rng)
        if not m or int(m.group(1)) != offset:
            raise RemoteChangedError(f"the server answered a resumed request with Content-Range {rng!r} where "
                                     f"byte {offset} was asked for; delete the partial file and rerun")
        return None if m.group(2) == "*" else int(m.group(2))
    length = resp.headers.get("Content-Length")
    return int(length) if length and length.isdigit() else None


def misreported(url: str, declared: int, ends: int, part: Path, manual: str) -> RemoteChangedError:
    return RemoteChangedError(
        f"{url} declares the archive as {declared} bytes (Content-Length) but sends nothing past byte {ends}, on "
        f"two tries alike: its size is misreported (or something between here and the server cuts the transfer "
        f"there), and a rerun would fail the same way. What arrived is kept in {part}. Fetch the archive another "
        f"way (a browser, another mirror with --mirror URL) and hand it over: {manual}")


def open_remote(url: str, part: Path, manual: str, timeout: float = TIMEOUT_S) -> Remote:
    """Ask for ``url`` from where ``part`` stops. ``manual`` says how to fetch it by hand; it ends
    every network error."""
    offset, meta = _earlier(part, url)
    headers = {"User-Agent": USER_AGENT}
    if offset:
        headers["Range"] = f"bytes={offset}-"
        if meta.get("validator"):
            headers["If-Range"] = meta["validator"]
    try:
        resp = urllib.request.urlopen(urllib.request.Request(url, headers=headers), timeout=timeout)
    except urllib.error.HTTPError as e:
        if e.code == 416 and offset and meta.get("total") == offset:
            return Remote(url, offset, offset, None, meta.get("validator"))   # received whole earlier
        if e.code == 416 and offset and (e.headers or {}).get("Content-Range") == f"bytes */{offset}":
            raise misreported(url, meta.get("total") or offset, offset, part, manual) from None   # ends where we do
        if e.code == 416:
            part.unlink(missing_ok=True)
            return open_remote(url, part, manual, timeout)
        if e.code >= 500:
            raise NetworkError(f"{url} answered HTTP {e.code} {e.reason}, a failure of the server: try again "
                               f"later. Without network here, {manual}") from None
        raise RemoteChangedError(f"{url} answered HTTP {e.code} {e.reason}: the file has moved or is gone. "
                                 f"Without network here, {manual}") from None
    except (urllib.error.URLError, OSError, HTTPException) as e:
        reason = getattr(e, "reason", e)
        raise NetworkError(f"cannot reach {url} ({reason}). Without network here, {manual}") from None
    if resp.status != 206:
        offset = 0   # the whole file: the server did not resume (or its file changed)
    total = _total(resp, offset)
    if offset and meta.get("total") not in (None, total):
        resp.close()
        part.unlink(missing_ok=True)
        return open_remote(url, part, manual, timeout)
    validator = resp.headers.get("ETag") or resp.headers.get("Last-Modified")
    short_at = meta.get("short_at") if meta.get("total") == total else None
    atomic_write_text(sidecar(part), json.dumps({"url": url, "total": total, "validator": validator,
                                                 "short_at": short_at}))
    return Remote(url, total, offset, resp, validator, short_at, manual)


def receive(remote: Remote, part: Path, progress: bool | None = None) -> None:
    """Stream the answer into ``part`` with a progress bar (bytes, rate, time left; ``progress``
    None: only on a terminal). A broken transfer or a full disk keeps what arrived, for a rerun."""
    from tqdm import tqdm

    if remote.response is None:
        return
    with open(part, "ab" if remote.offset else "wb") as f, \
            tqdm(total=remote.total, initial=remote.offset, unit="B", unit_scale=True, unit_divisor=1024,
                 desc=part.name.removesuffix(".part"), disable=None if progress is None else not progress) as bar:
        while True:
            chunk = _read(remote, f.tell())
            if not chunk:
                break
            _write(f, chunk, part)
            bar.update(len(chunk))
        got = f.tell()
    remote.close()
    if remote.total is not None and got != remote.total:
        if got == remote.short_at:   # the same end twice: not a broken connection
            raise misreported(remote.url, remote.total, got, part, remote.manual)
        meta = json.loads(sidecar(part).read_text())
        atomic_write_text(sidecar(part), json.dumps({**meta, "short_at": got}))
        raise NetworkError(f"the transfer of {remote.url} ended at byte {got} of {remote.total}; rerun the same "
                           "command to resume from there")


def _read(remote: Remote, at: int) -> bytes:
    try:
        return remote.response.read(CHUNK)
    except (OSError, HTTPException) as e:
        raise NetworkError(f"the transfer of {remote.url} broke off at byte {at} of {remote.total or '?'} "
                           f"({e!r}); rerun the same command to resume from there") from None


def _write(f, chunk: bytes, part: Path) -> None:
    try:
        f.write(chunk)
    except OSError as e:
        if e.errno in (errno.ENOSPC, errno.EDQUOT):
            raise DiskSpaceError(f"the disk holding {part} is full ({e.strerror}); what arrived is kept: free "
                                 "space (or pass --root on another disk) and rerun to resume") from None
        raise
