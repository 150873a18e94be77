"""Stiff and extreme inputs: every output and gradient finite, float32 close to float64.

Also shows each numerical hazard of Algorithm 1 as printed, next to the stable form we use.
"""

import math
from decimal import Decimal, getcontext

import pytest
import torch

from smgs.raster import MODES, backend_available, rasterize_splats
from smgs.raster.stability import GRAD_RTOL, H, KEYS, OUT_ATOL, W, base_scene, make_case, run, stiff_cases

# every SIMD path of the compiled CPU kernels this host runs (tests/conftest.py)
pytestmark = pytest.mark.usefixtures("cpu_isa")

@pytest.mark.parametrize("mode", ["softmax_gs", "softmax_only", "gef_only", "3dgs"])
@pytest.mark.parametrize("name,spec", stiff_cases(), ids=[c[0] for c in stiff_cases()])
def test_stiff_case_finite_and_float32_close_to_float64(name, spec, mode):
    o64, g64 = run(make_case(spec, torch.float64), mode)
    o32, g32 = run(make_case(spec, torch.float32), mode)
    for o in (o64, o32):
        for t in (o.rgb, o.alpha, o.depth):
            assert torch.isfinite(t).all(), name
    for g in (g64, g32):
        for k, v in g.items():
            assert v is None or torch.isfinite(v).all(), f"{name}: non-finite gradient of {k}"
    # conic_cond_1e8 too: the quadratic form in its LDLᵀ form (tests/test_raster_quad.py) keeps q^α
    # near q = 0 (α = 0.5) accurate; summed as written it was off by ~1e-4 here.
    atol = OUT_ATOL
    assert (o32.rgb.double() - o64.rgb).abs().max() < atol
    assert (o32.alpha.double() - o64.alpha).abs().max() < atol
    # depth is in scene units (1..3 here), so a relative bound
    assert (o32.depth.double() - o64.depth).abs().max() < atol * 3
    if name in ("beta=100000", "beta=1000") or name.startswith("stacked"):
        return  # sigmoid/product sensitivities: finiteness checked above, values not comparable
    for k in KEYS:
        a, b = g32[k], g64[k]
        if a is None:
            continue
        scale = b.abs().max().item() + 1e-6
        assert (a.double() - b).abs().max().item() <= GRAD_RTOL * scale, f"{name}: gradient of {k}"


# --- the hazards of Algorithm 1 as printed, one test each ------------------------------------


def printed_root(a_cur, a_past, T_orig):
    """Line 18 of Algorithm 1, literally."""
    A = a_cur + a_past
    B = a_cur * a_past
    C = 1 - T_orig
    return (A - math.sqrt(A * A - 4 * B * C)) / (2 * B)


def stable_root(a_cur, a_past, T_orig):
    D = (a_cur - a_past) ** 2 + 4 * a_cur * a_past * T_orig
    return 2 * (1 - T_orig) / (a_cur + a_past + math.sqrt(D))


def exact_root(a_cur, a_past, T_orig):
    getcontext().prec = 80
    a, b, t = Decimal(a_cur), Decimal(a_past), Decimal(T_orig)
    A, B, C = a + b, a * b, 1 - t
    return float((A - (A * A - 4 * B * C).sqrt()) / (2 * B))


def test_printed_quadratic_root_cancels_and_the_stable_form_does_not():
    # one side has lost the softmax: B = ā_cur·ā_past tiny
    cases = [(0.5, 1e-9, 0.4), (1e-12, 0.7, 0.29), (0.3, 1e-17, 0.69)]
    worst_printed = max(abs(printed_root(*c) - exact_root(*c)) / exact_root(*c) for c in cases)
    worst_stable = max(abs(stable_root(*c) - exact_root(*c)) / exact_root(*c) for c in cases)
    assert worst_printed > 1e-3          # float64 and still wrong in the third digit or worse
    assert worst_stable < 1e-14
    with pytest.raises(ZeroDivisionError):
        printed_root(0.5, 0.0, 0.4)     # B = 0: 0/0 as printed
    assert stable_root(0.5, 0.0, 0.4) == pytest.approx(1.2)


def test_one_minus_w_cur_rounds_to_zero_but_the_second_sigmoid_does_not():
    x = torch.tensor(40.0)               # β·Δp = 40: e^-40 ≈ 4e-18 < float32 epsilon
    assert (1 - torch.sigmoid(x)).item() == 0.0
    assert torch.sigmoid(-x).item() > 0.0
    # end to end: a huge β makes one side lose completely, the image stays finite and exact
    s = make_case({"beta": 1e5}, torch.float32)
    o, g = run(s, "softmax_gs")
    assert torch.isfinite(o.rgb).all() and all(torch.isfinite(v).all() for v in g.values())


def test_elongated_conic_rounding_negative_exponent_is_clamped():
    s = make_case("elongated", torch.float32)
    # the raw quadratic form does go negative in float32 for this conic at some pixel
    ys, xs = torch.meshgrid(torch.arange(H) + 0.5, torch.arange(W) + 0.5, indexing="ij")
    a, b, c = s["conics"][0]
    dx, dy = xs - s["means2d"][0, 0], ys - s["means2d"][0, 1]
    raw = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    assert (raw < 0).any()
    assert torch.isnan(raw.clamp(max=0).neg().pow(0.5).neg().pow(0.5)).any()  # (-p)^α of a negative
    o, g = run(s, "softmax_gs")
    assert torch.isfinite(o.rgb).all() and all(torch.isfinite(v).all() for v in g.values())


