"""A real single-node SLURM for the tests, from Debian's slurm-wlm and munge (``.ci/run`` installs
them): this host the only node, one partition ``debug``, no accounting storage, timers tuned for
fast tests. Started as root in seconds: munged, slurmctld and slurmd with a socket, ports, state and
spool of their own below a folder of this test session, so nothing of the machine's own SLURM or
munge is touched; stopped at the end. Every process of the cluster (its daemons and their jobs,
which inherit the sweep's environment) carries ``SMGS_TEST_SLURM=<folder>``: the processes of a
session that was killed are found by it and stopped before a new cluster starts.

Use the ``slurm_cluster`` fixture (import it into the test module); it skips, saying why, where the
tests do not run as root, the packages are not installed, or the cluster cannot start there (the
error and its daemons' logs in the reason).
"""

from __future__ import annotations

import os
import shutil
import signal
import socket
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import pytest

ROOT = Path(tempfile.gettempdir()) / "smgs-slurm-tests"
MARK = "SMGS_TEST_SLURM"
PROGRAMS = ("munged", "slurmctld", "slurmd", "sbatch", "srun", "squeue", "scontrol", "scancel", "sinfo")
# declared to SLURM (SlurmdParameters=config_overrides), more than the machine has: the tests' cells
# mostly sleep, and several must run at once
CPUS = 16
MEMORY_MB = 32000


@dataclass
class SlurmCluster:
    folder: Path
    env: dict[str, str]          # what a client (sbatch, a sweep) needs: SLURM_CONF and the mark
    partition: str = "debug"
    cpus: int = CPUS

    def run(self, *cmd: str, check: bool = True) -> subprocess.CompletedProcess:
        return subprocess.run(list(cmd), env={**os.environ, **self.env}, capture_output=True, text=True,
                              timeout=60, check=check)

    def logs(self) -> str:
        return "\n".join(f"--- {p.name}\n{p.read_text(errors='replace')[-3000:]}"
                         for p in sorted(self.folder.glob("*.log")))


def unavailable() -> str | None:
    """Why the cluster cannot start here (None when it can)."""
    if os.geteuid() != 0:
        return "the test SLURM cluster starts slurmctld, slurmd and munged as root; these tests do not run as root"
    missing = [p for p in PROGRAMS if shutil.which(p) is None]
    if missing:
        return (f"{', '.join(missing)} not installed: the SLURM tests need Debian's slurm-wlm and munge "
                "(apt-get install slurm-wlm munge; .ci/run installs them)")
    return None


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _conf(d: Path, host: str) -> str:
    return "\n".join([
        "ClusterName=smgstest", f"SlurmctldHost={host}(127.0.0.1)",
        f"SlurmctldPort={_free_port()}", f"SlurmdPort={_free_port()}",
        "SlurmUser=root", "SlurmdUser=root", "AuthType=auth/munge", "CredType=cred/munge",
        # cred_expire: a requeued job waits this long before it can start again (default 120 s)
        f"AuthInfo=socket={d}/munge.socket,cred_expire=5",
        f"StateSaveLocation={d}/state", f"SlurmdSpoolDir={d}/spool",
        f"SlurmctldPidFile={d}/slurmctld.pid", f"SlurmdPidFile={d}/slurmd.pid",
        f"SlurmctldLogFile={d}/slurmctld.log", f"SlurmdLogFile={d}/slurmd.log",
        # no cgroups in a container: processes tracked by their parents, no CPU binding
        "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none", "JobAcctGatherType=jobacct_gather/none",
        "AccountingStorageType=accounting_storage/none", "JobCompType=jobcomp/none", "MpiDefault=none",
        "SchedulerType=sched/builtin", "SchedulerParameters=sched_interval=2",
        "SelectType=select/cons_tres", "SelectTypeParameters=CR_CPU",
        "KillWait=2", "MinJobAge=300", "SlurmdTimeout=30", "InactiveLimit=0", "ReturnToService=2",
        "SlurmdParameters=config_overrides",
        f"NodeName={host} NodeAddr=127.0.0.1 CPUs={CPUS} RealMemory={MEMORY_MB} State=UNKNOWN",
        f"PartitionName=debug Nodes={host} Default=YES MaxTime=INFINITE State=UP", ""])


