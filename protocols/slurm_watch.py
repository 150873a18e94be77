"""Waiting for the cells' SLURM jobs without ever hanging on one that can no longer answer.

A cell ends when its job's result file is there, or, when its job ended without one (killed,
cancelled, out of memory, its node gone, a time limit with no requeue left), as a failure with
SLURM's reason within a bounded time: ``RESULT_GRACE_S`` after the controller (squeue, one call for
every job of the sweep) says it ended or no longer knows it. The reason comes from sacct where the
cluster keeps accounting, else from ``scontrol show job``, else from the job's own files. A cluster
without accounting storage is said once, not at every poll (submitit's own watcher, built on sacct,
is never asked).
"""

from __future__ import annotations

import subprocess
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Callable

POLL_S = 5.0            # how often the controller is asked (the result files are looked at every second)
RESULT_GRACE_S = 15.0   # an ended job's result may take this long to show on a shared file system
UNREACHABLE_S = 600.0   # a controller silent this long: the cells still waiting are given up
# job states after which a job runs no more (a requeued job passes through PENDING, not these)
ENDED = frozenset({"COMPLETED", "CANCELLED", "FAILED", "TIMEOUT", "NODE_FAIL", "PREEMPTED", "BOOT_FAIL",
                   "DEADLINE", "OUT_OF_MEMORY", "REVOKED"})
# states of a job on its way, and pending reasons that are the queue's ordinary business: not worth a line
UNDER_WAY = frozenset({"RUNNING", "COMPLETING", "CONFIGURING", "REQUEUED", "REQUEUE_FED", "RESIZING", "SIGNALING",
                       "STAGE_OUT"})
ORDINARY = frozenset({"None", "Priority", "Resources", "BeginTime", "JobArrayTaskLimit", "Dependency", ""})
HINTS = {
    "CANCELLED": "cancelled (scancel, or an administrator)",
    "OUT_OF_MEMORY": "out of memory: raise executor.slurm.mem_gb",
    "TIMEOUT": "killed at its time limit before it could requeue itself (executor.slurm.timeout_min, signal_lead_s)",
    "NODE_FAIL": "its node failed and the job was not requeued",
    "PREEMPTED": "preempted and not requeued",
    "BOOT_FAIL": "its node failed to boot",
    "DEADLINE": "past its deadline",
}


@dataclass
class JobState:
    state: str
    reason: str = ""


@dataclass
class Waiting:
    """A submitted cell: its index in the grid, its key and its submitit job."""

    index: int
    key: str
    job: Any
    ended_since: float | None = None

    @property
    def job_id(self) -> str:
        return str(self.job.job_id)


def _run(cmd: list[str]) -> subprocess.CompletedProcess | None:
    try:
        return subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None


class SlurmQueries:
    """What SLURM says about the sweep's jobs. ``note`` prints a line of the sweep's log."""

    def __init__(self, note: Callable[[str], None]) -> None:
        self.note = note
        self.accounting: bool | None = None   # unknown until first asked

    def states(self, job_ids: list[str]) -> dict[str, JobState] | None:
        """Each job the controller still knows (array tasks one by one), or None when it does not answer."""
        out = _run(["squeue", "--noheader", "--array", "--states=all", "--format=%i|%T|%r",
                    f"--jobs={','.join(sorted({j.split('_')[0] for j in job_ids}))}"])
        if out is None:
            return None
        if out.returncode != 0:   # every job forgotten, or the controller is down
            return {} if "invalid job id" in out.stderr.lower() else None
        states = {}
        for line in out.stdout.splitlines():
            parts = line.strip().split("|")
            if len(parts) == 3:
                states[parts[0]] = JobState(parts[1], parts[2])
        return states

    def has_accounting(self, job_id: str) -> bool:
        """Whether sacct answers (asked once; a cluster without accounting storage is said once)."""
        if self.accounting is None:
            out = _run(["sacct", "--noheader", "--allocations", f"--jobs={job_id}", "--format=State"])
            self.accounting = out is not None and out.returncode == 0
            if not self.accounting:
                said = (out.stderr.strip().splitlines() or ["no answer"])[-1] if out is not None else "not found"
                self.note(f"slurm: no job accounting here (sacct: {said}); job states come from the controller "
                          "(squeue, scontrol show job) and the jobs' own files")
        return self.accounting

    def why(self, job_id: str, seen: JobState | None) -> str:
        """How the job ended: sacct's state and exit code, else the controller's, else what was last seen."""
        if self.has_accounting(job_id):
            out = _run(["sacct", "--noheader", "--allocations", "--parsable2", f"--jobs={job_id}",
                        "--format=JobID,State,ExitCode"])
            for line in (out.stdout.splitlines() if out is not None and out.returncode == 0 else []):
                jid, state, code = (line.split("|") + ["", "", ""])[:3]
                if jid == job_id:
                    return _worded(state.split()[0] if state else "?", f"sacct: {state}, exit code {code}")
        out = _run(["scontrol", "--oneliner", "show", "job", job_id])
        if out is not None and out.returncode == 0:
            fields = dict(f.split("=", 1) for f in out.stdout.split() if "=" in f)
            state = fields.get("JobState", "?")
            return _worded(state, f"scontrol: JobState={state} Reason={fields.get('Reason', '?')} "
                                  f"ExitCode={fields.get('ExitCode', '?')}")
        if seen is not None:
            return _worded(seen.state, f"last seen {seen.state}; SLURM no longer knows the job")
        return "SLURM no longer knows the job"


