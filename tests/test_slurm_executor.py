"""``executor.kind=slurm`` against a real single-node SLURM (tests/slurm_cluster.py: skips where the
tests do not run as root or slurm-wlm and munge are not installed).

Four sweeps run at once, about two minutes in all (SLURM's time limits come in whole minutes):

- A: the docs' CPU-node example (docs/usage.md, "Running on a cluster") on tiny cells: every cell
  ok, the same metrics and the same progress lines as the sequential run with as many threads, each
  cell's threads those of its job, a cluster without accounting said once;
- B: a 1-min time limit and one requeue: a cell slow in every run of its job is warned, saves its
  checkpoint and is requeued, then fails at the limit again, saying so;
- C: 2-min time limits: a cell slow in its job's first run only reaches the limit, is warned, saves
  its checkpoint, is requeued and resumes from a step > 0 to end ok; a preemption
  (``scontrol requeue``), an ``scancel`` and a SIGKILL of one job's task: the preempted cell
  resumes and ends ok, the other two fail with SLURM's reason within 2 minutes, the rest finish,
  and the sweep exits non-zero naming the failures;
- D: a sweep stopped by SIGTERM cancels its job, whose cell saves its checkpoint and stops.

The slow cells are a method installed as a plug-in (``smgs.methods`` entry point, as a third party
installs one) that sleeps a fifth of a second a step, in every run of its job or in the first only.
"""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import subprocess
import sys
import threading
import time
from contextlib import redirect_stderr
from io import StringIO
from pathlib import Path

import pytest

from plugin_dist import install, uninstall
from protocols.results import find_results, read_result
from slurm_cluster import slurm_cluster  # noqa: F401  (the fixture)

REPO = Path(__file__).resolve().parent.parent
PLUGIN = '''
import os, time
from pathlib import Path
from baselines.method import MethodSpec
from baselines.splatting import GaussianSplatting


class Slow(GaussianSplatting):
    """A fifth of a second a step: a cell that needs longer than its job has (a big scene, a slow node)."""

    def slow_now(self):
        return True

    def train_step(self, step):
        if not getattr(self, "announced", False):   # the test acts on a job once its cell trains
            self.announced = True
            env = os.environ
            job = (f"{env['SLURM_ARRAY_JOB_ID']}_{env['SLURM_ARRAY_TASK_ID']}" if env.get("SLURM_ARRAY_JOB_ID")
                   else env["SLURM_JOB_ID"])
            where = Path(env["SMGS_TEST_PIDS"], f"{job}.{env.get('SLURM_RESTART_COUNT') or 0}")
            where.with_suffix(".tmp").write_text(str(os.getpid()))
            where.with_suffix(".tmp").rename(where)
        if self.slow_now():
            time.sleep(0.2)
        return super().train_step(step)


class SlowOnce(Slow):
    """Slow in its job's first run only: once requeued it trains at full speed."""

    def slow_now(self):
        return int(os.environ.get("SLURM_RESTART_COUNT") or 0) == 0


SLOW = MethodSpec("slow", Slow, {"mode": "3dgs"})
SLOW_ONCE = MethodSpec("slow_once", SlowOnce, {"mode": "3dgs"})
'''
# tiny cells: the docs' example with its short-run override (A), and 600 steps of a 16-pixel pattern
SHORT = ["seeds=1", "protocol.steps=8", "dataset.width=32", "dataset.height=24", "dataset.n_views=8",
         "eval.fps_repeats=1", "report=false"]
PATTERN = ["+experiment=patterns", "grid.budgets=[cap4]", "grid.scenes=[circle4]", "grid.seeds=[0]", "dataset.size=16",
           "dataset.steps=600", "report=false", "eval.fps_repeats=1", "eval.flip=false", "device=cpu",
           "executor.kind=slurm", "executor.slurm.partition=debug", "executor.slurm.cpus_per_task=1"]
KEY = "patterns/circle4/{}/cap4/seed{}"
WAIT_S = 300


