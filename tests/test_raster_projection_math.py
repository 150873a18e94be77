"""The per-Gaussian projection math in csrc/projection_math.h, through its CPU build.

* The compiled CPU projection, refactored to take its math from the shared header, gives the same
  bits as the pass before the refactoring (the source at commit 8887afe, built beside it) on the
  benchmark scenes and on the edge-case scene of tests/test_raster_projection_cpu.py.
* The colour stage (SH evaluation, the CUDA projection's too) against sh.py's ``eval_sh`` through
  autograd. Tolerances: the same formulas summed in another order (each basis times its
  coefficient, accumulated basis by basis) and the direction's normalisation, so ~1e-6 of the value
  scale; the gradient of the means goes through 1/|m − centre| (hence relative to the row).
"""

from __future__ import annotations

import shutil
import subprocess
from pathlib import Path

import numpy as np
import pytest
import torch

from smgs.camera import Camera
from smgs.raster import projection
from smgs.raster.cpu_build import cpu_extension
from smgs.raster.sh import eval_sh, num_sh_bases
from test_raster_projection_cpu import _scene

REPO = Path(__file__).resolve().parents[1]
OLD_COMMIT = "8887afe"   # the last projection_cpu.cpp with the math inline
BENCH = REPO.parent / "shared" / "bench"

needs_cc = pytest.mark.skipif(shutil.which("c++") is None, reason="no C++ compiler: no compiled projection")


def _old_source(tmp_dir: Path) -> Path:
    """projection_cpu.cpp as it was at OLD_COMMIT, or a skip where git or the commit is missing."""
    if shutil.which("git") is None:
        pytest.skip("no git: cannot read the projection source before the refactoring")
    r = subprocess.run(["git", "-C", str(REPO), "show", f"{OLD_COMMIT}:smgs/raster/csrc/projection_cpu.cpp"],
                       capture_output=True, text=True)
    if r.returncode != 0:
        pytest.skip(f"commit {OLD_COMMIT} not in this checkout (shallow clone?): {r.stderr.strip()[:200]}")
    path = tmp_dir / "projection_cpu.cpp"
    path.write_text(r.stdout)
    return path


def _recipe(n: int, width: int, height: int, seed: int) -> dict[str, np.ndarray]:
    """bench/raster.py's random scene (../shared/bench/README.md's recipe)."""
    rng = np.random.default_rng(seed)
    fx = float(width)
    z = rng.uniform(2, 6, n)
    u, v = rng.uniform(0, width, n), rng.uniform(0, height, n)
    means = np.stack([(u - width / 2) * z / fx, (v - height / 2) * z / fx, z], 1)
    sig = 2 * np.exp(rng.normal(0, 0.25, n))[:, None] * rng.uniform(0.8, 1.25, (n, 3))
    q = rng.normal(size=(n, 4))
    K = np.array([[fx, 0, width / 2], [0, fx, height / 2], [0, 0, 1]])
    return dict(means=means, scales=sig * z[:, None] / fx, quats_wxyz=q, K=K, viewmat=np.eye(4), width=width,
                height=height)


def _scenes() -> list[tuple[str, torch.Tensor, torch.Tensor, torch.Tensor, Camera, float]]:
    out = []
    files = sorted(BENCH.glob("scene_*.npz")) if BENCH.is_dir() else []
    dicts = [(f.stem, dict(np.load(f))) for f in files] or [("recipe_10k_256", _recipe(10_000, 256, 256, 0))]
    dicts.append(("recipe_20k_320x200_offaxis", _recipe(20_000, 320, 200, 3)))
    for name, d in dicts:
        t = lambda a: torch.as_tensor(np.asarray(a), dtype=torch.float32)  # noqa: E731
        cam = Camera(t(d["K"]), t(d["viewmat"]), int(d["width"]), int(d["height"]))
        means = t(d["means"])
        if "offaxis" in name:   # some behind the camera, some far beyond the image, the clamp binding
            means[:2000, 2] = -means[:2000, 2]
            means[2000:4000, 0] *= 6.0
        out.append((name, means, t(d["quats_wxyz"]), t(d["scales"]), cam, 0.3))
    cam = Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=60.0, fy=55.0, width=64, height=48)
    for seed, eps in ((0, 0.3), (2, 0.0)):
        out.append((f"edge_cases_{seed}", *_edge_scene(5000, seed), cam, eps))
    return out


