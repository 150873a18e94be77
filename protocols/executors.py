"""Where the cells of a grid run: in this process, in local worker processes, or on SLURM.

Every executor calls the same picklable function on the same payloads, so the results tree is the
same whichever ran it. A cell records its own failure in its results.json; an executor only has
to survive a worker (or a SLURM job: ``protocols.slurm_sweep``) that died without writing one.
"""

from __future__ import annotations

import concurrent.futures as cf
import multiprocessing as mp
import os
import traceback
from typing import Any, Callable

from protocols.cell_stop import Terminated
from protocols.progress import cell_status, progress

Payload = dict[str, Any]
Summary = dict[str, Any]

KINDS = ("sequential", "local", "slurm", "submitit_local")


def _died(payload: Payload, err: BaseException | str, what: str = "worker died: ") -> Summary:
    msg = err if isinstance(err, str) else f"{type(err).__name__}: {err}"
    out = {"key": payload.get("key"), "status": "failed", "error": f"{what}{msg}"}
    from protocols.cell import LOG   # here: the runner's start does not import the cell (torch)

    log = os.path.join(str(payload["run_dir"]), LOG) if payload.get("run_dir") else None
    if log and os.path.isfile(log):   # what the cell logged before its worker died
        out["log"] = log
    return out


def on_sigterm(signum: int, frame: object) -> None:
    raise Terminated()


def _init_worker(threads: int, parent: int) -> None:
    import signal
    import threading

    import torch
    torch.set_num_threads(threads)
    signal.signal(signal.SIGTERM, on_sigterm)  # a terminated worker stops its cell cleanly too
    threading.Thread(target=_watch_parent, args=(parent,), daemon=True, name="smgs-parent-watch").start()


def _watch_parent(parent: int, every: float = 1.0, grace: float = 60.0) -> None:
    """A local worker ends with the sweep that started it (killed with SIGKILL, it cannot stop its
    workers): once its parent is gone, the running cell is stopped as by SIGTERM (its checkpoint
    stays for the next run) and the worker exits; after ``grace`` seconds it exits in any case."""
    import signal
    import time

    while os.getppid() == parent:
        time.sleep(every)
    os.kill(os.getpid(), signal.SIGTERM)   # an idle worker ends here; a busy one in _in_worker
    time.sleep(grace)
    os._exit(128 + signal.SIGTERM)


def _in_worker(fn: Callable[[Payload], Summary], payload: Payload, parent: int) -> Summary:
    """``fn(payload)`` in a local worker, which exits after it when its sweep is gone (no one would
    read its summary or send it another cell)."""
    import signal

    try:
        return fn(payload)
    finally:
        if os.getppid() != parent:
            os._exit(128 + signal.SIGTERM)


def _advance(bar, summary: Summary) -> None:
    """One cell done: its name and status first, so that the line the step prints (a log's, where
    output is no terminal) names this cell and not the one before."""
    bar.set_postfix_str(f"{summary.get('key')}: {cell_status(summary)}")
    bar.update(1)


def execute(fn: Callable[[Payload], Summary], payloads: list[Payload], kind: str = "sequential",
            workers: int = 2, slurm: dict | None = None, folder: str | None = None) -> list[Summary]:
    """Run ``fn`` on every payload and return their summaries in payload order."""
    if kind not in KINDS:
        raise ValueError(f"unknown executor {kind!r}; expected one of {', '.join(KINDS)}")
    bar = progress(len(payloads), "grid", unit="run", disable=len(payloads) <= 1)
    out: list[Summary | None] = [None] * len(payloads)
    try:
        if kind == "sequential":
            for i, p in enumerate(payloads):
                out[i] = fn(p)
                _advance(bar, out[i])
        elif kind == "local":
            threads = max(1, (os.cpu_count() or 1) // max(1, workers))
            ctx = mp.get_context("spawn")  # no forked torch/OpenMP state
            with cf.ProcessPoolExecutor(max_workers=workers, mp_context=ctx, initializer=_init_worker,
                                        initargs=(threads, os.getpid())) as pool:
                futs = {pool.submit(_in_worker, fn, p, os.getpid()): i for i, p in enumerate(payloads)}
                try:
                    for f in cf.as_completed(futs):
                        i = futs[f]
                        try:
                            out[i] = f.result()
                        except Exception as e:  # the cell could not even record its failure
                            out[i] = _died(payloads[i], e)
                        _advance(bar, out[i])
                except BaseException:  # interrupted: stop the workers' cells too, not wait for them
                    pool.shutdown(wait=False, cancel_futures=True)
                    for proc in list(getattr(pool, "_processes", {}).values()):
                        proc.terminate()
                    raise
        elif kind == "slurm":
            from protocols.slurm_sweep import run_on_slurm

            def done(i: int, summary: Summary) -> None:
                out[i] = summary
                _advance(bar, summary)

            run_on_slurm(fn, payloads, slurm or {}, folder or "submitit", done, lambda p, why: _died(p, why, ""))
        else:
            out = _submitit_local(fn, payloads, slurm or {}, folder or "submitit", bar)
    finally:
        bar.close()
    return [o if o is not None else _died(p, "no result") for o, p in zip(out, payloads)]


def _submitit_local(fn, payloads, slurm: dict, folder: str, bar) -> list[Summary]:
    """submitit's local executor: the SLURM path's pickling and job files, in local processes."""
    import submitit

    ex = submitit.LocalExecutor(folder=folder)
    ex.update_parameters(timeout_min=int(slurm.get("timeout_min", 60)))
    jobs = ex.map_array(fn, payloads)
    out: list[Summary] = []
    for job, p in zip(jobs, payloads):
        try:
            out.append(job.result())
        except Exception as e:
            tb = traceback.format_exception_only(type(e), e)[-1].strip()
            out.append(_died(p, tb))
        _advance(bar, out[-1])
    return out
