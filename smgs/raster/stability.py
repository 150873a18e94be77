"""The renderer's stiff-case battery: extreme α, β, γ, opacities and geometry.

Shared by the tests (every backend must stay finite and close to the float64 reference on every case)
and by reports (the numerical-stability table). ``stiff_battery`` compares a backend and dtype with
the float64 reference backend on each case and mode.
"""

from __future__ import annotations

import math

import torch

from smgs.raster.api import backend_available, rasterize_splats
from smgs.raster.types import MODES

W, H = 10, 8

# float32 against float64 on the same inputs. Outputs: colours and alpha are sums of terms <= 1,
# each rounded at ~6e-8, so 2e-5 leaves room for ~100 roundings in the sequential state.
OUT_ATOL = 2e-5
# Gradients: compared relative to the largest gradient of the same input. At β·Δp ~ 1e5 a one-ulp
# change of p moves the sigmoid, so float32 gradients of the softmax parameters are only
# meaningful to ~1e-2 of their scale there; finiteness is the hard requirement.
GRAD_RTOL = 2e-2


def base_scene(dtype: torch.dtype, n: int = 4) -> dict[str, torch.Tensor]:
    g = torch.Generator().manual_seed(7)
    r = lambda *s: torch.rand(*s, generator=g, dtype=torch.float64)  # noqa: E731
    s = dict(means2d=torch.tensor([[3.0, 3.5], [5.2, 4.1], [4.4, 3.0], [6.0, 5.0]], dtype=torch.float64)[:n],
             conics=torch.stack([0.15 + 0.1 * r(n), 0.02 * (r(n) - 0.5), 0.15 + 0.1 * r(n)], 1),
             opacities=0.5 + 0.4 * r(n), colors=r(n, 3), depths=1 + 2 * r(n), alpha=1 + r(n),
             beta=5 * r(n), gamma=r(n))
    return s


def stiff_cases() -> list[tuple[str, object]]:
    """(name, spec) of every case of the battery (the renderer issue's list)."""
    cases = []
    for b in (0.0, 1e-6, 50.0, 1e3, 1e5):
        cases.append((f"beta={b:g}", {"beta": b}))
    for gm in (0.0, 1e-3, 1e3, 1e6, math.inf):
        cases.append((f"gamma={gm:g}", {"gamma": gm}))
    for al in (0.25, 0.5, 1.0, 3.0, 10.0, 30.0):
        cases.append((f"alpha={al:g}", {"alpha": al}))
    for o in (1e-6, 0.5, 0.99, 1 - 1e-7):
        cases.append((f"opacity={o:g}", {"opacities": o}))
    cases.append(("identical_depths", {"depths": 2.0}))
    cases.append(("identical_depths_big_gamma", {"depths": 2.0, "gamma": 1e6, "beta": 50.0}))
    cases.append(("stacked50", "stacked"))
    cases.append(("centred_on_pixel", "centred"))
    cases.append(("conic_cond_1e8", "elongated"))
    cases.append(("edge_of_3sigma", "edge"))
    cases.append(("leading_zero_opacity", "leading_zero"))
    return cases


