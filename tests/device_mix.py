"""A second device on a CPU-only machine, to catch operations that mix devices and to count host
synchronisations (tests/test_device_mix.py, tests/test_raster_syncs.py).

On a CPU-only machine every tensor is on the CPU, so an operation that mixes the camera's CPU
tensors with the run's device (``torch.stack`` of a CPU and a CUDA sum, which raised on every
``device=cuda`` render) passes unnoticed. Inside ``other_device()`` the ``meta`` device stands for
the GPU: a tensor "on meta" is a ``Remote`` (a wrapper that reports ``device='meta'`` and computes
on the CPU), made by ``.to('meta')``, ``device='meta'`` factories or any operation on a Remote. A
dispatch mode sees every operator and

* raises ``MixedDevices`` (naming the operator and the line of our code) where an operator's tensor
  inputs sit on both devices, with CUDA's own exceptions: a copy between devices (``_to_copy``,
  ``copy_``), and a 0-dim CPU tensor as an operand of an elementwise operator (CUDA reads it as a
  scalar on the host);
* counts what synchronises the host with a GPU: reading a Remote's value (``_local_scalar_dense``,
  ``.item()``, ``bool()``, ``.tolist()``), data-dependent shapes (``nonzero``, boolean indexing and
  boolean index assignment, ``unique``, ...), a blocking copy from a Remote to the CPU; and copies from the CPU to a Remote
  (which pageable memory makes blocking too). ``non_blocking=True`` copies to the host are counted
  apart (they do not wait);
* counts the device work a GPU's host would launch (``launches``: every operator on a Remote but
  views and bare allocations, each a kernel or a copy) and the calls into a stand-in binding
  (``bindings``; the binding's own kernels are its business: csrc/cuda_binding_common.h).

The meta device is used because autograd needs a device guard for the device a tensor reports,
which a CPU-only torch has for ``meta`` but not for ``cuda``. Code that branches on
``device.type == "cuda"`` sees another type here; ``Event`` below stands in for a CUDA event where
a test patches one in.
"""

from __future__ import annotations

import linecache
import sys
from collections import Counter
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import torch
from torch.utils._python_dispatch import TorchDispatchMode

REPO = Path(__file__).resolve().parent.parent
OTHER = torch.device("meta")
CPU = torch.device("cpu")
aten = torch.ops.aten
_HERE = Path(__file__).name
_REPO_PREFIX = str(REPO) + "/"

# operators whose output shape depends on the data: on a GPU they wait for it
_DATA_SHAPED = {aten.nonzero.default, aten.nonzero_static.default, aten.masked_select.default,
                aten._unique2.default, aten.unique_dim.default, aten.unique_consecutive.default,
                aten.repeat_interleave.Tensor, aten.is_nonzero.default, aten.equal.default,
                aten.allclose.default}
_READS = {aten._local_scalar_dense.default, aten.is_nonzero.default}
# indexing operators that wait when an index is a boolean mask (t[mask], t[mask] = v)
_INDEXED = {aten.index.Tensor, aten.index_put_.default, aten.index_put.default, aten._index_put_impl_.default}
# operators that run nothing on the device: views, and allocations without a fill
_NO_WORK = {aten._unsafe_view.default, aten.empty.memory_format, aten.empty_strided.default, aten.new_empty.default,
            aten.new_empty_strided.default, aten.empty_like.default, aten.is_nonzero.default}


def _device_work(func) -> bool:
    """Whether ``func`` on device tensors launches a kernel or a copy (what a GPU's host pays for)."""
    return not (getattr(func, "is_view", False) or func in _NO_WORK)


class MixedDevices(AssertionError):
    pass


def _our_frame() -> str:
    """The innermost stack frame in this repository's code (not torch's, not this file's)."""
    f = sys._getframe(2)
    while f is not None:
        p = Path(f.f_code.co_filename)
        if p.is_absolute() and p.name != _HERE and str(p).startswith(_REPO_PREFIX):
            line = linecache.getline(str(p), f.f_lineno).strip()
            return f"{p.relative_to(REPO)}:{f.f_lineno} {line}"
        f = f.f_back
    return "(no frame in this repository)"


class Remote(torch.Tensor):
    """A tensor on the stand-in device: reports ``meta``, holds its values in a CPU tensor."""

    inner: torch.Tensor

    @staticmethod
    def __new__(cls, inner: torch.Tensor) -> "Remote":
        r = torch.Tensor._make_wrapper_subclass(
            cls, inner.shape, strides=inner.stride(), storage_offset=inner.storage_offset(), dtype=inner.dtype,
            layout=inner.layout, device=OTHER, requires_grad=inner.requires_grad)
        r.inner = inner
        return r

    def __repr__(self) -> str:   # type: ignore[override]
        return f"Remote({self.inner!r})"

    @classmethod
    def __torch_dispatch__(cls, func, types, args=(), kwargs=None):
        raise RuntimeError(f"{func} on a Remote tensor outside other_device()")

    # what a CUDA tensor does with these
    def tolist(self):  # type: ignore[override]
        _MODE[-1].sync("tolist")
        return self.detach().inner.tolist()

    def new_tensor(self, data, dtype=None, device=None, requires_grad=False):  # type: ignore[override]
        return _tensor(data, dtype=self.dtype if dtype is None else dtype,
                       device=self.device if device is None else device, requires_grad=requires_grad)

    def numpy(self, *a, **k):  # type: ignore[override]
        raise TypeError("can't convert meta device type tensor to numpy. Use Tensor.cpu() to copy the "
                        "tensor to host memory first.")

    def __array__(self, *a, **k):
        return self.numpy()

    def __reduce_ex__(self, proto):   # torch.save of a device tensor: saved as the host values
        return (Remote, (self.detach().inner.clone(),))


