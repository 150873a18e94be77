"""Input checks of the public renderer entry points, the same whichever backend renders.

Policy (one per case, so no backend differs): a non-finite value (NaN or ±inf) in means, conics,
opacities, colours, depths, α or β, a NaN or −inf γ, a negative or non-finite 3D scale, a
non-finite camera matrix, a non-floating or mixed dtype, and an image size that is not a positive
integer up to ``MAX_IMAGE_SIDE`` are refused with a ValueError/TypeError that names the input and
how many entries are bad. γ = +inf is valid (a hard depth decay; the stiff-case battery renders it).

Cost: one stacked sum per call and one host synchronisation; a non-finite sum (NaN/inf anywhere,
or an overflow of finite values) then counts the bad entries per tensor to decide and to name them.
"""

from __future__ import annotations

import operator

import torch

MAX_IMAGE_SIDE = 16384
"""The largest width or height rendered (a 16384² RGB float32 image is 3 GiB with its buffers);
a larger size is almost always a unit mistake and is refused before anything is allocated."""

FLOAT_DTYPES = (torch.float32, torch.float64)


class NonFiniteInputError(ValueError):
    """A renderer input holds NaN or inf (a caller such as the trainer may name its source)."""


def image_size(width: object, height: object) -> tuple[int, int]:
    """(width, height) as ints, or a TypeError/ValueError that says what was given."""
    out = []
    for name, v in (("width", width), ("height", height)):
        if isinstance(v, bool):
            raise TypeError(f"{name} must be an integer number of pixels, got {v!r}")
        try:
            n = operator.index(v)
        except TypeError:
            raise TypeError(f"{name} must be an integer number of pixels, got {type(v).__name__} {v!r}") from None
        if not 1 <= n <= MAX_IMAGE_SIDE:
            raise ValueError(f"{name}={n} is outside 1..{MAX_IMAGE_SIDE} pixels")
        out.append(int(n))
    return out[0], out[1]


def float_dtypes(named: list[tuple[str, torch.Tensor | None]]) -> None:
    """Every given tensor is float32 or float64, all of the first one's dtype."""
    present = [(n, t) for n, t in named if t is not None]
    first_name, first = present[0]
    for name, t in present:
        if t.dtype not in FLOAT_DTYPES:
            raise TypeError(f"{name} has dtype {t.dtype}; the renderer takes float32 or float64 tensors "
                            f"(convert with .float())")
        if t.dtype != first.dtype:
            raise TypeError(f"{name} is {t.dtype} but {first_name} is {first.dtype}; give every input one dtype")


def finite(named: list[tuple[str, torch.Tensor | None]], pos_inf_ok: tuple[str, ...] = ()) -> None:
    """Refuse NaN/inf in the given tensors (+inf allowed in those named in ``pos_inf_ok``)."""
    present = [(n, t.detach()) for n, t in named if t is not None and t.numel()]
    if not present:
        return
    # One sum per tensor in its own dtype: NaN/inf propagate into it. A finite sum that overflows
    # only sends us to the exact per-element count below, which refuses nothing finite. (Summing in
    # float64 converted every element: 31 ms for 100k splats with SH degree 3, more than the render.)
    # One stack per device: the camera's tensors may stay on the CPU while the splats are on a GPU.
    by_device: dict[torch.device, list[torch.Tensor]] = {}
    for _, t in present:
        by_device.setdefault(t.device, []).append(t.sum().to(torch.float64))
    if all(bool(torch.isfinite(torch.stack(sums)).all()) for sums in by_device.values()):
        return
    for name, t in present:
        bad = torch.isnan(t) | (t == -torch.inf) if name in pos_inf_ok else ~torch.isfinite(t)
        count = int(bad.sum())
        if count:
            what = "NaN or -inf" if name in pos_inf_ok else "NaN or inf"
            raise NonFiniteInputError(f"{name} has {count} {what} value(s) of {t.numel()}; the renderer takes "
                             "finite inputs (find where they became non-finite, e.g. a diverged optimiser)")


def non_negative(name: str, t: torch.Tensor) -> None:
    if t.numel() and bool((t.detach() < 0).any()):
        raise ValueError(f"{name} has {int((t.detach() < 0).sum())} negative value(s); scales are activated "
                         "(positive) standard deviations, e.g. exp(log_scales)")
