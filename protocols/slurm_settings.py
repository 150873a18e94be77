"""What each cell's SLURM job asks for, read from ``executor.slurm`` (configs/config.yaml), and what
sbatch's refusals mean in those keys (docs/usage.md, "Running on a cluster").

GPUs follow the cell's device: a CUDA cell asks for them, a CPU cell for none, ``device=auto`` for
one where the partition has GPUs. CPUs and memory are the same for every cell; the cell's threads
follow its CPUs (``protocols.slurm_job``).
"""

from __future__ import annotations

import re
import subprocess
from dataclasses import dataclass, field
from typing import Any

KEYS = ("partition", "timeout_min", "max_requeues", "signal_lead_s", "gpus_per_node", "cpus_per_task", "mem_gb",
        "sbatch", "folder")


@dataclass(frozen=True)
class SlurmSettings:
    partition: str | None = None
    timeout_min: int = 240
    max_requeues: int = 3
    signal_lead_s: int = 90
    gpus_per_node: int | str = "auto"
    cpus_per_task: int = 2
    mem_gb: float | None = 8
    sbatch: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def of(cls, section: dict) -> SlurmSettings:
        """The settings of ``executor.slurm``; a ValueError names the key that cannot be and the fix."""
        unknown = sorted(set(section) - set(KEYS))
        if unknown:
            raise ValueError(f"executor.slurm.{unknown[0]} is no setting of the SLURM executor (known: "
                             f"{', '.join(KEYS)}); a further sbatch option goes in executor.slurm.sbatch, e.g. "
                             "+executor.slurm.sbatch.account=NAME")
        s = {k: v for k, v in section.items() if k != "folder"}
        for key, least in (("timeout_min", 1), ("max_requeues", 0), ("signal_lead_s", 1), ("cpus_per_task", 1)):
            if key in s:
                _whole(key, s[key], least)
        gpus = s.get("gpus_per_node", "auto")
        if gpus is None:
            s["gpus_per_node"] = 0
        elif gpus != "auto":
            _whole("gpus_per_node", gpus, 0, " or auto (GPUs for the cells that run on CUDA)")
        mem = s.get("mem_gb", 8)
        if mem is not None and (isinstance(mem, bool) or not isinstance(mem, (int, float)) or not mem > 0):
            raise ValueError(f"executor.slurm.mem_gb={mem!r}: give each job's memory in GB, a number > 0 (or null for "
                             "the partition's default)")
        if not isinstance(s.get("sbatch") or {}, dict):
            raise ValueError(f"executor.slurm.sbatch={s['sbatch']!r}: give further sbatch options as a mapping, e.g. "
                             "executor.slurm.sbatch={account:NAME,qos:normal}")
        s["sbatch"] = dict(s.get("sbatch") or {})
        if s.get("partition") is not None:
            s["partition"] = str(s["partition"])
        return cls(**s)

    def lead_s(self) -> int:
        """Seconds before the time limit at which a job is warned (SIGUSR2): ``signal_lead_s``, at most
        a quarter of the limit (SLURM sends it up to a minute early; a job warned before its handler is
        in place dies of it), and late enough that submitit takes it for the time limit, not for a
        preemption that requeues without counting (it does from 80 % of the limit, or its last 10
        minutes, on; two minutes spare for SLURM's early sending and the job's start)."""
        limit = 60 * self.timeout_min
        return max(1, min(self.signal_lead_s, limit // 4, max(limit // 5, 600) - 120))

    def gpus_for(self, device: Any, partition_gpus: bool | None) -> int:
        """The GPUs a cell of ``device`` asks for: ``gpus_per_node`` when it is a number; for auto,
        ``cuda:N`` asks for N+1 (the job sees its GPUs as cuda:0…), ``cpu`` for none, ``auto`` for one
        where the partition has GPUs (``partition_gpus``: None when sinfo could not say)."""
        if self.gpus_per_node != "auto":
            return int(self.gpus_per_node)
        d = str(device or "auto")
        if d == "cpu":
            return 0
        if d.startswith("cuda"):
            return int(d.split(":")[1]) + 1 if ":" in d else 1
        return 1 if partition_gpus else 0

    def parameters(self, gpus: int, job_name: str) -> dict[str, Any]:
        """submitit's ``SlurmExecutor`` parameters of a job that asks for ``gpus``."""
        params: dict[str, Any] = {"job_name": job_name, "time": self.timeout_min, "cpus_per_task": self.cpus_per_task,
                                  "signal_delay_s": self.lead_s(),
                                  # requeueable whatever the cluster's default: preemption, a node failure
                                  "additional_parameters": {"requeue": True, **self.sbatch}}
        if self.partition:
            params["partition"] = self.partition
        if self.mem_gb is not None:
            params["mem"] = f"{round(self.mem_gb * 1024)}M"
        if gpus:
            params["gpus_per_node"] = gpus
        return params

    def describe(self, gpus: int) -> str:
        """One job's request in words, for the sweep's log."""
        mem = "the partition's default memory" if self.mem_gb is None else f"{self.mem_gb:g} GB"
        gpu = "no GPU" if not gpus else f"{gpus} GPU" + ("s" if gpus > 1 else "")
        return (f"{self.cpus_per_task} CPU{'s' if self.cpus_per_task > 1 else ''}, {mem}, {gpu}; time limit "
                f"{self.timeout_min} min, warned {self.lead_s()} s before it, up to {self.max_requeues} "
                f"requeue{'s' if self.max_requeues != 1 else ''} at the limit")


def _whole(key: str, value: Any, least: int, alt: str = "") -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < least:
        raise ValueError(f"executor.slurm.{key}={value!r}: give a whole number >= {least}{alt}")


def partition_gpus(partition: str | None) -> bool | None:
    """Whether the nodes of ``partition`` (the default one for None) have GPUs, from sinfo's
    generic resources; None when sinfo does not answer."""
    cmd = ["sinfo", "--noheader", "--format=%G"] + ([f"--partition={partition}"] if partition else [])
    try:
        out = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    except (OSError, subprocess.SubprocessError):
        return None
    if out.returncode != 0:
        return None
    return any("gpu" in line for line in out.stdout.lower().splitlines())


def sbatch_said(text: str) -> str:
    """sbatch's own error lines out of submitit's exception text."""
    lines = [ln.strip() for ln in text.splitlines() if "sbatch: error" in ln]
    said = "; ".join(re.sub(r"^.*?sbatch: error:\s*", "", ln) for ln in lines)
    if said:
        return said
    return text.strip().splitlines()[-1] if text.strip() else "no message"


def refusal(text: str, s: SlurmSettings, gpus: int, devices: list[str]) -> str:
    """The one-block error for a job array sbatch refused (``text``: its error), naming the key and the fix."""
    said = sbatch_said(text)
    low = said.lower()
    where = f"partition {s.partition}" if s.partition else "the default partition"
    if "account" in low or "qos" in low:
        return (f"sbatch refused the jobs on {where} ({said}): name your account or QOS with "
                "+executor.slurm.sbatch.account=NAME or +executor.slurm.sbatch.qos=NAME")
    if "gres" in low or "generic resource" in low:
        return (f"sbatch refused {gpus} GPU(s) per job on {where} ({said}): executor.slurm.gpus_per_node="
                f"{s.gpus_per_node} with device={'/'.join(devices)}. On CPU nodes run the cells on the CPU "
                "(device=cpu, or executor.slurm.gpus_per_node=0); for GPUs choose a partition that has them "
                "(executor.slurm.partition=NAME; sinfo -o '%P %G' lists each partition's GPUs)")
    if "partition" in low:
        return (f"sbatch refused executor.slurm.partition={s.partition} ({said}): give one of the partitions "
                "sinfo -s lists (or null for the cluster's default)")
    if "time limit" in low:
        return (f"sbatch refused executor.slurm.timeout_min={s.timeout_min} on {where} ({said}): give a limit "
                "within the partition's (sinfo -o '%P %l' lists them); a cell that needs longer is requeued from its "
                "checkpoint (executor.slurm.max_requeues)")
    if "memory" in low or "node configuration" in low or "cpu" in low:
        return (f"sbatch refused a job of {s.describe(gpus).split(';')[0]} on {where} ({said}): no node there has "
                "that much; lower executor.slurm.cpus_per_task or executor.slurm.mem_gb (sinfo -o '%P %c %m' "
                "lists each partition's CPUs and memory in MB)")
    return (f"sbatch refused the jobs on {where} ({said}); the executor.slurm settings give each job "
            f"{s.describe(gpus)}, with the further options {s.sbatch or 'none'} (executor.slurm.sbatch)")
