"""Deterministic interpolated trajectories."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from smgs.camera import Camera
from smgs.metrics.consistency import Trajectory, frame_pairs, interpolate_trajectory
from smgs.data.trajectory import quat_to_rotmat, rotation_angle_deg, rotmat_to_quat


def orbit(deg: float, r: float = 3.0, w: int = 40, h: int = 30) -> Camera:
    th = math.radians(deg)
    return Camera.look_at([r * math.sin(th), 0.3, -r * math.cos(th)], [0, 0, 0], [0, -1, 0], 30, 30, w, h)


def test_frame_count_endpoints_and_slerp():
    targets = [orbit(0), orbit(20), orbit(50)]
    tr = interpolate_trajectory(targets, n_between=128)
    assert len(tr) == 2 * 129 + 1 and not tr.dropped
    for frame, k in ((tr.frames[0], 0), (tr.frames[129], 1), (tr.frames[-1], 2)):
        np.testing.assert_allclose(frame.viewmat, targets[k].viewmat.double().numpy(), atol=1e-6)
    # slerp: equal rotation steps within a segment; centres on the chord (lerp)
    R = [f.viewmat[:3, :3] for f in tr.frames[:130]]
    steps = [rotation_angle_deg(a, b) for a, b in zip(R, R[1:])]
    assert max(steps) - min(steps) < 1e-6 and sum(steps) == pytest.approx(
        rotation_angle_deg(R[0], R[-1]), abs=1e-6)
    mid = tr.frames[64]
    c0, c1 = tr.frames[0].center, tr.frames[129].center
    np.testing.assert_allclose(mid.center, c0 + mid.t * (c1 - c0), atol=1e-9)
    cams = tr.cameras()
    assert cams[5].width == 40 and torch.allclose(cams[5].K, targets[0].K)


def test_quaternion_roundtrip_including_half_turns():
    rng = np.random.default_rng(0)
    mats = [quat_to_rotmat(q) for q in rng.normal(size=(50, 4))]
    mats += [np.diag([1.0, -1, -1]), np.diag([-1.0, 1, -1]), np.diag([-1.0, -1, 1])]
    for R in mats:
        np.testing.assert_allclose(quat_to_rotmat(rotmat_to_quat(R)), R, atol=1e-12)


def test_static_frames_dropped_and_json_roundtrip(tmp_path):
    targets = [orbit(0), orbit(10), orbit(10), orbit(25)]  # a repeated target: a static segment
    tr = interpolate_trajectory(targets, n_between=8)
    # target 1 is kept once; the 8 inserted copies and target 2 (= target 1) are dropped
    assert [(d["segment"], round(d["t"] * 9)) for d in tr.dropped] == [(1, j) for j in range(1, 9)] + [(2, 0)]
    assert len(tr) == 3 * 9 + 1 - 9
    assert len(interpolate_trajectory(targets, n_between=8, drop_static=False)) == 28
    again = interpolate_trajectory(targets, n_between=8)
    assert again.to_json() == tr.to_json()  # deterministic
    path = tmp_path / "trajectory.json"
    tr.save(path)
    back = Trajectory.load(path)
    assert back.to_json() == tr.to_json()
    assert torch.equal(back.cameras()[3].viewmat, tr.cameras()[3].viewmat)


def test_errors_and_pairs():
    with pytest.raises(ValueError, match="two target"):
        interpolate_trajectory([orbit(0)])
    with pytest.raises(ValueError, match="size"):
        interpolate_trajectory([orbit(0), orbit(5, w=41)])
    assert frame_pairs(10, 7) == [(0, 7), (1, 8), (2, 9)]
    assert frame_pairs(5, 7) == []
