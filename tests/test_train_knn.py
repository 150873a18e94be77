"""The kNN scale of the initial Gaussians (3DGS ``distCUDA2``): exact values, bounded time and memory."""

import json
import subprocess
import sys
import textwrap
from pathlib import Path

import pytest
import torch

from smgs.train.gaussians import knn_scale

REPO = Path(__file__).resolve().parent.parent


def _exact(points: torch.Tensor, k: int = 3) -> torch.Tensor:
    """Brute force in float64: every pairwise distance, self excluded by index."""
    p = points.double()
    d2 = ((p[:, None, :] - p[None, :, :]) ** 2).sum(-1)
    d2.fill_diagonal_(float("inf"))
    return d2.topk(k, largest=False).values.mean(1).clamp_min(1e-7).sqrt()


def test_knn_scale_equals_the_exact_float64_answer():
    g = torch.Generator().manual_seed(0)
    cluster = torch.randn(300, 3, generator=g, dtype=torch.float64) * 1e-3        # a dense clump
    spread = (torch.rand(1500, 3, generator=g, dtype=torch.float64) - 0.5) * 40   # and wide space
    pts = torch.cat([cluster, spread, spread[:7], cluster[:5] + 1e-6]).float()  # exact and near duplicates
    got = knn_scale(pts)
    assert got.dtype == torch.float32 and got.shape == (pts.shape[0],)
    torch.testing.assert_close(got.double(), _exact(pts), rtol=1e-6, atol=0)
    # an exact duplicate is a neighbour at distance 0, as in distCUDA2; the clamp is 1e-7 before the sqrt
    assert float(knn_scale(torch.zeros(5, 3))[0]) == pytest.approx(1e-7 ** 0.5)
    torch.testing.assert_close(knn_scale(pts[:3], k=3).double(), _exact(pts[:3], k=2))   # k capped at n-1
    assert knn_scale(pts[:1]).tolist() == [1.0]


def test_knn_scale_refuses_non_finite_points():
    pts = torch.rand(10, 3)
    pts[4, 1] = float("nan")
    with pytest.raises(ValueError, match="1 of 10 points are not finite"):
        knn_scale(pts)


_MEASURE = textwrap.dedent("""
    import json, os, resource, sys, threading, time
    import torch
    from smgs.train.config import GaussianConfig
    from smgs.train.gaussians import Gaussians

    LIMIT_S, LIMIT_KB = float(sys.argv[1]), int(sys.argv[2])

    def watchdog():   # the old dense version took ~70 s and ~10 GB: stop it early instead of waiting
        t0 = time.perf_counter()
        while True:
            time.sleep(0.05)
            rss = int(open("/proc/self/statm").read().split()[1]) * os.sysconf("SC_PAGE_SIZE") // 1024
            if rss > LIMIT_KB or time.perf_counter() - t0 > LIMIT_S + 1:
                print(json.dumps({"aborted": True, "rss_kb": rss, "seconds": time.perf_counter() - t0}), flush=True)
                os._exit(3)

    torch.set_num_threads(1)
    g = torch.Generator().manual_seed(0)
    pts = ((torch.rand(100_000, 3, generator=g, dtype=torch.float64) - 0.5) * 0.53 * 4.0).float()
    cols = torch.rand(100_000, 3, generator=g)
    threading.Thread(target=watchdog, daemon=True).start()
    t0 = time.perf_counter()
    gs = Gaussians.from_points(pts, cols, GaussianConfig(), 4.0, sh_degree=3, device="cpu")
    seconds = time.perf_counter() - t0
    assert len(gs) == 100_000
    print(json.dumps({"aborted": False, "seconds": seconds,
                      "peak_rss_kb": resource.getrusage(resource.RUSAGE_SELF).ru_maxrss}), flush=True)
""")


def test_100k_random_points_initialise_in_seconds_and_bounded_memory():
    """The random initialisation of a scene without SfM points (100K points, as 3DGS): < 10 s and a
    peak resident size of the whole process (torch included) < 1.5 GB."""
    limit_s, limit_kb = 10.0, int(1.5e9 / 1024)
    done = subprocess.run([sys.executable, "-c", _MEASURE, str(limit_s), str(limit_kb)], cwd=REPO,
                          capture_output=True, text=True, timeout=120)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("{")]
    assert lines, done.stderr[-2000:]
    m = json.loads(lines[-1])
    assert not m["aborted"], f"stopped at {m['seconds']:.1f} s with {m['rss_kb'] / 1e6:.2f} GB resident"
    assert done.returncode == 0, done.stderr[-2000:]
    assert m["seconds"] < limit_s
    assert m["peak_rss_kb"] < limit_kb, f"peak {m['peak_rss_kb'] / 1e6:.2f} GB"
