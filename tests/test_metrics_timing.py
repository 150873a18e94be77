"""Render FPS, peak memory and train-time accounting."""

from __future__ import annotations

import time

import numpy as np
import pytest

from smgs.metrics.timing import TrainClock, device_name, measure_render_fps, track_peak_memory


def test_fps_median_warmup_and_device():
    calls = []

    def render(cam):
        calls.append(cam)
        time.sleep(0.03 if len(calls) <= 2 else 0.004)  # slow first calls are the warm-up

    res = measure_render_fps(render, ["a", "b"], warmup=2, repeats=3)
    assert len(calls) == 2 + 3 * 2
    assert 0.004 <= res.median_seconds_per_view < 0.02
    assert res.fps == pytest.approx(1 / res.median_seconds_per_view)
    assert res.device.startswith("cpu:") and res.n_views == 2 and len(res.seconds_per_view) == 3
    with pytest.raises(ValueError):
        measure_render_fps(render, [])


def test_peak_memory_sees_a_large_allocation():
    with track_peak_memory("cpu") as pm:
        a = np.ones(200 * 2**20 // 8)  # 200 MiB touched
        a.sum()
        del a
    assert pm.kind.startswith("cpu_peak_rss")
    assert pm.mib > 200
    if pm.kind == "cpu_peak_rss_vmhwm_reset":
        with track_peak_memory("cpu") as small:
            np.ones(1000).sum()
        assert small.bytes < pm.bytes - 150 * 2**20  # the reset forgets the earlier peak


def test_train_clock_excludes_evaluation():
    clock = TrainClock()
    with clock.training():
        time.sleep(0.02)
    with clock.exclude("eval"):
        time.sleep(0.05)
    with clock.training():
        time.sleep(0.02)
    assert 0.04 <= clock.seconds < 0.07
    assert clock.excluded["eval"] >= 0.05
    assert clock.to_json()["device"] == device_name("cpu")
