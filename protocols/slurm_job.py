"""A grid cell as a SLURM job: the callable that submitit runs on the node.

It is submitit-Checkpointable. At the time limit's warning (SIGUSR2, ``executor.slurm.signal_lead_s``
before the limit) the cell stops after its current step with that step's checkpoint saved, and
submitit requeues the job, which resumes from it; once the requeues at the limit
(``executor.slurm.max_requeues``) are used up, the cell fails saying so. SIGTERM (scancel, a
preemption, ``scontrol requeue``) stops it the same way without requeueing it: SLURM decides
whether the job runs again, and a job that runs again resumes from that checkpoint. The cell's
threads follow the job's CPUs (``protocols.job_cpus``).

The cell's function and payload travel as bytes, unpickled once the handlers are in place:
unpickling them imports torch (seconds), and a warning that landed before would kill the job.
"""

from __future__ import annotations

import inspect
import os
import pickle
import signal
import sys
from dataclasses import dataclass
from typing import Any, Callable

import submitit

from protocols.cell_stop import StopRequests, Terminated
from protocols.job_cpus import job_cpus


@dataclass(frozen=True)
class JobLimits:
    timeout_min: int
    max_requeues: int

    def used_up(self) -> str:
        restarts = os.environ.get("SLURM_RESTART_COUNT", "0")
        return (f"reached the time limit of its job again with no requeue left (executor.slurm.timeout_min="
                f"{self.timeout_min}, executor.slurm.max_requeues={self.max_requeues}; the job ran {int(restarts) + 1} "
                "time(s), preemptions included); its checkpoint stays: raise executor.slurm.timeout_min or "
                "executor.slurm.max_requeues and rerun the same command to resume it")


class TimeLimitReached(RuntimeError):
    """The cell's job reached its time limit with no requeue left."""


class CellJob(submitit.helpers.Checkpointable):
    """``fn(payload)`` (``protocols.cell.run_cell``) in a SLURM job; ``checkpoint`` (submitit's)
    resubmits it unchanged: the cell's own checkpoint, in its run directory, holds its progress."""

    def __init__(self, fn: Callable[..., dict], payload: dict, limits: JobLimits) -> None:
        self.fn = pickle.dumps(fn)
        self.payload = pickle.dumps(payload)
        self.limits = limits

    def __call__(self) -> dict:
        stops = StopRequests()
        self._handle_signals(stops)
        stops.begin()   # a signal while the cell starts up (torch, the scene) waits for its first step too
        cpus = job_cpus()
        import torch   # after the handlers: torch takes seconds to load

        torch.set_num_threads(cpus.count)
        fn, payload = pickle.loads(self.fn), pickle.loads(self.payload)
        try:
            if "stops" in inspect.signature(fn).parameters:
                return fn(payload, stops=stops)
            return fn(payload)
        except Terminated:   # its step's checkpoint is saved; SLURM decides whether the job runs again
            print(f"smgs: {payload.get('key')} stopped by SIGTERM", file=sys.stderr, flush=True)
            raise SystemExit(128 + signal.SIGTERM) from None

    def _handle_signals(self, stops: StopRequests) -> None:
        """Over submitit's handlers (in place when the job calls this): the warning and SIGTERM wait for
        the end of the current training step, or of the first one while the cell starts up
        (``protocols.cell_stop``), then act; after training, the warning requeues at once (the next run
        resumes from the last checkpoint) and SIGTERM is left to submitit."""
        warned, term = signal.getsignal(signal.SIGUSR2), signal.getsignal(signal.SIGTERM)

        def on_warning(signum: int, frame: Any) -> None:
            stops.request("the time limit's warning (SIGUSR2)", lambda: self._requeue(warned, signum))

        def on_term(signum: int, frame: Any) -> None:
            if stops.training:
                stops.request("SIGTERM", _terminate)
            elif callable(term):   # evaluating: submitit's (logged; the job ends by SLURM's SIGKILL or itself)
                term(signum, frame)

        signal.signal(signal.SIGUSR2, on_warning)
        signal.signal(signal.SIGTERM, on_term)

    def _requeue(self, submitit_handler: Any, signum: int) -> None:
        """submitit's time-limit handling: ``checkpoint``, then requeue and exit, or, with no requeue
        left, the cell's failure saying so."""
        try:
            if callable(submitit_handler):
                submitit_handler(signum, None)
        except submitit.core.utils.UncompletedJobError:
            raise TimeLimitReached(self.limits.used_up()) from None


def _terminate() -> None:
    raise Terminated()   # as a local worker's SIGTERM: the cell stops as on Ctrl-C (protocols.cell.run_cell)
