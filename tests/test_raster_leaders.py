"""The leading-splat map (``leaders=True``): each pixel's first two composited splats whose own
absorbance is at least constants.LEADER_ALPHA, in compositing order, as the view-consistency
popping ratio reads it."""

import pytest
import torch

from smgs.raster import MODES, rasterize
from smgs.raster import constants as K
from smgs.raster.composite_inputs import Splats2D, composite_settings
from test_raster_sort import _camera, _crowded


@torch.no_grad()
def test_reference_leaders_are_the_first_two_composited_splats_above_the_threshold():
    """An independent pixel-by-pixel 3DGS composite in the centres' depth order (the renderer's
    conventions: 3σ reach, absorbance clamp 0.99, skip below 1/255, stop before T < 1e-4)."""
    from smgs.raster.projection import project_gaussians

    sc = {k: v.double() for k, v in _crowded(n=60, seed=3).items()}
    cam = _camera(dtype=torch.float64)
    out = rasterize(**sc, camera=cam, mode="3dgs", backend="reference", leaders=True)
    assert out.leaders.shape == (cam.height, cam.width, 2) and out.leaders.dtype == torch.long
    proj = project_gaussians(sc["means3d"], sc["quats"], sc["scales"], cam, fused=False)
    order = torch.argsort(proj.depths, stable=True).tolist()
    n_two = 0
    for y in range(cam.height):
        for x in range(cam.width):
            T, lead = 1.0, []
            for k in order:
                dx, dy = x + 0.5 - proj.means2d[k, 0], y + 0.5 - proj.means2d[k, 1]
                a_, b_, c_ = proj.conics[k]
                q = float(0.5 * (a_ * dx * dx + c_ * dy * dy) + b_ * dx * dy)
                a = min(K.ALPHA_MAX, float(sc["opacities"][proj.ids[k]]) * torch.exp(torch.tensor(-q)).item())
                if q > -K.P_MIN or a < K.ALPHA_MIN:
                    continue
                if T * (1 - a) < K.T_MIN * (1 - K.T_STOP_SLACK):
                    break
                T *= 1 - a
                if a >= K.LEADER_ALPHA and len(lead) < 2:
                    lead.append(int(proj.ids[k]))
            lead += [-1] * (2 - len(lead))
            assert out.leaders[y, x].tolist() == lead, (x, y)
            n_two += lead[1] >= 0
    assert n_two > 50     # the scene gives many pixels two leaders


@pytest.mark.parametrize("mode", MODES)
@torch.no_grad()
def test_cpu_leaders_match_the_reference_in_both_orders(mode, cpu_backend):
    """Global order: the per-pixel kernel at window 1; per-pixel order: a window longer than every
    list (the exact sort). Same map, and the same image as the plain render."""
    from smgs.raster import rasterize_splats
    from smgs.raster.projection import project_gaussians
    from smgs.raster.ray_depth import ray_depth

    sc, cam = _crowded(), _camera(40, 32)
    ref = rasterize(**sc, camera=cam, mode=mode, k_max=8, backend="reference", leaders=True)
    got = rasterize(**sc, camera=cam, mode=mode, k_max=8, backend="cpu", leaders=True)
    plain = rasterize(**sc, camera=cam, mode=mode, k_max=8, backend="cpu")
    assert plain.leaders is None
    assert float((ref.leaders[..., 1] >= 0).float().mean()) > 0.1
    assert torch.equal(got.leaders, ref.leaders)
    torch.testing.assert_close(got.rgb, plain.rgb, rtol=0, atol=2e-6)
    # the exact per-pixel order
    proj = project_gaussians(sc["means3d"], sc["quats"], sc["scales"], cam)
    ids = proj.ids
    rd = ray_depth(sc["means3d"][ids], sc["quats"][ids], sc["scales"][ids], cam)
    args = (proj.means2d, proj.conics, sc["opacities"][ids], sc["colors_or_sh"][ids], proj.depths,
            sc["alpha"][ids], sc["beta"][ids], sc["gamma"][ids], cam.width, cam.height)
    exact = cpu_backend.rasterize_splats_cpu(Splats2D(*args[:8], ray_depth=rd),
                                             composite_settings(*args[8:], mode, 8, leaders=True, window=100_000))
    ref_pp = rasterize_splats(*args, mode=mode, k_max=8, backend="reference", ray_depth=rd, leaders=True)
    assert torch.equal(exact.leaders, ref_pp.leaders)
    assert not torch.equal(ref_pp.leaders, ref.leaders)   # the two orders differ somewhere