def _worded(state: str, detail: str) -> str:
    if state == "FAILED" and ("137" in detail or ":9" in detail):
        hint = "its task was killed (SIGKILL: by hand, or by the node's out-of-memory killer: executor.slurm.mem_gb)"
    else:
        hint = HINTS.get(state, "")
    return f"{state}" + (f", {hint}" if hint else "") + f" ({detail})"


def last_words(job: Any) -> str:
    """The job's own files: where they are and the last line SLURM or the task wrote there."""
    paths = [Path(job.paths.stderr), Path(job.paths.stdout)]
    for path in paths:
        try:
            lines = [ln.strip() for ln in path.read_text(errors="replace").splitlines() if ln.strip()]
        except OSError:
            continue
        # SLURM's word on the job ("*** JOB 12 ON node CANCELLED AT ... ***"), else srun's, else the last line
        said = ([ln for ln in lines if "***" in ln] or [ln for ln in lines if ln.startswith(("slurmstepd", "srun:"))]
                or lines)
        if said:
            return f"{path}: {said[-1][:300]}"
    return f"no output in {paths[0].parent}"


def wait(waiting: list[Waiting], queries: SlurmQueries, collect: Callable[[Waiting], dict],
         ended: Callable[[Waiting, str], dict], done: Callable[[int, dict], None]) -> None:
    """Until every cell of ``waiting`` is done (``done(index, summary)``): ``collect`` reads a job's
    result, ``ended(cell, what)`` makes the failure of one that ended without a result (``what``:
    "ended without a result: <SLURM's reason>")."""
    left = {w.index: w for w in waiting}
    last_poll, silent_since, said = 0.0, None, set()
    while left:
        for w in list(left.values()):
            if Path(w.job.paths.result_pickle).exists():
                done(w.index, collect(w))
                del left[w.index]
        now = time.monotonic()
        if left and now - last_poll >= POLL_S:
            last_poll = now
            states = queries.states([w.job_id for w in left.values()])
            if states is None:
                silent_since = silent_since or now
                if now - silent_since >= UNREACHABLE_S:
                    for w in list(left.values()):
                        done(w.index, ended(w, f"was given up: the SLURM controller has not answered squeue for "
                                               f"{UNREACHABLE_S / 60:.0f} min (the job may still finish: rerun the "
                                               "same command later to collect it)"))
                    return
            else:
                silent_since = None
                for w in list(left.values()):
                    _follow(w, states.get(w.job_id), now, queries, ended, done, left, said)
        if left:
            time.sleep(1.0)


def _follow(w: Waiting, st: JobState | None, now: float, queries: SlurmQueries, ended, done, left: dict,
            said: set) -> None:
    """One job's state: an ended or forgotten job waits ``RESULT_GRACE_S`` for its result, then fails."""
    if st is not None and st.state not in ENDED:
        w.ended_since = None
        why = f"{st.state.lower()}: {st.reason}"
        if st.state not in UNDER_WAY and not (st.state == "PENDING" and st.reason in ORDINARY) and why not in said:
            said.add(why)   # held, suspended, waiting for a node that is down: said once
            queries.note(f"slurm: job {w.job_id} ({w.key}) is {why} (the sweep waits for it; scancel {w.job_id} "
                         "gives it up)")
        return
    w.ended_since = w.ended_since or now
    if now - w.ended_since >= RESULT_GRACE_S and not Path(w.job.paths.result_pickle).exists():
        done(w.index, ended(w, f"ended without a result: {queries.why(w.job_id, st)}"))
        del left[w.index]
