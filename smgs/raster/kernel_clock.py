"""Wall time spent inside the compiled CPU kernels (projection and colours, compositing, the training
loss), for a profile of a training step (``Trainer.profile``, bench/train_step.py): what a step
spends outside them is its total minus these.

Off unless a ``KernelClock`` is running (``with clock.running():``): each kernel call then reads one
context variable and does nothing else. The clock is the caller's object, entered for a block of
work like ``torch.no_grad``; it holds no state between blocks. The backward kernels are timed too:
on the CPU autograd runs them in the thread that called ``backward``, inside the block.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from contextvars import ContextVar
from typing import Iterator

_RUNNING: ContextVar["KernelClock | None"] = ContextVar("smgs_kernel_clock", default=None)


class KernelClock:
    """Seconds per kernel name, added while ``running``."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = {}

    @contextmanager
    def running(self) -> Iterator["KernelClock"]:
        token = _RUNNING.set(self)
        try:
            yield self
        finally:
            _RUNNING.reset(token)


@contextmanager
def kernel(name: str) -> Iterator[None]:
    """Time the block as kernel ``name`` where a clock is running."""
    clock = _RUNNING.get()
    if clock is None:
        yield
        return
    t0 = time.perf_counter()
    try:
        yield
    finally:
        clock.seconds[name] = clock.seconds.get(name, 0.0) + time.perf_counter() - t0
