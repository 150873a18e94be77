"""Input checks of the public renderer entry points, the same whichever backend renders.

Policy (one per case, so no backend differs): a non-finite value (NaN or ±inf) in means, conics,
opacities, colours, depths, α or β, a NaN or −inf γ, a negative or non-finite 3D scale, a
non-finite camera matrix, a non-floating or mixed dtype, and an image size that is not a positive
integer up to ``MAX_IMAGE_SIDE`` are refused with a ValueError/TypeError that names the input and
how many entries are bad. γ = +inf is valid (a hard depth decay; the stiff-case battery renders it).

Cost: float32 CPU tensors (the CPU trainer's) are counted exactly in one compiled pass per call
(the compiled projection's ``input_checks``, once this process has loaded it: a check never builds
it). Otherwise one stacked sum per call and device and one host synchronisation per device; a
non-finite sum (NaN/inf anywhere, or an overflow of finite values) then counts the bad entries per
tensor to decide and to name them. Either way the same inputs are refused with the same words.
``InputChecks`` with ``defer`` (the lean GPU glue) keeps the checks of GPU tensors on the GPU (each
tensor's min and max, or a flag the fused projection kernel raises) and reads them after the render,
with the render's own wait; before the render, the splats' opacities are made NaN where an input is
bad, so that no backend renders anything of them (a NaN splat's tile box is the whole image).
"""

from __future__ import annotations

import math
import operator

import torch

from smgs.raster.device_glue import Event, to_host_async
from smgs.raster.projection import _JIT as _PROJECTION   # its compiled pass counts float32 CPU inputs

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


def _compiled_counts(present: list[tuple[str, torch.Tensor]],
                     pos_inf_ok: tuple[str, ...]) -> list[tuple[int, int]] | None:
    """(bad, negative) values of each tensor, counted by the compiled pass, where every tensor is float32
    on the CPU and this process has loaded the compiled projection; else None (the PyTorch path)."""
    if not all(t.device.type == "cpu" and t.dtype == torch.float32 for _, t in present):
        return None
    ext = _PROJECTION.loaded()
    if ext is None:
        return None
    flat = ext.input_checks([t for _, t in present], [n in pos_inf_ok for n, _ in present])
    return list(zip(flat[0::2], flat[1::2]))


def nonfinite_counts(tensors: list[torch.Tensor]) -> list[int] | None:
    """The NaN and ±inf values of each tensor, counted exactly in one compiled pass, where every tensor
    is float32 on the CPU and the compiled projection is loaded here; else None (nothing computed)."""
    counts = _compiled_counts([("", t.detach()) for t in tensors], ())
    return None if counts is None else [bad for bad, _ in counts]


def _refuse(name: str, t: torch.Tensor, count: int, pos_inf_ok: tuple[str, ...]) -> None:
    what = "NaN or -inf" if name in pos_inf_ok else "NaN or inf"
    raise NonFiniteInputError(f"{name} has {count} {what} value(s) of {t.numel()}; the renderer takes "
                              "finite inputs (find where they became non-finite, e.g. a diverged optimiser)")


def finite(named: list[tuple[str, torch.Tensor | None]], pos_inf_ok: tuple[str, ...] = (),
           non_negative_name: str | None = None) -> None:
    """Refuse NaN/inf in the given tensors (+inf allowed in those named in ``pos_inf_ok``), then
    negative values in the one named ``non_negative_name`` (``non_negative``; the compiled pass
    counts both at once)."""
    present = [(n, t.detach()) for n, t in named if t is not None and t.numel()]
    if not present:
        return
    counts = _compiled_counts(present, pos_inf_ok)
    if counts is not None:
        for (name, t), (bad, _) in zip(present, counts):
            if bad:
                _refuse(name, t, bad, pos_inf_ok)
        for (name, _), (_, negative) in zip(present, counts):
            if name == non_negative_name and negative:
                _refuse_negative(name, negative)
        return
    # One sum per tensor in its own dtype: NaN/inf propagate into it. A finite sum that overflows
    # only sends us to the exact per-element count below, which refuses nothing finite. (Summing in
    # float64 converted every element: 31 ms for 100k splats with SH degree 3, more than the render.)
    # One stack per device: the camera's tensors may stay on the CPU while the splats are on a GPU.
    by_device: dict[torch.device, list[torch.Tensor]] = {}
    for _, t in present:
        by_device.setdefault(t.device, []).append(t.sum().to(torch.float64))
    if not all(bool(torch.isfinite(torch.stack(sums)).all()) for sums in by_device.values()):
        for name, t in present:
            bad = torch.isnan(t) | (t == -torch.inf) if name in pos_inf_ok else ~torch.isfinite(t)
            count = int(bad.sum())
            if count:
                _refuse(name, t, count, pos_inf_ok)
    if non_negative_name is not None:
        sign = dict(present).get(non_negative_name)
        if sign is not None:
            non_negative(non_negative_name, sign)


def _refuse_negative(name: str, count: int) -> None:
    raise ValueError(f"{name} has {count} negative value(s); scales are activated "
                     "(positive) standard deviations, e.g. exp(log_scales)")


def non_negative(name: str, t: torch.Tensor) -> None:
    if not t.numel():
        return
    t = t.detach()
    counts = _compiled_counts([(name, t)], ())
    negative = counts[0][1] if counts is not None else int((t < 0).sum())
    if negative:
        _refuse_negative(name, negative)


