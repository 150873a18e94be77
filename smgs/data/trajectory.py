"""Deterministic video trajectories between target cameras (Softmax-GS supplement, Sec. 7).

``n_between`` (paper: 128) frames are inserted between each pair of consecutive target cameras:
the camera centre is interpolated linearly, the rotation by slerp, the intrinsics linearly (all
targets must share the image size). Near-static frames are dropped, as StopThePop removed
consecutive frames without camera motion by hand (r4dl/StopThePop#3); here the rule is on the
pose, so every method is scored on the same frames. The trajectory is saved as JSON beside the
results so the numbers can be reproduced.
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Sequence

import numpy as np
import torch

from smgs.camera import Camera
from smgs.atomic import atomic_write_text

TRAJECTORY_FORMAT = "smgs-trajectory-v1"


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotation matrix -> unit quaternion (w, x, y, z), w >= 0 (Shepperd's branch choice)."""
    R = np.asarray(R, dtype=np.float64)
    tr = np.trace(R)
    if tr > 0:
        s = 2.0 * math.sqrt(1.0 + tr)
        q = [0.25 * s, (R[2, 1] - R[1, 2]) / s, (R[0, 2] - R[2, 0]) / s, (R[1, 0] - R[0, 1]) / s]
    elif R[0, 0] > R[1, 1] and R[0, 0] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[0, 0] - R[1, 1] - R[2, 2])
        q = [(R[2, 1] - R[1, 2]) / s, 0.25 * s, (R[0, 1] + R[1, 0]) / s, (R[0, 2] + R[2, 0]) / s]
    elif R[1, 1] > R[2, 2]:
        s = 2.0 * math.sqrt(1.0 + R[1, 1] - R[0, 0] - R[2, 2])
        q = [(R[0, 2] - R[2, 0]) / s, (R[0, 1] + R[1, 0]) / s, 0.25 * s, (R[1, 2] + R[2, 1]) / s]
    else:
        s = 2.0 * math.sqrt(1.0 + R[2, 2] - R[0, 0] - R[1, 1])
        q = [(R[1, 0] - R[0, 1]) / s, (R[0, 2] + R[2, 0]) / s, (R[1, 2] + R[2, 1]) / s, 0.25 * s]
    q = np.array(q)
    q /= np.linalg.norm(q)
    return -q if q[0] < 0 else q


def quat_to_rotmat(q: np.ndarray) -> np.ndarray:
    w, x, y, z = np.asarray(q, dtype=np.float64) / np.linalg.norm(q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
                     [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
                     [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)]])


def slerp(q0: np.ndarray, q1: np.ndarray, t: float) -> np.ndarray:
    """Shortest-arc spherical interpolation of unit quaternions."""
    d = float(np.dot(q0, q1))
    if d < 0:  # q and -q are the same rotation: take the short way round
        q1, d = -q1, -d
    if d > 0.9995:  # nearly parallel: lerp is exact to float precision and avoids 0/0
        q = q0 + t * (q1 - q0)
        return q / np.linalg.norm(q)
    th = math.acos(min(1.0, d))
    return (math.sin((1 - t) * th) * q0 + math.sin(t * th) * q1) / math.sin(th)


def rotation_angle_deg(R0: np.ndarray, R1: np.ndarray) -> float:
    c = (np.trace(R0.T @ R1) - 1.0) / 2.0
    return math.degrees(math.acos(max(-1.0, min(1.0, c))))


@dataclass
class TrajectoryFrame:
    K: np.ndarray  # [3, 3]
    viewmat: np.ndarray  # [4, 4] world-to-camera
    width: int
    height: int
    segment: int  # between targets ``segment`` and ``segment + 1``
    t: float  # position within the segment, [0, 1]

    def camera(self) -> Camera:
        return Camera(torch.from_numpy(self.K).float(), torch.from_numpy(self.viewmat).float(),
                      self.width, self.height)

    @property
    def center(self) -> np.ndarray:
        R, tv = self.viewmat[:3, :3], self.viewmat[:3, 3]
        return -R.T @ tv

    def to_json(self) -> dict:
        return {"K": self.K.tolist(), "viewmat": self.viewmat.tolist(), "width": self.width,
                "height": self.height, "segment": self.segment, "t": self.t}

    @staticmethod
    def from_json(d: dict) -> "TrajectoryFrame":
        return TrajectoryFrame(np.array(d["K"], dtype=np.float64), np.array(d["viewmat"], dtype=np.float64),
                               int(d["width"]), int(d["height"]), int(d["segment"]), float(d["t"]))


