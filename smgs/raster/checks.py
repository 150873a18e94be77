"""Input checks of the public renderer entry points, the same whichever backend renders.

Policy (one per case, so no backend differs): a non-finite value (NaN or ±inf) in means, conics,
opacities, colours, depths, α or β, a NaN or −inf γ, a negative or non-finite 3D scale, a
non-finite camera matrix, a non-floating or mixed dtype, and an image size that is not a positive
integer up to ``MAX_IMAGE_SIDE`` are refused with a ValueError/TypeError that names the input and
how many entries are bad. γ = +inf is valid (a hard depth decay; the stiff-case battery renders it).

Cost: one stacked sum per call and device and one host synchronisation per device; a non-finite
sum (NaN/inf anywhere, or an overflow of finite values) then counts the bad entries per tensor to
decide and to name them. ``InputChecks`` with ``defer`` (the lean GPU glue) keeps the sums of GPU
tensors on the GPU and reads them after the render, with the render's own wait.
"""

from __future__ import annotations

import operator

import torch

from smgs.raster.device_glue import Event, to_host_async

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


class InputChecks:
    """The finiteness and sign checks of one render call. Without ``defer`` each check decides at
    once (``finite``, ``non_negative``). With ``defer``, checks of tensors off the CPU become flags
    on their device: ``start`` copies them to the host without waiting, just before the backend
    runs, and ``settle`` (after it, or when it raised) reads them; a raised flag re-runs the exact
    checks, which name the input. So a bad input still raises the same error, after the render
    instead of before it (a non-finite splat only ever widens its tile box to the whole image)."""

    def __init__(self, defer: bool = False) -> None:
        self.defer = defer
        self._flags: list[torch.Tensor] = []
        self._exact: list = []          # what re-runs when a flag is raised
        self._host: torch.Tensor | None = None
        self._event: Event | None = None

    def finite(self, named: list[tuple[str, torch.Tensor | None]], pos_inf_ok: tuple[str, ...] = ()) -> None:
        present = [(n, t) for n, t in named if t is not None and t.numel()]
        if not self.defer:
            finite(present, pos_inf_ok)
            return
        finite([(n, t) for n, t in present if t.device.type == "cpu"], pos_inf_ok)   # decided at once
        on_device = [(n, t.detach()) for n, t in present if t.device.type != "cpu"]
        if on_device:
            sums = torch.stack([t.sum().to(torch.float64) for _, t in on_device])
            self._flags.append(~torch.isfinite(sums).all())
            self._exact.append(lambda: finite(on_device, pos_inf_ok))

    def non_negative(self, name: str, t: torch.Tensor) -> None:
        if not self.defer or t.device.type == "cpu":
            non_negative(name, t)
        elif t.numel():
            t = t.detach()
            self._flags.append((t < 0).any())
            self._exact.append(lambda: non_negative(name, t))

    def start(self) -> None:
        """Copy the flags to the host without waiting (call just before the backend runs)."""
        if self._flags and self._host is None:
            flags = self._flags[0] if len(self._flags) == 1 else torch.stack(self._flags).any()
            self._host, self._event = to_host_async(flags)

    def settle(self) -> None:
        """Raise for a bad input; waits only where nothing has waited past the flags' copy yet."""
        if not self._flags:
            return
        self.start()
        if self._event is not None and not self._event.query():
            self._event.synchronize()
        raised = bool(self._host)
        self._flags, self._host, self._event = [], None, None
        if raised:
            for exact in self._exact:
                exact()
        self._exact = []
