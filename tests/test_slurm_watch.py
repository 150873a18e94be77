"""The SLURM executor's wait never hangs (protocols.slurm_watch), on a clock of its own: a job
that ended or that SLURM forgot fails its cell after the result's grace, a result that comes within
the grace is taken, a pending job held for a reason is said once, and a controller that stays
silent gives the cells up. tests/test_slurm_executor.py runs the same against a real SLURM."""

from types import SimpleNamespace

import pytest

from protocols import slurm_watch
from protocols.slurm_watch import JobState, SlurmQueries, Waiting, wait


class Clock:
    def __init__(self):
        self.now = 0.0

    def monotonic(self):
        return self.now

    def sleep(self, s):
        self.now += s


@pytest.fixture
def clock(monkeypatch):
    c = Clock()
    monkeypatch.setattr(slurm_watch, "time", c)
    return c


class Queries(SlurmQueries):
    """The controller's answers, from ``answer(now)``: job id -> JobState, or None (no answer)."""

    def __init__(self, clock, answer):
        self.notes: list[str] = []
        super().__init__(self.notes.append)
        self.clock, self.answer = clock, answer

    def states(self, job_ids):
        return self.answer(self.clock.now)

    def why(self, job_id, seen):
        return seen.state if seen else "SLURM no longer knows the job"


def _waiting(tmp_path, *ids):
    return [Waiting(i, f"cell{i}", SimpleNamespace(job_id=j, paths=SimpleNamespace(
        result_pickle=tmp_path / f"{j}_result.pkl"))) for i, j in enumerate(ids)]


def _run(waiting, queries, clock, results_at=None):
    """wait() with results appearing at the given times: {job id: time}."""
    out, finished = {}, {}

    def collect(w):
        return {"key": w.key, "status": "ok"}

    def ended(w, what):
        return {"key": w.key, "status": "failed", "error": what}

    def done(i, summary):
        out[i], finished[i] = summary, clock.now

    real = clock.sleep

    def sleep(s):
        real(s)
        for w in waiting:
            if (results_at or {}).get(w.job_id, float("inf")) <= clock.now:
                w.job.paths.result_pickle.touch()

    clock.sleep = sleep
    wait(waiting, queries, collect, ended, done)
    return out, finished


def test_ended_or_forgotten_jobs_fail_after_the_grace_and_a_late_result_is_taken(tmp_path, clock):
    jobs = _waiting(tmp_path, "1_0", "1_1", "1_2", "1_3")

    def answer(now):
        if now < 20:
            return {j: JobState("RUNNING", "None") for j in ("1_0", "1_1", "1_2", "1_3")}
        return {"1_1": JobState("CANCELLED", "None"), "1_3": JobState("COMPLETED", "None")}   # 1_0, 1_2 forgotten

    out, when = _run(jobs, Queries(clock, answer), clock, results_at={"1_0": 30, "1_3": 25})
    assert out[0]["status"] == "ok" and out[3]["status"] == "ok"   # results within the grace
    assert out[1] == {"key": "cell1", "status": "failed", "error": "ended without a result: CANCELLED"}
    assert out[2]["error"] == "ended without a result: SLURM no longer knows the job"
    assert 20 + slurm_watch.RESULT_GRACE_S <= when[1] <= 20 + slurm_watch.RESULT_GRACE_S + slurm_watch.POLL_S + 1


def test_a_held_job_is_said_once_and_a_silent_controller_gives_the_cells_up(tmp_path, clock):
    jobs = _waiting(tmp_path, "2_0")
    queries = Queries(clock, lambda now: {"2_0": JobState("PENDING", "JobHeldUser")} if now < 60 else None)
    out, when = _run(jobs, queries, clock)
    assert queries.notes == ["slurm: job 2_0 (cell0) is pending: JobHeldUser (the sweep waits for it; scancel 2_0 "
                             "gives it up)"]
    assert out[0]["status"] == "failed" and out[0]["error"].startswith("was given up: the SLURM controller has not "
                                                                       "answered squeue for 10 min")
    assert 60 + slurm_watch.UNREACHABLE_S <= when[0] <= 60 + slurm_watch.UNREACHABLE_S + slurm_watch.POLL_S + 1