@dataclass
class Trajectory:
    frames: list[TrajectoryFrame]
    n_targets: int
    n_between: int
    dropped: list[dict] = field(default_factory=list)  # {"segment", "t", "translation", "rotation_deg"}
    static_tolerance: dict = field(default_factory=dict)

    def __len__(self) -> int:
        return len(self.frames)

    def cameras(self) -> list[Camera]:
        return [f.camera() for f in self.frames]

    def to_json(self) -> dict:
        return {"format": TRAJECTORY_FORMAT, "n_targets": self.n_targets, "n_between": self.n_between,
                "static_tolerance": self.static_tolerance, "dropped": self.dropped,
                "frames": [f.to_json() for f in self.frames]}

    @staticmethod
    def from_json(d: dict) -> "Trajectory":
        if d.get("format") != TRAJECTORY_FORMAT:
            raise ValueError(f"not a {TRAJECTORY_FORMAT} trajectory (format={d.get('format')!r})")
        return Trajectory([TrajectoryFrame.from_json(f) for f in d["frames"]], int(d["n_targets"]),
                          int(d["n_between"]), list(d.get("dropped", [])), dict(d.get("static_tolerance", {})))

    def save(self, path: str | Path) -> None:
        path = Path(path)
        atomic_write_text(path, json.dumps(self.to_json()) + "\n")

    @staticmethod
    def load(path: str | Path) -> "Trajectory":
        return Trajectory.from_json(json.loads(Path(path).read_text()))


def _pose(cam: Camera) -> tuple[np.ndarray, np.ndarray]:
    """(camera-to-world rotation, camera centre) in float64."""
    V = cam.viewmat.detach().double().cpu().numpy()
    R = V[:3, :3]
    return R.T, -R.T @ V[:3, 3]


def interpolate_trajectory(targets: Sequence[Camera], n_between: int = 128, *, drop_static: bool = True,
                           static_fraction: float = 0.05, min_translation: float = 1e-9,
                           min_rotation_deg: float = 1e-6) -> Trajectory:
    """Frames ``targets[0], n_between inserted frames, targets[1], …, targets[-1]``.

    A frame is near-static, and dropped, when its motion since the last kept frame is at most
    ``static_fraction`` × the median per-frame motion of the whole trajectory (or the absolute
    floors ``min_translation`` / ``min_rotation_deg``, whichever is larger) in translation *and*
    in rotation. The first frame is always kept.
    """
    if len(targets) < 2:
        raise ValueError(f"a trajectory needs at least two target cameras, got {len(targets)}")
    if n_between < 0:
        raise ValueError(f"n_between must be >= 0, got {n_between}")
    w, h = targets[0].width, targets[0].height
    for k, c in enumerate(targets):
        if (c.width, c.height) != (w, h):
            raise ValueError(f"target {k} is {c.width}x{c.height}, target 0 is {w}x{h}; "
                             "resize the cameras to one size first (Camera.scaled)")
    poses = [_pose(c) for c in targets]
    quats = [rotmat_to_quat(R) for R, _ in poses]
    Ks = [c.K.detach().double().cpu().numpy() for c in targets]
    raw: list[TrajectoryFrame] = []
    steps = n_between + 1
    for k in range(len(targets) - 1):
        last = k == len(targets) - 2
        for j in range(steps + (1 if last else 0)):
            t = j / steps
            R = quat_to_rotmat(slerp(quats[k], quats[k + 1], t))
            c = (1 - t) * poses[k][1] + t * poses[k + 1][1]
            V = np.eye(4)
            V[:3, :3] = R.T
            V[:3, 3] = -R.T @ c
            raw.append(TrajectoryFrame((1 - t) * Ks[k] + t * Ks[k + 1], V, w, h, k, t))
    tol: dict = {}
    if not drop_static:
        return Trajectory(raw, len(targets), n_between, [], {"drop_static": False})
    trans = [float(np.linalg.norm(b.center - a.center)) for a, b in zip(raw, raw[1:])]
    rots = [rotation_angle_deg(a.viewmat[:3, :3], b.viewmat[:3, :3]) for a, b in zip(raw, raw[1:])]
    tol_t = max(min_translation, static_fraction * float(np.median(trans)))
    tol_r = max(min_rotation_deg, static_fraction * float(np.median(rots)))
    tol = {"drop_static": True, "translation": tol_t, "rotation_deg": tol_r,
           "static_fraction": static_fraction}
    kept, dropped = [raw[0]], []
    for f in raw[1:]:
        dt = float(np.linalg.norm(f.center - kept[-1].center))
        dr = rotation_angle_deg(kept[-1].viewmat[:3, :3], f.viewmat[:3, :3])
        if dt <= tol_t and dr <= tol_r:
            dropped.append({"segment": f.segment, "t": f.t, "translation": dt, "rotation_deg": dr})
        else:
            kept.append(f)
    return Trajectory(kept, len(targets), n_between, dropped, tol)


def frame_pairs(n_frames: int, step: int) -> list[tuple[int, int]]:
    """(i, i + step) for every i with both frames in range (StopThePop's ``--step``)."""
    if step < 1:
        raise ValueError(f"step must be >= 1, got {step}")
    return [(i, i + step) for i in range(max(0, n_frames - step))]
