"""The opt-in CUDA kernels ("v2", docs/cuda.md) on a GPU: the v2 compositing against the PyTorch
reference and against the default CUDA kernels, and the fused 3D path (projection, SH, compositing)
against the reference pipeline. Marked ``gpu``; skipped where no CUDA device is visible.

Tolerances are tests/test_raster_cuda.py's (imported, with its scenes and helpers): the v2 kernels
contract a·b + c into FMAs and use the hardware reciprocal and square root in the softmax step
(~1 ulp), but the reach arithmetic is unfused (mul_rn/add_rn), so ``n_contrib`` must equal the
reference's and the default kernels' exactly, and the outputs and gradients stay within the default
kernels' bounds. The fused projection is checked bit for bit against the CPU projection in
tests/test_raster_projection_cuda.py.
"""

from __future__ import annotations

import warnings

import pytest
import torch

from smgs import Camera
from smgs.raster import MODES, Renderer, rasterize
from smgs.raster import constants as K
from smgs.raster.composite_inputs import Splats2D, composite_settings

pytestmark = pytest.mark.gpu

if not torch.cuda.is_available():
    pytest.skip("no CUDA device visible (torch.cuda.is_available() is False)", allow_module_level=True)

from test_raster_cuda import (GRAD_RTOL32, KEYS, OUT_ATOL32, OUT_ATOL64, GRAD_RTOL64, H, W,  # noqa: E402
                              assert_same, check_stiff_battery, random_scene, render_and_grad)

DEV = "cuda"
V2 = Renderer("cuda", kernels="v2")            # the opt-in kernels
DEFAULT = Renderer("cuda", kernels="default")   # the default kernels, whatever SMGS_CUDA_KERNELS says


def test_v2_builds_and_its_constants_mirror_the_default():
    from smgs.raster import cuda, cuda_v2

    assert cuda_v2.is_available(), cuda_v2.unavailable_reason()
    assert cuda_v2.extension().constants() == cuda.extension().constants()