def docs_cpu_example() -> list[str]:
    """The overrides of the CPU-node command in docs/usage.md's "Running on a cluster"."""
    text = (REPO / "docs" / "usage.md").read_text()
    section = text.split("## Running on a cluster", 1)[1].split("\n## ", 1)[0]
    for block in re.findall(r"```bash\n(.*?)```", section, re.S):
        for cmd in block.replace("\\\n", " ").splitlines():
            words = shlex.split(cmd, comments=True)
            if "executor.kind=slurm" in words and "device=cpu" in words:
                assert words[:3] == ["python", "-m", "protocols.run"], cmd
                return words[3:]
    raise AssertionError("docs/usage.md's 'Running on a cluster' has no CPU-node example (device=cpu)")


class Sweep:
    """``python -m protocols.run`` in the background, its output lines kept with the time each came."""

    def __init__(self, args: list[str], env: dict[str, str]) -> None:
        self.args = args
        self.lines: list[tuple[float, str]] = []
        self.proc = subprocess.Popen([sys.executable, "-m", "protocols.run", *args], cwd=REPO, env=env, text=True,
                                     stdout=subprocess.PIPE, stderr=subprocess.STDOUT, bufsize=1)
        self.reader = threading.Thread(target=self._read, daemon=True)
        self.reader.start()

    def _read(self) -> None:
        for line in self.proc.stdout:
            self.lines.append((time.monotonic(), line.rstrip("\n")))

    def wait(self) -> int:
        try:
            rc = self.proc.wait(timeout=WAIT_S)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            raise AssertionError(f"the sweep still runs after {WAIT_S} s:\n{self.text()[-4000:]}") from None
        self.reader.join(timeout=10)
        return rc

    def text(self) -> str:
        return "\n".join(line for _, line in self.lines)

    def grid_lines(self) -> dict[str, tuple[float, str]]:
        """Each cell's progress line: its key -> (when, status)."""
        out = {}
        for when, line in self.lines:
            m = re.fullmatch(r"grid: run \d+/\d+ \(\d+%\), \d+ s, (\S+): (.+)", line)
            if m:
                out[m[1]] = (when, m[2])
        return out


def _results(root: Path) -> dict[str, object]:
    return {str(p.parent.relative_to(root)): read_result(p) for p in find_results(root)}


def _jobs(folder: Path, n: int) -> dict[str, str]:
    """Cell key -> SLURM job id, from the sweep's cells.tsv."""
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        path = folder / "cells.tsv"
        rows = [ln.split("\t") for ln in path.read_text().splitlines()] if path.exists() else []
        if len(rows) == n:
            return {key: job for job, key in rows}
        time.sleep(0.2)
    raise AssertionError(f"{folder / 'cells.tsv'} did not list {n} jobs")


def _training(pids: Path, job: str, restart: int = 0, timeout: float = 120) -> int:
    """The pid of the job's task once its cell trains."""
    path = pids / f"{job}.{restart}"
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert time.monotonic() < deadline, f"job {job} did not start training in {timeout} s"
        time.sleep(0.2)
    return int(path.read_text())


def _act_on_c(cluster, folder: Path, pids: Path, acted: dict[str, float]) -> None:
    """Sweep C's interventions, each once its cell trains: a preemption, an scancel, a SIGKILL of the task."""
    jobs = _jobs(folder, 5)
    preempted, cancelled, killed = (jobs[KEY.format("slow_once", 0)], jobs[KEY.format("slow", 0)],
                                    jobs[KEY.format("slow", 1)])
    _training(pids, preempted)
    cluster.run("scontrol", "requeue", preempted)
    acted["preempted"] = time.monotonic()
    _training(pids, cancelled)
    cluster.run("scancel", cancelled)
    acted["cancelled"] = time.monotonic()
    os.kill(_training(pids, killed), signal.SIGKILL)
    acted["killed"] = time.monotonic()


def _stop_d(d: Sweep, folder: Path, pids: Path, acted: dict[str, float]) -> None:
    """Sweep D stopped by SIGTERM once its cell trains."""
    (job,) = _jobs(folder, 1).values()
    _training(pids, job)
    d.proc.send_signal(signal.SIGTERM)
    acted["sweep"] = time.monotonic()
    acted["d_job"] = job


