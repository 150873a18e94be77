"""A run's flythrough as videos made from the frames the view-consistency metric renders anyway
(``smgs.metrics.consistency.score.FrameTap``): nothing is rendered again.

Two videos of the same frames, in step (``smgs.io.video``):
- ``FRAMES``: the trajectory's frames exactly as scored (8-bit, as the metric quantised them);
- ``ERRORS``: frame j dimmed, with the flow-warped error of the pair (j − step, j) over it: the mean
  over RGB of |frame j − step warped onto j − frame j| on the error maps' one scale
  (``smgs.metrics.image.heat_colors``: black 0 → red → yellow → white at ≥ ``ERROR_MAP_VMAX``);
  pixels outside the scored mask (occluded, out of view, the border) darker and without colour; the
  first ``step`` frames, which end no pair, dimmed only.
Each has a poster: its first frame as PNG (lossless).
"""

from __future__ import annotations

import io
import time
from pathlib import Path

import numpy as np
from PIL import Image

from smgs.atomic import atomic_write_bytes
from smgs.io.video import DESCRIPTION, FPS, VideoWriter
from smgs.metrics.image import ERROR_MAP_VMAX, heat_colors

FRAMES, ERRORS = "trajectory.webm", "trajectory_error.webm"
POSTER, ERROR_POSTER = "poster.png", "poster_error.png"
DIM = 0.4         # the frame's brightness under the error map
UNSCORED = 0.15   # its brightness where no error is scored


def to_uint8(rgb: np.ndarray) -> np.ndarray:
    """A frame in [0, 1] as 8-bit (exact for a frame of 8-bit values, as the metric quantises them)."""
    return np.clip(np.rint(np.asarray(rgb, dtype=np.float32) * np.float32(255)), 0, 255).astype(np.uint8)


def error_overlay(frame: np.ndarray, err: np.ndarray | None = None, valid: np.ndarray | None = None) -> np.ndarray:
    """The uint8 frame dimmed, with the error map ``err`` [H, W] over it where ``valid``."""
    f = frame.astype(np.float32) * np.float32(1 / 255)
    if err is None:
        return to_uint8(f * np.float32(DIM))
    shown = f * np.float32(DIM) + heat_colors(err.astype(np.float32), ERROR_MAP_VMAX)
    return to_uint8(np.where(valid[..., None], shown, f * np.float32(UNSCORED)))


def _png(img: np.ndarray) -> bytes:
    buf = io.BytesIO()
    Image.fromarray(img).save(buf, format="PNG")
    return buf.getvalue()


class FlythroughTap:
    """A ``FrameTap`` that writes the two videos of one method into ``folder`` as its frames come
    (rendered out of order, written in order; a few frames are held). ``finish`` closes them and
    returns what results.json records; ``abort`` leaves no file. A failure to encode or write (a full
    disk) never stops the scoring: the tap stops, and ``finish`` raises with the reason."""

    def __init__(self, folder: Path | str, n_frames: int, width: int, height: int, step: int, fps: int = FPS) -> None:
        t0 = time.perf_counter()
        self.folder, self.n, self.step = Path(folder), int(n_frames), int(step)
        self.frames = VideoWriter(self.folder / FRAMES, width, height, fps)
        self.errors = VideoWriter(self.folder / ERRORS, width, height, fps)
        self.held: dict[int, np.ndarray] = {}               # frames not yet in both videos
        self.maps: dict[int, tuple[np.ndarray, np.ndarray]] = {}   # pair (j - step, j)'s error and mask, by j
        self.next_frame = self.next_error = 0
        self.posters: dict[str, np.ndarray] = {}             # written with the videos, at the end
        self.failed = ""
        self.seconds = time.perf_counter() - t0

    def frame(self, k: int, rgb: np.ndarray) -> None:
        if self.failed:
            return
        t0 = time.perf_counter()
        self.held[k] = to_uint8(rgb)
        self._flush()
        self.seconds += time.perf_counter() - t0

    def pair(self, i: int, j: int, warped: np.ndarray, target: np.ndarray, valid: np.ndarray) -> None:
        if j - i != self.step or self.failed:
            return
        t0 = time.perf_counter()
        err = np.abs(np.clip(warped, 0.0, 1.0, dtype=np.float32) - target).mean(-1, dtype=np.float32)
        self.maps[j] = (err, np.asarray(valid, dtype=bool))
        self._flush()
        self.seconds += time.perf_counter() - t0

    def _flush(self) -> None:
        try:
            self._write_ready()
        except Exception as e:  # noqa: BLE001 - OSError, PyAV's errors: the scores go on without a video
            self.failed = f"{type(e).__name__}: {e}"
            self.abort()

    def _write_ready(self) -> None:
        while self.next_frame in self.held:
            k = self.next_frame
            self.frames.add(self.held[k])
            if k == 0:
                self.posters[POSTER] = self.held[0]
            self.next_frame += 1
        while self.next_error < self.next_frame and (self.next_error < self.step or self.next_error in self.maps):
            j = self.next_error
            err, valid = self.maps.pop(j, (None, None))
            pic = error_overlay(self.held.pop(j), err, valid)
            self.errors.add(pic)
            if j == 0:
                self.posters[ERROR_POSTER] = pic
            self.next_error += 1

    def finish(self) -> dict:
        """Close both videos; what results.json records (the files relative to the run directory's
        parent of ``folder``: ``<folder name>/<file>``)."""
        t0 = time.perf_counter()
        if self.failed:
            raise RuntimeError(f"the video could not be written ({self.failed})")
        if self.next_frame != self.n or self.next_error != self.n:
            self.abort()
            raise ValueError(f"the metric gave {self.next_frame} frames and {self.next_error} error maps in order, "
                             f"of the trajectory's {self.n}: no video written")
        a, b = self.frames.close(), self.errors.close()
        for name, pic in self.posters.items():
            atomic_write_bytes(self.folder / name, _png(pic))
        self.seconds += time.perf_counter() - t0
        rel = self.folder.name
        return {"frames_file": f"{rel}/{FRAMES}", "error_file": f"{rel}/{ERRORS}", "poster": f"{rel}/{POSTER}",
                "error_poster": f"{rel}/{ERROR_POSTER}", "frames": a.frames, "fps": a.fps, "width": a.width,
                "height": a.height, "source_width": a.source_width, "source_height": a.source_height,
                "scale": a.scale, "step": self.step, "bytes": a.bytes + b.bytes,
                "bytes_per_second": a.bytes_per_second + b.bytes_per_second, "seconds": self.seconds,
                "encode_seconds": a.seconds + b.seconds, "codec": DESCRIPTION, "error_vmax": ERROR_MAP_VMAX}

    def abort(self) -> None:
        self.frames.abort()
        self.errors.abort()
