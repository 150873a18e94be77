"""The training loss: fast SSIM equals the metric's SSIM; the per-ray variance regulariser."""

import torch

from smgs.metrics.ssim import ssim
from smgs.raster import rasterize_splats
from smgs.metrics.image import psnr
from smgs.train.loss import SSIMLoss, l1, ray_variance


def test_fast_ssim_matches_metric_value_and_gradient():
    torch.manual_seed(0)
    f = SSIMLoss()
    for h, w in ((24, 40), (17, 9)):
        y = torch.rand(h, w, 3)
        x = (0.7 * y + 0.3 * torch.rand(h, w, 3)).requires_grad_(True)
        v_ref = ssim(x, y)
        (g_ref,) = torch.autograd.grad(v_ref, x)
        v = f(x, y)
        (g,) = torch.autograd.grad(v, x)
        torch.testing.assert_close(v, v_ref, atol=1e-6, rtol=0)
        torch.testing.assert_close(g, g_ref, atol=1e-7, rtol=1e-4)
        v2 = f(x, y)            # cached target statistics
        torch.testing.assert_close(v2, v)


def test_ray_variance_by_hand():
    # layout [Σw, Σw·v1, Σw·v2, Σw·v1², Σw·v2²]. pixel 0: v1 = 1 and 3 with weights 1 and 1
    # -> variance 1; pixel 1: one splat -> 0; pixel 2: no splat -> left out of the mean.
    reg = torch.zeros(1, 3, 5)
    reg[0, 0] = torch.tensor([2.0, 4.0, 0.0, 10.0, 0.0])
    reg[0, 1] = torch.tensor([0.5, 1.0, 0.5, 2.0, 0.5])
    var = ray_variance(reg)
    torch.testing.assert_close(var, torch.tensor([0.5, 0.0]))
    assert ray_variance(torch.zeros(2, 2, 5)).eq(0).all()


def test_regulariser_from_renderer_pulls_values_together():
    """Two overlapping splats with different β: the variance is positive, weighted by depth, and its
    gradient moves the values towards each other."""
    m = torch.tensor([[8.0, 8.0], [8.5, 8.0]])
    con = torch.tensor([[0.05, 0.0, 0.05]] * 2)
    args = dict(width=16, height=16, mode="softmax_gs", backend="reference")
    beta = torch.tensor([1.0, 3.0], requires_grad=True)
    vals = torch.stack([beta, torch.zeros(2)], 1)
    out = rasterize_splats(m, con, torch.full((2,), 0.5), torch.rand(2, 3), torch.tensor([1.0, 1.0]),
                           torch.ones(2), beta.detach(), torch.ones(2), reg_values=vals, reg_depth_scale=1.0, **args)
    vb, vg = ray_variance(out.reg)
    assert float(vg.detach()) == 0.0
    torch.testing.assert_close(vb, torch.tensor(1.0), atol=1e-5, rtol=0)   # equal weights at equal depth
    vb.backward()
    assert beta.grad[0] < 0 < beta.grad[1]
    # the splat behind gets a smaller weight: the variance drops below the equal-weight value
    out2 = rasterize_splats(m, con, torch.full((2,), 0.5), torch.rand(2, 3), torch.tensor([1.0, 2.0]),
                            torch.ones(2), beta.detach(), torch.ones(2), reg_values=vals.detach(),
                            reg_depth_scale=0.1, **args)
    assert 0 < float(ray_variance(out2.reg)[0]) < 1.0


def test_l1_and_psnr():
    x, y = torch.zeros(2, 2, 3), torch.full((2, 2, 3), 0.1)
    assert abs(float(l1(x, y)) - 0.1) < 1e-7
    assert abs(psnr(x, y) - 20.0) < 1e-4
    assert psnr(y, y) == float("inf")


def test_ray_variance_gradient_matches_autograd_formula():
    gen = torch.Generator().manual_seed(0)
    w = torch.rand(6, 5, 1, generator=gen, dtype=torch.float64)
    w[0, :3] = 0                                               # uncovered pixels
    v = torch.rand(6, 5, 2, generator=gen, dtype=torch.float64)
    reg = torch.cat([w, w * v, w * v * v * 1.3], -1).requires_grad_(True)

    def by_hand(reg):
        f = reg.reshape(-1, 5)
        f = f[f[:, 0] > 0]
        mean = f[:, 1:3] / f[:, :1]
        return (f[:, 3:] / f[:, :1] - mean * mean).clamp_min(0).mean(0)

    torch.testing.assert_close(ray_variance(reg), by_hand(reg))
    gw = torch.tensor([0.7, -1.1], dtype=torch.float64)
    (g,) = torch.autograd.grad((ray_variance(reg) * gw).sum(), reg)
    (g_ref,) = torch.autograd.grad((by_hand(reg) * gw).sum(), reg)
    torch.testing.assert_close(g, g_ref)
