"""The colours from spherical harmonics inside the compiled CPU projection (csrc/projection_cpu.cpp,
``projection.ShColours``) against the float64 oracle: ``_Project`` and ``sh.eval_sh`` through
autograd, every degree, with and without the clamp, the coefficients in two parts (the trainer's
sh0 / shN, read in place) and as one tensor, on every SIMD path this host runs.

Tolerances: float32 against float64. The colours are sums of up to 16 products of a basis value
(|b| < 3) and a coefficient (~0.5), so ~1e-6 absolute; the coefficients' gradients are a basis
value times the colour's gradient (1e-6 of the row); the means' gradient through the view direction
goes through 1/|m − centre| and adds to the projection's, whose float32 rounding the projection's
own tests bound at 1e-4 of the row (1e-3 for the quaternions: tests/test_raster_projection_cpu.py).
"""

from __future__ import annotations

import shutil

import pytest
import torch

from smgs.camera import Camera
from smgs.raster import projection
from smgs.raster.projection import ShColours, host_view, project_gaussians
from smgs.raster.sh import num_sh_bases
from test_raster_projection_cpu import _assert_rows_close, _camera, _scene

pytestmark = [pytest.mark.usefixtures("cpu_isa"),
              pytest.mark.skipif(shutil.which("c++") is None, reason="no C++ compiler: no compiled projection")]


def _inputs(n: int, degree: int, seed: int):
    means, quats, scales = _scene(n, seed)
    g = torch.Generator().manual_seed(100 + seed)
    k = 16 if degree == 3 else num_sh_bases(degree) + 2    # more coefficients than the degree reads
    sh0 = torch.randn(n, 1, 3, generator=g) * 0.8           # some colours under 0: the clamp binds
    rest = torch.randn(n, k - 1, 3, generator=g) * 0.4
    return means, quats, scales, sh0, rest


def _project(means, quats, scales, sh0, rest, degree, clamp, fused, one_tensor=False, dtype=torch.float32):
    """The projection with colours and the gradients of a loss over its outputs: (projected, grads of
    means, quats, scales, and the coefficients (sh0, rest; or the one tensor))."""
    leaves = [t.to(dtype).clone().requires_grad_(True) for t in (means, quats, scales)]
    if one_tensor:
        coefs = [torch.cat([sh0, rest], 1).to(dtype).requires_grad_(True)]
        sh = ShColours(coefs[0], None, degree, clamp)
    else:
        coefs = [t.to(dtype).clone().requires_grad_(True) for t in (sh0, rest)]
        sh = ShColours(coefs[0], coefs[1], degree, clamp)
    cam = _camera()
    view = host_view(cam, dtype, center=True)
    p = project_gaussians(*leaves, cam, fused=fused, view=view, sh=sh)
    return p, leaves + coefs


def _weights(p, seed=5):
    g = torch.Generator().manual_seed(seed)
    return [torch.randn(t.shape, generator=g, dtype=torch.float64) for t in (p.means2d, p.conics, p.depths, p.colors)]


