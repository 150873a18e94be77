"""The CUDA backend against the PyTorch reference on a GPU: images, alpha, depth, stats, regulariser
sums and every gradient, in every mode, with k_max above and below the overlap; the stiff-case
battery. Marked ``gpu`` (``python -m pytest -m gpu``); skipped where no CUDA device is visible.

The reference runs on the CPU on the same float32 inputs (the CUDA results are copied back).
Tolerances, against the CPU backend's (tests/test_raster_cpu.py: 2e-6 outputs, 2e-5 gradients):
* outputs 5e-6: the kernel runs the reference's operations in the same order without FMA
  contraction (--fmad=false), with IEEE division and square root, but CUDA's expf/logf may differ
  from the host's by up to 2 ulp, and the 3DGS backward rebuilds T by division;
* gradients 5e-5 of the largest gradient of the same input: per-splat sums over pixels are
  accumulated by float atomics in an arbitrary order.
Against the float64 reference and in the stiff battery: the same tolerances as the CPU backend.
"""

import math

import pytest
import torch

from smgs import Camera
from smgs.raster import MODES, rasterize, rasterize_splats, resolve_backend
from smgs.raster import constants as K
from smgs.raster import stability

pytestmark = pytest.mark.gpu

BACKEND, DEV = "cuda", "cuda"
OUT_ATOL32, GRAD_RTOL32 = 5e-6, 5e-5
OUT_ATOL64, GRAD_RTOL64 = 2e-5, 2e-4
KEYS = ["means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma"]

if not torch.cuda.is_available():
    pytest.skip("no CUDA device visible (torch.cuda.is_available() is False)", allow_module_level=True)


def test_backend_builds_and_is_available():
    from smgs.raster import cuda

    assert cuda.is_available(), cuda.unavailable_reason()


def test_compiled_constants_mirror_python():
    from smgs.raster import cuda

    got = cuda.extension().constants()
    want = [K.ALPHA_MAX, K.ALPHA_MIN, K.T_MIN, -K.P_MIN, -K.EXP_ARG_MIN, K.DECAY_ARG_MAX, K.PIXEL_CENTER,
            K.TILE_SIZE, K.T_MIN * (1 - K.T_STOP_SLACK), K.TINY]
    assert len(got) == len(want)
    for g, w in zip(got, want):
        assert g == pytest.approx(w, rel=1e-7)   # compiled as float32


def test_auto_picks_cuda_for_float32_cuda_tensors():
    assert resolve_backend("auto", "cuda", torch.float32) == "cuda"
    assert resolve_backend("auto", "cuda", torch.float64) == "reference"
    assert resolve_backend("auto", "cpu", torch.float32) in ("cpu", "reference")
    with pytest.raises(RuntimeError):
        resolve_backend("cuda", "cpu", torch.float32)


def random_scene(n, w, h, seed=0, n_ch=3, n_reg=0):
    """Splats of mixed size and shape over the image, some partly or wholly off screen, two long
    thin rotated ones crossing several tiles, a depth tie (float32, CPU)."""
    g = torch.Generator().manual_seed(seed)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    means = (r(n, 2) * 1.2 - 0.1) * torch.tensor([w, h], dtype=torch.float64)
    sig = 0.7 + 3.0 * r(n, 2)
    th = math.pi * r(n)
    c, s = torch.cos(th), torch.sin(th)
    l1, l2 = 1 / sig[:, 0] ** 2, 1 / sig[:, 1] ** 2
    l2[:2] = l1[:2] * 1e-4
    conics = torch.stack([l1 * c * c + l2 * s * s, (l1 - l2) * c * s, l1 * s * s + l2 * c * c], 1)
    sc = dict(means2d=means, conics=conics, opacities=0.1 + 0.85 * r(n), colors=r(n, n_ch),
              depths=1 + 3 * r(n), alpha=0.4 + 2.5 * r(n), beta=12 * r(n), gamma=3 * r(n))
    if n > 4:
        sc["depths"][3] = sc["depths"][4]
    if n_reg:
        sc["reg_values"] = r(n, n_reg)
    return {k: v.float() for k, v in sc.items()}


