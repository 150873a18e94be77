"""A kill at any instant of a checkpoint save or re-save leaves a resumable run.

Deterministic, not by luck: a forked child performs the save and SIGKILLs itself just before its
k-th file-system operation (open, mkdir, fsync, rename, unlink, rmdir); k runs over every operation
of the save. After each kill the run folder must resume: the pointer names a complete checkpoint.
"""

from __future__ import annotations

import json
import logging
import os
import signal
import time

import pytest

from baselines import create_method
from protocols.results import POINTER
from protocols.train_loop import _load_checkpoint, _save_checkpoint
from smgs.data.patterns import pattern_scene
from smgs.train import pattern_config, to_dict

HOOKED = ("open", "mkdir", "fsync", "replace", "rename", "unlink", "rmdir", "fchmod")


def _method(scene):
    return create_method("3dgs", scene, to_dict(pattern_config("3dgs", cap=4, steps=6)), device="cpu")


def _progress(step):
    return {"step": step, "train_seconds": 1.0, "curve": [], "config_hash": "h"}


def _save_killed_at(k: int, run_dir, method, step) -> bool:
    """Save in a forked child that SIGKILLs itself before its k-th file-system operation; True when
    the save ran to its end (fewer than k operations)."""
    pid = os.fork()
    if pid == 0:   # the child: never returns into pytest
        try:
            count = [0]

            def hook(name, real):
                def op(*a, **kw):
                    count[0] += 1
                    if count[0] == k:
                        os.kill(os.getpid(), signal.SIGKILL)
                    return real(*a, **kw)
                return op

            for name in HOOKED:
                setattr(os, name, hook(name, getattr(os, name)))
            _save_checkpoint(run_dir, method, _progress(step))
            os._exit(0)
        except BaseException:
            os._exit(1)
    deadline = time.monotonic() + 60
    while True:
        done, status = os.waitpid(pid, os.WNOHANG)
        if done:
            break
        if time.monotonic() > deadline:
            os.kill(pid, signal.SIGKILL)
            pytest.fail("the save hung in the child")
        time.sleep(0.01)
    if os.WIFSIGNALED(status):
        assert os.WTERMSIG(status) == signal.SIGKILL
        return False
    assert os.WEXITSTATUS(status) == 0, "the save raised in the child"
    return True


def _resumable(run_dir, scene, steps: set[int]) -> int:
    fresh = _method(scene)
    progress = _load_checkpoint(run_dir, fresh, "h", logging.getLogger("test"))
    assert progress is not None, "no checkpoint in force"
    assert progress["step"] in steps
    assert fresh.describe()["step"] == progress["step"]
    return progress["step"]


@pytest.mark.parametrize("resave", [False, True], ids=["next-step", "same-step-again"])
def test_a_kill_at_every_instant_of_a_save_leaves_a_resumable_checkpoint(tmp_path, resave):
    """``same-step-again``: a run killed between its final checkpoint and results.json is resumed at
    its last step and saves that step again; the checkpoint in force must survive the re-save."""
    scene = pattern_scene("circle4", 12)
    method = _method(scene)
    for s in range(3):
        method.train_step(s)
    run_dir = tmp_path / "run"
    run_dir.mkdir()
    _save_checkpoint(run_dir, method, _progress(3))
    new_step = 3
    if not resave:
        for s in range(3, 5):
            method.train_step(s)
        new_step = 5
    for k in range(1, 500):
        finished = _save_killed_at(k, run_dir, method, new_step)
        _resumable(run_dir, scene, {3, new_step})
        if finished:
            break
    else:
        pytest.fail("the save never finished")
    assert k > 10, "the hooks saw too few operations to test anything"
    assert _resumable(run_dir, scene, {new_step}) == new_step   # the finished save is the one in force
    # and it left one checkpoint folder, the one the pointer names
    ptr = json.loads((run_dir / POINTER).read_text())["dir"]
    assert sorted(p.name for p in run_dir.glob("ckpt-*")) == [ptr]
