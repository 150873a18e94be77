"""A registered method ``counting`` for the runner's rerun tests: GaussianSplatting that records the
steps it trains and stops with KeyboardInterrupt (or fails) once at a chosen step.

Use the ``counting`` fixture (import it into the test module); it registers the method, resets the
class's state and unregisters it after the test."""

from __future__ import annotations

import pytest

from baselines.method import MethodSpec
from baselines.registry import register, unregister
from baselines.splatting import GaussianSplatting


class Counting(GaussianSplatting):
    """Records the steps it trains; raises KeyboardInterrupt once at ``interrupt_at``, RuntimeError
    at ``fail_at``."""

    calls: list = []
    interrupt_at: int | None = None
    fail_at: int | None = None

    def train_step(self, step):
        Counting.calls.append(step)
        if step == Counting.interrupt_at:
            Counting.interrupt_at = None
            raise KeyboardInterrupt
        if step == Counting.fail_at:
            raise RuntimeError("diverged on purpose")
        return super().train_step(step)


@pytest.fixture
def counting():
    register(MethodSpec("counting", Counting, {"mode": "3dgs"}))
    Counting.calls.clear()
    Counting.interrupt_at = Counting.fail_at = None
    yield Counting
    unregister("counting")
