"""The compiled float32 CPU projection (csrc/projection_cpu.cpp) against its oracle, the PyTorch
``_Project``: culling, values, gradients, the camera quantities, thread-count independence and the
dispatch rule.

Tolerances: both paths evaluate the same formulas in float32 but not in the same order (PyTorch's
addmm/bmm/addcmul), so they differ by rounding, amplified where the math cancels: means2d = c + f·x/z
loses digits near the image centre and for Gaussians close to the camera (hence 1e-4 px absolute),
the conic and gradient components of one Gaussian share its scale (hence a tolerance relative to the
largest component of the row), and the quaternion gradient projects out the radial part of g_q
(hence 1e-3 of the row). Against float64, both paths' errors are of the same size.
"""

import shutil

import pytest
import torch

from smgs.camera import Camera
from smgs.raster import projection
from smgs.raster.cpu_build import cpu_extension
from smgs.raster.projection import _view, project_gaussians, quat_to_rotmat

# every SIMD path of the compiled CPU kernels this host runs (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("cpu_isa")

needs_cc = pytest.mark.skipif(shutil.which("c++") is None, reason="no C++ compiler: no compiled projection")


def _camera() -> Camera:
    return Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=60.0, fy=55.0, width=64, height=48)


def _scene(n: int, seed: int, tiny: bool = False):
    """Random float32 Gaussians around the origin (the camera is at z ≈ −3) with the edge cases in
    tenths: behind the camera, far off-image (small), off-axis beyond 1.3× fov but large enough to
    reach the image (the Jacobian clamp binds), and with ``tiny`` scales of 1e-5 plus one of 0 (with
    eps2d = 0 their determinant is clamped to 1e-12). Quaternions are unnormalised."""
    g = torch.Generator().manual_seed(seed)
    means = torch.randn(n, 3, generator=g) * 2.0
    quats = torch.randn(n, 4, generator=g) * (torch.rand(n, 1, generator=g) * 3 + 0.1)
    scales = torch.rand(n, 3, generator=g) * 0.3 + 0.01
    k = n // 10
    means[:k, 2] = -3.5 - torch.rand(k, generator=g)
    means[k:2 * k, 0] = 30 + 10 * torch.rand(k, generator=g)
    means[2 * k:3 * k, 0] = 3.5 + torch.rand(k, generator=g)
    scales[2 * k:3 * k] = 2.5 + torch.rand(k, 3, generator=g)
    if tiny:
        scales[3 * k:4 * k] = 1e-5 * (1 + torch.rand(k, 3, generator=g))
        scales[4 * k] = 0.0
    return means, quats, scales


def _f64_facts(means, quats, scales, cam: Camera, eps2d: float):
    """Per Gaussian, in float64 with the textbook formula: camera z, whether the Jacobian clamp binds,
    and the unclamped determinant of the dilated 2D covariance."""
    v = _view(cam, torch.float64, torch.device("cpu"))
    m, q, s = means.double(), quats.double(), scales.double()
    pc = m @ v.rw.T + v.tw
    z = pc[:, 2]
    r = pc[:, :2] / z[:, None]
    u = torch.minimum(torch.maximum(r, v.lo), v.hi)
    T = (v.rw[:2] - u[:, :, None] * v.rw[2]) * (v.f / z[:, None])[:, :, None]
    P = T @ quat_to_rotmat(q) * s[:, None, :]
    cov = P @ P.transpose(1, 2) + eps2d * torch.eye(2, dtype=torch.float64)
    return z, (r != u).any(1), torch.linalg.det(cov)


def _run(means, quats, scales, cam, eps2d, fused):
    leaves = [t.clone().requires_grad_(True) for t in (means, quats, scales)]
    p = project_gaussians(*leaves, cam, eps2d=eps2d, fused=fused)
    g = torch.Generator().manual_seed(5)
    w = [torch.randn(t.shape, generator=g) for t in (p.means2d, p.conics, p.depths)]
    loss = sum((o * v).sum() for o, v in zip((p.means2d, p.conics, p.depths), w))
    return p, torch.autograd.grad(loss, leaves)


