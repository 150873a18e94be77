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

    res = measure_render_fps(render, ["a", "b"], warmup=2, repeats=3, device="cpu")
    assert len(calls) == 2 + 3 * 2
    assert 0.004 <= res.median_seconds_per_view < 0.02
    assert res.fps == pytest.approx(1 / res.median_seconds_per_view)
    assert res.device.startswith("cpu ") and res.n_views == 2 and len(res.seconds_per_view) == 3
    with pytest.raises(ValueError):
        measure_render_fps(render, [], device="cpu")


# The peak-memory checks run in a fresh interpreter: the pytest process has run everything before
# them (it holds ~900 MiB in a full suite, some of it freed memory the allocator keeps resident), so
# its resident size says nothing certain about one 200 MiB array. A child starts from the interpreter
# and numpy alone, whatever ran before.
_PROBE = """
import json, sys
import numpy as np
from smgs.metrics.timing import track_peak_memory
if sys.argv[1] == "retained":
    # glibc keeps freed heap memory resident: raise the mmap threshold (free a 30 MiB mapping), fill
    # the heap with 2 MiB arrays, pin its top, free the arrays: ~600 MiB free but resident
    a = np.ones(30 * 2**20 // 8); del a
    keep = [np.ones(2 * 2**20 // 8) for _ in range(300)]
    pin = np.ones(2**20 // 8)
    del keep
with track_peak_memory("cpu") as pm:
    a = np.ones(200 * 2**20 // 8)  # 200 MiB touched
    a.sum()
    del a
with track_peak_memory("cpu") as small:
    np.ones(1000).sum()
print(json.dumps({"kind": pm.kind, "big": pm.bytes, "big_base": pm.baseline_bytes, "small": small.bytes}))
"""


def _probe_in_child(scenario: str) -> dict:
    import json
    import subprocess
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    out = subprocess.run([sys.executable, "-c", _PROBE, scenario], cwd=root, capture_output=True, text=True,
                         timeout=120, env={**__import__("os").environ, "PYTHONPATH": str(root)})
    assert out.returncode == 0, out.stderr
    return json.loads(out.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("scenario", ["fresh", "retained"])
def test_peak_memory_sees_a_large_allocation(scenario):
    """The block's 200 MiB show in its peak, and the next block's reset forgets them; also after the
    process freed ~600 MiB that glibc kept resident ("retained": without the probe's malloc_trim the
    array is served from those pages and both peaks equal the resident size at entry)."""
    r = _probe_in_child(scenario)
    assert r["kind"].startswith("cpu_peak_rss")
    assert r["big"] > 200 * 2**20
    if r["kind"] == "cpu_peak_rss_vmhwm_reset":
        assert r["big"] - r["big_base"] > 190 * 2**20   # the increment is the array's
        assert r["small"] < r["big"] - 150 * 2**20      # the reset forgets the earlier peak


def test_train_clock_excludes_evaluation():
    # Bounds from the blocks' own durations, not from the sleeps' nominal lengths: on a loaded
    # machine a 20 ms sleep can take 100 ms, and the clock must still count exactly its blocks.
    clock = TrainClock("cpu")
    spans = []
    for block, nap in ((clock.training, 0.02), (lambda: clock.exclude("eval"), 0.05), (clock.training, 0.02)):
        t0 = time.perf_counter()
        with block():
            time.sleep(nap)
        spans.append(time.perf_counter() - t0)
    assert 0.04 <= clock.seconds <= spans[0] + spans[2]
    assert 0.05 <= clock.excluded["eval"] <= spans[1]
    assert clock.seconds < spans[0] + spans[1] + spans[2] - clock.excluded["eval"] + 1e-9
    assert clock.to_json()["device"] == device_name("cpu")


def test_cuda_timing_synchronises_and_peak_memory_is_max_memory_allocated(monkeypatch):
    """On a CUDA device the clock and the FPS probe synchronise that device around each timed block
    (queued kernels are charged to the block), and peak memory is torch.cuda.max_memory_allocated
    after a reset; checked here with torch.cuda's calls recorded instead of a GPU."""
    import torch

    calls = []
    monkeypatch.setattr(torch.cuda, "synchronize", lambda d=None: calls.append(("sync", str(d))))
    monkeypatch.setattr(torch.cuda, "reset_peak_memory_stats", lambda d=None: calls.append(("reset", str(d))))
    monkeypatch.setattr(torch.cuda, "max_memory_allocated", lambda d=None: calls.append(("max", str(d))) or 123)
    monkeypatch.setattr(torch.cuda, "current_device", lambda: 0)
    monkeypatch.setattr(torch.cuda, "get_device_name", lambda d=None: "NVIDIA H200")
    clock = TrainClock("cuda:1")
    with clock.training():
        calls.append("work")
    assert calls == [("sync", "cuda:1"), "work", ("sync", "cuda:1")]
    calls.clear()
    with track_peak_memory("cuda:1") as pm:
        calls.append("work")
    assert calls == [("sync", "cuda:1"), ("reset", "cuda:1"), "work", ("sync", "cuda:1"), ("max", "cuda:1")]
    assert (pm.bytes, pm.kind, pm.device) == (123, "cuda_max_memory_allocated", "cuda:1 NVIDIA H200")
    calls.clear()
    res = measure_render_fps(lambda c: calls.append("render"), ["a"], warmup=1, repeats=1, device="cuda:1")
    assert calls == ["render", ("sync", "cuda:1"), "render", ("sync", "cuda:1")]
    assert res.device == "cuda:1 NVIDIA H200"