@pytest.mark.parametrize("scope", ["pixel", "patch"])   # docs/kmax-scope.md
@pytest.mark.parametrize("k_max", [2, 128])
@pytest.mark.parametrize("mode", MODES)
def test_v2_matches_reference_and_default_kernels(mode, k_max, scope):
    sc = random_scene(40, W, H, seed=k_max)
    kw = dict(k_max=k_max, background=torch.tensor([0.2, 0.5, 0.9]), k_max_scope=scope)
    ov, gv = render_and_grad(sc, W, H, V2, mode, device=DEV, **kw)
    od, gd = render_and_grad(sc, W, H, DEFAULT, mode, device=DEV, **kw)
    orf, gr = render_and_grad(sc, W, H, "reference", mode, **kw)
    assert ov.stats.n_contrib.max() > 2
    assert ov.stats.pairs_evaluated == od.stats.pairs_evaluated   # the same tile lists
    assert_same(ov, gv, orf, gr, OUT_ATOL32, GRAD_RTOL32)
    assert_same(ov, gv, od, gd, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("scope", ["pixel", "patch"])
@pytest.mark.parametrize("k_max", [3, 128])
@pytest.mark.parametrize("mode", MODES)
def test_v2_crowded_tiles(mode, k_max, scope):
    """More splats per tile than one batch holds, pixels that stop, softmax heads of dozens."""
    sc = random_scene(700, 40, 30, seed=3)
    sc["opacities"] = 0.3 + 0.6 * sc["opacities"]
    kw = dict(k_max=k_max, k_max_scope=scope)
    ov, gv = render_and_grad(sc, 40, 30, V2, mode, device=DEV, **kw)
    od, gd = render_and_grad(sc, 40, 30, DEFAULT, mode, device=DEV, **kw)
    orf, gr = render_and_grad(sc, 40, 30, "reference", mode, **kw)
    assert orf.stats.n_contrib.max() > 20
    assert_same(ov, gv, orf, gr, 2 * OUT_ATOL32, 2 * GRAD_RTOL32)
    assert_same(ov, gv, od, gd, 2 * OUT_ATOL32, 2 * GRAD_RTOL32)


@pytest.mark.parametrize("scope", ["pixel", "patch"])
@pytest.mark.parametrize("n_ch,n_reg", [(1, 2), (5, 1)])
@pytest.mark.parametrize("mode", ["softmax_only", "softmax_gs", "3dgs"])
def test_v2_general_channel_path(mode, n_ch, n_reg, scope):
    """nch != 3: state in global memory, head records of 8 (1 channel + depth) and 12 floats (5 + depth:
    three float4)."""
    sc = random_scene(30, W, H, seed=5, n_ch=n_ch, n_reg=n_reg)
    kw = dict(k_max=3, eq15="printed", reg_depth_scale=0.7, background=torch.rand(n_ch), k_max_scope=scope)
    ov, gv = render_and_grad(sc, W, H, V2, mode, device=DEV, **kw)
    orf, gr = render_and_grad(sc, W, H, "reference", mode, **kw)
    assert ov.rgb.shape == (H, W, n_ch) and ov.reg.shape == (H, W, 1 + 2 * n_reg)
    assert_same(ov, gv, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("mode", ["softmax_only", "softmax_gs"])
def test_v2_k_max_zero_is_all_vanilla(mode):
    sc = random_scene(25, 20, 18, seed=2)
    ov, gv = render_and_grad(sc, 20, 18, V2, mode, device=DEV, k_max=0)
    orf, gr = render_and_grad(sc, 20, 18, "reference", mode, k_max=0)
    assert_same(ov, gv, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("mode", MODES)
def test_v2_float32_close_to_reference_float64(mode):
    sc = random_scene(30, W, H, seed=11, n_ch=3, n_reg=1)
    bg = torch.tensor([0.1, 0.0, 0.4])
    ov, gv = render_and_grad(sc, W, H, V2, mode, device=DEV, k_max=4, background=bg)
    o64, g64 = render_and_grad(sc, W, H, "reference", mode, dtype=torch.float64, k_max=4, background=bg)
    assert_same(ov, gv, o64, g64, OUT_ATOL64, GRAD_RTOL64)


@pytest.mark.slow   # builds another variant (bench/gpu_check.py runs it after the renderer's tests)
@pytest.mark.parametrize("mode", ["3dgs", "softmax_gs"])
def test_v2_t_min_variant(mode):
    sc = random_scene(300, 40, 30, seed=6)
    ov, gv = render_and_grad(sc, 40, 30, V2, mode, device=DEV, k_max=4, t_min=0.05)
    orf, gr = render_and_grad(sc, 40, 30, "reference", mode, k_max=4, t_min=0.05)
    assert 0.9 < orf.alpha.max() <= 0.95 + 1e-5
    assert_same(ov, gv, orf, gr, 2 * OUT_ATOL32, 2 * GRAD_RTOL32)


def test_v2_persistent_grid_of_one_block_gives_the_same_gradients(monkeypatch):
    """A head budget of one byte leaves one block, which takes every tile from the counter."""
    from smgs.raster import cuda_v2

    sc = random_scene(80, 70, 50, seed=4)
    o1, g1 = render_and_grad(sc, 70, 50, V2, "softmax_gs", device=DEV, k_max=5)
    monkeypatch.setattr(cuda_v2, "HEAD_BUDGET_BYTES", 1)
    o2, g2 = render_and_grad(sc, 70, 50, V2, "softmax_gs", device=DEV, k_max=5)
    assert torch.equal(o1.rgb, o2.rgb)
    plan = cuda_v2.extension().backward_plan(3, 70, 50, True, True, 5, 1)
    assert plan[0] == 1 and plan[1] >= 1
    for k in g1:
        torch.testing.assert_close(g1[k], g2[k], rtol=1e-5, atol=1e-6, msg=k)   # atomics: any order


def test_v2_radii_leave_rows_out():
    """Rows with radii (0, 0) are not splats: the image and n_contrib are those of the other rows
    alone (default kernels), and the left-out rows get zero gradients."""
    from smgs.raster import cuda_v2

    sc = random_scene(60, W, H, seed=8)
    keep = torch.ones(60, dtype=torch.bool)
    keep[::3] = False
    radii = torch.where(keep[:, None], torch.full((60, 2), 5.0), torch.zeros(60, 2)).to(DEV)
    ins = {k: sc[k].to(DEV).clone().requires_grad_(True) for k in KEYS}
    out = cuda_v2.rasterize_splats_cuda_v2(Splats2D(*[ins[k] for k in KEYS], radii=radii),
                                           composite_settings(W, H, "softmax_gs", 4))
    (out.rgb.sum() + out.alpha.sum()).backward()
    kept = {k: sc[k][keep].to(DEV).clone().requires_grad_(True) for k in KEYS}
    from smgs.raster import rasterize_splats

    ref = rasterize_splats(*[kept[k] for k in KEYS], W, H, mode="softmax_gs", k_max=4, backend=DEFAULT)
    (ref.rgb.sum() + ref.alpha.sum()).backward()
    assert torch.equal(out.stats.n_contrib, ref.stats.n_contrib)
    torch.testing.assert_close(out.rgb, ref.rgb, rtol=0, atol=OUT_ATOL32)
    for k in KEYS:
        assert (ins[k].grad[~keep.to(DEV)] == 0).all(), k
        g, r = ins[k].grad[keep.to(DEV)], kept[k].grad
        assert (g - r).abs().max() <= GRAD_RTOL32 * (r.abs().max() + 1e-8), k


def test_v2_no_visible_splat_gives_the_background_and_zero_gradients():
    for n in (0, 3):
        sc = random_scene(5, 10, 8)
        sc = {k: v[:n] for k, v in sc.items()}
        sc["means2d"] = sc["means2d"] + 100.0
        bg = torch.tensor([0.2, 0.4, 0.6])
        o, g = render_and_grad(sc, 10, 8, V2, "softmax_gs", device=DEV, background=bg)
        torch.testing.assert_close(o.rgb.cpu(), bg.expand(8, 10, 3), rtol=0, atol=0)
        assert (o.alpha == 0).all() and o.stats.n_contrib.sum() == 0
        for k in KEYS:
            assert (g[k] == 0).all()


def test_v2_stiff_battery_finite_and_close_to_float64(monkeypatch):
    monkeypatch.setenv("SMGS_CUDA_KERNELS", "v2")   # check_stiff_battery renders through rasterize_splats
    check_stiff_battery()


def _params3d(n: int, seed: int, sh_bases: int):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    means = (r(n, 3) - 0.5) * torch.tensor([3.0, 2.0, 2.0])
    means[:4, 2] = -6.0          # behind the camera (at z = -4)
    means[4:8, 0] = 60.0         # far off the image
    return dict(means3d=means, quats=r(n, 4) - 0.5, scales=0.05 + 0.15 * r(n, 3), opacities=0.2 + 0.75 * r(n),
                sh=0.5 * (r(n, sh_bases, 3) - 0.5), alpha=0.5 + 2 * r(n), beta=10 * r(n), gamma=2 * r(n))


def _run3d(params, cam, mode, sh_degree, backend, device, **kw):
    p = {k: v.to(device).clone().requires_grad_(True) for k, v in params.items()}
    bg = torch.tensor([0.1, 0.2, 0.3], device=device, requires_grad=True)
    out = rasterize(p["means3d"], p["quats"], p["scales"], p["opacities"], p["sh"], cam, alpha=p["alpha"],
                    beta=p["beta"], gamma=p["gamma"], mode=mode, k_max=3, sh_degree=sh_degree, background=bg,
                    backend=backend, **kw)
    wr = torch.linspace(0, 1, out.rgb.numel(), device=device).reshape(out.rgb.shape)
    ((out.rgb * wr).sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
    grads = {**{k: v.grad for k, v in p.items()}, "background": bg.grad}
    return out, {k: None if v is None else v.cpu() for k, v in grads.items()}


@pytest.mark.parametrize("sh_degree", [1, 3])
@pytest.mark.parametrize("mode", MODES)
def test_fused_3d_path_matches_reference(mode, sh_degree):
    """rasterize(..., backend=Renderer("cuda", kernels="v2")): fused projection and SH, then the v2 compositing, against
    the reference pipeline on the CPU (the bounds of test_rasterize_3d_cuda_matches_reference)."""
    cam = Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0], fx=40.0, fy=40.0,
                         width=40, height=30)
    params = _params3d(50, 3, (sh_degree + 1) ** 2)
    ov, gv = _run3d(params, cam, mode, sh_degree, V2, DEV)
    orf, gr = _run3d(params, cam, mode, sh_degree, "reference", "cpu")
    assert orf.stats.n_contrib.max() > 3
    torch.testing.assert_close(ov.rgb.cpu(), orf.rgb, rtol=0, atol=4 * OUT_ATOL32)
    torch.testing.assert_close(ov.alpha.cpu(), orf.alpha, rtol=0, atol=4 * OUT_ATOL32)
    torch.testing.assert_close(ov.depth.cpu(), orf.depth, rtol=0, atol=4 * OUT_ATOL32 * 8)
    for k, v in gr.items():
        if v is None:
            assert gv[k] is None
            continue
        scale = v.abs().max().item() + 1e-8
        assert (gv[k] - v).abs().max().item() <= GRAD_RTOL32 * 10 * scale, k
    # no compaction: every Gaussian has a row, the culled ones radii (0, 0), as the densifier reads them
    n = params["means3d"].shape[0]
    assert torch.equal(ov.extras["ids"].cpu(), torch.arange(n))
    culled = torch.ones(n, dtype=torch.bool)
    culled[orf.extras["ids"]] = False
    assert culled[:8].all()
    assert (ov.extras["radii"].cpu()[culled] == 0).all()
    torch.testing.assert_close(ov.extras["radii"].cpu()[~culled], orf.extras["radii"], rtol=1e-5, atol=1e-4)


def test_fused_3d_path_synchronises_once_per_forward():
    """One forward through the fused path (inputs already checked) synchronises for the pair count
    (and, until the stats are lazy, for pairs_evaluated); the backward of a mode without softmax
    not at all, with softmax once (the largest per-pixel count)."""
    from smgs.raster import cuda_v2

    cam = Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0], fx=40.0, fy=40.0,
                         width=40, height=30)
    params = _params3d(200, 5, 4)
    for mode in ("3dgs", "softmax_gs"):
        p = {k: v.to(DEV).clone().requires_grad_(True) for k, v in params.items()}
        args = (p["means3d"], p["quats"], p["scales"], p["opacities"], p["sh"], cam, p["alpha"], p["beta"],
                p["gamma"], None, None, composite_settings(40, 30, mode, 3), 1, K.NEAR_PLANE, K.EPS2D, True)
        cuda_v2.rasterize_fused(*args)   # builds and warms up
        torch.cuda.synchronize()
        syncs = []
        for phase in ("forward", "backward"):
            with warnings.catch_warnings(record=True) as caught:
                warnings.simplefilter("always")
                torch.cuda.set_sync_debug_mode("warn")
                try:
                    if phase == "forward":
                        out = cuda_v2.rasterize_fused(*args)
                    else:
                        (out.rgb.sum() + out.alpha.sum()).backward()
                finally:
                    torch.cuda.set_sync_debug_mode("default")
            syncs.append(sum("synchroniz" in str(w.message).lower() for w in caught))
        assert 1 <= syncs[0] <= 2, (mode, syncs)
        assert syncs[1] == (1 if mode == "softmax_gs" else 0), (mode, syncs)


