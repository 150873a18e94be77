"""The CPUs a cell's process was given, and the SLURM job it runs in, as results.json records them.

A SLURM job's CPUs are its ``--cpus-per-task`` (``SLURM_CPUS_PER_TASK``), not the node's cores:
torch's default would start a thread per core of the node, and eight cells on a 64-core node would
each start 64. Elsewhere the process's affinity mask says which CPUs it may use. Plain reads of the
environment, no torch: the SLURM job side (``protocols.slurm_job``) reads them before torch loads.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Mapping


@dataclass(frozen=True)
class JobCpus:
    count: int
    source: str   # "SLURM_CPUS_PER_TASK", "affinity mask" or "os.cpu_count()"


def job_cpus(env: Mapping[str, str] | None = None) -> JobCpus:
    """The CPUs this process was given: the SLURM job's ``SLURM_CPUS_PER_TASK``, else the affinity mask."""
    env = os.environ if env is None else env
    given = env.get("SLURM_CPUS_PER_TASK", "")
    if given.isdigit() and int(given) > 0:
        return JobCpus(int(given), "SLURM_CPUS_PER_TASK")
    if hasattr(os, "sched_getaffinity"):
        return JobCpus(len(os.sched_getaffinity(0)), "affinity mask")
    return JobCpus(os.cpu_count() or 1, "os.cpu_count()")


def slurm_job(env: Mapping[str, str] | None = None) -> dict | None:
    """The SLURM job this process runs in (None outside one): its id (``ARRAY_TASK`` form for an
    array's task), partition, node, what it was given (CPUs per task, memory in MB, GPUs) and how
    many times it was requeued."""
    env = os.environ if env is None else env
    if "SLURM_JOB_ID" not in env:
        return None
    array, task = env.get("SLURM_ARRAY_JOB_ID"), env.get("SLURM_ARRAY_TASK_ID")
    facts = {"job_id": f"{array}_{task}" if array and task else env["SLURM_JOB_ID"],
             "partition": env.get("SLURM_JOB_PARTITION"), "node": env.get("SLURMD_NODENAME"),
             "cpus_per_task": _int(env.get("SLURM_CPUS_PER_TASK")), "mem_mb": _int(env.get("SLURM_MEM_PER_NODE")),
             "gpus": _int(env.get("SLURM_GPUS_ON_NODE")) or 0, "restarts": _int(env.get("SLURM_RESTART_COUNT")) or 0}
    return {k: v for k, v in facts.items() if v is not None}


def train_conditions(env: Mapping[str, str] | None = None) -> dict:
    """What ``diagnostics.train_conditions`` of results.json records about the job: ``cpus`` (the
    count given), ``cpus_from`` (where it was read) and, in a SLURM job, ``slurm`` (``slurm_job``)."""
    cpus = job_cpus(env)
    out: dict = {"cpus": cpus.count, "cpus_from": cpus.source}
    job = slurm_job(env)
    if job is not None:
        out["slurm"] = job
    return out


def _int(value: str | None) -> int | None:
    return int(value) if value and value.isdigit() else None