def make_case(spec, dtype: torch.dtype) -> dict[str, torch.Tensor]:
    """The inputs of one case; float64 takes the float32-rounded values."""
    s = base_scene(dtype)
    if isinstance(spec, dict):
        for k, v in spec.items():
            s[k] = torch.full_like(s[k], v)
    elif spec == "stacked":
        n = 50
        s = {k: v[:1].repeat(n, *([1] * (v.dim() - 1))) for k, v in s.items()}
        s["opacities"] = torch.full((n,), 0.9, dtype=torch.float64)
    elif spec == "centred":
        s["means2d"][0] = torch.tensor([4.5, 3.5])  # exactly on pixel (4, 3): p = 0
        s["alpha"][0] = 0.25
    elif spec == "elongated":
        # eigenvalues 0.546 and 0.546e-8 (condition number 1e8), thin axis at 48.6°, found by a
        # search so that the float32 quadratic form rounds below 0 at a pixel of splat 0
        th, l1 = 0.8479028246589062, 0.5458454370498658
        c, sn = math.cos(th), math.sin(th)
        l2 = l1 * 1e-8
        s["conics"][:] = torch.tensor([l2 * c * c + l1 * sn * sn, (l2 - l1) * c * sn, l2 * sn * sn + l1 * c * c])
        s["means2d"][0] = torch.tensor([2.75, 3.25])
        s["alpha"][:] = 0.5
    elif spec == "edge":
        # a pixel exactly on the 3σ ellipse: q = 4.5 at pixel (6, 3) for splat 0
        s["conics"][0] = torch.tensor([1.0, 0.0, 1.0])
        s["means2d"][0] = torch.tensor([6.5 - 3.0, 3.5])
    elif spec == "leading_zero":
        s["opacities"][0] = 0.0
        s["depths"][0] = 0.5
        s["opacities"][1] = 1e-9
        s["depths"][1] = 0.6
    # float64 runs take the float32-rounded inputs, so the comparison sees only the arithmetic
    return {k: v.float().to(dtype) for k, v in s.items()}


KEYS = ["means2d", "conics", "opacities", "colors", "depths", "alpha", "beta", "gamma"]


def run(s: dict, mode: str, eq15: str = "solved", backend: str = "reference"):
    """Render a case and back-propagate a fixed loss; returns (output, {input: gradient})."""
    inputs = [s[k].clone().requires_grad_(True) for k in KEYS]
    out = rasterize_splats(*inputs, W, H, mode=mode, k_max=64, backend=backend, eq15=eq15)
    loss = (out.rgb * torch.linspace(0.5, 1.5, 3, dtype=out.rgb.dtype, device=out.rgb.device)).sum() + out.alpha.sum() \
        + 0.1 * out.depth.sum()
    if not loss.requires_grad:  # no splat reached any pixel: the image does not depend on them
        return out, {k: torch.zeros_like(t) for k, t in zip(KEYS, inputs)}
    loss.backward()
    return out, {k: t.grad for k, t in zip(KEYS, inputs)}


def stiff_battery(backends=("reference", "cpu"), dtypes=("float32",), modes=MODES) -> list[dict]:
    """Rows {case, mode, backend, dtype, max_abs_err, max_grad_rel_err, nonfinite_outputs,
    nonfinite_grads}: errors of each backend/dtype against the float64 reference on each case.
    ``max_grad_rel_err`` is relative to the largest reference gradient of the same input.
    Backends unavailable here are left out."""
    rows = []
    for name, spec in stiff_cases():
        ref64 = {m: run(make_case(spec, torch.float64), m) for m in modes}
        for backend in backends:
            for dt in dtypes:
                dtype = getattr(torch, dt)
                case = make_case(spec, dtype)
                if not backend_available(backend, case["means2d"].device, dtype):
                    continue
                for m in modes:
                    out, grads = run(case, m, backend=backend)
                    o64, g64 = ref64[m]
                    outs = [(out.rgb, o64.rgb), (out.alpha, o64.alpha), (out.depth, o64.depth)]
                    nonfinite_out = sum(int((~torch.isfinite(a.detach())).sum()) for a, _ in outs)
                    err = max(float((a.detach().double() - b.detach()).abs().max()) for a, b in outs)
                    nonfinite_g, gerr = 0, 0.0
                    for k in KEYS:
                        a, b = grads.get(k), g64.get(k)
                        if a is None or b is None:
                            continue
                        nonfinite_g += int((~torch.isfinite(a)).sum())
                        scale = float(b.abs().max()) + 1e-6
                        gerr = max(gerr, float((a.double() - b).abs().max()) / scale)
                    rows.append(dict(case=name, mode=m, backend=backend, dtype=dt, max_abs_err=err,
                                     max_grad_rel_err=gerr, nonfinite_outputs=nonfinite_out,
                                     nonfinite_grads=nonfinite_g))
    return rows
