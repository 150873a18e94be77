"""The compiled CPU backend against the PyTorch reference: images, alpha, depth, stats, the
regulariser sums and every gradient, in every mode.

Tolerances (float32 cpu against the float32 reference, same inputs):
* outputs: both backends run the same operations in the same order (the kernel is compiled
  without FMA contraction), so they differ only where exp/log/pow differ by an ulp or two and
  where the 3DGS backward rebuilds T by division; colours and alpha are sums of terms <= 1, so
  OUT_ATOL32 = 2e-6 (~30 ulp of 1); depth is in scene units (<= 4 here), hence 4x that.
* gradients: each is a sum over pixels accumulated in a different order (autograd vs tiles), and
  the backward rebuilds T_before = T_after / (1 - a) instead of storing it, so relative to the
  largest gradient of the same input, GRAD_RTOL32 = 2e-5.
Against the float64 reference the float32 rounding of the whole chain dominates: the shared
stiff-battery tolerances of smgs.raster.stability (outputs 2e-5, gradients 2e-2 of scale) for the
stiff cases, and for random scenes OUT_ATOL64 = 2e-5, GRAD_RTOL64 = 2e-4 (observed ~1e-5: the
softmax weights of nearly equal exponents are the most sensitive terms).
"""

import math
import shutil

import pytest
import torch

from smgs import Camera
from smgs.raster import MODES, backend_available, rasterize, rasterize_splats, resolve_backend
from smgs.raster import constants as K
from smgs.raster.stability import GRAD_RTOL, OUT_ATOL, stiff_battery

# every SIMD path of the compiled CPU kernels this host runs (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("cpu_isa")

OUT_ATOL32, GRAD_RTOL32 = 2e-6, 2e-5
OUT_ATOL64, GRAD_RTOL64 = 2e-5, 2e-4
KEYS = ["means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma"]

if shutil.which("c++") is None:  # a machine without a compiler has no cpu backend; that is not a bug
    pytest.skip("no C++ compiler: the cpu backend cannot be built here", allow_module_level=True)


def test_backend_builds_and_is_available():
    from smgs.raster import cpu

    assert cpu.is_available(), cpu.unavailable_reason()


def test_compiled_constants_mirror_python():
    from smgs.raster import cpu

    got = cpu.extension().constants()
    want = [K.ALPHA_MAX, K.ALPHA_MIN, K.T_MIN, -K.P_MIN, -K.EXP_ARG_MIN, K.DECAY_ARG_MAX, K.PIXEL_CENTER,
            K.TILE_SIZE, K.T_MIN * (1 - K.T_STOP_SLACK), K.TINY]
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g == pytest.approx(w, rel=1e-7)   # compiled as float32


def test_auto_picks_cpu_for_float32_cpu_tensors():
    assert resolve_backend("auto", "cpu", torch.float32) == "cpu"
    assert resolve_backend("auto", "cpu", torch.float64) == "reference"   # cpu is float32 only
    with pytest.raises(RuntimeError):
        resolve_backend("cpu", "cpu", torch.float64)


