"""The backward of sort="per_pixel" on the compiled CPU backend (csrc/cpu_pixel.cpp) against the
reference's exact per-pixel order under autograd, in every mode.

The splats are projected once (PyTorch path) and both backends composite the same 2D inputs with
the same peak-depth coefficients; the CPU window is longer than every pixel's list, so its order is
the exact sort. Tolerances as tests/test_raster_cpu.py states them for float32 against float32
(outputs OUT_ATOL32; gradients GRAD_RTOL32 of the largest gradient of the same input): the CPU
backward stores T before every step, so only the summation order of the per-pixel terms differs.
"""

import math
import shutil

import pytest
import torch

from smgs import Camera
from smgs.raster import MODES, rasterize, rasterize_splats
from smgs.raster.composite_inputs import Splats2D, composite_settings
from smgs.raster.projection import project_gaussians, quat_to_rotmat
from smgs.raster.ray_depth import ray_depth

if shutil.which("c++") is None:  # a machine without a compiler has no cpu backend; that is not a bug
    pytest.skip("no C++ compiler: the cpu backend cannot be built here", allow_module_level=True)

OUT_ATOL32, GRAD_RTOL32 = 2e-6, 2e-5
KEYS = ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")
EXACT = 100_000   # a window longer than any list: the exact per-pixel order


def _camera(w: int, h: int) -> Camera:
    R = quat_to_rotmat(torch.tensor([0.99, 0.05, -0.08, 0.02], dtype=torch.float64))
    V = torch.eye(4, dtype=torch.float64)
    V[:3, :3] = R
    V[:3, 3] = torch.tensor([0.3, -0.2, 4.0], dtype=torch.float64)
    K = torch.tensor([[30.0, 0, w / 2], [0, 30.0, h / 2], [0, 0, 1]], dtype=torch.float64)
    return Camera(K.float(), V.float(), w, h)


def _crowded(n: int, seed: int) -> dict:
    """Overlapping anisotropic Gaussians in a slab: long lists whose peak-depth order differs from
    the centres' order."""
    g = torch.Generator().manual_seed(seed)
    return dict(means3d=torch.randn(n, 3, generator=g) * torch.tensor([0.5, 0.4, 0.3]),
                quats=torch.randn(n, 4, generator=g), scales=0.03 + 0.25 * torch.rand(n, 3, generator=g),
                opacities=0.2 + 0.6 * torch.rand(n, generator=g), colors=torch.rand(n, 3, generator=g),
                alpha=0.8 + torch.rand(n, generator=g), beta=5 * torch.rand(n, generator=g),
                gamma=torch.rand(n, generator=g))


def _crossing() -> dict:
    """Flat splats on planes crossing at ±15° through nearly the same centre, plus a round one
    behind: each plane is in front on one side of the crossing."""
    half = math.radians(15)
    quats = torch.tensor([[math.cos(half / 2), 0, math.sin(half / 2), 0],
                          [math.cos(-half / 2), 0, math.sin(-half / 2), 0], [1.0, 0, 0, 0]])
    return dict(means3d=torch.tensor([[0.0, 0, 0.0], [0.05, 0.02, 1e-3], [0.1, -0.1, 0.6]]), quats=quats,
                scales=torch.tensor([[0.6, 0.5, 0.0], [0.55, 0.6, 0.0], [0.4, 0.4, 0.4]]),
                opacities=torch.tensor([0.9, 0.85, 0.95]), colors=torch.tensor([[1.0, 0, 0], [0, 0, 1.0], [0, 1, 0]]),
                alpha=torch.tensor([1.3, 0.9, 2.0]), beta=torch.tensor([3.0, 1.0, 6.0]),
                gamma=torch.tensor([0.5, 2.0, 1.0]))


def _splats(sc: dict, cam: Camera):
    """The projected 2D inputs (leaves) and the peak-depth coefficients of the visible splats."""
    with torch.no_grad():
        proj = project_gaussians(sc["means3d"], sc["quats"], sc["scales"], cam, fused=False)
        ids = proj.ids
        rd = ray_depth(sc["means3d"][ids], sc["quats"][ids], sc["scales"][ids], cam)
    ins = dict(means2d=proj.means2d, conics=proj.conics, opacities=sc["opacities"][ids], colors=sc["colors"][ids],
               depths=proj.depths, alpha=sc["alpha"][ids], beta=sc["beta"][ids], gamma=sc["gamma"][ids])
    return {k: v.detach().float().contiguous() for k, v in ins.items()}, rd


def _render_and_grad(ins: dict, rd, cam: Camera, mode: str, backend: str, window: int = EXACT,
                     background: torch.Tensor | None = None, k_max: int = 8, seed: int = 1, scope: str = "pixel"):
    """Render, back-propagate a loss weighting every output pixel differently; (output, grads)."""
    from smgs.raster import cpu

    leaves = {k: v.clone().requires_grad_(True) for k, v in ins.items()}
    bg = None if background is None else background.clone().requires_grad_(True)
    args = [leaves[k] for k in KEYS] + [cam.width, cam.height]
    if backend == "cpu":
        out = cpu.rasterize_splats_cpu(Splats2D(*args[:8], background=bg, ray_depth=rd),
                                       composite_settings(*args[8:], mode, k_max, k_max_scope=scope, window=window))
    else:
        out = rasterize_splats(*args, mode=mode, k_max=k_max, background=bg, backend=backend, ray_depth=rd,
                               k_max_scope=scope)
    g = torch.Generator().manual_seed(seed)
    wt = lambda t: torch.rand(t.shape, generator=g)  # noqa: E731
    loss = (out.rgb * wt(out.rgb)).sum() + (out.alpha * wt(out.alpha)).sum() + 0.1 * (out.depth * wt(out.depth)).sum()
    loss.backward()
    grads = {k: t.grad for k, t in leaves.items()}
    if bg is not None:
        grads["background"] = bg.grad
    return out, grads


