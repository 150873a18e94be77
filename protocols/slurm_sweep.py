"""A grid's cells as SLURM jobs (``executor.kind=slurm``): one job array per GPU count the cells ask
for (``protocols.slurm_settings``), each cell a checkpointable job (``protocols.slurm_job``), waited
for without ever hanging on a dead one (``protocols.slurm_watch``). What sbatch refuses stops the
sweep in one block naming the key and the fix, before any cell runs or is marked failed; a Ctrl-C
or SIGTERM of the sweep cancels its jobs (each stops after its current step, its checkpoint saved).
"""

from __future__ import annotations

import contextlib
import io
import re
import shutil
import subprocess
from pathlib import Path
from typing import Any, Callable

from protocols.refused import Refused
from protocols.slurm_settings import SlurmSettings, partition_gpus, refusal
from protocols.slurm_watch import SlurmQueries, Waiting, last_words, wait

Payload = dict[str, Any]
Summary = dict[str, Any]
CELLS_FILE = "cells.tsv"   # in the submitit folder: each job's id and its cell's key


def note(line: str) -> None:
    print(line, flush=True)


def run_on_slurm(fn: Callable[[Payload], Summary], payloads: list[Payload], section: dict, folder: str,
                 done: Callable[[int, Summary], None], died: Callable[[Payload, str], Summary]) -> None:
    """Run ``fn`` on every payload as SLURM jobs; ``done(index, summary)`` as each cell ends
    (``died(payload, why)`` makes the summary of one whose job ended without a result)."""
    if not payloads:
        return
    s = checked_settings(section)
    if s.lead_s() < s.signal_lead_s:
        note(f"slurm: executor.slurm.signal_lead_s={s.signal_lead_s} does not fit a {s.timeout_min}-min limit: jobs "
             f"are warned {s.lead_s()} s before it")
    waiting: list[Waiting] = []
    finished: set[int] = set()

    def finish(i: int, summary: Summary) -> None:
        finished.add(i)
        done(i, summary)

    def ended(w: Waiting, what: str) -> Summary:
        return died(payloads[w.index], f"slurm job {w.job_id} {what}; its output: {last_words(w.job)}")

    def collect(w: Waiting) -> Summary:
        try:
            return w.job.result()
        except Exception as e:   # the job's Python failed outside the cell: the last line of its trace
            return died(payloads[w.index], f"slurm job {w.job_id} failed: {_raised(str(e))}")

    queries = SlurmQueries(note)
    try:
        _submit(fn, payloads, s, folder, waiting)
        queries.has_accounting(waiting[0].job_id)   # a cluster without accounting is said now, once
        wait(waiting, queries, collect, ended, finish)
    except BaseException:   # Ctrl-C, SIGTERM, a refusal: the jobs stop too (each saves its step's checkpoint)
        _cancel([w.job_id for w in waiting if w.index not in finished])
        raise


def checked_settings(section: dict) -> SlurmSettings:
    """The settings of ``executor.slurm`` on a machine that has SLURM's commands, else ``Refused``
    naming the key or the commands and the fix (``protocols.run.prepare`` asks before anything is
    written)."""
    try:
        s = SlurmSettings.of(section)
    except ValueError as e:
        raise Refused(f"invalid config, nothing was run: {e}") from None
    missing = [c for c in ("sbatch", "srun", "squeue", "scontrol") if shutil.which(c) is None]
    if missing:
        raise Refused(f"executor.kind=slurm: {', '.join(missing)} not found on this machine; run the sweep where "
                      "SLURM's commands are (a login node of the cluster), or use executor.kind=local")
    return s


def _submit(fn, payloads: list[Payload], s: SlurmSettings, folder: str, waiting: list[Waiting]) -> None:
    """Every cell submitted, in one array per GPU count (into ``waiting``); a refusal stops the sweep
    naming the key (the caller cancels what was submitted)."""
    import submitit

    from protocols.slurm_job import CellJob, JobLimits

    limits = JobLimits(s.timeout_min, s.max_requeues)
    has_gpus = partition_gpus(s.partition) if s.gpus_per_node == "auto" and any(
        str(p["config"].get("device", "auto")) == "auto" for p in payloads) else None
    groups: dict[int, list[int]] = {}
    for i, p in enumerate(payloads):
        groups.setdefault(s.gpus_for(p["config"].get("device"), has_gpus), []).append(i)
    name = f"smgs-{payloads[0]['config'].get('experiment_name', 'grid')}"
    for gpus, idx in sorted(groups.items()):
        ex = submitit.SlurmExecutor(folder=folder, max_num_timeout=s.max_requeues)
        ex.update_parameters(**s.parameters(gpus, name))
        try:
            with contextlib.redirect_stderr(io.StringIO()):   # submitit prints sbatch's refusal; e holds it
                jobs = ex.submit_array([CellJob(fn, payloads[i], limits) for i in idx])
        except submitit.core.utils.FailedJobError as e:
            devices = sorted({str(payloads[i]["config"].get("device", "auto")) for i in idx})
            raise Refused(f"invalid config, nothing was run: {refusal(str(e), s, gpus, devices)}") from None
        waiting += [Waiting(i, payloads[i]["key"], j) for i, j in zip(idx, jobs)]
        array = str(jobs[0].job_id).split("_")[0]
        where = f"partition {s.partition}" if s.partition else "the default partition"
        auto = " (device=auto: the partition has GPUs)" if gpus and has_gpus else ""
        note(f"slurm: {len(idx)} cell(s) as job {'array ' if len(idx) > 1 else ''}{array} on {where}, each "
             f"{s.describe(gpus)}{auto}; which job runs which cell: {Path(folder) / CELLS_FILE}")
        with open(Path(folder) / CELLS_FILE, "a", encoding="utf-8") as f:
            f.writelines(f"{job.job_id}\t{payloads[i]['key']}\n" for i, job in zip(idx, jobs))


def _raised(text: str) -> str:
    """The exception line of the trace submitit puts between two dashed lines (else its last line)."""
    parts = re.split(r"^-{10,}$", text, flags=re.M)
    lines = [ln for ln in (parts[1] if len(parts) > 2 else text).splitlines() if ln.strip()]
    return lines[-1].strip() if lines else "no message"


def _cancel(job_ids: list[str]) -> None:
    if job_ids:
        subprocess.run(["scancel", *job_ids], capture_output=True, timeout=60)
        note(f"slurm: cancelled {len(job_ids)} job(s) of this sweep")
