"""The fused photometric loss (compiled CPU pass) against the metric's SSIM and torch's L1 under
autograd: value, gradient, parts, and independence from the thread count."""

import shutil

import pytest
import torch
import torch.nn.functional as F

from smgs.metrics.ssim import ssim
from smgs.train.image_loss import PhotometricLoss, fused_available, ray_variance

# every SIMD path of the compiled CPU kernels this host runs (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("cpu_isa")

needs_cc = pytest.mark.skipif(shutil.which("c++") is None, reason="no C++ compiler: no compiled loss")


def oracle(x, y, lam):
    return (1 - lam) * F.l1_loss(x, y) + lam * (1 - ssim(x, y))


@needs_cc
@pytest.mark.parametrize("h,w,c", [(24, 40, 3), (17, 9, 3), (5, 30, 1), (64, 48, 4)])
def test_fused_matches_metric_ssim_and_l1(h, w, c):
    assert fused_available()
    g = torch.Generator().manual_seed(h * w + c)
    y = torch.rand(h, w, c, generator=g)
    x = (0.7 * y + 0.3 * torch.rand(h, w, c, generator=g))
    x[0, 0] = y[0, 0]                                   # |x − y| at 0: torch's L1 gradient is 0 there
    x = x.requires_grad_(True)
    lam = 0.2
    ref = oracle(x, y, lam)
    (g_ref,) = torch.autograd.grad(ref, x)
    parts = PhotometricLoss(lam, fused=True)(x, y)
    (g_f,) = torch.autograd.grad(parts.total * 3.0, x)  # the upstream gradient is applied
    torch.testing.assert_close(parts.total, ref.detach(), atol=2e-6, rtol=0)
    torch.testing.assert_close(g_f, 3.0 * g_ref, atol=1e-7, rtol=1e-4)
    assert parts.l1 == pytest.approx(float(F.l1_loss(x.detach(), y)), abs=1e-7)
    assert parts.ssim == pytest.approx(float(ssim(x.detach(), y)), abs=2e-6)
    assert parts.mse == pytest.approx(float(F.mse_loss(x.detach(), y)), rel=1e-5)


@needs_cc
def test_fused_and_torch_paths_agree_and_the_thread_count_does_not_matter():
    g = torch.Generator().manual_seed(1)
    y = torch.rand(37, 53, 3, generator=g)
    x = torch.rand(37, 53, 3, generator=g).requires_grad_(True)
    out = {}
    n0 = torch.get_num_threads()
    try:
        for name, fused, threads in (("torch", False, 1), ("fused1", True, 1), ("fused2", True, 2)):
            torch.set_num_threads(threads)
            p = PhotometricLoss(0.2, fused=fused)(x, y)
            (gr,) = torch.autograd.grad(p.total, x)
            out[name] = (p, gr)
    finally:
        torch.set_num_threads(n0)
    assert out["fused1"][0].total.item() == out["fused2"][0].total.item()
    assert torch.equal(out["fused1"][1], out["fused2"][1])
    torch.testing.assert_close(out["fused1"][0].total, out["torch"][0].total, atol=2e-6, rtol=0)
    torch.testing.assert_close(out["fused1"][1], out["torch"][1], atol=1e-7, rtol=1e-4)


def test_float64_takes_the_torch_path_and_bad_shapes_are_refused():
    y = torch.rand(12, 12, 3, dtype=torch.float64)
    x = y.clone().requires_grad_(True)
    p = PhotometricLoss(0.2)(x, y)
    assert p.total.dtype == torch.float64 and p.ssim == pytest.approx(1.0) and p.l1 == 0.0
    with pytest.raises(ValueError, match="float32 CPU"):
        PhotometricLoss(0.2, fused=True)(x, y)
    with pytest.raises(ValueError, match="one shape"):
        PhotometricLoss(0.2)(x, y[:, :5])


@needs_cc
def test_fused_ray_variance_matches_the_torch_path():
    gen = torch.Generator().manual_seed(3)
    w = torch.rand(20, 17, 1, generator=gen)
    w[w < 0.3] = 0                                               # uncovered pixels
    v = torch.randn(20, 17, 2, generator=gen)
    reg = torch.cat([w, w * v, w * v * v * 1.2], -1)
    reg[0, 0, 0], reg[0, 0, 3] = 0.5, -1.0                        # a negative variance: clamped to 0
    gw = torch.tensor([0.7, -1.3])
    out = {}
    for fused in (True, False):
        r = reg.clone().requires_grad_(True)
        var = ray_variance(r, fused=fused)
        (g,) = torch.autograd.grad((var * gw).sum(), r)
        out[fused] = (var.detach(), g)
    torch.testing.assert_close(out[True][0], out[False][0], rtol=1e-5, atol=1e-7)
    torch.testing.assert_close(out[True][1], out[False][1], rtol=1e-5, atol=1e-8)
    assert out[True][1][0, 0, 3] == 0 and out[True][1][reg[..., 0] == 0].eq(0).all()
    assert ray_variance(torch.zeros(3, 3, 5), fused=True).eq(0).all()          # nothing covered
    with pytest.raises(RuntimeError, match="float32 CPU"):
        ray_variance(reg.double(), fused=True)