@pytest.fixture(scope="module")
def sweeps(slurm_cluster, tmp_path_factory):  # noqa: F811
    """The three sweeps, started together, and the sequential run of A's grid meanwhile."""
    import torch

    from protocols.run import run_experiment

    root = tmp_path_factory.mktemp("slurm")
    site, pids = root / "site", root / "pids"
    pids.mkdir()
    with pytest.MonkeyPatch.context() as mp:
        install(site, mp, "smgs_slurm_test_methods", PLUGIN, "smgs.methods",
                {"slow": "smgs_slurm_test_methods:SLOW", "slow_once": "smgs_slurm_test_methods:SLOW_ONCE"})
        env = {**os.environ, **slurm_cluster.env, "PYTHONPATH": f"{REPO}{os.pathsep}{site}",
               "SMGS_TEST_PIDS": str(pids), "SMGS_CELLS_DIR": str(root / "cells")}
        b = Sweep(PATTERN + ["grid.methods=[slow]", "executor.slurm.timeout_min=1", "executor.slurm.max_requeues=1",
                             f"out_dir={root / 'b'}"], env)
        c = Sweep(PATTERN + ["grid.methods=[slow_once,slow,3dgs]", "+grid.seeds_of.slow=[0,1]",
                             "+grid.seeds_of.slow_once=[0,1]", "executor.slurm.timeout_min=2",
                             f"out_dir={root / 'c'}"], env)
        d = Sweep(PATTERN + ["grid.methods=[slow]", f"out_dir={root / 'd'}"], env)
        acted: dict = {}
        actors = [threading.Thread(target=_act_on_c, args=(slurm_cluster, root / "c" / "_submitit", pids, acted),
                                   daemon=True),
                  threading.Thread(target=_stop_d, args=(d, root / "d" / "_submitit", pids, acted), daemon=True)]
        for actor in actors:
            actor.start()
        docs = docs_cpu_example()
        a = Sweep(docs + SHORT + [f"out_dir={root / 'a'}"], env)
        threads = torch.get_num_threads()
        torch.set_num_threads(2)   # the SLURM cells' default: executor.slurm.cpus_per_task=2
        try:
            with redirect_stderr(StringIO()) as seq_lines:
                seq = run_experiment([w for w in docs if not w.startswith("executor.")] + SHORT
                                     + [f"out_dir={root / 'seq'}"])
        finally:
            torch.set_num_threads(threads)
        yield {"a": a, "b": b, "c": c, "d": d, "root": root, "acted": acted, "actors": actors, "seq": seq,
               "seq_lines": seq_lines.getvalue()}
        for s in (a, b, c, d):
            if s.proc.poll() is None:
                s.proc.kill()
        uninstall("smgs_slurm_test_methods")


def _accounting_lines(sweep: Sweep) -> list[str]:
    return [line for _, line in sweep.lines if "sacct" in line or "accounting" in line]


def test_the_docs_cpu_example_equals_the_sequential_run(sweeps):
    a, root = sweeps["a"], sweeps["root"]
    assert a.wait() == 0, a.text()[-4000:]
    on_slurm, seq = _results(root / "a"), _results(root / "seq")
    assert len(seq) == 4 and sorted(on_slurm) == sorted(seq)
    for key, r in on_slurm.items():
        assert r.status == "ok", (key, r.error)
        assert (r.config_hash, r.metrics, r.per_view, r.num_gaussians) == \
            (seq[key].config_hash, seq[key].metrics, seq[key].per_view, seq[key].num_gaussians), key
        cond = r.diagnostics["train_conditions"]
        assert (cond["threads"], cond["cpus"], cond["cpus_from"]) == (2, 2, "SLURM_CPUS_PER_TASK"), cond
        assert cond["slurm"]["partition"] == "debug" and cond["slurm"]["cpus_per_task"] == 2, cond
    # the same progress lines as the sequential executor's: one per cell, naming it and its status
    seq_lines = {m[1]: m[2] for m in re.finditer(r"grid: run \d+/4 \(\d+%\), \d+ s, (\S+): (.+)",
                                                 sweeps["seq_lines"])}
    assert {k: s for k, (_, s) in a.grid_lines().items()} == seq_lines == {k: "ok" for k in seq}
    lines = _accounting_lines(a)
    assert len(lines) == 1 and "no job accounting here" in lines[0], lines
    assert "Bypassing" not in a.text()


