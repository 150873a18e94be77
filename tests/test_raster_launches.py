"""Launches and host waits of one render's forward and one backward, per path and mode, held to
budgets: counted without a GPU on the stand-in device (tests/device_mix.py), the compiled bindings
stood in for (tests/cuda_standin.py, tests/cuda_v2_standin.py). A GPU's host pays for each launch
(~5-25 us of Python and driver time; docs/results/overhead.md) and each wait drains the GPU's queue, so these
counts are the floor of a small scene's time (gsplat: ~15-30 launches and one wait per forward).

``launches`` are the operators on device tensors that run a kernel or a copy (views and bare
allocations are free); ``bindings`` the calls into the compiled extensions (their own kernels:
binning, sort, compositing, are a fixed handful per call); ``waits`` the host synchronisations.
BUDGETS are the counts measured when they were set, so a change that adds work shows here; lower
them when the counts fall. ``python -m pytest tests/test_raster_launches.py -s`` prints the rows of
the table that docs/gpu/README.md quotes.
"""

from __future__ import annotations

import pytest
import torch
from cuda_v2_standin import OnHost, StandInCompositing, StandInProjection
from device_mix import OTHER, simulated_gpu

from smgs import Camera
from smgs.raster import cuda_v2, projection_cuda, rasterize
from smgs.raster.backends import GLUE_ENV, KERNELS_ENV

PATHS = {"default": {}, "lean glue": {GLUE_ENV: "lean"}, "v2": {KERNELS_ENV: "v2"},
         "v2 + lean glue": {KERNELS_ENV: "v2", GLUE_ENV: "lean"}}
MODES = ("3dgs", "softmax_gs")
SH = (None, 3)
# (path, mode, sh degree) -> forward (launches, bindings, waits), backward (launches, bindings, waits)
BUDGETS: dict[tuple[str, str, int | None], tuple[tuple[int, int, int], tuple[int, int, int]]] = {
    ("default", "3dgs", None): ((87, 1, 6), (86, 1, 0)),
    ("default", "3dgs", 3): ((173, 1, 6), (288, 1, 0)),
    ("default", "softmax_gs", None): ((93, 1, 6), (92, 1, 1)),
    ("default", "softmax_gs", 3): ((179, 1, 6), (294, 1, 1)),
    ("lean glue", "3dgs", None): ((63, 1, 1), (78, 1, 0)),
    ("lean glue", "3dgs", 3): ((148, 1, 1), (278, 1, 0)),
    ("lean glue", "softmax_gs", None): ((67, 1, 1), (78, 1, 1)),
    ("lean glue", "softmax_gs", 3): ((152, 1, 1), (278, 1, 1)),
    ("v2", "3dgs", None): ((23, 2, 3), (8, 2, 0)),
    ("v2", "3dgs", 3): ((23, 2, 3), (7, 2, 0)),
    ("v2", "softmax_gs", None): ((29, 2, 3), (11, 2, 1)),
    ("v2", "softmax_gs", 3): ((29, 2, 3), (10, 2, 1)),
    ("v2 + lean glue", "3dgs", None): ((2, 2, 1), (8, 2, 0)),
    ("v2 + lean glue", "3dgs", 3): ((2, 2, 1), (7, 2, 0)),
    ("v2 + lean glue", "softmax_gs", None): ((2, 2, 1), (11, 2, 1)),
    ("v2 + lean glue", "softmax_gs", 3): ((2, 2, 1), (10, 2, 1)),
}


def _scene(sh: int | None, n: int = 40) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(5)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    z = 1.5 + 3 * r(n)
    means = torch.stack([(r(n) - 0.5) * 1.6 * z, (r(n) - 0.5) * 1.2 * z, z], 1)
    means[:3, 2] = -1.0                         # behind the camera: culled
    colors = 0.3 * (r(n, (sh + 1) ** 2, 3) - 0.5) if sh is not None else r(n, 3)
    d = dict(means3d=means, quats=torch.randn(n, 4, generator=g), scales=0.03 + 0.1 * r(n, 3),
             opacities=0.3 + 0.6 * r(n), colors=colors, alpha=0.5 + 2 * r(n), beta=4 * r(n), gamma=2 * r(n))
    return {k: v.to(OTHER).requires_grad_(True) for k, v in d.items()}


def count(monkeypatch, path: str, mode: str, sh: int | None) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    """(launches, bindings, waits) of the second forward (the first fills what is kept per camera
    and per process) and of its backward, through ``path``."""
    for k in (GLUE_ENV, KERNELS_ENV):
        monkeypatch.delenv(k, raising=False)
    for k, v in PATHS[path].items():
        monkeypatch.setenv(k, v)
    cam = Camera.look_at([0.1, 0.0, -0.5], [0, 0, 3], [0, -1, 0], 30.0, 30.0, 32, 24)   # on the host
    with simulated_gpu(monkeypatch) as m:
        proj, comp = OnHost(StandInProjection(), m), OnHost(
            StandInCompositing(), m, "binding forward: the pair count", "binding backward: the most crowded pixel's count")
        monkeypatch.setattr(projection_cuda, "extension", lambda: proj)
        monkeypatch.setattr(cuda_v2, "extension", lambda t_min=None: comp)
        s = _scene(sh)
        bg = torch.tensor([0.2, 0.3, 0.4]).to(OTHER)
        for _ in range(2):
            m.reset()
            out = rasterize(s["means3d"], s["quats"], s["scales"], s["opacities"], s["colors"], cam,
                            alpha=s["alpha"], beta=s["beta"], gamma=s["gamma"], mode=mode, sh_degree=sh,
                            background=bg)
        fwd = (sum(m.launches.values()), sum(m.bindings.values()), _waits(m))
        grads = [torch.ones_like(out.rgb), torch.ones_like(out.depth)]
        m.reset()
        torch.autograd.backward([out.rgb, out.depth], grads)
        bwd = (sum(m.launches.values()), sum(m.bindings.values()), _waits(m))
    return fwd, bwd


def _waits(m) -> int:
    return sum(v for k, v in m.counts.items() if "non_blocking" not in k)


@pytest.mark.parametrize("sh", SH)
@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("path", PATHS)
def test_launches_and_waits_stay_within_their_budget(monkeypatch, path, mode, sh):
    fwd, bwd = count(monkeypatch, path, mode, sh)
    print(f"| {path} | {mode} | {'-' if sh is None else sh} | {' / '.join(map(str, fwd))} | {' / '.join(map(str, bwd))} |")
    want_fwd, want_bwd = BUDGETS[(path, mode, sh)]
    assert all(a <= b for a, b in zip(fwd, want_fwd)), f"forward {fwd} over its budget {want_fwd}"
    assert all(a <= b for a, b in zip(bwd, want_bwd)), f"backward {bwd} over its budget {want_bwd}"