def _assert_rows_close(x: torch.Tensor, y: torch.Tensor, tol: float, what: str) -> None:
    """|x − y| <= tol · max |y| over the row (a Gaussian's components share its scale)."""
    scale = y.abs().amax(1, keepdim=True)
    bad = (x - y).abs() > tol * scale
    assert not bad.any(), f"{what}: {int(bad.sum())} entries off, worst {((x - y).abs() / scale).max():.3g}"


@needs_cc
@pytest.mark.parametrize("seed,eps2d,tiny", [(0, 0.3, False), (1, 0.3, False), (2, 0.0, True), (3, 0.0, True)])
def test_compiled_matches_torch_path(seed, eps2d, tiny):
    assert projection.fused_available()
    cam = _camera()
    means, quats, scales = _scene(3000, seed, tiny)
    pc, gc = _run(means, quats, scales, cam, eps2d, fused=True)
    pt, gt = _run(means, quats, scales, cam, eps2d, fused=False)

    # The scene has every edge case, among the culled or among the survivors.
    z, clamped, det = _f64_facts(means, quats, scales, cam, eps2d)
    assert (z <= 0.01).sum() >= 300 and not torch.isin(torch.nonzero(z <= 0.01)[:, 0], pc.ids).any()
    off_image = torch.ones(len(z), dtype=torch.bool)
    off_image[pc.ids] = False
    assert (off_image & (z > 0.01)).sum() >= 300
    assert clamped[pc.ids].sum() >= 100
    if tiny:
        assert (det[pc.ids] < 1e-12).sum() >= 50

    assert pc.ids.dtype == torch.long and torch.equal(pc.ids, pt.ids)
    assert not pc.radii.requires_grad and pc.means2d.requires_grad
    torch.testing.assert_close(pc.means2d, pt.means2d, rtol=1e-5, atol=1e-4)
    torch.testing.assert_close(pc.depths, pt.depths, rtol=1e-5, atol=1e-5)
    torch.testing.assert_close(pc.radii, pt.radii, rtol=1e-5, atol=1e-4)
    _assert_rows_close(pc.conics, pt.conics, 1e-4, "conics")
    for name, a, b, tol in zip(("means3d", "quats", "scales"), gc, gt, (1e-4, 1e-3, 1e-4)):
        _assert_rows_close(a, b, tol, f"gradient of {name}")
        culled = torch.ones(len(a), dtype=torch.bool)
        culled[pc.ids] = False
        assert a[culled].eq(0).all()


@needs_cc
def test_camera_quantities_are_those_of_view():
    ext = projection._JIT.module()
    cams = [_camera(), Camera.look_at([1.0, 2.0, -5.0], [0.1, 0.0, 0.3], [0, -1, 0], fx=333.3, fy=312.7,
                                      width=641, height=377, cx=300.1, cy=201.9)]
    cams.append(Camera(cams[1].K.double() * 1.0001, cams[1].viewmat.double() * 0.999, 640, 480))   # float64 camera
    cams.append(Camera(torch.tensor([[50, 0, 31], [0, 50, 23], [0, 0, 1]]), torch.eye(4), 64, 48))  # integer K
    for cam in cams:
        v = _view(cam, torch.float32, torch.device("cpu"))
        want = torch.cat([v.rw.reshape(-1), v.tw, v.f, v.c, v.lo, v.hi, v.size])
        assert torch.equal(ext.camera(projection._packed_view(v)), want)


@needs_cc
def test_thread_count_does_not_change_the_bits():
    cam = _camera()
    means, quats, scales = _scene(20000, 7, tiny=True)   # > 2048 Gaussians: the loops run in parallel
    n0 = torch.get_num_threads()
    out = []
    try:
        for threads in (1, 2):
            torch.set_num_threads(threads)
            p, g = _run(means, quats, scales, cam, 0.3, fused=True)
            out.append([p.ids, p.means2d, p.conics, p.depths, p.radii, *g])
    finally:
        torch.set_num_threads(n0)
    for a, b in zip(*out):
        assert torch.equal(a, b)


