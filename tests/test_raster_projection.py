"""The fused EWA projection: culling, values and its hand-written backward."""

import torch

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster.projection import project_gaussians, quat_to_rotmat


def _camera() -> Camera:
    return Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=60.0, fy=55.0, width=64, height=48)


def _gaussians(n: int = 40):
    """Random Gaussians plus the edge cases: one behind the camera, one far off-screen, and a large
    off-axis one whose Jacobian direction is clamped (1.3× fov) but whose 3σ box reaches the image."""
    gen = torch.Generator().manual_seed(0)
    means = torch.randn(n, 3, generator=gen, dtype=torch.float64) * 1.5
    quats = torch.randn(n, 4, generator=gen, dtype=torch.float64)
    scales = torch.rand(n, 3, generator=gen, dtype=torch.float64) * 0.3 + 0.01
    means[0] = torch.tensor([0.3, -0.2, -4.0])          # behind the camera
    means[1] = torch.tensor([40.0, 0.0, 0.0])           # off to the side, small
    means[2] = torch.tensor([4.0, 0.0, 0.0])            # off-axis beyond 1.3× fov, large
    scales[2] = torch.tensor([3.0, 3.0, 3.0])
    return means, quats, scales


def _autograd_projection(means, quats, scales, cam: Camera):
    """The textbook formula with autograd: Σ2D = J W R S Sᵀ Rᵀ Wᵀ Jᵀ + eps2d·I at the mean clamped
    to 1.3× the field of view (3DGS), for every Gaussian (no culling)."""
    V, Kc = cam.viewmat.to(means.dtype), cam.K.to(means.dtype)
    W = V[:3, :3]
    pc = means @ W.T + V[:3, 3]
    x, y, z = pc.unbind(1)
    fx, fy, cx, cy = Kc[0, 0], Kc[1, 1], Kc[0, 2], Kc[1, 2]
    mx, my = 0.15 * cam.width / fx, 0.15 * cam.height / fy
    tx = z * torch.clamp(x / z, -cx / fx - mx, (cam.width - cx) / fx + mx)
    ty = z * torch.clamp(y / z, -cy / fy - my, (cam.height - cy) / fy + my)
    zero = torch.zeros_like(z)
    J = torch.stack([fx / z, zero, -fx * tx / z**2, zero, fy / z, -fy * ty / z**2], 1).reshape(-1, 2, 3)
    M = quat_to_rotmat(quats) * scales[:, None, :]
    cov = J @ W @ M @ M.transpose(1, 2) @ W.T @ J.transpose(1, 2)
    a, b, c = cov[:, 0, 0] + K.EPS2D, cov[:, 0, 1], cov[:, 1, 1] + K.EPS2D
    det = a * c - b * b
    conics = torch.stack([c, -b, a], 1) / det[:, None]
    means2d = torch.stack([fx * x / z + cx, fy * y / z + cy], 1)
    return means2d, conics, z


def test_culling_keeps_the_visible_gaussians_in_order():
    means, quats, scales = _gaussians()
    p = project_gaussians(means, quats, scales, _camera())
    ids = p.ids.tolist()
    assert ids == sorted(ids) and 0 not in ids and 1 not in ids and 2 in ids
    assert p.means2d.shape == (len(ids), 2) and p.radii.shape == (len(ids), 2)
    box = p.means2d + p.radii
    assert (box > 0).all() and ((p.means2d - p.radii) < torch.tensor([64.0, 48.0], dtype=torch.float64)).all()


def test_values_and_gradients_match_the_autograd_formula():
    means, quats, scales = _gaussians()
    cam = _camera()
    a = [t.clone().requires_grad_(True) for t in (means, quats, scales)]
    b = [t.clone().requires_grad_(True) for t in (means, quats, scales)]
    p = project_gaussians(*a, cam)
    m2, con, dep = _autograd_projection(*b, cam)
    m2, con, dep = m2[p.ids], con[p.ids], dep[p.ids]
    torch.testing.assert_close(p.means2d, m2)
    torch.testing.assert_close(p.conics, con)
    torch.testing.assert_close(p.depths, dep)
    gen = torch.Generator().manual_seed(1)
    w = [torch.randn(t.shape, generator=gen, dtype=t.dtype) for t in (m2, con, dep)]
    ga = torch.autograd.grad(sum((o * v).sum() for o, v in zip((p.means2d, p.conics, p.depths), w)), a)
    gb = torch.autograd.grad(sum((o * v).sum() for o, v in zip((m2, con, dep), w)), b)
    for x, y in zip(ga, gb):
        torch.testing.assert_close(x, y)
    assert ga[0][0].eq(0).all() and ga[0][1].eq(0).all()     # culled: no gradient


def test_backward_passes_gradcheck():
    means, quats, scales = _gaussians(12)
    cam = _camera()

    def f(m, q, s):
        p = project_gaussians(m, q, s, cam)
        return p.means2d, p.conics, p.depths

    assert torch.autograd.gradcheck(f, [t.requires_grad_(True) for t in (means, quats, scales)])


def test_nothing_visible():
    means = torch.tensor([[0.3, -0.2, -4.0]], requires_grad=True)
    p = project_gaussians(means, torch.tensor([[1.0, 0, 0, 0]]), torch.full((1, 3), 0.1), _camera())
    assert p.ids.numel() == 0 and p.means2d.shape == (0, 2)
    (p.means2d.sum() + p.conics.sum()).backward()
    assert means.grad.eq(0).all()
