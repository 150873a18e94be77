"""Videos a browser plays, written and read with PyAV (the ``av`` package: FFmpeg bound for Python, its
wheel bundles FFmpeg with libvpx).

VP9 in WebM, 4:2:0 (VP9 profile 0): what a stock Chromium and Firefox decode without proprietary
codecs (Debian's chromium has no H.264), hardware decoders too. Frames go in as 8-bit RGB exactly as
given; the codec's loss is the only change. 4:2:0 keeps one colour sample per 2x2 pixels, which
blurs the colour of a one-pixel edge: a frame narrower than ``MIN_WIDTH`` is enlarged by an integer
factor (each pixel a k x k block, no new values) so that every rendered pixel keeps its own colour.

Size is bounded: quality-targeted (``CRF``) with a ceiling of ``MAX_BITS_PER_PIXEL`` bits per encoded
pixel per frame on the average bitrate (``max_bytes_per_second``). A file appears complete or not at
all (``smgs.atomic.atomic_file``).
"""

from __future__ import annotations

import contextlib
import math
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from smgs.atomic import atomic_file

CODEC = "libvpx-vp9"
CONTAINER = "webm"
PIX_FMT = "yuv420p"
FPS = 30
CRF = 28                   # libvpx's constant-quality level (0-63, lower is better)
MAX_BITS_PER_PIXEL = 0.3   # the ceiling on the average bitrate, per encoded pixel and frame
MIN_WIDTH = 256            # narrower frames are enlarged by an integer factor (module docstring)
# libvpx's realtime mode at cpu-used 6: 5-8x faster than its "good" mode at cpu-used 5 on a smoke run's
# frames, for ~0.7 dB less at the same size (docs/usage.md#videos)
DEADLINE, SPEED = "realtime", 6
DESCRIPTION = (f"VP9 (libvpx, {DEADLINE}, cpu-used {SPEED}) in WebM, {PIX_FMT}, crf {CRF}, at most "
               f"{MAX_BITS_PER_PIXEL} bit per pixel per frame, {FPS} fps")


def video_unavailable() -> str | None:
    """Why no video can be written here (None when it can): PyAV missing, or its FFmpeg without VP9."""
    try:
        import av
    except ImportError as e:
        return f"PyAV is not installed ({e}); pip install av"
    try:
        av.codec.Codec(CODEC, "w")
    except Exception as e:  # noqa: BLE001 - av raises its own error classes
        return f"this PyAV's FFmpeg has no {CODEC} encoder ({type(e).__name__}: {e})"
    return None


def enlargement(width: int) -> int:
    """The integer factor a frame ``width`` px wide is enlarged by (1 at ``MIN_WIDTH`` and above)."""
    return max(1, math.ceil(MIN_WIDTH / max(1, int(width))))


def encoded_size(width: int, height: int) -> tuple[int, int, int]:
    """(width, height, factor) of the encoded picture: enlarged, then padded to even sides (4:2:0)."""
    k = enlargement(width)
    return (width * k + 1) // 2 * 2, (height * k + 1) // 2 * 2, k


def max_bytes_per_second(width: int, height: int, fps: int = FPS) -> float:
    """The ceiling on the average bytes per second of a video whose frames are ``width`` x ``height``."""
    w, h, _ = encoded_size(width, height)
    return MAX_BITS_PER_PIXEL * w * h * fps / 8


@dataclass(frozen=True)
class VideoInfo:
    """What was written: the file, its frames and picture, and what it cost."""

    path: str
    frames: int
    fps: int
    width: int           # of the encoded picture
    height: int
    source_width: int    # of the frames given
    source_height: int
    scale: int           # the enlargement factor
    bytes: int
    seconds: float       # spent encoding and writing

    @property
    def bytes_per_second(self) -> float:
        return self.bytes * self.fps / max(1, self.frames)

    def to_json(self) -> dict:
        return {**asdict(self), "bytes_per_second": self.bytes_per_second, "codec": DESCRIPTION}


