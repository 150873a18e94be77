"""The CUDA projection (csrc/projection_cuda.cu, part of the opt-in kernels; docs/cuda.md) against the
compiled CPU projection: both build csrc/projection_math.h without FMA contraction, with IEEE
division and square root, so every kept row, every gradient and every SH colour must be the same
bits. Culled rows are zeros with radii (0, 0) (no compaction), and their gradients zero. Marked
``gpu``; skipped where no CUDA device is visible.
"""

from __future__ import annotations

import pytest
import torch

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster import projection, projection_cuda

pytestmark = pytest.mark.gpu

if not torch.cuda.is_available():
    pytest.skip("no CUDA device visible (torch.cuda.is_available() is False)", allow_module_level=True)

from test_raster_projection_math import _edge_scene, _scenes  # noqa: E402


def _bits_equal(a: torch.Tensor, b: torch.Tensor, what: str) -> None:
    a, b = a.detach().cpu(), b.detach().cpu()
    assert a.shape == b.shape, what
    if not torch.equal(a, b):
        bad = a != b
        raise AssertionError(f"{what}: {int(bad.sum())} of {a.numel()} entries differ, worst "
                             f"{float((a - b).abs().max()):.3g}")


@pytest.mark.parametrize("idx", range(4))
def test_cuda_projection_equals_the_cpu_projection_bit_for_bit(idx):
    scenes = _scenes()
    if idx >= len(scenes):
        pytest.skip("fewer scenes here")
    name, means, quats, scales, cam, eps = scenes[idx]
    cpu = projection._JIT.module()
    view = projection._packed_view(projection._view(cam, torch.float32, torch.device("cpu")))
    ids, m2, con, dep, rad = cpu.forward(means, quats, scales, view, K.NEAR_PLANE, eps, K.SIGMA_EXTENT)
    ext = projection_cuda.extension()
    floats = projection_cuda.camera_floats(cam)
    dev = [t.cuda() for t in (means, quats, scales)]
    empty = torch.empty(0, device="cuda")
    gm2, gcon, gdep, grad, gcol, _ = ext.forward(*dev, empty, floats, K.NEAR_PLANE, eps, K.SIGMA_EXTENT, -1, True,
                                                 False, [], [], empty)
    n = means.shape[0]
    kept = torch.zeros(n, dtype=torch.bool)
    kept[ids] = True
    assert kept.sum() > 100 and (~kept).sum() > 0, name
    _bits_equal(gm2.cpu()[ids], m2, f"{name} means2d")
    _bits_equal(gcon.cpu()[ids], con, f"{name} conics")
    _bits_equal(gdep.cpu()[ids], dep, f"{name} depths")
    _bits_equal(grad.cpu()[ids], rad, f"{name} radii")
    for t in (gm2, gcon, gdep, grad):
        assert (t.cpu()[~kept] == 0).all(), name
    # gradients: the same random gradients of the kept rows on both sides
    g = torch.Generator().manual_seed(2)
    gr = [torch.randn(n, 2, generator=g), torch.randn(n, 3, generator=g), torch.randn(n, generator=g)]
    want = cpu.backward(means, quats, scales, view, K.NEAR_PLANE, eps, ids, gr[0][ids], gr[1][ids], gr[2][ids])
    got = ext.backward(*dev, empty, floats, K.NEAR_PLANE, eps, -1, True, grad, *(t.cuda() for t in gr), empty)
    # a kept Gaussian of zero extent (zero scales with eps2d = 0: radii (0, 0)) is culled by the fused
    # path (docs/cuda.md); everywhere else the gradients are the same bits
    live = (grad.cpu() != 0).any(1)
    assert (kept & ~live).sum() <= 1, name
    for a, b, what in zip(got[:3], want, ("means3d", "quats", "scales")):
        _bits_equal(a.cpu()[live], b[live], f"{name} gradient of {what}")
        assert (a.cpu()[~live] == 0).all(), name


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
def test_cuda_sh_colours_equal_the_cpu_stage_bit_for_bit(degree):
    means, quats, scales = _edge_scene(4000, degree)
    cam = Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=60.0, fy=55.0, width=64, height=48)
    sh = torch.randn(4000, 16, 3, generator=torch.Generator().manual_seed(degree)) * 0.5
    ext, cpu = projection_cuda.extension(), projection._JIT.module()
    floats = projection_cuda.camera_floats(cam)
    center = floats[22:]
    dev = [t.cuda() for t in (means, quats, scales, sh)]
    m2, con, dep, rad, col, _ = ext.forward(*dev, floats, K.NEAR_PLANE, 0.3, K.SIGMA_EXTENT, degree, True, False, [],
                                            [], dev[0].new_empty(0))
    kept = (rad.cpu() != 0).any(1)
    want = cpu.sh_forward(means, sh, center, degree, True)
    _bits_equal(col.cpu()[kept], want[kept], f"SH degree {degree} colours")
    assert (col.cpu()[~kept] == 0).all()
    g_col = torch.randn(4000, 3, generator=torch.Generator().manual_seed(7))
    g_col[~kept] = 0.0   # the compositing gives culled rows nothing
    zeros = [torch.zeros(4000, 2), torch.zeros(4000, 3), torch.zeros(4000)]
    gm, gq, gs, gsh = ext.backward(*dev, floats, K.NEAR_PLANE, 0.3, degree, True, rad, *(t.cuda() for t in zeros),
                                   g_col.cuda())
    wm, wsh = cpu.sh_backward(means, sh, center, degree, True, g_col)
    # with zero 2D gradients the projection adds exactly 0 to the means: only the SH part remains
    _bits_equal(gsh.cpu()[kept], wsh[kept], f"SH degree {degree} coefficient gradients")
    _bits_equal(gm.cpu()[kept], wm[kept], f"SH degree {degree} means gradients")
    assert (gsh.cpu()[~kept] == 0).all() and (gm.cpu()[~kept] == 0).all()