class _Mode(TorchDispatchMode):
    def __init__(self, strict: bool = True) -> None:
        super().__init__()
        self.strict = strict
        self.counts: Counter[str] = Counter()
        self.syncs = 0      # host waits so far (never reset: FakeEvent compares against it)
        self.where: list[str] = []
        self.mixed: list[str] = []
        # device work (kernels and copies, by operator) and calls into a compiled binding
        self.launches: Counter[str] = Counter()
        self.bindings: Counter[str] = Counter()

    def sync(self, what: str) -> None:
        self.counts[what] += 1
        self.syncs += 1
        self.where.append(f"{what}: {_our_frame()}")

    def reset(self) -> None:
        self.counts.clear()
        self.where.clear()
        self.launches.clear()
        self.bindings.clear()

    def _mixed(self, func, tensors) -> None:
        msg = f"{func} mixes {', '.join(sorted({str(t.device) for t in tensors}))} tensors: {_our_frame()}"
        self.mixed.append(msg)
        if self.strict:
            raise MixedDevices(msg)

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = dict(kwargs or {})
        flat: list[torch.Tensor] = []
        _tensors((args, kwargs), flat)
        remote = [t for t in flat if type(t) is Remote]
        host = [t for t in flat if type(t) is not Remote]
        if any(t.device.type == OTHER.type for t in host):
            raise RuntimeError(f"{func}: a tensor on {OTHER} without values (made by a path that bypasses "
                               f"dispatch; other_device() patches torch.tensor and torch.as_tensor): {_our_frame()}")
        dev = kwargs.get("device")
        dev = None if dev is None else torch.device(dev)
        to_remote = dev is not None and dev.type == OTHER.type
        if to_remote:
            kwargs["device"] = CPU
        if func is aten._to_copy.default and dev is not None:
            way = "copy to host" if remote and dev.type == "cpu" else "copy to device" if host and to_remote else None
            if way and kwargs.get("non_blocking"):
                self.counts[way + ", non_blocking"] += 1
            elif way:
                self.sync(way)
        elif func is aten.copy_.default:
            if remote and host:
                self.sync("copy to device" if type(args[0]) is Remote else "copy to host")
        elif remote and host:
            # CUDA's exception: a 0-dim CPU tensor in an elementwise operator is read as a scalar
            if not (torch.Tag.pointwise in func.tags and all(t.dim() == 0 for t in host)):
                self._mixed(func, flat)
        if remote and (func in _READS or func in _DATA_SHAPED):
            self.sync(str(func.overloadpacket.__name__))
        elif remote and func in _INDEXED and any(t.dtype == torch.bool for t in flat[1:]):
            self.sync(f"boolean {func.overloadpacket.__name__}")   # a mask index finds its rows first
        if (remote or to_remote) and _device_work(func):
            self.launches[str(func.overloadpacket.__name__)] += 1
        out = func(*_unwrap(args), **{k: _unwrap(v) for k, v in kwargs.items()})
        if func is aten.copy_.default:
            return args[0]
        wrap = to_remote if func is aten._to_copy.default and dev is not None else to_remote or bool(remote)
        return _wrap(out) if wrap else out


def _tensors(x, acc: list) -> None:
    if isinstance(x, torch.Tensor):
        acc.append(x)
    elif isinstance(x, (list, tuple)):
        for y in x:
            _tensors(y, acc)
    elif isinstance(x, dict):
        for y in x.values():
            _tensors(y, acc)


def _unwrap(x):
    if type(x) is Remote:
        return x.inner
    if isinstance(x, (list, tuple)):
        return type(x)(_unwrap(y) for y in x)
    return x


def _wrap(x):
    if isinstance(x, torch.Tensor):
        return x if type(x) is Remote else Remote(x)
    if isinstance(x, (list, tuple)):
        return type(x)(_wrap(y) for y in x)
    return x


_MODE: list[_Mode] = []
_TENSOR, _AS_TENSOR = torch.tensor, torch.as_tensor


def _tensor(data, *, dtype=None, device=None, requires_grad=False, pin_memory=False):
    """torch.tensor for the stand-in device: made on the host and copied over (as on a GPU)."""
    if device is None or torch.device(device).type != OTHER.type:
        return _TENSOR(data, dtype=dtype, device=device, requires_grad=requires_grad, pin_memory=pin_memory)
    return _TENSOR(data, dtype=dtype).to(device).requires_grad_(requires_grad)