def _assert_grads_close(g_cpu: dict, g_ref: dict) -> None:
    for k, gr in g_ref.items():
        gc = g_cpu[k]
        if gr is None:   # the mode ignores the input
            assert gc is None or (gc == 0).all(), k
            continue
        assert gc is not None and torch.isfinite(gc).all(), k
        scale = gr.abs().max().item()
        assert scale > 0, k
        err = (gc.double() - gr.double()).abs().max().item()
        assert err <= GRAD_RTOL32 * scale, f"gradient of {k}: max error {err:.3g}, scale {scale:.3g}"


@pytest.mark.parametrize("scope", ["pixel", "patch"])   # patch: the head need not come first (docs/kmax-scope.md)
@pytest.mark.parametrize("scene", ["crowded", "crossing"])
@pytest.mark.parametrize("mode", MODES)
def test_per_pixel_gradients_match_the_reference_exact_order(cpu_backend, mode, scene, scope):
    cam = _camera(40, 32)
    sc = _crowded(160, seed=3) if scene == "crowded" else _crossing()
    ins, rd = _splats(sc, cam)
    bg = torch.tensor([0.2, 0.5, 0.9])
    oc, gc = _render_and_grad(ins, rd, cam, mode, "cpu", background=bg, scope=scope)
    orf, gr = _render_and_grad(ins, rd, cam, mode, "reference", background=bg, scope=scope)
    glob = rasterize_splats(*[ins[k] for k in KEYS], cam.width, cam.height, mode=mode, k_max=8, background=bg,
                            backend="reference")
    assert (orf.rgb - glob.rgb).abs().max() > 0.05     # the per-pixel order differs visibly from the global
    torch.testing.assert_close(oc.rgb, orf.rgb, rtol=0, atol=OUT_ATOL32)
    torch.testing.assert_close(oc.alpha, orf.alpha, rtol=0, atol=OUT_ATOL32)
    torch.testing.assert_close(oc.depth, orf.depth, rtol=0, atol=8 * OUT_ATOL32)   # depths ~3-5
    assert torch.equal(oc.stats.n_contrib, orf.stats.n_contrib)
    assert (oc.stats.list_end is None) == (scope == "pixel") == (orf.stats.list_end is None)
    if scope == "patch":
        assert torch.equal(oc.stats.list_end, orf.stats.list_end)
    _assert_grads_close(gc, gr)


def test_window_one_gradients_are_the_global_backward(cpu_backend):
    """Window 1 composites in the global order: the same gradients as the global CPU backward."""
    cam = _camera(40, 32)
    ins, rd = _splats(_crowded(160, seed=5), cam)
    _, g1 = _render_and_grad(ins, rd, cam, "softmax_gs", "cpu", window=1)
    leaves = {k: v.clone().requires_grad_(True) for k, v in ins.items()}
    out = rasterize_splats(*[leaves[k] for k in KEYS], cam.width, cam.height, mode="softmax_gs", k_max=8,
                           backend="cpu")
    g = torch.Generator().manual_seed(1)
    wt = lambda t: torch.rand(t.shape, generator=g)  # noqa: E731
    ((out.rgb * wt(out.rgb)).sum() + (out.alpha * wt(out.alpha)).sum()
     + 0.1 * (out.depth * wt(out.depth)).sum()).backward()
    # the global backward rebuilds T by division (tests/test_raster_cpu.py): rounding-level differences
    _assert_grads_close(g1, {k: t.grad for k, t in leaves.items()})


def test_per_pixel_gradients_do_not_depend_on_the_thread_count(cpu_backend):
    cam = _camera(70, 50)
    ins, rd = _splats(_crowded(300, seed=8), cam)
    n0 = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        o1, g1 = _render_and_grad(ins, rd, cam, "softmax_gs", "cpu", window=16)
        torch.set_num_threads(max(3, n0))
        o2, g2 = _render_and_grad(ins, rd, cam, "softmax_gs", "cpu", window=16)
    finally:
        torch.set_num_threads(n0)
    assert torch.equal(o1.rgb, o2.rgb)
    for k in g1:
        assert (g1[k] is None and g2[k] is None) or torch.equal(g1[k], g2[k]), k
    assert g1["means2d"].abs().sum() > 0


@pytest.mark.parametrize("mode", ["3dgs", "softmax_gs"])
def test_auto_trains_per_pixel_on_the_cpu(cpu_backend, mode):
    cam = _camera(24, 20)
    sc = _crowded(40, seed=2)
    sc["colors_or_sh"] = sc.pop("colors")
    leaves = {k: v.clone().requires_grad_(True) for k, v in sc.items()}
    cpu_out = rasterize(**leaves, camera=cam, mode=mode, backend="cpu", sort="per_pixel")
    auto_out = rasterize(**leaves, camera=cam, mode=mode, backend="auto", sort="per_pixel")
    assert torch.equal(cpu_out.rgb, auto_out.rgb)     # auto picks the cpu window for training too
    auto_out.rgb.sum().backward()
    assert leaves["means3d"].grad.abs().sum() > 0 and leaves["scales"].grad.abs().sum() > 0
    g_beta = leaves["beta"].grad
    assert (g_beta is not None and g_beta.abs().sum() > 0) == (mode == "softmax_gs")