@needs_cc
def test_dispatch_and_structure():
    cam = _camera()
    means, quats, scales = _scene(50, 0)
    p32 = project_gaussians(*(t.clone().requires_grad_(True) for t in (means, quats, scales)), cam)
    assert type(p32.means2d.grad_fn).__name__ == "_ProjectCPUBackward"
    p_torch = project_gaussians(*(t.clone().requires_grad_(True) for t in (means, quats, scales)), cam, fused=False)
    assert type(p_torch.means2d.grad_fn).__name__ == "_ProjectBackward"
    p64 = project_gaussians(*(t.double().requires_grad_(True) for t in (means, quats, scales)), cam)
    assert type(p64.means2d.grad_fn).__name__ == "_ProjectBackward" and p64.means2d.dtype == torch.float64
    with pytest.raises(RuntimeError, match="float32 CPU"):
        project_gaussians(means.double(), quats.double(), scales.double(), cam, fused=True)
    with pytest.raises(RuntimeError, match="float32 CPU"):                 # one input of another dtype
        project_gaussians(means, quats.double(), scales, cam, fused=True)
    for a, b in zip((p32.ids, p32.means2d, p32.conics, p32.depths, p32.radii),
                    (p_torch.ids, p_torch.means2d, p_torch.conics, p_torch.depths, p_torch.radii)):
        assert a.dtype == b.dtype and a.shape == b.shape and a.requires_grad == b.requires_grad


@needs_cc
def test_strided_inputs_expanded_gradients_and_no_grad():
    cam = _camera()
    means, quats, scales = _scene(200, 4)
    wide = torch.cat([quats, torch.zeros(200, 3)], 1).requires_grad_(True)
    leaves = [means.clone().requires_grad_(True), wide, scales.clone().requires_grad_(True)]
    q = wide[:, :4]                                                            # rows 7 floats apart
    assert not q.is_contiguous()
    p = project_gaussians(leaves[0], q, leaves[2], cam, fused=True)
    (p.means2d.sum() + p.conics.sum() + p.depths.sum()).backward()           # expanded (stride-0) gradients
    ref = [t.clone().requires_grad_(True) for t in (means, quats, scales)]
    pr = project_gaussians(*ref, cam, fused=False)
    (pr.means2d.sum() + pr.conics.sum() + pr.depths.sum()).backward()
    for a, b in zip((leaves[0].grad, leaves[1].grad[:, :4], leaves[2].grad), (r.grad for r in ref)):
        _assert_rows_close(a, b, 1e-3, "gradient")
    with torch.no_grad():
        pn = project_gaussians(means, quats, scales, cam, fused=True)
    assert torch.equal(pn.means2d, p.means2d.detach()) and pn.means2d.grad_fn is None


@needs_cc
def test_nothing_visible_and_no_gaussians():
    cam = _camera()
    means = torch.tensor([[0.3, -0.2, -4.0], [40.0, 0.0, 0.0]], requires_grad=True)
    p = project_gaussians(means, torch.tensor([[1.0, 0, 0, 0]] * 2), torch.full((2, 3), 0.1), cam, fused=True)
    assert p.ids.numel() == 0 and p.means2d.shape == (0, 2) and p.conics.shape == (0, 3)
    (p.means2d.sum() + p.conics.sum()).backward()
    assert means.grad.eq(0).all()
    empty = torch.zeros(0, 3, requires_grad=True)
    p = project_gaussians(empty, torch.zeros(0, 4), torch.zeros(0, 3), cam, fused=True)
    assert p.ids.shape == (0,) and p.radii.shape == (0, 2)
    p.depths.sum().backward()
    assert empty.grad.shape == (0, 3)


def test_unavailable_extension_falls_back_or_raises(monkeypatch):
    monkeypatch.setenv("SMGS_DISABLE_CPU_BACKEND", "1")   # a fresh extension checks it before building
    monkeypatch.setattr(projection, "_JIT", cpu_extension("x", [], "projection kernel"))
    cam = _camera()
    means, quats, scales = _scene(20, 0)
    p = project_gaussians(means.requires_grad_(True), quats, scales, cam)
    assert type(p.means2d.grad_fn).__name__ == "_ProjectBackward"
    with pytest.raises(RuntimeError, match="disabled by SMGS_DISABLE_CPU_BACKEND"):
        project_gaussians(means, quats, scales, cam, fused=True)