class VideoWriter:
    """Frames in order (``add``), a file at ``close``; used as a context manager, an error inside the
    block leaves no file (a previous one stays as it was)."""

    def __init__(self, path: Path | str, width: int, height: int, fps: int = FPS) -> None:
        import av

        why = video_unavailable()
        if why:
            raise RuntimeError(why)
        self.path, self.fps = Path(path), int(fps)
        self.source = (int(width), int(height))
        self.width, self.height, self.scale = encoded_size(width, height)
        self.frames, self.seconds = 0, 0.0
        self._stack = contextlib.ExitStack()
        t0 = time.perf_counter()
        self._file = self._stack.enter_context(atomic_file(self.path))
        self._out = av.open(self._file, "w", format=CONTAINER)
        self._stream = self._out.add_stream(CODEC, rate=self.fps)
        self._stream.width, self._stream.height, self._stream.pix_fmt = self.width, self.height, PIX_FMT
        self._stream.bit_rate = int(max_bytes_per_second(width, height, self.fps) * 8)
        self._stream.options = {"crf": str(CRF), "deadline": DEADLINE, "cpu-used": str(SPEED), "row-mt": "1"}
        self.seconds += time.perf_counter() - t0

    def picture(self, frame: np.ndarray) -> np.ndarray:
        """A [H, W, 3] uint8 frame as encoded: enlarged, the padding a copy of the last row/column."""
        if frame.dtype != np.uint8 or frame.shape != (self.source[1], self.source[0], 3):
            raise ValueError(f"{self.path.name}: frame {self.frames} is {frame.dtype} {frame.shape}, expected "
                             f"uint8 ({self.source[1]}, {self.source[0]}, 3)")
        k = self.scale
        big = frame.repeat(k, 0).repeat(k, 1) if k > 1 else frame
        pad_h, pad_w = self.height - big.shape[0], self.width - big.shape[1]
        return np.pad(big, ((0, pad_h), (0, pad_w), (0, 0)), mode="edge") if pad_h or pad_w else big

    def add(self, frame: np.ndarray) -> None:
        import av

        t0 = time.perf_counter()
        pic = av.VideoFrame.from_ndarray(np.ascontiguousarray(self.picture(frame)), format="rgb24")
        for packet in self._stream.encode(pic):
            self._out.mux(packet)
        self.frames += 1
        self.seconds += time.perf_counter() - t0

    def close(self) -> VideoInfo:
        t0 = time.perf_counter()
        if self.frames == 0:
            self.abort()
            raise ValueError(f"{self.path}: no frame was given; no video written")
        for packet in self._stream.encode():
            self._out.mux(packet)
        self._out.close()
        self._stack.close()   # the file is complete: it replaces the target now
        self.seconds += time.perf_counter() - t0
        return VideoInfo(str(self.path), self.frames, self.fps, self.width, self.height, *self.source, self.scale,
                         self.path.stat().st_size, self.seconds)

    def abort(self) -> None:
        """Stop without a file (the temporary one is removed)."""
        with contextlib.suppress(Exception):
            self._out.close()
        with contextlib.suppress(_Aborted):
            self._stack.__exit__(_Aborted, _Aborted(), None)

    def __enter__(self) -> "VideoWriter":
        return self

    def __exit__(self, kind, *_) -> None:
        if kind is not None:
            self.abort()


class _Aborted(Exception):
    """Raised into ``atomic_file`` so that it removes its temporary file."""


def read_video(path: Path | str) -> tuple[list[np.ndarray], float]:
    """Every frame of a video decoded as [H, W, 3] uint8 RGB, and its frame rate."""
    import av

    with av.open(str(path)) as f:
        stream = f.streams.video[0]
        frames = [fr.to_ndarray(format="rgb24") for fr in f.decode(stream)]
        return frames, float(stream.average_rate or stream.guessed_rate or 0)


def shrink(picture: np.ndarray, width: int, height: int) -> np.ndarray:
    """A decoded picture back at the frames' size: the padding cut, each k x k block averaged."""
    k = enlargement(width)
    crop = picture[:height * k, :width * k].astype(np.float64)
    return crop.reshape(height, k, width, k, 3).mean(axis=(1, 3))