def _pixel_inputs(n: int, seed: int):
    """2D splats and their peak-depth coefficients from one 3D scene, on the CPU (so both backends
    composite the same floats)."""
    from smgs.raster.projection import project_gaussians
    from smgs.raster.ray_depth import ray_depth

    cam = Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0], fx=40.0, fy=40.0,
                         width=40, height=30)
    p3 = _params3d(n, seed, 1)
    p = project_gaussians(p3["means3d"], p3["quats"], p3["scales"], cam, fused=False)
    ids = p.ids
    rd = ray_depth(p3["means3d"][ids], p3["quats"][ids], p3["scales"][ids], cam)
    sc = dict(means2d=p.means2d.detach(), conics=p.conics.detach(), opacities=p3["opacities"][ids],
              colors=p3["sh"][ids, 0] + 0.5, depths=p.depths.detach(), alpha=p3["alpha"][ids], beta=p3["beta"][ids],
              gamma=p3["gamma"][ids])
    return sc, rd


@pytest.mark.parametrize("scope", ["pixel", "patch"])
@pytest.mark.parametrize("mode", MODES)
def test_v2_per_pixel_order_and_leaders_match_the_cpu_window(mode, scope):
    """sort="per_pixel" with the leading-splat map on the GPU (csrc/cuda_pixel.cu) against the CPU
    backend's window on the same floats: n_contrib and the leaders exactly, images and gradients
    within the CUDA bounds."""
    from smgs.raster.types import RayDepth

    sc, rd = _pixel_inputs(300, 7)
    rd_dev = RayDepth(rd.coefs.to(DEV), rd.fx, rd.fy, rd.cx, rd.cy)
    kw = dict(k_max=4, background=torch.tensor([0.2, 0.5, 0.9]), k_max_scope=scope, leaders=True)
    ov, gv = render_and_grad(sc, 40, 30, V2, mode, device=DEV, ray_depth=rd_dev, **kw)
    oc, gc = render_and_grad(sc, 40, 30, "cpu", mode, ray_depth=rd, **kw)
    assert ov.rgb.device.type == "cuda" and oc.stats.n_contrib.max() > 4
    assert torch.equal(ov.leaders.cpu(), oc.leaders)
    assert ov.stats.pairs_evaluated == oc.stats.pairs_evaluated   # the same boxes
    assert_same(ov, gv, oc, gc, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("mode", ["3dgs", "softmax_gs"])
def test_v2_leaders_in_the_global_order_match_the_cpu(mode):
    sc, _ = _pixel_inputs(300, 8)
    ov, gv = render_and_grad(sc, 40, 30, V2, mode, device=DEV, k_max=4, leaders=True)
    oc, gc = render_and_grad(sc, 40, 30, "cpu", mode, k_max=4, leaders=True)
    od, _ = render_and_grad(sc, 40, 30, DEFAULT, mode, device=DEV, k_max=4)
    assert torch.equal(ov.leaders.cpu(), oc.leaders) and (ov.leaders >= 0).any()
    assert torch.equal(ov.stats.n_contrib.cpu(), od.stats.n_contrib.cpu())   # the global order's
    assert_same(ov, gv, oc, gc, OUT_ATOL32, GRAD_RTOL32)


def test_v2_per_pixel_order_stays_on_the_gpu(monkeypatch):
    """auto with kernels="v2" renders sort="per_pixel" on the GPU: no host copies."""
    from smgs.raster import api

    def no_host(*a, **k):
        raise AssertionError("rendered on host copies")

    monkeypatch.setattr(api, "_on_host", no_host)
    cam = Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0], fx=40.0, fy=40.0,
                         width=40, height=30)
    params = _params3d(100, 9, 1)
    p = {k: v.to(DEV) for k, v in params.items()}
    out = rasterize(p["means3d"], p["quats"], p["scales"], p["opacities"], p["sh"], cam, alpha=p["alpha"],
                    beta=p["beta"], gamma=p["gamma"], mode="softmax_gs", sh_degree=0, sort="per_pixel", leaders=True,
                    backend=Renderer(kernels="v2"))
    assert out.rgb.device.type == "cuda" and out.leaders.device.type == "cuda"
    assert (out.leaders < params["means3d"].shape[0]).all()


def test_v2_per_pixel_window_of_one_is_the_global_order():
    from smgs.raster.types import RayDepth

    sc, rd = _pixel_inputs(300, 10)
    rd_dev = RayDepth(rd.coefs.to(DEV), rd.fx, rd.fy, rd.cx, rd.cy)
    from smgs.raster import cuda_v2

    ins = {k: v.to(DEV) for k, v in sc.items()}
    args = [ins[k] for k in KEYS]
    w1 = cuda_v2.rasterize_splats_pixel_cuda(Splats2D(*args, ray_depth=rd_dev),
                                             composite_settings(40, 30, "softmax_gs", 4, window=1))
    glob = cuda_v2.rasterize_splats_cuda_v2(Splats2D(*args), composite_settings(40, 30, "softmax_gs", 4))
    assert torch.equal(w1.stats.n_contrib, glob.stats.n_contrib)
    torch.testing.assert_close(w1.rgb, glob.rgb, rtol=0, atol=OUT_ATOL32)