def _grads(p, leaves, w, colours_only: bool):
    outs = (p.colors,) if colours_only else (p.means2d, p.conics, p.depths, p.colors)
    ws = w[3:] if colours_only else w
    loss = sum((o * v.to(o.dtype)).sum() for o, v in zip(outs, ws))
    return torch.autograd.grad(loss, leaves, allow_unused=True, retain_graph=True)


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("clamp", [True, False])
def test_colours_and_every_gradient_equal_the_float64_reference(degree, clamp):
    means, quats, scales, sh0, rest = _inputs(3000, degree, seed=degree)
    pc, leaves_c = _project(means, quats, scales, sh0, rest, degree, clamp, fused=True)
    pr, leaves_r = _project(means, quats, scales, sh0, rest, degree, clamp, fused=False, dtype=torch.float64)
    assert type(pc.colors.grad_fn).__name__ == "_ProjectCPUBackward"     # the colours are the kernel's
    assert torch.equal(pc.ids, pr.ids) and 500 < pc.ids.numel() < 3000     # some culled, many kept
    torch.testing.assert_close(pc.colors.double(), pr.colors, rtol=1e-5, atol=2e-6)
    if clamp:   # the clamp binds on some rows and passes no gradient there
        assert (pr.colors == 0).sum() >= 50 and pc.colors[pr.colors == 0].eq(0).all()
    else:
        assert (pc.colors < 0).any()
    w = _weights(pr)
    for colours_only in (True, False):
        gc = _grads(pc, leaves_c, w, colours_only)
        gr = _grads(pr, leaves_r, w, colours_only)
        names = ("means3d", "quats", "scales", "sh0", "rest")
        for name, a, b in zip(names, gc, gr):
            if colours_only and name in ("quats", "scales"):       # the colours do not depend on them
                assert a is None or a.eq(0).all(), name
                continue
            if b is None:   # degree 0: the means get nothing from the colours (no view direction)
                assert a is None or a.eq(0).all(), name
                continue
            flat = lambda t: t.reshape(t.shape[0], -1).double()  # noqa: E731
            _assert_rows_close(flat(a), flat(b), {"means3d": 1e-4, "quats": 1e-3, "scales": 1e-4}.get(name, 1e-5),
                               f"gradient of {name} ({'colours' if colours_only else 'every output'})")
        culled = torch.ones(len(means), dtype=torch.bool)
        culled[pc.ids] = False
        assert gc[3][culled].eq(0).all() and gc[4][culled].eq(0).all()     # culled rows: zero
        nb = num_sh_bases(degree)
        assert gc[4][:, nb - 1:].eq(0).all()                               # past the degree: zero
        if degree and colours_only:   # the view direction moves the colours: the means get a gradient
            assert gc[0][pc.ids].abs().amax() > 0


@pytest.mark.parametrize("degree", [0, 1, 3])
def test_two_parts_and_one_tensor_give_the_same_bits(degree):
    """The trainer's sh0 / shN read in place and the same coefficients as one [N, K, C] tensor: one
    arithmetic, so the same colours and gradients to the bit (the gradient of the one tensor is the
    two parts' side by side)."""
    means, quats, scales, sh0, rest = _inputs(2500, degree, seed=7)
    p2, l2 = _project(means, quats, scales, sh0, rest, degree, True, fused=True)
    p1, l1 = _project(means, quats, scales, sh0, rest, degree, True, fused=True, one_tensor=True)
    assert torch.equal(p1.colors, p2.colors) and torch.equal(p1.ids, p2.ids)
    w = _weights(p2)
    g2, g1 = _grads(p2, l2, w, False), _grads(p1, l1, w, False)
    for a, b in zip(g1[:3], g2[:3]):
        assert torch.equal(a, b)
    assert torch.equal(g1[3], torch.cat([g2[3], g2[4]], 1))


@pytest.mark.parametrize("degree", [0, 1, 2, 3])
@pytest.mark.parametrize("clamp", [True, False])
def test_rgb_colours_side_by_side_give_the_bits_of_a_channel_at_a_time(degree, clamp):
    """The projection sums the three channels' coefficients side by side (``sh_colour_parts<3>``); the
    colour stage alone (``sh_forward`` / ``sh_backward``, the CUDA kernels' twin) a channel at a time.
    The same operations per channel: the same colours and SH gradients to the bit, and the same
    gradient of the means where the projection's own part of it is zero."""
    ext = projection._JIT.module()
    means, quats, scales, sh0, rest = _inputs(2500, degree, seed=11 + degree)
    cam = _camera()
    view = host_view(cam, torch.float32, center=True)
    center = view[22:].tolist()
    ids, *_, colours = ext.forward(means, quats, scales, view, 0.01, 0.3, 3.0, sh0, rest, degree, clamp)
    assert 500 < ids.numel() < 2500
    one = torch.cat([sh0, rest], 1)[ids].contiguous()
    kept = means[ids].contiguous()
    assert torch.equal(colours, ext.sh_forward(kept, one, center, degree, clamp))
    g_col = torch.randn(colours.shape, generator=torch.Generator().manual_seed(3))
    none = torch.empty(0)
    g_means, _, _, g_sh0, g_rest = ext.backward(means, quats, scales, view, 0.01, 0.3, ids, none, none, none,
                                                sh0, rest, degree, clamp, g_col)
    gm_alone, gsh_alone = ext.sh_backward(kept, one, center, degree, clamp, g_col)
    assert torch.equal(torch.cat([g_sh0, g_rest], 1)[ids], gsh_alone)
    assert torch.equal(g_means[ids], gm_alone)