def _as_tensor(data, dtype=None, device=None):
    if device is None or torch.device(device).type != OTHER.type or isinstance(data, torch.Tensor):
        return _AS_TENSOR(data, dtype=dtype, device=device)
    return _AS_TENSOR(data, dtype=dtype).to(device)


@contextmanager
def other_device(strict: bool = True) -> Iterator[_Mode]:
    """Inside, ``meta`` is a second device whose tensors compute on the CPU. ``strict``: an operator
    mixing devices raises ``MixedDevices`` (else it is only listed in ``mode.mixed``). The mode's
    ``counts`` (and ``where``, with our line) tally the host synchronisations."""
    mode = _Mode(strict)
    _MODE.append(mode)
    torch.tensor, torch.as_tensor = _tensor, _as_tensor
    try:
        with mode:
            yield mode
    finally:
        torch.tensor, torch.as_tensor = _TENSOR, _AS_TENSOR
        _MODE.pop()


# -- the CUDA backend on the stand-in device ----------------------------------------------------

class HostStandIn:
    """The CUDA binding for Remote tensors: ``cuda_standin.StandInExtension`` computing with the
    compiled CPU backend on the host values (outside the mode: that is the GPU's own work), its
    outputs on the stand-in device, and the binding's host synchronisations counted as it makes
    them (tests/test_raster_syncs.py checks those against the binding's source)."""

    def __init__(self, mode: _Mode) -> None:
        from cuda_standin import StandInExtension, cpp_params

        from smgs.raster.cpu import rasterize_splats_cpu

        self.base = StandInExtension(render=rasterize_splats_cpu)
        self.mode = mode
        self.backward_params = [n for _, n in cpp_params("backward_torch")]

    def _on_host(self, fn, args):
        from torch.utils._python_dispatch import _disable_current_modes

        with _disable_current_modes():
            out = fn(*[a.inner if type(a) is Remote else a for a in args])
        return [Remote(t) for t in out]

    def forward(self, *args):
        self.mode.bindings["forward"] += 1
        out = self._on_host(self.base.forward, args)
        self.mode.sync("binding forward: the pair count")
        return out

    def backward(self, *args):
        self.mode.bindings["backward"] += 1
        if dict(zip(self.backward_params, args))["use_softmax"]:
            self.mode.sync("binding backward: the most crowded pixel's count")
        return self._on_host(self.base.backward, args)


class FakeEvent:
    """A CUDA event on the stand-in device's one stream: complete once the host has waited on the
    stream after it was recorded (any counted synchronisation drains the stream)."""

    def __init__(self, mode: _Mode) -> None:
        self.mode = mode
        self.at = mode.syncs

    def query(self) -> bool:
        return self.mode.syncs > self.at

    def synchronize(self) -> None:
        if not self.query():
            self.mode.sync("event wait")


@contextmanager
def simulated_gpu(monkeypatch, strict: bool = True) -> Iterator[_Mode]:
    """``other_device`` plus what a run on it needs: ``device="meta"`` accepted where a run's device
    is resolved, generators for it (CPU ones: ``meta`` has none), torch's fused Adam allowed on it,
    and the CUDA backend available for its tensors, with ``HostStandIn`` as the compiled extension
    and ``FakeEvent`` as its events.
    So a render, a training step or a protocol cell takes the CUDA backend's Python path while the
    camera and the scene stay on the host."""
    import smgs.device
    import smgs.raster.api as api
    import smgs.raster.cuda as cuda_backend
    import smgs.raster.device_glue as glue

    real_resolve, real_available, real_gen = smgs.device.resolve_device, api.backend_available, torch.Generator

    def resolve(spec):
        return OTHER if str(spec) == str(OTHER) else real_resolve(spec)

    for mod in list(sys.modules.values()):
        if getattr(mod, "resolve_device", None) is real_resolve:
            monkeypatch.setattr(mod, "resolve_device", resolve)

    class Generator(real_gen):   # a CPU generator where the stand-in device's is asked for
        def __new__(cls, device=None):
            on_other = device is not None and torch.device(device).type == OTHER.type
            return real_gen(device=CPU if on_other else device)

    def available(name, device, dtype=torch.float32):
        if name == "cuda" and torch.device(device).type == OTHER.type:
            return dtype == torch.float32
        return real_available(name, device, dtype)

    import torch.optim.optimizer as optimizer

    fused = optimizer._get_fused_kernels_supported_devices
    monkeypatch.setattr(optimizer, "_get_fused_kernels_supported_devices", lambda: fused() + [OTHER.type])
    monkeypatch.setattr(api, "backend_available", available)
    with other_device(strict) as mode:
        ext = HostStandIn(mode)
        monkeypatch.setattr(cuda_backend, "extension", lambda t_min=None: ext)
        real_event = glue.record_event
        monkeypatch.setattr(glue, "record_event",
                            lambda device: FakeEvent(mode) if device.type == OTHER.type else real_event(device))
        monkeypatch.setattr(torch, "Generator", Generator)
        yield mode