def render_and_grad(sc, w, h, backend, mode, dtype=torch.float32, device="cpu", seed=1, **kw):
    """Render on ``device``, back-propagate a loss weighting every output pixel differently; returns
    (output, {input: grad}) on the CPU."""
    names = KEYS + (["reg_values"] if "reg_values" in sc else [])
    ins = {k: sc[k].to(device, dtype).clone().requires_grad_(True) for k in names}
    bg = kw.pop("background", None)
    if bg is not None:
        bg = bg.to(device, dtype).clone().requires_grad_(True)
    out = rasterize_splats(*[ins[k] for k in KEYS], w, h, mode=mode, backend=backend, background=bg,
                           reg_values=ins.get("reg_values"), **kw)
    g = torch.Generator().manual_seed(seed)
    wt = lambda t: torch.rand(t.shape, generator=g, dtype=torch.float64).to(device, dtype)  # noqa: E731
    loss = (out.rgb * wt(out.rgb)).sum() + (out.alpha * wt(out.alpha)).sum() + 0.1 * (out.depth * wt(out.depth)).sum()
    if out.reg is not None:
        loss = loss + (out.reg * wt(out.reg)).sum()
    loss.backward()
    grads = {k: None if t.grad is None else t.grad.cpu() for k, t in ins.items()}
    if bg is not None:
        grads["background"] = None if bg.grad is None else bg.grad.cpu()
    return out, grads


def assert_same(o, g, o_ref, g_ref, out_atol, grad_rtol):
    def cpu32(t):
        return t.detach().cpu().to(o.rgb.dtype)

    torch.testing.assert_close(cpu32(o.rgb), cpu32(o_ref.rgb), rtol=0, atol=out_atol)
    torch.testing.assert_close(cpu32(o.alpha), cpu32(o_ref.alpha), rtol=0, atol=out_atol)
    torch.testing.assert_close(cpu32(o.depth), cpu32(o_ref.depth), rtol=0, atol=4 * out_atol)
    assert torch.equal(o.stats.n_contrib.cpu(), o_ref.stats.n_contrib.cpu())
    assert o.stats.k_max == o_ref.stats.k_max
    assert o.stats.scope == o_ref.stats.scope
    assert (o.stats.list_end is None) == (o_ref.stats.list_end is None)
    if o_ref.stats.list_end is not None:   # patch scope: the emulated tile lists are the kernel's
        assert torch.equal(o.stats.list_end.cpu(), o_ref.stats.list_end.cpu())
    if o_ref.reg is not None:
        torch.testing.assert_close(cpu32(o.reg), cpu32(o_ref.reg), rtol=1e-5, atol=out_atol)
    else:
        assert o.reg is None
    assert g.keys() == g_ref.keys()
    for k, gr in g_ref.items():
        gc = g[k]
        if gr is None:
            assert gc is None or (gc == 0).all(), k
            continue
        assert gc is not None and torch.isfinite(gc).all(), k
        scale = gr.abs().max().item() + 1e-8
        err = (gc.double() - gr.double()).abs().max().item()
        assert err <= grad_rtol * scale, f"gradient of {k}: max error {err:.3g}, scale {scale:.3g}"


W, H = 37, 29   # 3x2 tiles, partial tiles on both edges


