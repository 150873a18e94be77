"""A SLURM job's SIGTERM (scancel, a preemption) asks its cell to stop at the next step boundary
(protocols.cell_stop); carried out, it ends the job with status 128 + SIGTERM, as a local worker's
SIGTERM does (protocols.cell_stop.Terminated). Run in this process: no cluster needed."""

import os
import signal

import pytest
import torch

from protocols.slurm_job import CellJob, JobLimits


def _signalled_then_at_a_step_boundary(payload, stops):
    os.kill(os.getpid(), signal.SIGTERM)   # lands mid-step: only asks
    pending = stops.take()                 # the train loop's look after the step
    assert pending is not None and pending.reason == "SIGTERM"
    pending.action()
    return {"key": payload["key"], "status": "ok"}


def test_sigterm_stops_the_cell_at_a_step_boundary_and_ends_the_job_with_143():
    handlers = {s: signal.getsignal(s) for s in (signal.SIGTERM, signal.SIGUSR2)}
    threads = torch.get_num_threads()
    try:
        with pytest.raises(SystemExit) as e:
            CellJob(_signalled_then_at_a_step_boundary, {"key": "a/cell"}, JobLimits(5, 1))()
    finally:
        for s, h in handlers.items():
            signal.signal(s, h)
        torch.set_num_threads(threads)
    assert e.value.code == 128 + signal.SIGTERM
