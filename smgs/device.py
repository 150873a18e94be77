"""Where a run computes: the ``device`` setting (``auto`` | ``cpu`` | ``cuda`` | ``cuda:N``), checked
once at the edge (``resolve_device``; ``as_device`` where a function takes either) and then passed as
a ``torch.device`` to everything that creates a tensor.

``auto`` is the first CUDA device when torch sees one, else the CPU. Asking for CUDA where there is
none is an error, never a silent CPU run; so is a renderer backend that cannot render on the
device (``backend=cuda`` with ``device=cpu`` and the reverse: ``smgs.raster.backends.check_backend``).
"""

from __future__ import annotations

import re

import torch

from smgs.env import cpu_model

DEVICE_CHOICES = "auto, cpu, cuda or cuda:N"
_CUDA_RE = re.compile(r"^cuda(?::(\d+))?$")


class DeviceError(ValueError):
    """A device setting that cannot be honoured here; the message names the problem and the fix."""


def _no_cuda_reason() -> str:
    if torch.version.cuda is None:
        return f"this torch ({torch.__version__}) is a CPU-only build"
    return "torch sees no CUDA device (torch.cuda.is_available() is False: no GPU visible, or no driver)"


def parse_device(spec: str | torch.device | None) -> torch.device | None:
    """Check a setting's spelling without looking at the hardware: None for ``auto``, else the
    device it names (``cuda`` without an index stays index-less). For planning runs that execute
    on other machines (a cluster's GPU nodes)."""
    text = "auto" if spec is None else str(spec).strip().lower()
    if text == "auto":
        return None
    if text == "cpu":
        return torch.device("cpu")
    m = _CUDA_RE.match(text)
    if m is None:
        hint = " (a GPU is 'cuda' or 'cuda:N')" if text.startswith(("gpu", "nvidia")) else ""
        raise DeviceError(f"unknown device {spec!r}{hint}; use {DEVICE_CHOICES}")
    return torch.device("cuda", None if m.group(1) is None else int(m.group(1)))


def resolve_device(spec: str | torch.device | None) -> torch.device:
    """The ``torch.device`` a setting names; ``auto`` (or None) picks CUDA where torch sees it. A
    bare ``cuda`` becomes ``cuda:<current device>``, so results and checkpoints name one device."""
    dev = parse_device(spec)
    if dev is None:
        return torch.device("cuda", torch.cuda.current_device()) if torch.cuda.is_available() \
            else torch.device("cpu")
    if dev.type == "cpu":
        return dev
    if not torch.cuda.is_available():
        raise DeviceError(f"device={spec} asks for CUDA, but {_no_cuda_reason()}; install a CUDA build "
                          "of torch on a machine with a GPU, or use device=cpu (or device=auto)")
    n = torch.cuda.device_count()
    index = torch.cuda.current_device() if dev.index is None else dev.index
    if index >= n:
        raise DeviceError(f"device={spec}, but torch sees {n} CUDA device(s) (cuda:0..cuda:{n - 1}); "
                          f"use one of those or device=cuda (check CUDA_VISIBLE_DEVICES)")
    return torch.device("cuda", index)


def as_device(device: torch.device | str | None) -> torch.device:
    """The ``torch.device`` to compute on, resolved once, where a setting enters: a device as
    ``resolve_device`` returns one (the CPU, or CUDA with an index) is used as it is; a setting (a
    string, None for ``auto``, an index-less ``cuda``) is resolved here."""
    if isinstance(device, torch.device) and (device.type == "cpu"
                                             or (device.type == "cuda" and device.index is not None)):
        return device
    return resolve_device(device)


def device_name(device: torch.device | str) -> str:
    """The device and its model, as results and reports print it: ``cuda:0 NVIDIA H200``, or
    ``cpu <CPU model> (<torch threads> threads)``."""
    device = torch.device(device)
    if device.type == "cuda":
        index = torch.cuda.current_device() if device.index is None else device.index
        return f"cuda:{index} {torch.cuda.get_device_name(index)}"
    return f"cpu {cpu_model()} ({torch.get_num_threads()} threads)"


def generator_state(gen: torch.Generator) -> dict:
    """A generator's state for a checkpoint, tagged with its kind of device (a CPU and a CUDA
    generator's states are different formats)."""
    return {"device_type": gen.device.type, "state": gen.get_state()}


def restore_generator(gen: torch.Generator, saved: dict | torch.Tensor, seed: int) -> bool:
    """Put a saved state into ``gen``. From a generator of the same kind of device the stream
    continues exactly (True). From another kind (trained on a GPU, resumed on the CPU, or back)
    the state cannot be carried over: ``gen`` is re-seeded from ``seed`` and the saved state's
    bytes, deterministically, and False says the resumed run draws other numbers than an
    uninterrupted one would."""
    if isinstance(saved, torch.Tensor):          # checkpoints before the tag: a CPU generator
        saved = {"device_type": "cpu", "state": saved}
    # Generator states are CPU byte tensors whatever the generator's device (torch's API), even
    # when the checkpoint was mapped onto a GPU.
    state = saved["state"].to(device=torch.device("cpu"), dtype=torch.uint8)
    if saved["device_type"] == gen.device.type:
        gen.set_state(state)
        return True
    import hashlib

    digest = hashlib.sha256(int(seed).to_bytes(8, "little", signed=True) + bytes(state.tolist())).digest()
    gen.manual_seed(int.from_bytes(digest[:8], "little") & ((1 << 63) - 1))
    return False