def test_equal_depths_keep_s_exactly_one_at_huge_gamma():
    """A weighted mean of equal depths must stay bit-exact, or s = exp(-γ·ulp) ≠ 1 at large γ."""
    s = make_case({"depths": 2.3}, torch.float32)
    s["beta"] = torch.full_like(s["beta"], 5.0)
    o_big, _ = run({**s, "gamma": torch.full_like(s["gamma"], 1e6)}, "softmax_gs")
    o_zero, _ = run({**s, "gamma": torch.zeros_like(s["gamma"])}, "softmax_gs")
    torch.testing.assert_close(o_big.rgb, o_zero.rgb, rtol=0, atol=0)
    # the ratio form of the printed line 25 does drift for these weights
    d = torch.tensor(2.3, dtype=torch.float32)
    T, acc = torch.tensor(1.0), torch.tensor(0.0)
    drift = False
    for a in (0.37, 0.11, 0.58, 0.23):
        a = torch.tensor(a)
        acc = (acc * (1 - T) + d * a * T) / (1 - T + a * T)
        T = T * (1 - a)
        drift |= bool(acc != d)
    assert drift


def test_gamma_inf_times_zero_depth_gap():
    s = make_case({"depths": 2.0, "gamma": math.inf}, torch.float64)
    o, g = run(s, "softmax_gs")
    assert torch.isfinite(o.rgb).all() and all(torch.isfinite(v).all() for v in g.values())
    assert math.isnan(math.inf * 0.0)


def test_gef_gradient_at_the_centre_is_finite_for_alpha_below_one():
    s = make_case("centred", torch.float64)
    o, g = run(s, "gef_only")
    assert all(torch.isfinite(v).all() for v in g.values() if v is not None)
    q = torch.zeros((), dtype=torch.float64, requires_grad=True)
    q.pow(0.25).backward()               # what a plain pow would give
    assert math.isinf(q.grad.item())


def test_tiny_absorbance_survives_in_alpha():
    """alpha = 1 - T is carried as A + a·T: a single faint splat keeps full relative precision."""
    s = {k: v.float() for k, v in base_scene(torch.float32, n=1).items()}
    s["opacities"] = torch.tensor([0.0045])
    o = rasterize_splats(*[s[k] for k in KEYS], W, H, mode="softmax_gs", backend="reference")
    s64 = {k: v.double() for k, v in s.items()}
    o64 = rasterize_splats(*[s64[k] for k in KEYS], W, H, mode="softmax_gs", backend="reference")
    hit = o64.alpha > 0
    rel = ((o.alpha.double() - o64.alpha).abs()[hit] / o64.alpha[hit]).max()
    assert rel < 1e-6


@pytest.mark.parametrize("mode", MODES)
def test_leading_splats_with_zero_absorbance_are_skipped(mode):
    s = make_case("leading_zero", torch.float64)
    o, _ = run(s, mode)
    s2 = {k: v[2:] for k, v in s.items()}
    o2, _ = run(s2, mode)
    torch.testing.assert_close(o.rgb, o2.rgb, rtol=0, atol=0)


def test_deep_softmax_stack_stays_finite():
    """40 saturated splats in the softmax head (no stop there): T underflows to 0 in float32 after
    ~20 of them, and at β = 1e5 the later splats' softmax weights underflow too; ã_cur's denominator
    is then 0 (or denormal: rcp14 gives inf). Outputs and gradients stay finite in both dtypes,
    and the cpu kernel matches the reference."""
    n = 40
    g = torch.Generator().manual_seed(0)
    base = dict(means2d=0.5 + 3 * torch.rand(n, 2, generator=g), conics=torch.tensor([[1e-3, 0.0, 1e-3]] * n),
                opacities=torch.ones(n), colors=torch.rand(n, 3, generator=g),
                depths=1 + 0.01 * torch.arange(n, dtype=torch.float32), alpha=torch.ones(n),
                beta=torch.full((n,), 1e5), gamma=torch.ones(n))
    rgbs = {}
    for dtype, backend in [(torch.float64, "reference"), (torch.float32, "reference")] + \
            ([(torch.float32, "cpu")] if backend_available("cpu", "cpu") else []):
        ins = {k: v.to(dtype).requires_grad_(True) for k, v in base.items()}
        out = rasterize_splats(*[ins[k] for k in KEYS], 1, 1, mode="softmax_gs", backend=backend)
        (out.rgb * torch.tensor([1.0, 2.0, 3.0], dtype=dtype)).sum().backward()
        assert torch.isfinite(out.rgb).all() and torch.isfinite(out.depth).all(), (dtype, backend)
        assert out.stats.n_contrib.item() == n, (dtype, backend)
        for k in KEYS:
            assert torch.isfinite(ins[k].grad).all(), (dtype, backend, k)
        rgbs[(dtype, backend)] = out.rgb.detach()
    if (torch.float32, "cpu") in rgbs:
        torch.testing.assert_close(rgbs[(torch.float32, "cpu")], rgbs[(torch.float32, "reference")], atol=1e-6, rtol=0)