@torch.no_grad()
def test_leaders_name_the_callers_gaussians_and_follow_the_depth_order(cpu_backend):
    """Two overlapping discs facing the camera, plus a Gaussian behind it (culled, so projected and
    input indices differ): the centre pixel's leaders are (front, back) by the callers' indices,
    and swap when the discs swap depths."""
    means = torch.tensor([[0.0, 0.0, -10.0], [0.05, 0.0, 0.0], [-0.05, 0.0, 0.3]])
    quats = torch.tensor([[1.0, 0, 0, 0]] * 3)
    scales = torch.tensor([[0.4, 0.4, 1e-3]] * 3)
    opac = torch.tensor([0.9, 0.8, 0.8])
    cols = torch.eye(3)
    from smgs.camera import Camera

    cam = Camera.look_at([0.0, 0.0, -3.0], [0, 0, 0], [0, -1, 0], 40, 40, 32, 24)
    for backend in ("reference", "cpu"):
        out = rasterize(means, quats, scales, opac, cols, cam, mode="3dgs", backend=backend, leaders=True)
        assert out.extras["ids"].tolist() == [1, 2]          # the first is behind the camera
        assert out.leaders[12, 16].tolist() == [1, 2], backend
        flipped = means.clone()
        flipped[1, 2], flipped[2, 2] = 0.3, 0.0
        out = rasterize(flipped, quats, scales, opac, cols, cam, mode="3dgs", backend=backend, leaders=True)
        assert out.leaders[12, 16].tolist() == [2, 1], backend
        faint = rasterize(means, quats, scales, torch.tensor([0.9, 0.8, 0.2]), cols, cam, mode="3dgs",
                          backend=backend, leaders=True)
        assert faint.leaders[12, 16].tolist() == [1, -1], backend    # a = 0.2 < LEADER_ALPHA


def test_leaders_with_regulariser_values_on_the_cpu_backend_are_refused_with_the_fix(cpu_backend):
    sc = _crowded(n=20)
    with pytest.raises(ValueError, match="no variance-regulariser sums"):
        rasterize(**sc, camera=_camera(), mode="softmax_gs", backend="cpu", leaders=True,
                  reg_values=torch.rand(20, 2))


def test_what_cuda_has_no_kernel_for_is_composited_on_host_copies(monkeypatch, cpu_backend):
    """The CUDA path's logic, on the CPU: the backend resolves to 'cuda' (no leading-splat kernel)
    and auto's per-pixel order to 'host' (no per-pixel kernel), so rasterize_splats composites host
    copies through the cpu backend and hands back its outputs, gradients included."""
    import smgs.raster.api as api

    sc, cam = _crowded(n=80, seed=5), _camera(40, 32)
    want = {}
    for s in ("global", "per_pixel"):
        p = {k: v.clone().requires_grad_(True) for k, v in sc.items()}
        out = rasterize(**p, camera=cam, mode="softmax_gs", k_max=8, backend="cpu", sort=s, leaders=True)
        out.rgb.sum().backward()
        want[s] = (out, {k: v.grad for k, v in p.items()})
    real = api.resolve_backend
    monkeypatch.setattr(api, "resolve_backend", lambda b, d, t: "cuda" if b == "cuda" else real(b, d, t))
    monkeypatch.setattr(api, "_per_pixel_backend", lambda d, t, r: "host")
    for s, (ref, grads) in want.items():
        p = {k: v.clone().requires_grad_(True) for k, v in sc.items()}
        got = rasterize(**p, camera=cam, mode="softmax_gs", k_max=8, backend="cuda" if s == "global" else "auto",
                        sort=s, leaders=True)
        assert torch.equal(got.leaders, ref.leaders), s
        torch.testing.assert_close(got.rgb, ref.rgb, rtol=0, atol=0)
        got.rgb.sum().backward()
        for k, g in grads.items():
            torch.testing.assert_close(p[k].grad, g, rtol=0, atol=0, msg=f"{s} {k}")