def test_gpus_on_a_cpu_partition_are_refused_before_any_cell(slurm_cluster, tmp_path, monkeypatch):  # noqa: F811
    from protocols.run import run_experiment

    for k, v in slurm_cluster.env.items():
        monkeypatch.setenv(k, v)
    args = PATTERN[:-3] + ["grid.methods=[3dgs]", "device=cuda", "executor.kind=slurm",
                           "executor.slurm.partition=debug", f"out_dir={tmp_path}"]
    with pytest.raises(SystemExit) as e:
        run_experiment(args)
    said = str(e.value)
    assert said.startswith("invalid config, nothing was run: sbatch refused 1 GPU(s) per job on partition debug"), said
    assert "executor.slurm.gpus_per_node=auto with device=cuda" in said and "device=cpu" in said, said
    assert "Traceback" not in said and not list(find_results(tmp_path))


def test_without_slurm_commands_the_sweep_says_where_to_run(tmp_path, monkeypatch):
    from protocols.run import run_experiment

    monkeypatch.setenv("PATH", str(tmp_path))   # no sbatch, srun, squeue here
    with pytest.raises(SystemExit) as e:
        run_experiment(PATTERN[:-2] + ["grid.methods=[3dgs]", "dataset.steps=2", f"out_dir={tmp_path}"])
    assert str(e.value).startswith("executor.kind=slurm: sbatch, srun, squeue, scontrol not found on this machine")


def test_a_slurm_refusal_exits_with_status_2_in_one_block_before_hydra_writes_its_log(tmp_path, monkeypatch,
                                                                                      capsys):
    """As every refusal of smgs run does (protocols.refused), not as a failed run (1)."""
    from protocols.run import cli

    monkeypatch.setenv("PATH", str(tmp_path))
    out = tmp_path / "runs"
    for setting, said in (("executor.slurm.timeout_min=0", "error: invalid config, nothing was run: "
                                                           "executor.slurm.timeout_min=0: give a whole number >= 1"),
                          ("executor.slurm.cpus_per_task=1", "error: executor.kind=slurm: sbatch, srun, squeue, "
                                                             "scontrol not found")):
        with pytest.raises(SystemExit) as e:
            cli(PATTERN[:-2] + [setting, "grid.methods=[3dgs]", "dataset.steps=2", f"out_dir={out}"])
        err = capsys.readouterr().err
        assert e.value.code == 2 and err.startswith(said), err
        assert err.count("\n") == 1 and "Traceback" not in err, err
        assert not out.exists(), "refused before anything is written"


def test_preempted_resumes_cancelled_and_killed_fail_within_2_minutes(sweeps):
    c, root, acted = sweeps["c"], sweeps["root"], sweeps["acted"]
    rc = c.wait()
    sweeps["actors"][0].join(timeout=10)
    assert {"preempted", "cancelled", "killed"} <= set(acted), c.text()[-4000:]
    assert rc == 1 and "error: 2 of 5 run(s) failed" in c.text(), c.text()[-4000:]
    lines, out = c.grid_lines(), c.text()
    cancelled, killed = KEY.format("slow", 0), KEY.format("slow", 1)
    for key, why, when in ((cancelled, "ended without a result: CANCELLED", acted["cancelled"]),
                           (killed, "ended without a result: FAILED, its task was killed", acted["killed"])):
        assert lines[key][1] == "failed", lines
        assert lines[key][0] - when < 120, f"{key} failed {lines[key][0] - when:.0f} s after its job was stopped"
        assert re.search(rf"^  {re.escape(key)}: failed: slurm job \S+ {why}", out, re.M), out[-4000:]
    results = _results(root / "c")
    for key in (KEY.format("slow_once", 0), KEY.format("slow_once", 1), KEY.format("3dgs", 0)):
        assert lines[key][1] == "ok" and results[key].status == "ok", (key, lines)
    preempted = root / "c" / KEY.format("slow_once", 0)
    resumed = re.search(r"resumed from step (\d+)", (preempted / "log.txt").read_text())
    assert resumed and int(resumed[1]) > 0, (preempted / "log.txt").read_text()[-3000:]
    assert "stopping for SIGTERM; checkpoint saved" in (preempted / "log.txt").read_text()
    assert results[KEY.format("slow_once", 0)].diagnostics["train_conditions"]["slurm"]["restarts"] >= 1
    assert len(_accounting_lines(c)) == 1


