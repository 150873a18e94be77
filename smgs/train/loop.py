"""A minimal training loop for tests and scripts. The protocol runner owns the real one
(evaluation schedule, checkpoints, results.json)."""

from __future__ import annotations

from typing import Callable, Iterable

Callback = Callable[[int, dict], object]


def train(method, steps: int, callbacks: Iterable[Callback] = (), start: int = 0) -> list[dict]:
    """Run ``method.train_step`` for steps ``start .. steps-1``; each callback gets
    (steps done, logs) after every step and may return False to stop. Returns the logs."""
    logs = []
    callbacks = list(callbacks)
    for step in range(start, steps):
        out = method.train_step(step)
        logs.append(out)
        if any(cb(step + 1, out) is False for cb in callbacks):
            break
    return logs
