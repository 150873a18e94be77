"""A run's flythrough videos, made during its view-consistency scoring from the frames the metric
renders (``smgs.io.flythrough``): ``RUN_DIR/video/`` holds them, results.json's ``consistency.video``
records the files, their frames, size and what encoding cost, or ``{"missing": why}``.
"""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Sequence

from protocols.sections import EvalConfig
from smgs.metrics.result import Missing

VIDEO_DIR = "video"
TRAJECTORY_FILE = "trajectory.json"
BETWEEN = 128   # frames between consecutive test cameras (paper supp. Sec. 7)


def video_cameras(cameras: Sequence, max_width: int | None) -> list:
    """The trajectory's cameras as the consistency video renders them: at most ``max_width`` wide
    (``eval.consistency_max_width``; FLIP and flow cost grows with the image)."""
    cams = list(cameras)
    if max_width and cams and cams[0].width > max_width:
        cams = [c.scaled(max_width / c.width) for c in cams]
    return cams


def save_trajectory(run_dir: Path, scene) -> list:
    """The cameras of the run's view-consistency path, saved as ``RUN_DIR/trajectory.json``: the
    scene's own (``"source": "scene"``), else ``BETWEEN`` frames between consecutive test cameras
    (``smgs.data.trajectory.Trajectory``); ``read_trajectory`` reads it back."""
    import json

    from smgs.atomic import atomic_write_text
    from smgs.data.trajectory import interpolate_trajectory

    if scene.trajectory:
        cams = list(scene.trajectory)
        atomic_write_text(run_dir / TRAJECTORY_FILE, json.dumps(
            {"source": "scene", "cameras": [{"K": c.K.tolist(), "viewmat": c.viewmat.tolist(),
                                             "width": c.width, "height": c.height} for c in cams]}))
        return cams
    traj = interpolate_trajectory([v.camera for v in scene.test], BETWEEN)
    traj.save(run_dir / TRAJECTORY_FILE)
    return traj.cameras()


def read_trajectory(path: Path) -> list:
    """The cameras of a run's ``trajectory.json`` (``save_trajectory``): a scene's own path
    (``"source": "scene"``) or an interpolated one (``smgs.data.trajectory.Trajectory``)."""
    import json

    from smgs.camera import Camera
    from smgs.data.trajectory import Trajectory

    try:
        d = json.loads(Path(path).read_text())
        if d.get("source") == "scene":
            return [Camera(c["K"], c["viewmat"], int(c["width"]), int(c["height"])) for c in d["cameras"]]
        return Trajectory.from_json(d).cameras()
    except (OSError, ValueError, KeyError, TypeError) as e:
        raise ValueError(f"{path}: not a readable trajectory ({type(e).__name__}: {e})") from None


def start_video(run_dir: Path, cameras: Sequence, step: int, ev: EvalConfig):
    """(the tap that writes the run's videos, "") or (None, why the run has no video)."""
    if not ev.save_renders:
        return None, "eval.save_renders=false: the run saves no renders and no video"
    from smgs.io.flythrough import FlythroughTap
    from smgs.io.video import video_unavailable

    why = video_unavailable()
    if why:
        return None, why
    return FlythroughTap(run_dir / VIDEO_DIR, len(cameras), cameras[0].width, cameras[0].height, step), ""


def end_video(tap, why: str, log: logging.Logger) -> dict:
    """What results.json records of the run's videos (closing them)."""
    if tap is None:
        return Missing(why).to_json()
    try:
        rec = tap.finish()
    except (OSError, ValueError, RuntimeError) as e:   # the scores stand without their video
        log.warning("video not written: %s", e)
        return Missing(f"not written: {type(e).__name__}: {e}").to_json()
    log.info("video: %d frames, %d x %d (x%d), %.0f kB (%.1f kB/s), %.2f s to encode (%s)", rec["frames"],
             rec["width"], rec["height"], rec["scale"], rec["bytes"] / 1e3, rec["bytes_per_second"] / 1e3,
             rec["seconds"], rec["codec"])
    return rec