@pytest.mark.parametrize("scope", ["pixel", "patch"])   # docs/kmax-scope.md
@pytest.mark.parametrize("k_max", [2, 128])   # below and above the splats overlapping a pixel
@pytest.mark.parametrize("mode", MODES)
def test_cuda_matches_reference_float32(mode, k_max, scope):
    sc = random_scene(40, W, H, seed=k_max)
    bg = torch.tensor([0.2, 0.5, 0.9])
    kw = dict(k_max=k_max, background=bg, k_max_scope=scope)
    oc, gc = render_and_grad(sc, W, H, BACKEND, mode, device=DEV, **kw)
    orf, gr = render_and_grad(sc, W, H, "reference", mode, **kw)
    assert oc.rgb.device.type == DEV
    assert oc.stats.n_contrib.max() > 2    # so k_max = 2 truncates somewhere
    assert 0 < oc.stats.pairs_evaluated < orf.stats.pairs_evaluated   # tiling skipped pairs
    assert_same(oc, gc, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("scope", ["pixel", "patch"])
@pytest.mark.parametrize("k_max", [3, 128, 300])   # 300 (patch): a tile head past one shared-memory batch
@pytest.mark.parametrize("mode", MODES)
def test_cuda_matches_reference_crowded_tiles(mode, k_max, scope):
    """More splats per tile than one shared-memory batch holds (256 rows), pixels that stop at
    T < 1e-4, and (k_max = 128) softmax heads of dozens of entries."""
    sc = random_scene(700, 40, 30, seed=3)
    sc["opacities"] = 0.3 + 0.6 * sc["opacities"]
    oc, gc = render_and_grad(sc, 40, 30, BACKEND, mode, device=DEV, k_max=k_max, k_max_scope=scope)
    orf, gr = render_and_grad(sc, 40, 30, "reference", mode, k_max=k_max, k_max_scope=scope)
    assert orf.stats.n_contrib.max() > 20
    assert_same(oc, gc, orf, gr, 2 * OUT_ATOL32, 2 * GRAD_RTOL32)   # longer chains


@pytest.mark.parametrize("scope", ["pixel", "patch"])
@pytest.mark.parametrize("mode", ["softmax_only", "softmax_gs", "3dgs"])
def test_cuda_matches_reference_printed_eq15_one_channel_and_regulariser(mode, scope):
    """nch != 3 takes the kernels' general channel path (state in global memory)."""
    sc = random_scene(30, W, H, seed=5, n_ch=1, n_reg=2)
    kw = dict(k_max=3, eq15="printed", reg_depth_scale=0.7, background=torch.tensor([0.3]), k_max_scope=scope)
    oc, gc = render_and_grad(sc, W, H, BACKEND, mode, device=DEV, **kw)
    orf, gr = render_and_grad(sc, W, H, "reference", mode, **kw)
    assert oc.rgb.shape == (H, W, 1) and oc.reg.shape == (H, W, 5)
    assert_same(oc, gc, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("mode", ["softmax_only", "softmax_gs"])
def test_cuda_k_max_zero_is_all_vanilla(mode):
    sc = random_scene(25, 20, 18, seed=2)
    oc, gc = render_and_grad(sc, 20, 18, BACKEND, mode, device=DEV, k_max=0)
    orf, gr = render_and_grad(sc, 20, 18, "reference", mode, k_max=0)
    assert_same(oc, gc, orf, gr, OUT_ATOL32, GRAD_RTOL32)


@pytest.mark.parametrize("mode", MODES)
def test_cuda_float32_close_to_reference_float64(mode):
    sc = random_scene(30, W, H, seed=11, n_ch=3, n_reg=1)
    bg = torch.tensor([0.1, 0.0, 0.4])
    oc, gc = render_and_grad(sc, W, H, BACKEND, mode, device=DEV, k_max=4, background=bg)
    o64, g64 = render_and_grad(sc, W, H, "reference", mode, dtype=torch.float64, k_max=4, background=bg)
    assert_same(oc, gc, o64, g64, OUT_ATOL64, GRAD_RTOL64)


@pytest.mark.slow   # builds another variant (bench/gpu_check.py runs it after the renderer's tests)
@pytest.mark.parametrize("mode", ["3dgs", "softmax_gs"])
def test_cuda_t_min_variant_matches_reference(mode):
    """A transmittance threshold other than 1e-4 is compiled into a variant build."""
    sc = random_scene(300, 40, 30, seed=6)

    def run(fn, device):
        ins = {k: sc[k].to(device).clone().requires_grad_(True) for k in KEYS}
        out = fn(*[ins[k] for k in KEYS], 40, 30, mode=mode, k_max=4, t_min=0.05)
        wr = torch.linspace(0, 1, out.rgb.numel(), device=device).reshape(out.rgb.shape)
        ((out.rgb * wr).sum() + out.alpha.sum()).backward()
        return out, {k: None if t.grad is None else t.grad.cpu() for k, t in ins.items()}

    oc, gc = run(lambda *a, **kw: rasterize_splats(*a, backend="cuda", **kw), DEV)   # through api.py
    orf, gr = run(lambda *a, **kw: rasterize_splats(*a, backend="reference", **kw), "cpu")
    # The stop holds where it applies: every vanilla step keeps T >= t_min = 0.05 (alpha <= 0.95). In
    # the softmax modes no step inside a pixel's first k_max splats stops the ray (a later splat can
    # still win it), so T may fall below t_min there (alpha up to 0.992 here); a pixel that
    # composited more than k_max splats took its later steps only while T stayed above t_min.
    stopped = orf.stats.n_contrib > (4 if mode != "3dgs" else -1)
    assert 0.9 < orf.alpha[stopped].max() <= 0.95 + 1e-5
    if mode != "3dgs":
        assert orf.alpha.max() > 0.95 + 1e-5      # the head does not stop: the variant's bound is per step kind
    torch.testing.assert_close(oc.alpha.cpu(), orf.alpha, rtol=0, atol=2 * OUT_ATOL32)
    torch.testing.assert_close(oc.rgb.cpu(), orf.rgb, rtol=0, atol=2 * OUT_ATOL32)
    assert torch.equal(oc.stats.n_contrib.cpu(), orf.stats.n_contrib)
    for k, v in gr.items():
        if v is not None:
            assert (gc[k] - v).abs().max().item() <= 2 * GRAD_RTOL32 * (v.abs().max().item() + 1e-8), k


def test_backward_in_chunks_of_tiles_gives_the_same_gradients(monkeypatch):
    """A head-scratch budget of one tile makes the backward run tile by tile."""
    if BACKEND != "cuda":
        pytest.skip("cuda only")
    from smgs.raster import cuda

    sc = random_scene(80, 70, 50, seed=4)
    o1, g1 = render_and_grad(sc, 70, 50, BACKEND, "softmax_gs", device=DEV, k_max=5)
    monkeypatch.setattr(cuda, "HEAD_BUDGET_BYTES", 1)
    o2, g2 = render_and_grad(sc, 70, 50, BACKEND, "softmax_gs", device=DEV, k_max=5)
    assert torch.equal(o1.rgb, o2.rgb)
    for k in g1:
        torch.testing.assert_close(g1[k], g2[k], rtol=1e-5, atol=1e-6, msg=k)   # atomics: any order


def test_no_visible_splat_gives_the_background_and_zero_gradients():
    for n in (0, 3):
        sc = random_scene(5, 10, 8)
        sc = {k: v[:n] for k, v in sc.items()}
        sc["means2d"] = sc["means2d"] + 100.0
        bg = torch.tensor([0.2, 0.4, 0.6])
        o, g = render_and_grad(sc, 10, 8, BACKEND, "softmax_gs", device=DEV, background=bg)
        torch.testing.assert_close(o.rgb.cpu(), bg.expand(8, 10, 3), rtol=0, atol=0)
        assert (o.alpha == 0).all() and (o.depth == 0).all() and o.stats.n_contrib.sum() == 0
        for k in KEYS:
            assert (g[k] == 0).all()
        assert torch.isfinite(g["background"]).all()


@pytest.mark.parametrize("mode", MODES)
def test_rasterize_3d_cuda_matches_reference(mode):
    """Through the public 3D entry point: projection and SH on the GPU, then the kernel; gradients
    of every 3D parameter against the reference pipeline on the CPU."""
    g = torch.Generator().manual_seed(3)
    n, w, h = 50, 40, 30
    r = lambda *s: torch.rand(*s, generator=g)  # noqa: E731
    cam = Camera.look_at(eye=[0.0, 0.0, -4.0], target=[0.0, 0.0, 0.0], up=[0.0, -1.0, 0.0], fx=40.0, fy=40.0,
                         width=w, height=h)
    params = dict(means3d=(r(n, 3) - 0.5) * torch.tensor([3.0, 2.0, 2.0]), quats=r(n, 4) - 0.5,
                  scales=0.05 + 0.15 * r(n, 3), opacities=0.2 + 0.75 * r(n), sh=0.5 * (r(n, 4, 3) - 0.5),
                  alpha=0.5 + 2 * r(n), beta=10 * r(n), gamma=2 * r(n))

    def run(backend, device):
        p = {k: v.to(device).clone().requires_grad_(True) for k, v in params.items()}
        bg = torch.tensor([0.1, 0.2, 0.3], device=device, requires_grad=True)
        out = rasterize(p["means3d"], p["quats"], p["scales"], p["opacities"], p["sh"], cam, alpha=p["alpha"],
                        beta=p["beta"], gamma=p["gamma"], mode=mode, k_max=3, sh_degree=1, background=bg,
                        backend=backend)
        wr = torch.linspace(0, 1, out.rgb.numel(), device=device).reshape(out.rgb.shape)
        ((out.rgb * wr).sum() + out.alpha.sum() + 0.1 * out.depth.sum()).backward()
        grads = {**{k: v.grad for k, v in p.items()}, "background": bg.grad}
        return out, {k: None if v is None else v.cpu() for k, v in grads.items()}

    oc, gc = run(BACKEND, DEV)
    orf, gr = run("reference", "cpu")
    assert orf.stats.n_contrib.max() > 3
    # projection on the GPU rounds differently from the CPU's: a little more room than the 2D tests
    torch.testing.assert_close(oc.rgb.cpu(), orf.rgb, rtol=0, atol=4 * OUT_ATOL32)
    torch.testing.assert_close(oc.alpha.cpu(), orf.alpha, rtol=0, atol=4 * OUT_ATOL32)
    torch.testing.assert_close(oc.depth.cpu(), orf.depth, rtol=0, atol=4 * OUT_ATOL32 * 8)
    for k, v in gr.items():
        if v is None:
            assert gc[k] is None
            continue
        scale = v.abs().max().item() + 1e-8
        assert (gc[k] - v).abs().max().item() <= GRAD_RTOL32 * 10 * scale, k


def _stiff_run(s, mode, backend, device):
    """stability.run on ``device`` (the battery's loss, k_max = 64); results on the CPU."""
    inputs = [s[k].to(device).clone().requires_grad_(True) for k in KEYS]
    out = rasterize_splats(*inputs, stability.W, stability.H, mode=mode, k_max=64, backend=backend)
    wts = torch.linspace(0.5, 1.5, 3, dtype=out.rgb.dtype, device=device)
    loss = (out.rgb * wts).sum() + out.alpha.sum() + 0.1 * out.depth.sum()
    if not loss.requires_grad:
        return out, {k: torch.zeros_like(t).cpu() for k, t in zip(KEYS, inputs)}
    loss.backward()
    return out, {k: None if t.grad is None else t.grad.cpu() for k, t in zip(KEYS, inputs)}


def test_stiff_battery_cuda_finite_and_close_to_float64():
    """The renderer's stiff cases (smgs.raster.stability: β up to 1e5, γ up to 1e6 and inf, α
    0.25..30, opacity 1-1e-7, identical depths, 50 stacked splats, conic condition number 1e8, ...)
    on the GPU in float32, against the float64 reference: every output and gradient finite, within
    the battery's tolerances (the thresholds of the CPU backend's test)."""
    check_stiff_battery()


def check_stiff_battery() -> None:
    """The stiff battery through ``rasterize_splats`` on the CUDA backend (whichever kernels
    ``$SMGS_CUDA_KERNELS`` selects) against the float64 reference."""
    sensitive = ("beta=100000", "beta=1000", "conic_cond_1e8", "stacked50")
    n_rows = 0
    for name, spec in stability.stiff_cases():
        for mode in MODES:
            o64, g64 = stability.run(stability.make_case(spec, torch.float64), mode)
            out, grads = _stiff_run(stability.make_case(spec, torch.float32), mode, BACKEND, DEV)
            outs = [(out.rgb, o64.rgb), (out.alpha, o64.alpha), (out.depth, o64.depth)]
            for a, _ in outs:
                assert torch.isfinite(a).all(), (name, mode)
            err = max(float((a.detach().cpu().double() - b.detach()).abs().max()) for a, b in outs)
            atol = (2e-4 if name == "conic_cond_1e8" else stability.OUT_ATOL) * 3
            assert err < atol, (name, mode, err)
            gerr = 0.0
            for k in KEYS:
                a, b = grads.get(k), g64.get(k)
                if a is None or b is None:
                    continue
                assert torch.isfinite(a).all(), (name, mode, k)
                gerr = max(gerr, float((a.double() - b).abs().max()) / (float(b.abs().max()) + 1e-6))
            if name not in sensitive:
                assert gerr <= stability.GRAD_RTOL, (name, mode, gerr)
            n_rows += 1
    assert n_rows > 100