def test_unused_outputs_and_no_colour_gradient():
    """Gradients the loss does not reach are not made (the kernel reads them as zero): a loss of the
    colours alone, or of the means alone, gives what the reference gives for it."""
    means, quats, scales, sh0, rest = _inputs(800, 2, seed=3)
    pc, lc = _project(means, quats, scales, sh0, rest, 2, True, fused=True)
    pr, lr = _project(means, quats, scales, sh0, rest, 2, True, fused=False, dtype=torch.float64)
    gc = torch.autograd.grad(pc.means2d.sum(), lc, allow_unused=True)
    gr = torch.autograd.grad(pr.means2d.sum(), lr, allow_unused=True)
    _assert_rows_close(gc[0].double(), gr[0], 1e-4, "means3d")
    assert gc[3].eq(0).all() and gc[4].eq(0).all()


def test_the_kernel_refuses_what_it_cannot_read():
    ext = projection._JIT.module()
    cam = _camera()
    means, quats, scales, sh0, rest = _inputs(10, 1, seed=0)
    view = host_view(cam, torch.float32, center=True)
    with pytest.raises(RuntimeError, match="sh degree must be 0..3"):
        ext.forward(means, quats, scales, view, 0.01, 0.3, 3.0, sh0, rest, 4, True)
    with pytest.raises(RuntimeError, match=r"rest of the SH coefficients must be float32 CPU \[10, >= 8, C\]"):
        ext.forward(means, quats, scales, view, 0.01, 0.3, 3.0, sh0, rest, 2, True)
    with pytest.raises(RuntimeError, match="need the camera centre"):
        ext.forward(means, quats, scales, view[:22], 0.01, 0.3, 3.0, sh0, rest, 1, True)
    with pytest.raises(ValueError, match="need the camera centre"):
        project_gaussians(means, quats, scales, cam, view=view[:22], sh=ShColours(sh0, rest, 1))


def test_rasterize_takes_the_two_parts_and_refuses_bad_shapes():
    """``rasterize(..., sh_rest=...)`` (the trainer's call) renders what the one-tensor call renders, on
    the compiled path and on the reference; bad shapes are named."""
    from smgs.raster import rasterize

    cam = Camera.look_at([0.3, -0.2, -3.0], [0.0, 0.0, 0.0], [0, -1, 0], fx=40.0, fy=40.0, width=32, height=24)
    means, quats, scales, sh0, rest = _inputs(300, 3, seed=1)
    opac = torch.full((300,), 0.6)
    for backend in ("cpu", "reference"):
        one = rasterize(means, quats, scales, opac, torch.cat([sh0, rest], 1), cam, mode="3dgs", sh_degree=3,
                        backend=backend)
        two = rasterize(means, quats, scales, opac, sh0, cam, mode="3dgs", sh_degree=3, sh_rest=rest, backend=backend)
        assert torch.equal(one.rgb, two.rgb), backend
    with pytest.raises(ValueError, match=r"colors_or_sh must be \[N,1,C\]"):
        rasterize(means, quats, scales, opac, torch.cat([sh0, rest], 1), cam, sh_degree=3, sh_rest=rest)
    with pytest.raises(ValueError, match="sh_degree 3 needs 16 SH coefficients"):
        rasterize(means, quats, scales, opac, sh0, cam, sh_degree=3, sh_rest=rest[:, :3])
    with pytest.raises(ValueError, match="sh_rest .* needs sh_degree"):
        rasterize(means, quats, scales, opac, sh0[:, 0], cam, sh_rest=rest)