def _marked(folder: Path | None = None) -> list[int]:
    """The processes carrying the mark (of ``folder``, or of any session's folder)."""
    want = f"{MARK}={folder}".encode() if folder else f"{MARK}={ROOT}".encode()
    pids = []
    for proc in Path("/proc").iterdir():
        if not proc.name.isdigit() or int(proc.name) == os.getpid():
            continue
        try:
            env = (proc / "environ").read_bytes().split(b"\0")
        except OSError:
            continue
        if any(e == want or (folder is None and e.startswith(want + b"/")) for e in env):
            pids.append(int(proc.name))
    return pids


def _alive(pid: int) -> bool:
    try:
        return Path(f"/proc/{pid}/stat").read_text().split(") ")[1][0] != "Z"
    except (OSError, IndexError):
        return False


def _owner_alive(folder: Path) -> bool:
    try:
        pid, started = (folder / "owner").read_text().split()
        return _alive(int(pid)) and Path(f"/proc/{pid}/stat").read_text().split()[21] == started
    except (OSError, ValueError, IndexError):
        return False


def clean_leftovers() -> None:
    """Stop the processes and remove the folders of earlier sessions whose pytest is gone."""
    for folder in ROOT.glob("*/") if ROOT.is_dir() else []:
        if _owner_alive(folder):
            continue
        for pid in _marked(folder):
            try:
                os.kill(pid, signal.SIGKILL)
            except ProcessLookupError:
                pass
        shutil.rmtree(folder, ignore_errors=True)


def start() -> SlurmCluster:
    """A fresh cluster below ROOT/<this pid>; raises with the daemons' logs when it does not come up."""
    ROOT.mkdir(parents=True, exist_ok=True)
    d = ROOT / str(os.getpid())
    shutil.rmtree(d, ignore_errors=True)
    for sub in ("state", "spool"):
        (d / sub).mkdir(parents=True)
    d.chmod(0o755)
    (d / "owner").write_text(f"{os.getpid()} {Path(f'/proc/{os.getpid()}/stat').read_text().split()[21]}")
    (d / "munge.key").write_bytes(os.urandom(128))
    (d / "munge.key").chmod(0o600)
    host = socket.gethostname().split(".")[0]
    (d / "slurm.conf").write_text(_conf(d, host))
    cluster = SlurmCluster(d, {"SLURM_CONF": str(d / "slurm.conf"), MARK: str(d)})
    env = {**os.environ, **cluster.env}
    subprocess.run(["munged", "--force", f"--socket={d}/munge.socket", f"--key-file={d}/munge.key",
                    f"--log-file={d}/munged.log", f"--pid-file={d}/munged.pid", f"--seed-file={d}/munged.seed"],
                   env=env, check=True, capture_output=True, timeout=30)
    for daemon in ("slurmctld", "slurmd"):
        subprocess.run([daemon, "-f", str(d / "slurm.conf")], env=env, check=True, capture_output=True, timeout=30)
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        up = cluster.run("sinfo", "--noheader", "--format=%T", check=False)
        if up.returncode == 0 and up.stdout.strip() == "idle":
            return cluster
        time.sleep(0.2)
    logs = cluster.logs()
    stop(cluster)
    raise RuntimeError(f"the test SLURM cluster did not come up in 30 s:\n{logs}")


def stop(cluster: SlurmCluster) -> None:
    """Cancel its jobs, stop its daemons, then end whatever of it is left, and remove its folder."""
    cluster.run("scancel", "--user=root", check=False)
    for name in ("slurmd", "slurmctld", "munged"):
        try:
            os.kill(int((cluster.folder / f"{name}.pid").read_text()), signal.SIGTERM)
        except (OSError, ValueError):
            pass
    deadline = time.monotonic() + 5   # a job that has just written its result may still be exiting
    while [p for p in _marked(cluster.folder) if _alive(p)] and time.monotonic() < deadline:
        time.sleep(0.2)
    for pid in _marked(cluster.folder):
        try:
            os.kill(pid, signal.SIGKILL)
        except ProcessLookupError:
            pass
    shutil.rmtree(cluster.folder, ignore_errors=True)


@pytest.fixture(scope="session")
def slurm_cluster():
    why = unavailable()
    if why:
        pytest.skip(why)
    clean_leftovers()
    try:
        cluster = start()
    except (RuntimeError, OSError, subprocess.SubprocessError) as e:   # installed, but cannot start here
        detail = getattr(e, "stderr", None) or ""
        pytest.skip(f"the single-node test SLURM cannot start here: {type(e).__name__}: {e} {detail}"[:2000])
    try:
        yield cluster
    finally:
        stop(cluster)