def _edge_scene(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """test_raster_projection_cpu's edge-case scene with its tiny and zero scales."""
    return _scene(n, seed, tiny=True)


@needs_cc
def test_refactored_cpu_pass_equals_the_old_one_bit_for_bit(tmp_path):
    old = cpu_extension("smgs_projection_cpu_before_header", [_old_source(tmp_path)], "projection kernel (before)")
    new = projection._JIT
    assert new.is_available() and old.is_available()
    old_m, new_m = old.module(), new.module()
    for name, means, quats, scales, cam, eps in _scenes():
        view = projection._packed_view(projection._view(cam, torch.float32, torch.device("cpu")))
        none = torch.empty(0)   # no colour stage
        fo = old_m.forward(means, quats, scales, view, 0.01, eps, 3.0)
        fn = new_m.forward(means, quats, scales, view, 0.01, eps, 3.0, none, none, 0, True)
        assert fn[0].numel() > 100, name
        for a, b, what in zip(fn, fo, ("ids", "means2d", "conics", "depths", "radii")):
            assert a.dtype == b.dtype and torch.equal(a, b), f"{name}: {what} differs"
        m = fn[0].numel()
        g = torch.Generator().manual_seed(1)
        grads = [torch.randn(m, 2, generator=g), torch.randn(m, 3, generator=g), torch.randn(m, generator=g)]
        bo = old_m.backward(means, quats, scales, view, 0.01, eps, fn[0], *grads)
        bn = new_m.backward(means, quats, scales, view, 0.01, eps, fn[0], *grads, none, none, 0, True, none)
        for a, b, what in zip(bn, bo, ("means3d", "quats", "scales")):
            assert torch.equal(a, b), f"{name}: gradient of {what} differs"


def _sh_inputs(n: int, k: int, c: int, seed: int):
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 2
    sh = torch.randn(n, k, c, generator=g) * 0.5
    means[0] = torch.tensor([0.3, -0.2, -3.0])   # at the camera centre: the clamped norm
    return means, sh


@needs_cc
@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("clamp", [True, False])
def test_sh_colour_stage_matches_eval_sh(degree, clamp):
    ext = projection._JIT.module()
    cam = Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=60.0, fy=55.0, width=64, height=48)
    center = cam.center.to(torch.float32)
    k = 16 if degree == 3 else num_sh_bases(degree) + 1   # more coefficients than the degree uses
    means, sh = _sh_inputs(3000, k, 3, degree)
    m_ref, sh_ref = means.clone().requires_grad_(True), sh.clone().requires_grad_(True)
    dirs = m_ref - center
    dirs = dirs / dirs.norm(dim=-1, keepdim=True).clamp_min(1e-12)
    want = eval_sh(degree, sh_ref, dirs) + 0.5
    if clamp:
        want = want.clamp_min(0.0)
    got = ext.sh_forward(means, sh, center.tolist(), degree, clamp)
    torch.testing.assert_close(got, want.detach(), rtol=1e-5, atol=2e-6)
    if clamp:
        assert (want == 0).any() and got[want.detach() == 0].eq(0).all()
    g_col = torch.randn(want.shape, generator=torch.Generator().manual_seed(9))
    gm_ref, gsh_ref = torch.autograd.grad(want, (m_ref, sh_ref), g_col, allow_unused=True)
    gm_ref = torch.zeros_like(means) if gm_ref is None else gm_ref   # degree 0 has no direction
    gm, gsh = ext.sh_backward(means, sh, center.tolist(), degree, clamp, g_col)
    torch.testing.assert_close(gsh, gsh_ref, rtol=1e-5, atol=1e-6)
    scale = gm_ref.abs().amax(1, keepdim=True).clamp_min(1e-30)
    rows = ((gm - gm_ref).abs() / scale).amax(1)
    assert (rows[1:] < 1e-4).all(), f"worst means3d row off by {rows[1:].max():.3g} of its scale"
    if degree == 0:
        assert gm.eq(0).all()
    # at the camera centre the direction is 0/1e-12: finite, the gradient through a constant divisor
    assert torch.isfinite(gm[0]).all() and torch.isfinite(got[0]).all()


@needs_cc
def test_sh_stage_refuses_bad_input():
    ext = projection._JIT.module()
    means, sh = _sh_inputs(10, 4, 3, 0)
    with pytest.raises(RuntimeError, match="degree must be 0..3"):
        ext.sh_forward(means, sh, [0.0, 0.0, 0.0], 4, True)
    with pytest.raises(RuntimeError, match=r"sh must be float32 CPU \[10, >= 9, C\]"):
        ext.sh_forward(means, sh, [0.0, 0.0, 0.0], 2, True)
    with pytest.raises(RuntimeError, match="three floats"):
        ext.sh_forward(means, sh, [0.0, 0.0], 1, True)
