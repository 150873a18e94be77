"""Videos: the encoder (PyAV, VP9 in WebM) keeps frame count and loses little; the frames of the
consistency metric are written in order whatever order they come in."""

from __future__ import annotations

import math

import numpy as np
import pytest

from smgs.io.video import VideoWriter, encoded_size, max_bytes_per_second, read_video, shrink


MIN_PSNR = 35.0   # the codec's loss a frame may carry (dB)


def psnr(a: np.ndarray, b: np.ndarray) -> float:
    mse = float(np.mean((np.asarray(a, np.float64) - np.asarray(b, np.float64)) ** 2))
    return math.inf if mse == 0 else 10 * math.log10(255.0 ** 2 / mse)


def smooth_frames(n: int, w: int, h: int) -> list[np.ndarray]:
    """A moving colour gradient with a soft disc: what a flythrough of a splat model looks like."""
    y, x = np.mgrid[0:h, 0:w] / max(w, h)
    out = []
    for k in range(n):
        d = np.exp(-((x - 0.3 - 0.02 * k) ** 2 + (y - 0.4) ** 2) / 0.02)
        img = np.stack([0.2 + 0.6 * x, 0.3 + 0.4 * y, 0.5 + 0.4 * d], -1)
        out.append((np.clip(img, 0, 1) * 255 + 0.5).astype(np.uint8))
    return out


# ---- the encoder --------------------------------------------------------------------------------

def test_a_video_keeps_every_frame_within_the_codecs_loss(tmp_path):
    frames = smooth_frames(20, 41, 30)
    with VideoWriter(tmp_path / "v.webm", 41, 30) as v:
        for f in frames:
            v.add(f)
        info = v.close()
    assert (info.width, info.height, info.scale) == encoded_size(41, 30) == (288, 210, 7)   # enlarged 7x, padded to even sides
    got, fps = read_video(tmp_path / "v.webm")
    assert len(got) == info.frames == 20 and fps == 30 and got[0].shape == (210, 288, 3)
    assert min(psnr(shrink(g, 41, 30), f) for g, f in zip(got, frames)) >= MIN_PSNR
    assert info.bytes == (tmp_path / "v.webm").stat().st_size
    assert info.bytes_per_second <= 1.2 * max_bytes_per_second(41, 30)   # the ceiling is on the average rate
    assert [p.name for p in tmp_path.iterdir()] == ["v.webm"]   # no temporary file left


def test_an_error_while_writing_leaves_the_previous_file(tmp_path):
    path = tmp_path / "v.webm"
    path.write_bytes(b"previous")
    with pytest.raises(ValueError, match=r"frame 1 is uint8 \(10, 10, 3\), expected uint8 \(30, 40, 3\)"):
        with VideoWriter(path, 40, 30) as v:
            v.add(smooth_frames(1, 40, 30)[0])
            v.add(np.zeros((10, 10, 3), np.uint8))
    assert path.read_bytes() == b"previous" and [p.name for p in tmp_path.iterdir()] == ["v.webm"]


def test_frames_given_out_of_order_are_written_in_order(tmp_path):
    from smgs.io.flythrough import ERRORS, FRAMES, FlythroughTap

    frames = [np.full((30, 40, 3), 20 * k, np.uint8) for k in range(6)]   # flat frames: 0, 20, 40, ...
    tap = FlythroughTap(tmp_path / "video", 6, 40, 30, step=2)
    for k in (0, 1, 2, 4, 3, 5):   # as the metric's window renders them
        tap.frame(k, frames[k].astype(np.float32) / 255)
        if k >= 2:   # the pair (k - 2, k), warped with a flow of zero
            tap.pair(k - 2, k, frames[k - 2] / 255.0, frames[k] / 255.0, np.ones((30, 40), bool))
    rec = tap.finish()
    assert rec["frames"] == 6 and rec["frames_file"] == f"video/{FRAMES}" and rec["error_file"] == f"video/{ERRORS}"
    got, _ = read_video(tmp_path / "video" / FRAMES)
    assert [round(float(g.mean()) / 20) for g in got] == [0, 1, 2, 3, 4, 5]
    errs, _ = read_video(tmp_path / "video" / ERRORS)
    assert len(errs) == 6 and float(errs[1][..., 1].mean()) < 12 and float(errs[5][..., 0].mean()) > 100   # red: error


def test_a_failure_to_write_stops_the_video_not_the_scoring(tmp_path, monkeypatch):
    from smgs.io.flythrough import FlythroughTap

    tap = FlythroughTap(tmp_path / "video", 4, 40, 30, step=2)
    tap.frame(0, np.zeros((30, 40, 3), np.float32))

    def full_disk(frame):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(tap.frames, "add", full_disk)
    for k in (1, 2, 3):
        tap.frame(k, np.zeros((30, 40, 3), np.float32))   # no error reaches the metric
    with pytest.raises(RuntimeError, match="could not be written .OSError: .Errno 28. No space left on device"):
        tap.finish()
    assert list((tmp_path / "video").iterdir()) == []
