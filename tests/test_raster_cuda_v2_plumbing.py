"""The opt-in CUDA kernels' Python side (smgs.raster.cuda_v2, smgs.raster.projection_cuda), without
a GPU: the switch, and the argument plumbing between the autograd Functions and the torch bindings,
through the stand-in extensions of tests/cuda_v2_standin.py (the bindings' contracts read from their
C++ sources, computed with the PyTorch oracles). Through them, ``rasterize_fused`` must give the
reference backend's images and gradients of every 3D input. A swapped argument, a misplaced saved
tensor, a misrouted gradient or a culled row that leaks into the image fails here.
"""

from __future__ import annotations

import re

import pytest
import torch
from cuda_v2_standin import CSRC, LAYOUT, PYTYPE, StandInCompositing, StandInProjection, params, py_args, returned

from smgs.camera import Camera
from smgs.raster import constants as K
from smgs.raster import Renderer, cuda_v2, rasterize, rasterize_splats
from smgs.raster.composite_inputs import Splats2D, composite_settings
from smgs.raster.types import MODES

def _scene(n: int, seed: int, sh_degree: int | None):
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    means = (r(n, 3) - 0.5) * torch.tensor([2.0, 1.6, 1.0]) + torch.tensor([0.0, 0.0, 3.0])
    means[:3, 2] = -3.0                               # behind the camera (at z = -2)
    means[3:5, 0] = 40.0                              # far off the image
    quats = torch.randn(n, 4, generator=g)
    scales = 0.05 + 0.1 * r(n, 3)
    colors = r(n, 9, 3) - 0.5 if sh_degree is not None else r(n, 3)
    return dict(means3d=means, quats=quats, scales=scales, opacities=0.3 + 0.6 * r(n), colors_or_sh=colors,
                alpha=0.5 + 2 * r(n), beta=8 * r(n), gamma=2 * r(n))


def _render(sc, cam, mode, via_fused: bool, sh_degree, **kw):
    leaves = {k: t.clone().requires_grad_(True) for k, t in sc.items()}
    if via_fused:
        exts = (StandInProjection(), StandInCompositing())
        st = composite_settings(cam.width, cam.height, mode, 4, **kw)
        out = cuda_v2.rasterize_fused(leaves["means3d"], leaves["quats"], leaves["scales"], leaves["opacities"],
                                      leaves["colors_or_sh"], cam, leaves["alpha"], leaves["beta"], leaves["gamma"],
                                      None, None, st, sh_degree, K.NEAR_PLANE, K.EPS2D, True, exts=exts)
    else:
        exts = ()
        out = rasterize(leaves["means3d"], leaves["quats"], leaves["scales"], leaves["opacities"],
                        leaves["colors_or_sh"], cam, leaves["alpha"], leaves["beta"], leaves["gamma"],
                        mode=mode, k_max=4, sh_degree=sh_degree, backend="reference", **kw)
    g = torch.Generator().manual_seed(3)
    loss = sum((t * torch.rand(t.shape, generator=g)).sum() for t in (out.rgb, out.alpha, out.depth))
    loss.backward()
    return out, {k: t.grad for k, t in leaves.items()}, exts


@pytest.mark.parametrize("mode,sh_degree,scope", [(m, None, "pixel") for m in MODES]
                         + [(m, 2, "pixel") for m in MODES] + [("softmax_gs", 2, "patch")])
def test_fused_plumbing_matches_the_reference(mode, sh_degree, scope):
    cam = Camera.look_at([0.1, -0.1, -2.0], [0.0, 0.0, 3.0], [0, -1, 0], fx=40.0, fy=38.0, width=23, height=19)
    sc = _scene(40, 1, sh_degree)
    of, gf, exts = _render(sc, cam, mode, True, sh_degree, k_max_scope=scope)
    orf, gr, _ = _render(sc, cam, mode, False, sh_degree, k_max_scope=scope)
    assert of.stats.scope == scope
    assert exts[0].calls == ["project_forward_torch", "project_backward_torch"]
    assert exts[1].calls == ["forward_v2", "backward_v2"]
    for a, b in ((of.rgb, orf.rgb), (of.alpha, orf.alpha), (of.depth, orf.depth)):
        torch.testing.assert_close(a, b, rtol=0, atol=1e-6)
    assert torch.equal(of.stats.n_contrib, orf.stats.n_contrib) and of.stats.pairs_evaluated == 12345
    n = sc["means3d"].shape[0]
    assert torch.equal(of.extras["ids"], torch.arange(n))
    culled = torch.ones(n, dtype=torch.bool)
    culled[orf.extras["ids"]] = False
    assert culled[:5].all() and (of.extras["radii"][culled] == 0).all()
    assert torch.equal(of.extras["radii"][~culled], orf.extras["radii"])
    for k, want in gr.items():
        got = gf[k]
        if want is None:
            assert got is None or (got == 0).all(), k
            continue
        scale = want.abs().max().clamp_min(1e-12)
        torch.testing.assert_close(got / scale, want / scale, rtol=0, atol=1e-5, msg=k)