def test_cuda_projection_autograd_and_strided_gradients():
    """project_fused through autograd, the 2D gradients handed as columns of one packed buffer (as
    the v2 compositing does): the same gradients as from contiguous copies."""
    means, quats, scales = _edge_scene(3000, 4)
    cam = Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=60.0, fy=55.0, width=64, height=48)
    packed = torch.randn(3000, 13, generator=torch.Generator().manual_seed(1)).cuda()
    outs = []
    for strided in (True, False):
        leaves = [t.cuda().requires_grad_(True) for t in (means, quats, scales)]
        p = projection_cuda.project_fused(*leaves, cam)
        g2, gc, gd = packed[:, 0:2], packed[:, 2:5], packed[:, 6]
        if not strided:
            g2, gc, gd = g2.contiguous(), gc.contiguous(), gd.contiguous()
        torch.autograd.backward([p.means2d, p.conics, p.depths], [g2, gc, gd])
        outs.append([t.grad.cpu() for t in leaves])
        assert not p.radii.requires_grad and p.colors is None
    for a, b in zip(*outs):
        assert torch.equal(a, b)


def test_the_forward_kernel_checks_the_renderers_inputs_where_asked():
    """The lean glue's input checks inside the projection (projection_cuda.h ProjChecks): a Gaussian
    with a non-finite input among its own, its checked rows (+inf allowed in gamma's) or a negative
    scale is culled (zeros, radii (0, 0)) and raises the flag; so does a bad background; the other
    rows are the unchecked kernel's to the bit."""
    means, quats, scales = _edge_scene(2000, 0)
    cam = Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=60.0, fy=55.0, width=64, height=48)
    ext, floats = projection_cuda.extension(), projection_cuda.camera_floats(cam)
    dev = [t.cuda() for t in (means, quats, scales)]
    empty = torch.empty(0, device="cuda")
    opac, gamma = torch.full((2000,), 0.5, device="cuda"), torch.ones(2000, device="cuda")
    gamma[3] = float("inf")   # allowed
    bg = torch.tensor([0.1, 0.2, 0.3], device="cuda")
    args = (K.NEAR_PLANE, 0.3, K.SIGMA_EXTENT, -1, True)
    plain = ext.forward(*dev, empty, floats, *args, False, [], [], empty)
    good = ext.forward(*dev, empty, floats, *args, True, [opac, gamma], [0, 1], bg)
    assert int(good[5].item()) == 0
    for a, b, what in zip(plain[:4], good[:4], ("means2d", "conics", "depths", "radii")):
        _bits_equal(a, b, what)
    live = (plain[3].cpu() != 0).any(1).nonzero()[:, 0]
    rows = live[:4].tolist()
    dev[0][rows[0], 1] = float("nan")
    dev[2][rows[1], 0] = -0.1
    opac[rows[2]] = float("inf")
    gamma[rows[3]] = -float("inf")
    out = ext.forward(*dev, empty, floats, *args, True, [opac, gamma], [0, 1], bg)
    assert int(out[5].item()) != 0
    assert (out[3].cpu()[rows] == 0).all() and torch.isfinite(out[0]).all() and torch.isfinite(out[1]).all()
    dev[0][rows[0], 1], dev[2][rows[1], 0], opac[rows[2]], gamma[rows[3]] = 0.0, 0.1, 0.5, 1.0
    bg[1] = float("nan")
    assert int(ext.forward(*dev, empty, floats, *args, True, [opac, gamma], [0, 1], bg)[5].item()) != 0
    empty3 = [t[:0].contiguous() for t in dev]   # no Gaussians: the background is checked all the same
    assert int(ext.forward(*empty3, empty, floats, *args, True, [], [], bg)[5].item()) != 0
