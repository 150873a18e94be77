"""Asking a training cell to stop at its next step boundary, with its checkpoint saved first.

A signal lands between any two bytecodes, maybe halfway through an optimiser step: a checkpoint
saved there would not be a state the run was ever in. So a signal handler only *asks*
(``StopRequests.request``); the train loop (``protocols.train_loop.train``) looks after each step,
saves the checkpoint of that step and then runs the request's action (requeue the job, stop the
cell). A SLURM job begins waiting before its cell starts up (``protocols.slurm_job``), so a request
during start-up waits for the first step. One that comes after the loop's last look is carried out
when the loop ends, its final checkpoint saved first. After the loop (the final evaluation) there is
no step to finish: the action runs at once and the next run resumes from that final checkpoint
without retraining, as after any interruption.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Callable


class Terminated(KeyboardInterrupt):
    """SIGTERM as an interruption: the running cell stops as on Ctrl-C (its last checkpoint stays, the
    next run resumes from it) and the process ends with a sentence, not a signal's default death
    (``protocols.executors.on_sigterm``; in a SLURM job at a step boundary, ``protocols.slurm_job``)."""


@dataclass
class StopRequest:
    reason: str                  # for the cell's log: "the time limit's warning (SIGUSR2)"
    action: Callable[[], None]   # run once the checkpoint is saved; it raises or exits


class StopRequests:
    """The stop requests of one cell's process (the first one wins)."""

    def __init__(self) -> None:
        self._pending: StopRequest | None = None
        self._training = False

    @property
    def training(self) -> bool:
        """Whether the train loop is running, so that a request waits for its next step boundary."""
        return self._training

    def request(self, reason: str, action: Callable[[], None]) -> None:
        """Stop at the next step boundary (``action`` after the checkpoint); outside the loop, now."""
        if not self._training:
            action()
        elif self._pending is None:
            self._pending = StopRequest(reason, action)

    def take(self) -> StopRequest | None:
        """The pending request, which the caller now carries out (called by the loop after each step)."""
        pending, self._pending = self._pending, None
        return pending

    def begin(self) -> None:
        """Requests now wait for the end of a training step (the loop starts, or the job that will run
        it). A loop that raises never calls ``end``: its cell is failing or stopping already, and a
        later request is dropped, as is one pending when a cell ends without training."""
        self._training = True

    def end(self) -> None:
        """The train loop is done; a request that came after its last look is carried out now."""
        self._training = False
        late = self.take()
        if late is not None:
            late.action()
