"""The quadratic form -p = ½dᵀQd of elongated splats against float64 on every backend.

Summed as a·dx² + 2b·dx·dy + c·dy² in float32 the terms of a splat with condition number κ cancel to
an absolute error of ~eps·λmax·|d|² (1.2e-3 in alpha on these splats). Every backend
evaluates the LDLᵀ form of the conic instead (splat_factor in splat_math.h, quadratic_form in
reference.py), whose error is ~eps·√(λmax·q)·|d|: each one must match a float64 evaluation of the
same float32 inputs to the float32-vs-float64 tolerance of the other tests (stability.OUT_ATOL);
so must conics that are not positive definite, which keep their (unclamped) quadratic form.
"""

import math
import shutil

import pytest
import torch

from smgs.raster import rasterize_splats
from smgs.raster import constants as K
from smgs.raster.stability import OUT_ATOL

W, H = 64, 48
OPACITY = 0.9   # below ALPHA_MAX, so alpha = o·exp(-q) unclamped


def elongated_splats() -> list[tuple[float, float, float, tuple[float, float]]]:
    """(λmax, κ, angle, mean): thin axes of σ = 1 and 0.18 pixel, condition numbers 1e4..1e8,
    means near the centre and near two corners (|d| up to ~70 pixels)."""
    out = []
    for lmax in (1.0, 30.0):
        for kappa in (1e4, 1e6, 1e8):
            for th in (0.1, 0.55, 1.2, 1.9, 2.6):
                for mean in ((31.3, 23.7), (3.2, 44.1), (60.9, 2.6)):
                    out.append((lmax, kappa, th, mean))
    return out


def splat(lmax: float, kappa: float, th: float, mean: tuple[float, float]) -> dict[str, torch.Tensor]:
    """One splat; its conic rounded to float32, as every backend sees it."""
    lmin = lmax / kappa
    c, s = math.cos(th), math.sin(th)
    conic = [lmax * c * c + lmin * s * s, (lmax - lmin) * c * s, lmax * s * s + lmin * c * c]
    f = torch.float32
    return dict(means2d=torch.tensor([mean], dtype=f), conics=torch.tensor([conic], dtype=f),
                opacities=torch.tensor([OPACITY], dtype=f), colors=torch.ones(1, 3, dtype=f),
                depths=torch.ones(1, dtype=f))


def non_positive_definite() -> list[dict[str, torch.Tensor]]:
    """Conics no projection produces, which keep their quadratic form: a = 0 (no LDLᵀ pivot, the
    summed form's branch), a < 0, and indefinite with a > 0."""
    out = []
    for conic in ([0.0, 0.3, 0.05], [-0.02, 0.01, 0.04], [0.03, 0.05, 0.02]):
        sc = splat(1.0, 1.0, 0.0, (30.2, 21.6))
        sc["conics"] = torch.tensor([conic], dtype=torch.float32)
        out.append(sc)
    return out


def exact_alpha(sc: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """alpha from q in float64 of the float32 inputs, and the pixels not within rounding of the
    reach thresholds (q <= 4.5, alpha >= 1/255), where a backend may decide either way."""
    ys, xs = torch.meshgrid(torch.arange(H, dtype=torch.float64) + K.PIXEL_CENTER,
                            torch.arange(W, dtype=torch.float64) + K.PIXEL_CENTER, indexing="ij")
    (mx, my), (a, b, c) = sc["means2d"][0].double().tolist(), sc["conics"][0].double().tolist()
    dx, dy = xs - mx, ys - my
    q = 0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy
    alpha = OPACITY * torch.exp(-q.clamp(min=0))
    reach = (q <= -K.P_MIN) & (alpha >= K.ALPHA_MIN)
    clear = ((q + K.P_MIN).abs() > 1e-3) & ((alpha - K.ALPHA_MIN).abs() > 1e-5)
    return torch.where(reach, alpha, torch.zeros_like(alpha)), clear


def worst_error(backend: str, device: str = "cpu") -> float:
    worst = 0.0
    for sc in [splat(*spec) for spec in elongated_splats()] + non_positive_definite():
        want, clear = exact_alpha(sc)
        sc = {k: v.to(device) for k, v in sc.items()}
        out = rasterize_splats(sc["means2d"], sc["conics"], sc["opacities"], sc["colors"], sc["depths"],
                               None, None, None, W, H, mode="3dgs", backend=backend)
        worst = max(worst, (out.alpha.cpu().double() - want).abs()[clear].max().item())
    return worst


def test_reference_float32_matches_float64():
    assert worst_error("reference") < OUT_ATOL


@pytest.mark.skipif(shutil.which("c++") is None, reason="no C++ compiler: the cpu backend cannot be built here")
def test_cpu_matches_float64(cpu_isa):
    assert worst_error("cpu") < OUT_ATOL


@pytest.mark.gpu
@pytest.mark.skipif(not torch.cuda.is_available(), reason="no CUDA device visible")
def test_cuda_matches_float64():
    assert worst_error("cuda", "cuda") < OUT_ATOL


def test_summed_quadratic_form_misses_the_tolerance_on_these_splats():
    """The hazard is real on this set: the form as written, in float32, is off by far more."""
    worst = 0.0
    for spec in elongated_splats():
        sc = splat(*spec)
        want, clear = exact_alpha(sc)
        ys, xs = torch.meshgrid(torch.arange(H) + K.PIXEL_CENTER, torch.arange(W) + K.PIXEL_CENTER, indexing="ij")
        a, b, c = sc["conics"][0]
        dx, dy = xs - sc["means2d"][0, 0], ys - sc["means2d"][0, 1]
        q = torch.clamp(0.5 * (a * dx * dx + c * dy * dy) + b * dx * dy, min=0.0)
        alpha = OPACITY * torch.exp(-q)
        alpha = torch.where((q <= -K.P_MIN) & (alpha >= K.ALPHA_MIN), alpha, torch.zeros_like(alpha))
        worst = max(worst, (alpha.double() - want).abs()[clear].max().item())
    assert worst > 20 * OUT_ATOL
