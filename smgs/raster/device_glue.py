"""How the renderer's Python side drives a GPU without making the host wait for it.

Every host synchronisation drains the GPU's queue: with a dozen per render the host and the GPU
take turns, and a small scene costs the sum of both (docs/gpu/README.md has the counts). Here:

* ``to_device``: a small host tensor (the packed camera) copied from pinned memory without waiting;
* ``record_event``: a marker on the current stream whose completion the host can test without
  waiting; a non-blocking copy to the host followed by an event is read for free once anything
  else (the binding's one pair-count read) has waited on the stream past it;
* the lean glue, the cuda backend's opt-in glue variant (``smgs.raster.backends``:
  ``renderer.glue=lean`` in a run's config, ``Renderer("cuda", glue="lean")`` or
  ``SMGS_CUDA_GLUE=lean``), keeps the input checks on the device (read after the render with the
  binding's own wait) and projects without compaction (culled splats keep their rows with radius 0
  and opacity 0, so nothing waits for a count of survivors). It stays opt-in until a GPU run has
  verified it (``python -m bench.gpu_check``, docs/gpu/README.md); the default ("verified") is the
  path verified there.
"""

from __future__ import annotations

from typing import Protocol

import torch


class Event(Protocol):
    def query(self) -> bool: ...

    def synchronize(self) -> None: ...


def to_device(t: torch.Tensor, device: torch.device) -> torch.Tensor:
    """A small host tensor on ``device`` without making the host wait: on CUDA from pinned memory
    with a non-blocking copy (a copy from pageable memory synchronises the stream; torch's pinned
    memory cache keeps the buffer until the copy has run)."""
    if device.type == "cpu":
        return t
    if device.type == "cuda":
        t = t.pin_memory()
    return t.to(device, non_blocking=True)


def to_host_async(t: torch.Tensor) -> tuple[torch.Tensor, Event | None]:
    """A non-blocking copy of a device tensor to the host, and the event after it (None where the
    copy is already complete: a CPU tensor, or a device without events, where it waited)."""
    if t.device.type == "cpu":
        return t, None
    host = t.to("cpu", non_blocking=True)   # pinned by torch for a CUDA source
    return host, record_event(t.device)


def record_event(device: torch.device) -> Event | None:
    """An event recorded on ``device``'s current stream (CUDA), else None."""
    if device.type != "cuda":
        return None
    ev = torch.cuda.Event()
    ev.record(torch.cuda.current_stream(device))
    return ev
