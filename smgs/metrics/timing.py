"""Render FPS, peak memory and train-time accounting, each naming the device and the method.

FPS follows nerfbaselines/3DGS practice: warm-up renders first, the device synchronised around
``perf_counter``, the median over repeats of the per-view time on the test cameras.
Peak memory on CUDA is ``torch.cuda.max_memory_allocated`` after a reset (tensor memory only).
On CPU it is the process's peak resident set size (Linux ``VmHWM``) over the block, reset first
through ``/proc/self/clear_refs``; where that reset is impossible it is the lifetime peak
(``getrusage`` ``ru_maxrss``), and ``kind`` says so. CPU numbers include the interpreter and
every library loaded, so compare them only between runs of the same process layout.

Before the reset, glibc's ``malloc_trim(0)`` hands back the memory the allocator kept from earlier
work (freed, still resident): without it a block's allocations can be served from those resident
pages, its peak is then just the resident size at entry, and a run measured after other work in the
same process (a sequential sweep, a test suite) sees nothing of its own allocations. ``baseline_bytes``
is the resident size at entry after the trim, so ``bytes - baseline_bytes`` is the block's increment.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import resource
import statistics
import sys
import time
from contextlib import AbstractContextManager, contextmanager
from dataclasses import asdict, dataclass, field
from typing import Any, Callable, Iterator, Sequence

import torch

from smgs.device import device_name  # noqa: F401  (re-exported: reports and bench import it here)


def synchronize(device: torch.device) -> None:
    """Wait for the work queued on ``device`` (a GPU runs asynchronously; the CPU needs nothing)."""
    if device.type == "cuda":
        torch.cuda.synchronize(device)


@dataclass
class FPSResult:
    fps: float
    median_seconds_per_view: float
    seconds_per_view: list[float]  # one entry per repeat (mean over the views of that repeat)
    n_views: int
    warmup: int
    repeats: int
    device: str

    def to_json(self) -> dict:
        return asdict(self)


def measure_render_fps(render: Callable[[Any], Any], cameras: Sequence[Any], *, device: torch.device | str,
                       warmup: int = 3, repeats: int = 5) -> FPSResult:
    """Frames per second of ``render(camera)`` over ``cameras``.

    ``warmup`` renders (cycling through the cameras) are discarded; then each repeat renders every
    camera once; FPS = 1 / median over repeats of (repeat time / number of views).
    """
    if not cameras:
        raise ValueError("measure_render_fps needs at least one camera")
    if repeats < 1 or warmup < 0:
        raise ValueError(f"repeats must be >= 1 and warmup >= 0, got {repeats}, {warmup}")
    dev = torch.device(device)
    with torch.no_grad():
        for i in range(warmup):
            render(cameras[i % len(cameras)])
        synchronize(dev)
        per_view = []
        for _ in range(repeats):
            t0 = time.perf_counter()
            for cam in cameras:
                render(cam)
            synchronize(dev)
            per_view.append((time.perf_counter() - t0) / len(cameras))
    med = statistics.median(per_view)
    return FPSResult(fps=(1.0 / med) if med > 0 else float("inf"), median_seconds_per_view=med,
                     seconds_per_view=per_view, n_views=len(cameras), warmup=warmup, repeats=repeats,
                     device=device_name(dev))


@dataclass
class PeakMemory:
    """Result of ``track_peak_memory``: ``bytes`` is filled when the block exits."""

    device: str
    kind: str
    bytes: int = 0
    baseline_bytes: int = 0  # resident at entry (CPU, after the trim); 0 where unknown

    @property
    def increment_mib(self) -> float:
        return max(0, self.bytes - self.baseline_bytes) / 2**20

    @property
    def mib(self) -> float:
        return self.bytes / 2**20

    def to_json(self) -> dict:
        return {"device": self.device, "kind": self.kind, "bytes": self.bytes,
                "baseline_bytes": self.baseline_bytes}


def _status_bytes(field_name: str) -> int | None:
    try:
        with open("/proc/self/status") as f:
            for line in f:
                if line.startswith(field_name + ":"):
                    return int(line.split()[1]) * 1024
    except OSError:
        return None
    return None


def _vm_hwm_bytes() -> int | None:
    return _status_bytes("VmHWM")


def release_retained_heap() -> bool:
    """glibc's ``malloc_trim(0)``: return the free memory the allocator keeps resident to the OS.
    False where the C library has no such call (musl, macOS)."""
    name = ctypes.util.find_library("c")
    try:
        trim = ctypes.CDLL(name).malloc_trim if name else None
    except (OSError, AttributeError):
        trim = None
    if trim is None:
        return False
    trim(ctypes.c_size_t(0))
    return True


def _reset_vm_hwm() -> bool:
    try:
        with open("/proc/self/clear_refs", "w") as f:
            f.write("5")  # 5 = reset the peak RSS (Linux >= 4.0)
    except OSError:
        return False
    return True


def _ru_maxrss_bytes() -> int:
    rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
    return rss if sys.platform == "darwin" else rss * 1024  # bytes on macOS, KiB on Linux


@contextmanager
def track_peak_memory(device: torch.device | str) -> Iterator[PeakMemory]:
    """``with track_peak_memory(dev) as pm: ...``; afterwards ``pm.bytes`` and ``pm.kind``."""
    dev = torch.device(device)
    if dev.type == "cuda":
        synchronize(dev)
        torch.cuda.reset_peak_memory_stats(dev)
        pm = PeakMemory(device_name(dev), "cuda_max_memory_allocated")
        try:
            yield pm
        finally:
            synchronize(dev)
            pm.bytes = int(torch.cuda.max_memory_allocated(dev))
        return
    release_retained_heap()
    if _reset_vm_hwm() and _vm_hwm_bytes() is not None:
        pm = PeakMemory(device_name(dev), "cpu_peak_rss_vmhwm_reset", baseline_bytes=_status_bytes("VmRSS") or 0)
        try:
            yield pm
        finally:
            pm.bytes = int(_vm_hwm_bytes() or 0)
        return
    pm = PeakMemory(device_name(dev), "cpu_peak_rss_process_lifetime")
    try:
        yield pm
    finally:
        pm.bytes = _ru_maxrss_bytes()


@dataclass
class TrainClock:
    """Wall-clock seconds of training only: time inside ``training()`` blocks counts, everything
    else (evaluation, checkpoints, logging outside the blocks) does not. Synchronises CUDA at each
    boundary so queued GPU work is charged to the block that launched it."""

    device: str | torch.device
    seconds: float = 0.0
    excluded: dict[str, float] = field(default_factory=dict)

    @contextmanager
    def _timed(self, sink: Callable[[float], None]) -> Iterator[None]:
        dev = torch.device(self.device)
        synchronize(dev)
        t0 = time.perf_counter()
        try:
            yield
        finally:
            synchronize(dev)
            sink(time.perf_counter() - t0)

    def training(self) -> AbstractContextManager[None]:
        """Time a block of training; it adds to ``seconds``."""
        def add(dt: float) -> None:
            self.seconds += dt
        return self._timed(add)

    def exclude(self, what: str) -> AbstractContextManager[None]:
        """Time a non-training phase (e.g. "eval") for the log; it never adds to ``seconds``."""
        def add(dt: float) -> None:
            self.excluded[what] = self.excluded.get(what, 0.0) + dt
        return self._timed(add)

    def to_json(self) -> dict:
        return {"train_seconds": self.seconds, "excluded_seconds": dict(self.excluded),
                "device": device_name(self.device)}