def test_layout_matches_the_kernel_header():
    body = re.search(r"enum \{([^}]*)\}", (CSRC / "packed_row.h").read_text()).group(1)
    P = {s.split("=")[0].strip(): i for i, s in enumerate(body.split(","))}
    assert LAYOUT == [P[k] for k in ("P_MX", "P_MY", "P_CA", "P_CC", "P_O", "P_D", "P_AL", "P_BE", "P_GA", "P_COL")]
    layout = re.search(r'm\.def\("layout", \[\]\(\) \{.*?return std::vector<int>\{([^}]*)\}', (CSRC / "cuda_v2_binding.cpp")
                       .read_text(), re.S).group(1)
    assert [s.strip() for s in layout.split(",")] == ["P_MX", "P_MY", "P_CA", "P_CC", "P_O", "P_D", "P_AL", "P_BE",
                                                      "P_GA", "P_COL"]


def test_bindings_signatures_and_pybind_names_agree():
    for src, pairs in (((CSRC / "projection_cuda_binding.cpp").read_text(),
                        (("project_forward_torch", "forward"), ("project_backward_torch", "backward"))),
                       ((CSRC / "cuda_v2_binding.cpp").read_text(), (("forward_v2", "forward"),
                                                                      ("backward_v2", "backward"),
                                                                      ("forward_pixel_v2", "forward_pixel"),
                                                                      ("backward_pixel_v2", "backward_pixel")))):
        for fn, name in pairs:
            ps = params(src, fn)
            assert [n for _, n in ps] == py_args(src, name), fn
            assert all(t in PYTYPE for t, _ in ps), ps
    v2 = (CSRC / "cuda_v2_binding.cpp").read_text()
    assert len(returned(v2, "forward_v2")) == 11 and len(returned(v2, "forward_pixel_v2")) == 12
    assert len(returned((CSRC / "projection_cuda_binding.cpp").read_text(), "project_forward_torch")) == 6


def test_the_kernels_are_the_asked_ones_then_the_environments(monkeypatch):
    from smgs.raster.backends import KERNELS_ENV, Renderer, variant

    monkeypatch.delenv(KERNELS_ENV, raising=False)
    assert variant(Renderer(), "cuda").kernels == "default"
    assert variant(Renderer(kernels="v2"), "cuda").kernel_set.fused == "smgs.raster.cuda_v2:rasterize_fused"
    monkeypatch.setenv(KERNELS_ENV, "v2")
    assert variant(Renderer(), "cuda").kernels == "v2" and variant(Renderer(kernels="default"), "cuda").kernels == "default"
    assert variant(Renderer(), "cpu").describe() == "cpu"    # a backend without kernel sets reads no variable
    monkeypatch.setenv(KERNELS_ENV, "v3")
    with pytest.raises(ValueError, match="SMGS_CUDA_KERNELS='v3' names no cuda kernels variant; expected one of default, v2"):
        variant(Renderer(), "cuda")
    with pytest.raises(ValueError, match="kernels='fast' names no kernels variant of any renderer backend"):
        Renderer("cuda", kernels="fast")


def test_v2_applies_only_where_the_cuda_backend_renders(monkeypatch):
    """On CPU tensors the choice changes nothing (the cpu/reference backends render)."""
    cam = Camera.look_at([0.1, -0.1, -2.0], [0.0, 0.0, 3.0], [0, -1, 0], fx=40.0, fy=38.0, width=23, height=19)
    sc = _scene(20, 2, None)
    kw = dict(mode="3dgs", backend="reference")
    a = rasterize(sc["means3d"], sc["quats"], sc["scales"], sc["opacities"], sc["colors_or_sh"], cam, **kw)
    b = rasterize(sc["means3d"], sc["quats"], sc["scales"], sc["opacities"], sc["colors_or_sh"], cam,
                  **{**kw, "backend": Renderer("reference", kernels="v2")})
    assert torch.equal(a.rgb, b.rgb) and torch.equal(a.extras["ids"], b.extras["ids"])