def test_a_cell_past_its_time_limit_resumes_from_its_checkpoint(sweeps):
    c, root = sweeps["c"], sweeps["root"]
    c.wait()
    cell = root / "c" / KEY.format("slow_once", 1)
    log = (cell / "log.txt").read_text()
    assert "stopping for the time limit's warning (SIGUSR2); checkpoint saved" in log, log[-3000:]
    resumed = re.search(r"resumed from step (\d+)", log)
    assert resumed and int(resumed[1]) > 0, log[-3000:]
    ok = read_result(cell / "results.json")
    assert ok.status == "ok" and ok.diagnostics["train_conditions"]["slurm"]["restarts"] == 1
    assert ok.diagnostics["train_conditions"]["threads"] == 1   # executor.slurm.cpus_per_task=1
    assert "executor.slurm.signal_lead_s=90 does not fit a 2-min limit: jobs are warned 30 s before it" in c.text()


def test_past_max_requeues_a_cell_fails_saying_so(sweeps):
    b, root = sweeps["b"], sweeps["root"]
    rc = b.wait()
    out = b.text()
    assert rc == 1 and "error: 1 of 1 run(s) failed" in out, out
    cell = root / "b" / KEY.format("slow", 0)
    log = (cell / "log.txt").read_text()
    assert log.count("stopping for the time limit's warning (SIGUSR2); checkpoint saved") == 2, log[-3000:]
    never = read_result(cell / "results.json")
    assert never.status == "failed", never
    assert never.error.startswith("TimeLimitReached: reached the time limit of its job again with no requeue left "
                                  "(executor.slurm.timeout_min=1, executor.slurm.max_requeues=1"), never.error
    assert re.search(rf"^  {re.escape(KEY.format('slow', 0))}: failed: TimeLimitReached", out, re.M), out
    assert "executor.slurm.signal_lead_s=90 does not fit a 1-min limit: jobs are warned 15 s before it" in out
    assert len(_accounting_lines(b)) == 1
    assert json.loads((cell / "checkpoint.json").read_text())["dir"]   # kept for a rerun with a longer limit


def test_a_sweep_stopped_by_sigterm_cancels_its_jobs(sweeps, slurm_cluster):  # noqa: F811
    d, root, acted = sweeps["d"], sweeps["root"], sweeps["acted"]
    assert d.wait() == 128 + signal.SIGTERM, d.text()[-4000:]
    assert "slurm: cancelled 1 job(s) of this sweep" in d.text() and "stopped by SIGTERM" in d.text()
    job = acted["d_job"]
    deadline = time.monotonic() + 60
    while True:
        state = slurm_cluster.run("squeue", "--noheader", "--states=all", f"--jobs={job}", "--format=%T").stdout
        if state.strip() == "CANCELLED" or time.monotonic() > deadline:
            break
        time.sleep(0.5)
    assert state.strip() == "CANCELLED", state
    log = root / "d" / KEY.format("slow", 0) / "log.txt"
    deadline = time.monotonic() + 30   # the job's cell stops after its current step
    while "stopping for SIGTERM; checkpoint saved" not in log.read_text() and time.monotonic() < deadline:
        time.sleep(0.5)
    assert "stopping for SIGTERM; checkpoint saved" in log.read_text(), log.read_text()[-2000:]


def test_a_cluster_left_by_a_killed_session_is_stopped_before_the_next():
    from slurm_cluster import _alive, _marked, clean_leftovers, unavailable

    why = unavailable()
    if why:
        pytest.skip(why)
    tests = Path(__file__).resolve().parent
    code = ("import sys, time; import slurm_cluster as sc; c = sc.start(); print(c.folder, flush=True); "
            "time.sleep(600)")
    session = subprocess.Popen([sys.executable, "-c", code], cwd=tests, text=True, stdout=subprocess.PIPE,
                               env={**os.environ, "PYTHONPATH": f"{tests}{os.pathsep}{REPO}"})
    try:
        folder = Path(session.stdout.readline().strip())
        assert folder.name == str(session.pid), folder
    finally:
        session.kill()   # killed: it stops nothing
        session.wait()
    assert len([p for p in _marked(folder) if _alive(p)]) >= 3   # munged, slurmctld, slurmd
    clean_leftovers()
    assert not [p for p in _marked(folder) if _alive(p)] and not folder.exists()