def random_scene(n, w, h, seed=0, n_ch=3, n_reg=0):
    """Splats of mixed size and shape over the image, some partly or wholly off screen, two long
    thin rotated ones crossing several tiles."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    means = (r(n, 2) * 1.2 - 0.1) * torch.tensor([w, h], dtype=torch.float64)
    sig = 0.7 + 3.0 * r(n, 2)                               # pixel sigmas
    th = math.pi * r(n)
    c, s = torch.cos(th), torch.sin(th)
    l1, l2 = 1 / sig[:, 0] ** 2, 1 / sig[:, 1] ** 2
    l2[:2] = l1[:2] * 1e-4                                  # condition number 1e4
    conics = torch.stack([l1 * c * c + l2 * s * s, (l1 - l2) * c * s, l1 * s * s + l2 * c * c], 1)
    sc = dict(means2d=means, conics=conics, opacities=0.1 + 0.85 * r(n), colors=r(n, n_ch),
              depths=1 + 3 * r(n), alpha=0.4 + 2.5 * r(n), beta=12 * r(n), gamma=3 * r(n))
    if n > 4:
        sc["depths"][3] = sc["depths"][4]                   # a tie, broken by index
    if n_reg:
        sc["reg_values"] = r(n, n_reg)
    return {k: v.float() for k, v in sc.items()}


def render_and_grad(sc, w, h, backend, mode, dtype=torch.float32, seed=1, **kw):
    """Render, back-propagate a loss that weights every output pixel differently, return
    (output, {input: grad})."""
    names = KEYS + (["reg_values"] if "reg_values" in sc else [])
    ins = {k: sc[k].to(dtype).clone().requires_grad_(True) for k in names}
    bg = kw.pop("background", None)
    if bg is not None:
        bg = bg.to(dtype).clone().requires_grad_(True)
    out = rasterize_splats(*[ins[k] for k in KEYS], w, h, mode=mode, backend=backend, background=bg,
                           reg_values=ins.get("reg_values"), **kw)
    g = torch.Generator().manual_seed(seed)
    wt = lambda t: torch.rand(t.shape, generator=g, dtype=torch.float64).to(dtype)  # noqa: E731
    loss = (out.rgb * wt(out.rgb)).sum() + (out.alpha * wt(out.alpha)).sum() + 0.1 * (out.depth * wt(out.depth)).sum()
    if out.reg is not None:
        loss = loss + (out.reg * wt(out.reg)).sum()
    loss.backward()
    grads = {k: t.grad for k, t in ins.items()}
    if bg is not None:
        grads["background"] = bg.grad
    return out, grads


def assert_same(o_cpu, g_cpu, o_ref, g_ref, out_atol, grad_rtol):
    o_ref_rgb = o_ref.rgb.to(o_cpu.rgb.dtype)
    torch.testing.assert_close(o_cpu.rgb, o_ref_rgb, rtol=0, atol=out_atol)
    torch.testing.assert_close(o_cpu.alpha, o_ref.alpha.to(o_cpu.alpha.dtype), rtol=0, atol=out_atol)
    torch.testing.assert_close(o_cpu.depth, o_ref.depth.to(o_cpu.depth.dtype), rtol=0, atol=4 * out_atol)
    assert torch.equal(o_cpu.stats.n_contrib, o_ref.stats.n_contrib)
    assert o_cpu.stats.k_max == o_ref.stats.k_max
    assert o_cpu.stats.scope == o_ref.stats.scope
    assert (o_cpu.stats.list_end is None) == (o_ref.stats.list_end is None)
    if o_ref.stats.list_end is not None:   # patch scope: the emulated tile lists are the kernel's
        assert torch.equal(o_cpu.stats.list_end, o_ref.stats.list_end)
    if o_ref.reg is not None:
        torch.testing.assert_close(o_cpu.reg, o_ref.reg.to(o_cpu.reg.dtype), rtol=1e-5, atol=out_atol)
    else:
        assert o_cpu.reg is None
    assert g_cpu.keys() == g_ref.keys()
    for k, gr in g_ref.items():
        gc = g_cpu[k]
        if gr is None:
            # the reference leaves it out of the graph (mode ignores it, or k_max = 0): no gradient
            assert gc is None or (gc == 0).all(), k
            continue
        assert gc is not None and torch.isfinite(gc).all(), k
        scale = gr.abs().max().item() + 1e-8
        err = (gc.double() - gr.double()).abs().max().item()
        assert err <= grad_rtol * scale, f"gradient of {k}: max error {err:.3g}, scale {scale:.3g}"


W, H = 37, 29   # 3x2 tiles, partial tiles and partial 4x4 blocks on both edges


@pytest.mark.parametrize("scope", ["pixel", "patch"])   # docs/kmax-scope.md
@pytest.mark.parametrize("k_max", [2, 128])   # below and above the splats overlapping a pixel
@pytest.mark.parametrize("mode", MODES)
def test_cpu_matches_reference_float32(mode, k_max, scope):
    sc = random_scene(40, W, H, seed=k_max)
    bg = torch.tensor([0.2, 0.5, 0.9])
    kw = dict(k_max=k_max, background=bg, k_max_scope=scope)
    oc, gc = render_and_grad(sc, W, H, "cpu", mode, **kw)
    orf, gr = render_and_grad(sc, W, H, "reference", mode, **kw)
    assert oc.stats.n_contrib.max() > 2    # so k_max = 2 truncates somewhere
    assert 0 < oc.stats.pairs_evaluated < orf.stats.pairs_evaluated   # tiling skipped pairs
    assert_same(oc, gc, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("scope", ["pixel", "patch"])
@pytest.mark.parametrize("mode", ["softmax_only", "softmax_gs", "3dgs"])
def test_cpu_matches_reference_printed_eq15_one_channel_and_regulariser(mode, scope):
    sc = random_scene(30, W, H, seed=5, n_ch=1, n_reg=2)
    kw = dict(k_max=3, eq15="printed", reg_depth_scale=0.7, background=torch.tensor([0.3]), k_max_scope=scope)
    oc, gc = render_and_grad(sc, W, H, "cpu", mode, **kw)
    orf, gr = render_and_grad(sc, W, H, "reference", mode, **kw)
    assert oc.rgb.shape == (H, W, 1) and oc.reg.shape == (H, W, 5)
    assert_same(oc, gc, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("mode", ["softmax_only", "softmax_gs"])
def test_cpu_k_max_zero_is_all_vanilla(mode):
    sc = random_scene(25, 20, 18, seed=2)
    oc, gc = render_and_grad(sc, 20, 18, "cpu", mode, k_max=0)
    orf, gr = render_and_grad(sc, 20, 18, "reference", mode, k_max=0)
    assert_same(oc, gc, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("scope", ["pixel", "patch"])
@pytest.mark.parametrize("mode", MODES)
def test_cpu_float32_close_to_reference_float64(mode, scope):
    sc = random_scene(30, W, H, seed=11, n_ch=3, n_reg=1)
    bg = torch.tensor([0.1, 0.0, 0.4])
    oc, gc = render_and_grad(sc, W, H, "cpu", mode, k_max=4, background=bg, k_max_scope=scope)
    o64, g64 = render_and_grad(sc, W, H, "reference", mode, dtype=torch.float64, k_max=4, background=bg,
                               k_max_scope=scope)
    assert_same(oc, gc, o64, g64, OUT_ATOL64, GRAD_RTOL64)


def test_gradients_do_not_depend_on_the_thread_count():
    sc = random_scene(60, 70, 50, seed=4)
    n0 = torch.get_num_threads()
    try:
        torch.set_num_threads(1)
        o1, g1 = render_and_grad(sc, 70, 50, "cpu", "softmax_gs", k_max=3)
        torch.set_num_threads(max(2, n0))
        o2, g2 = render_and_grad(sc, 70, 50, "cpu", "softmax_gs", k_max=3)
    finally:
        torch.set_num_threads(n0)
    assert torch.equal(o1.rgb, o2.rgb)
    for k in g1:
        assert torch.equal(g1[k], g2[k]), k


def test_no_visible_splat_gives_the_background_and_zero_gradients():
    for n in (0, 3):
        sc = random_scene(5, 10, 8)
        sc = {k: v[:n] for k, v in sc.items()}
        sc["means2d"] = sc["means2d"] + 100.0          # all off screen
        bg = torch.tensor([0.2, 0.4, 0.6])
        o, g = render_and_grad(sc, 10, 8, "cpu", "softmax_gs", background=bg)
        torch.testing.assert_close(o.rgb, bg.expand(8, 10, 3), rtol=0, atol=0)
        assert (o.alpha == 0).all() and (o.depth == 0).all() and o.stats.n_contrib.sum() == 0
        for k in KEYS:
            assert (g[k] == 0).all()
        torch.testing.assert_close(g["background"], torch.zeros(3) + g["background"])  # finite


@pytest.mark.parametrize("mode", MODES)
def test_rasterize_3d_cpu_matches_reference(mode):
    """Through the public 3D entry point: projection, SH colours, then each backend; gradients of
    every 3D parameter."""
    g = torch.Generator().manual_seed(3)
    n, w, h = 50, 40, 30
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    cam = Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0], fx=40.0, fy=40.0,
                         width=w, height=h)
    params = dict(means3d=(r(n, 3) - 0.5) * torch.tensor([3.0, 2.0, 2.0]), quats=r(n, 4) - 0.5,
                  scales=0.05 + 0.15 * r(n, 3), opacities=0.2 + 0.75 * r(n), sh=0.5 * (r(n, 4, 3) - 0.5),
                  alpha=0.5 + 2 * r(n), beta=10 * r(n), gamma=2 * r(n))

    def run(backend):
        p = {k: v.clone().requires_grad_(True) for k, v in params.items()}
        bg = torch.tensor([0.1, 0.2, 0.3], requires_grad=True)
        out = rasterize(p["means3d"], p["quats"], p["scales"], p["opacities"], p["sh"], cam, alpha=p["alpha"],
                        beta=p["beta"], gamma=p["gamma"], mode=mode, k_max=3, sh_degree=1, background=bg,
                        backend=backend)
        wr = torch.linspace(0, 1, out.rgb.numel()).reshape(out.rgb.shape)
        ((out.rgb * wr).sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        return out, {**{k: v.grad for k, v in p.items()}, "background": bg.grad}

    oc, gc = run("cpu")
    orf, gr = run("reference")
    assert orf.stats.n_contrib.max() > 3
    torch.testing.assert_close(oc.rgb, orf.rgb, rtol=0, atol=OUT_ATOL32)
    torch.testing.assert_close(oc.alpha, orf.alpha, rtol=0, atol=OUT_ATOL32)
    torch.testing.assert_close(oc.depth, orf.depth, rtol=0, atol=OUT_ATOL32 * 8)   # depths ~3-5
    for k, v in gr.items():
        if v is None:
            assert gc[k] is None
            continue
        scale = v.abs().max().item() + 1e-8
        assert (gc[k] - v).abs().max().item() <= GRAD_RTOL32 * 5 * scale, k   # + projection chain


def test_stiff_battery_cpu_finite_and_close_to_float64():
    """The issue's stiff cases (smgs.raster.stability): β up to 1e5, γ up to 1e6 and inf, α 0.25..30,
    opacity 1-1e-7, identical depths, 50 stacked identical splats, conic condition number 1e8, ...:
    every cpu output and gradient finite and within the battery's tolerances of float64."""
    rows = stiff_battery(backends=("cpu",))
    assert len(rows) > 100
    # values not comparable in float32 at all (see tests/test_raster_stiff.py): finiteness only
    sensitive = ("beta=100000", "beta=1000", "stacked50")
    for row in rows:
        assert row["nonfinite_outputs"] == 0 and row["nonfinite_grads"] == 0, row
        # outputs include depth in scene units (1..3): 3·OUT_ATOL
        atol = OUT_ATOL * 3
        assert row["max_abs_err"] < atol, row
        if row["case"] not in sensitive:
            assert row["max_grad_rel_err"] <= GRAD_RTOL, row