@pytest.mark.parametrize("mode", MODES)
@pytest.mark.parametrize("sorted_per_pixel,leaders,scope", [(True, False, "pixel"), (True, True, "patch"),
                                                             (False, True, "pixel")])
def test_per_pixel_plumbing_matches_the_cpu_window(mode, sorted_per_pixel, leaders, scope, cpu_backend):
    """The per-pixel entries (cuda_pixel.cu) through a stand-in computing with the CPU window: the
    wrapper's images, leaders and gradients equal the CPU backend's own per-pixel path (the compiled
    CPU renderer: conftest's ``cpu_backend``, which names why where it cannot be built)."""
    from smgs.raster.ray_depth import ray_depth

    cam = Camera.look_at([0.1, -0.1, -2.0], [0.0, 0.0, 3.0], [0, -1, 0], fx=40.0, fy=38.0, width=23, height=19)
    sc = _scene(40, 3, None)
    from smgs.raster.projection import project_gaussians

    p = project_gaussians(sc["means3d"], sc["quats"], sc["scales"], cam, fused=False)
    ids = p.ids
    rd = ray_depth(sc["means3d"][ids], sc["quats"][ids], sc["scales"][ids], cam) if sorted_per_pixel else None
    base = dict(means2d=p.means2d.detach(), conics=p.conics.detach(), opacities=sc["opacities"][ids],
                colors=sc["colors_or_sh"][ids], depths=p.depths.detach(), alpha=sc["alpha"][ids],
                beta=sc["beta"][ids], gamma=sc["gamma"][ids])

    def run(via_v2: bool):
        ins = {k: v.clone().requires_grad_(True) for k, v in base.items()}
        bg = torch.tensor([0.2, 0.5, 0.7], requires_grad=True)
        args = [ins[k] for k in ("means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma")]
        if via_v2:
            ext = StandInCompositing()
            out = cuda_v2.composite_pixel(ext, Splats2D(*args, background=bg, ray_depth=rd),
                                          composite_settings(23, 19, mode, 4, k_max_scope=scope, leaders=leaders))
            assert ext.calls == ["forward_pixel_v2"]
        else:
            out = rasterize_splats(*args, 23, 19, mode=mode, k_max=4, background=bg, backend="cpu", ray_depth=rd,
                                   leaders=leaders, k_max_scope=scope)
        g = torch.Generator().manual_seed(2)
        loss = sum((t * torch.rand(t.shape, generator=g)).sum() for t in (out.rgb, out.alpha, out.depth))
        loss.backward()
        return out, {**{k: t.grad for k, t in ins.items()}, "background": bg.grad}

    ov, gv = run(True)
    oc, gc = run(False)
    for a, b in ((ov.rgb, oc.rgb), (ov.alpha, oc.alpha), (ov.depth, oc.depth)):
        torch.testing.assert_close(a, b, rtol=0, atol=0)
    assert torch.equal(ov.stats.n_contrib, oc.stats.n_contrib)
    assert (ov.leaders is None) == (not leaders)
    if leaders:
        assert torch.equal(ov.leaders, oc.leaders)
    for k, want in gc.items():
        got = gv[k]
        if want is None:
            assert got is None or (got == 0).all(), k
        else:
            torch.testing.assert_close(got, want, rtol=1e-6, atol=1e-7, msg=k)


def test_per_pixel_order_on_the_cuda_kernels_with_reg_values_is_refused_naming_them():
    """The per-pixel order has no regulariser sums: asked of the cuda backend with reg_values (and the
    opt-in kernels, which have the order), the error names reg_values, before any extension loads."""
    from smgs.raster import rasterize_splats
    from smgs.raster.types import RayDepth

    n = 3
    z = lambda *s: torch.rand(*s)  # noqa: E731
    rd = RayDepth(coefs=torch.zeros(n, 9), fx=10.0, fy=10.0, cx=5.0, cy=5.0)
    with pytest.raises(ValueError, match="per_pixel' on the CUDA kernels takes no reg_values"):
        rasterize_splats(z(n, 2) * 8, torch.tensor([[1.0, 0.0, 1.0]] * n), z(n) * 0.5, z(n, 3), z(n) + 1, z(n), z(n),
                         z(n), 8, 8, mode="3dgs", backend=Renderer("cuda", kernels="v2"), ray_depth=rd,
                         reg_values=z(n, 2))