class InputChecks:
    """The finiteness and sign checks of one render call. Without ``defer`` each check decides at
    once (``finite``, with ``non_negative`` of the one so named). With ``defer``, checks of tensors
    off the CPU stay on their device: each tensor's min and max (one kernel; NaN propagates, ±inf shows, nothing overflows),
    or a flag a kernel raises itself (``in_kernel``/``kernel_flag``: the fused projection). ``gate``
    makes the opacities NaN where a value is bad (every backend skips such a splat: nothing renders
    before the refusal); ``start`` copies the values to the host without waiting, just before the
    backend runs, and ``settle`` (after it, or when it raised) decides on the host and re-runs the
    exact checks of a bad input, which name it. So a bad input still raises the same error, after
    the render instead of before it."""

    def __init__(self, defer: bool = False) -> None:
        self.defer = defer
        self._finite: list[torch.Tensor] = []   # 0-dim device values, finite where their input is
        self._signs: list[torch.Tensor] = []    # 0-dim device values, >= 0 where their input is
        self._flags: list[torch.Tensor] = []    # kernels' int flags [1], non-zero where an input is bad
        self._exact: list = []                  # what re-runs (and names the input) when a value is bad
        self._kernel_exact = None               # the exact checks of what a kernel checks (in_kernel)
        self._stacked: torch.Tensor | None = None
        self._host: torch.Tensor | None = None
        self._event: Event | None = None

    def finite(self, named: list[tuple[str, torch.Tensor | None]], pos_inf_ok: tuple[str, ...] = (),
               non_negative_name: str | None = None) -> None:
        """``finite`` of these (and the sign of ``non_negative_name``'s), decided now or deferred."""
        present = [(n, t) for n, t in named if t is not None and t.numel()]
        if not self.defer:
            finite(present, pos_inf_ok, non_negative_name)
            return
        # decided at once
        finite([(n, t) for n, t in present if t.device.type == "cpu"], pos_inf_ok, non_negative_name)
        on_device = [(n, t.detach()) for n, t in present if t.device.type != "cpu"]
        for name, t in on_device:
            if name in pos_inf_ok:   # NaN or -inf shows in the min; +inf is allowed (min(x, 0): finite)
                lo = t.amin()
                self._finite.append(lo.clamp(max=0.0))
            else:
                lo, hi = torch.aminmax(t)
                self._finite += [lo, hi]
            if name == non_negative_name:   # the sign from the same min
                self._signs.append(lo)
        if on_device:
            self._exact.append(lambda: finite(on_device, pos_inf_ok, non_negative_name))

    def in_kernel(self, named: list[tuple[str, torch.Tensor | None]], pos_inf_ok: tuple[str, ...] = (),
                  non_negative_name: str | None = None) -> None:
        """These are checked by a kernel of the render itself, which culls what is bad and raises a
        flag (``kernel_flag``): nothing to launch here; ``non_negative_name`` names the input whose
        sign it checks too."""
        present = [(n, t.detach()) for n, t in named if t is not None and t.numel()]
        self._kernel_exact = lambda: finite(present, pos_inf_ok, non_negative_name)

    @property
    def awaits_kernel_flag(self) -> bool:
        """Whether ``in_kernel`` left checks to a kernel whose flag has not come yet."""
        return self._kernel_exact is not None

    def kernel_flag(self, bad: torch.Tensor) -> None:
        """The flag of the kernel that made the ``in_kernel`` checks (non-zero: an input was bad)."""
        self._flags.append(bad)
        self._exact.append(self._kernel_exact)
        self._kernel_exact = None
        self._stacked = self._host = self._event = None   # values copied before the kernel ran lack its flag

    def _values(self) -> torch.Tensor | None:
        """Every deferred value in one device tensor (finite values, signs, kernel flags), made once."""
        if self._stacked is None and (self._finite or self._signs or self._flags):
            vals = self._finite + self._signs
            dtype = vals[0].dtype if vals else self._flags[0].dtype
            parts = ([vals[0].reshape(1) if len(vals) == 1 else torch.stack(vals)] if vals else []) \
                + [f.to(dtype) for f in self._flags]
            self._stacked = parts[0] if len(parts) == 1 else torch.cat(parts)
        return self._stacked

    def gate(self, opacities: torch.Tensor) -> torch.Tensor:
        """``opacities``, NaN throughout where a deferred finite value is bad (with the lean glue, before
        the render): every backend skips a splat whose opacity is not >= 1/255, so nothing of a bad
        input renders (a non-finite splat's tile box is the whole image). The gate carries no gradient."""
        vals = self._values()
        if not self._finite or vals is None:
            return opacities
        m = vals[:len(self._finite)].abs().amax()    # finite, or the inf/NaN of a bad input
        return opacities + (m - m).to(opacities.dtype)

    def start(self) -> None:
        """Copy the deferred values to the host without waiting (call just before the backend runs)."""
        vals = self._values()
        if vals is not None and self._host is None:
            self._host, self._event = to_host_async(vals)

    def settle(self) -> None:
        """Raise for a bad input; waits only where nothing has waited past the values' copy yet."""
        if self._values() is None:
            return
        self.start()
        if self._event is not None and not self._event.query():
            self._event.synchronize()
        host = self._host.tolist()
        nf, ns = len(self._finite), len(self._signs)
        raised = (not all(math.isfinite(v) for v in host[:nf]) or not all(v >= 0 for v in host[nf:nf + ns])
                  or any(v != 0 for v in host[nf + ns:]))
        exact = self._exact
        self._finite, self._signs, self._flags, self._exact = [], [], [], []
        self._stacked, self._host, self._event = None, None, None
        if raised:
            for check in exact:
                check()
