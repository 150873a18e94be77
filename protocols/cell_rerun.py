"""A rerun of a finished cell (another config, ``--force``) works beside it, never over it.

The finished cell's folder (its results.json, checkpoint, config.yaml, log and renders) stays whole
until the rerun has a complete result of its own: the rerun works in a hidden folder beside it
(``.seed0.rerun`` next to ``seed0``), which is then put in place of the finished one in one step
(an atomic exchange where Linux offers it). An interrupted or failed rerun leaves the finished
cell as it was, and its own progress in the hidden folder, which the same rerun resumes
(docs/runs.md). Everything here runs with the cell's lock held (``protocols.cell_lock``).
"""

from __future__ import annotations

import os
import shutil
from pathlib import Path

from protocols.cell_lock import LOCK
from protocols.results import POINTER, RESULTS_FILE
from smgs.atomic import exchange_dirs

RERUN = "rerun"
OLD = "old-"
CONFIG_FILE = "config.yaml"
# What a run writes into its folder (``ckpt-*`` and temporary ``.*.tmp`` files too): a rerun's
# folder replaces these; anything else in the finished folder is the user's and is carried over.
RUN_FILES = (RESULTS_FILE, POINTER, CONFIG_FILE, LOCK, "log.txt", "renders", "consistency", "trajectory.json",
             "point_cloud.ply", "video")


def rerun_dir(run_dir: Path) -> Path:
    """The hidden folder beside ``run_dir`` in which a rerun of its finished cell works."""
    return run_dir.parent / f".{run_dir.name}.{RERUN}"


def remove_leftovers(run_dir: Path) -> None:
    """Remove the finished folders that earlier swaps put aside and were stopped before removing
    (only ever made with the cell's lock held, so none of them is still in use)."""
    for old in run_dir.parent.glob(f".{run_dir.name}.{OLD}*"):
        shutil.rmtree(old, ignore_errors=True)


def swap_in(work: Path, run_dir: Path) -> None:
    """Put the rerun's complete folder ``work`` in place of the finished ``run_dir``, then remove
    the finished one. The user's own files in ``run_dir`` are carried over (hard links), and the
    lock file is shared, so that the lock this process holds stays the folder's lock. Until the
    exchange ``run_dir`` is the finished cell; after it, the rerun's; a kill in between leaves one
    of the two whole and the other beside it, which the next run of its config swaps back."""
    _carry_over(run_dir, work)
    _share_lock(run_dir, work)
    aside = run_dir.parent / f".{run_dir.name}.{OLD}{os.getpid()}"
    if exchange_dirs(work, run_dir):
        os.rename(work, aside)   # now the finished folder: never left under the rerun's name half removed
    else:   # no atomic exchange here: a moment without the folder (docs/runs.md)
        os.rename(run_dir, aside)
        os.rename(work, run_dir)
    shutil.rmtree(aside, ignore_errors=True)


def _run_file(name: str) -> bool:
    return name in RUN_FILES or name.startswith("ckpt-") or (name.startswith(".") and name.endswith(".tmp"))


def _carry_over(old: Path, new: Path) -> None:
    for entry in old.iterdir():
        dst = new / entry.name
        if _run_file(entry.name) or dst.exists() or dst.is_symlink():
            continue
        if entry.is_symlink():
            os.symlink(os.readlink(entry), dst)
        elif entry.is_dir():
            shutil.copytree(entry, dst, symlinks=True, copy_function=_link)
        else:
            _link(entry, dst)


def _link(src: str | Path, dst: str | Path) -> None:
    try:
        os.link(src, dst)
    except OSError:   # another file system, or no hard links there
        shutil.copy2(src, dst)


def _share_lock(run_dir: Path, work: Path) -> None:
    tmp = work / f".{LOCK}.{os.getpid()}.tmp"
    tmp.unlink(missing_ok=True)
    os.link(run_dir / LOCK, tmp)
    os.replace(tmp, work / LOCK)
