"""Stand-ins for the datasets' servers and archives, for tests/test_download.py: tiny scenes in the
real layout (JPEG images, a binary COLMAP model under sparse/0), zipped as the authors' archives are,
and served from 127.0.0.1 by an HTTP server that honours Range and If-Range, can answer 404 and can
break a transfer off after a given number of bytes. Nothing reaches outside the machine."""

from __future__ import annotations

import hashlib
import io
import re
import struct
import threading
import zipfile
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

from PIL import Image

PINHOLE = 1   # COLMAP's camera model id


def tiny_jpeg(w: int = 24, h: int = 16) -> bytes:
    buf = io.BytesIO()
    Image.new("RGB", (w, h), (90, 120, 30)).save(buf, "JPEG")
    return buf.getvalue()


def colmap_model(names: list[str], w: int = 24, h: int = 16) -> dict[str, bytes]:
    """cameras.bin, images.bin and points3D.bin (COLMAP's binary layout): one PINHOLE camera, each
    image registered on a circle around the origin, one point seen by none."""
    cams = struct.pack("<Q", 1) + struct.pack("<iiQQ4d", 1, PINHOLE, w, h, 10.0, 10.0, w / 2, h / 2)
    imgs = struct.pack("<Q", len(names))
    for i, name in enumerate(names, start=1):
        imgs += struct.pack("<i4d3di", i, 1.0, 0.0, 0.0, 0.0, float(i % 7), float(i // 7), 4.0, 1)
        imgs += name.encode() + b"\0" + struct.pack("<Q", 0)
    pts = struct.pack("<Q", 1) + struct.pack("<Q3d3BdQ", 1, 0.0, 0.0, 0.0, 200, 100, 50, 0.5, 0)
    return {"cameras.bin": cams, "images.bin": imgs, "points3D.bin": pts}


def scene_files(n_images: int, folders: tuple[str, ...] = ("images",),
                registered: int | None = None) -> dict[str, bytes]:
    """A scene's files by path inside it: ``n_images`` images in each folder, a model registering
    the first ``registered`` (default all) of them."""
    names = [f"frame_{i:05d}.jpg" for i in range(n_images)]
    jpg = tiny_jpeg()
    files = {f"{folder}/{n}": jpg for folder in folders for n in names}
    files.update({f"sparse/0/{k}": v for k, v in colmap_model(names[:registered or n_images]).items()})
    return files


def zip_bytes(scenes: dict[str, dict[str, bytes]]) -> bytes:
    """A zip of scene folders: prefix (``tandt/train/``, ``stump/``) -> that scene's files."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", zipfile.ZIP_STORED) as zf:
        for prefix, files in scenes.items():
            for rel, data in files.items():
                zf.writestr(prefix + rel, data)
    return buf.getvalue()


def tandt_db_zip() -> bytes:
    """tandt_db.zip as the 3DGS authors publish it: tandt/{train,truck}, db/{drjohnson,playroom},
    each with its real registered image count."""
    return zip_bytes({"tandt/train/": scene_files(301), "tandt/truck/": scene_files(251),
                      "db/drjohnson/": scene_files(263), "db/playroom/": scene_files(225)})


class Server:
    """``files``: name -> bytes, served at /<name>. ``cut_after``: name -> byte count at which the next
    answer for it is broken off (once). ``failing``: names answered 503. ``overstate``: name -> bytes a
    lying server adds to the file's size in every answer (Content-Length, Content-Range), sending only
    the real bytes; with ``honest_ranges`` it answers a range past the real end 416 with the real size
    (as a server whose full answers alone go through a broken proxy). ``requests`` records (path,
    Range, If-Range) of each GET."""

    def __init__(self, files: dict[str, bytes]):
        self.files = dict(files)
        self.cut_after: dict[str, int] = {}
        self.overstate: dict[str, int] = {}
        self.honest_ranges = False
        self.failing: set[str] = set()   # names answered 503 (a server failure), else 404 when absent
        self.requests: list[tuple[str, str | None, str | None]] = []
        server = self

        class Handler(BaseHTTPRequestHandler):
            def log_message(self, *args):   # keep the test output clean
                pass

            def do_GET(self):
                server._answer(self)

        self.httpd = ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.httpd.server_address[1]}"
        self.thread = threading.Thread(target=self.httpd.serve_forever, daemon=True)

    def etag(self, name: str) -> str:
        return '"' + hashlib.sha1(self.files[name]).hexdigest()[:16] + '"'

    def _answer(self, h: BaseHTTPRequestHandler) -> None:
        name = h.path.lstrip("/")
        rng, if_range = h.headers.get("Range"), h.headers.get("If-Range")
        self.requests.append((h.path, rng, if_range))
        if name not in self.files:
            h.send_error(503 if name in self.failing else 404)
            return
        data, start = self.files[name], 0
        size = len(data) + self.overstate.get(name, 0)   # the size the server claims
        m = re.fullmatch(r"bytes=(\d+)-", rng or "")
        if m and (if_range is None or if_range == self.etag(name)):
            start = int(m.group(1))
            end = len(data) if self.honest_ranges else size
            if start >= end:
                h.send_response(416)
                h.send_header("Content-Range", f"bytes */{end}")
                h.send_header("Content-Length", "0")
                h.end_headers()
                return
        h.send_response(206 if start else 200)
        if start:
            h.send_header("Content-Range", f"bytes {start}-{size - 1}/{size}")
        h.send_header("Content-Length", str(size - start))
        h.send_header("ETag", self.etag(name))
        h.end_headers()
        body = data[start:]
        cut = self.cut_after.pop(name, None)
        h.wfile.write(body if cut is None else body[:cut])
        if cut is not None:
            h.close_connection = True

    def __enter__(self) -> Server:
        self.thread.start()
        return self

    def __exit__(self, *exc) -> None:
        self.httpd.shutdown()
        self.httpd.server_close()
