"""The compilers of a build in a process group of their own, stopped whole when the build is.

torch's ``cpp_extension.load`` runs ninja, which runs the compilers (``c++`` -> ``cc1plus``, ``nvcc`` ->
``cicc`` ...). Interrupted (Ctrl-C, the harness's SIGTERM turned into an exception), torch kills
ninja alone and the compilers run on as orphans for minutes; killed outright, nothing is stopped.
So a build runs in a child Python started in a session of its own (its own process group, which
ninja and the compilers inherit):

- an exception in the caller while it waits (KeyboardInterrupt, ``protocols``' SIGTERM) stops the
  whole group (SIGTERM, then SIGKILL) before it propagates;
- the child watches its parent and stops its group when the parent is gone (a caller killed with
  SIGKILL, or by a SIGTERM it does not handle).

The caller imports the library the child built (``smgs.raster.buildcache``).
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

# Run by ``python -c``: needs torch only (not smgs), so it starts as fast as torch imports. ninja
# runs each compiler in a process group of its own and, on SIGTERM, passes it on to those groups
# before it exits; so a build is stopped with SIGTERM first (this process outlives it: its own
# handler does nothing), then SIGKILL for whatever is left of the group.
_CHILD = r"""
import json, os, signal, sys, threading, time

parent = os.getppid()
signal.signal(signal.SIGTERM, lambda *_: None)

def watch():
    while True:
        time.sleep(0.5)
        if os.getppid() != parent:   # the caller is gone: so is the reason to build
            os.killpg(0, signal.SIGTERM)
            time.sleep(float(sys.argv[2]))
            os.killpg(0, signal.SIGKILL)

threading.Thread(target=watch, daemon=True).start()
from torch.utils.cpp_extension import load
try:
    load(**json.loads(sys.argv[1]))
except Exception as e:
    sys.stderr.write(str(e))
    sys.exit(1)
"""
GRACE = 3.0   # seconds between SIGTERM and SIGKILL


def session_members(sid: int) -> list[int]:
    """The processes of session ``sid`` (Linux: /proc; elsewhere none are found)."""
    out = []
    for d in Path("/proc").glob("[0-9]*"):
        try:
            stat = (d / "stat").read_text()
            if int(stat.rsplit(")", 1)[1].split()[3]) == sid:   # after the name: state ppid pgrp session
                out.append(int(d.name))
        except (OSError, ValueError, IndexError):
            continue
    return out


def stop_group(proc: subprocess.Popen, grace: float = GRACE) -> None:
    """Stop ``proc``'s session (``proc`` leads it): SIGTERM to its group, ``grace`` seconds for the
    leader, SIGKILL to what is left of the group and then of the session (ninja's compilers have
    groups of their own in it); the leader is reaped."""
    for sig in (signal.SIGTERM, signal.SIGKILL):
        try:
            os.killpg(proc.pid, sig)
        except (ProcessLookupError, PermissionError):   # the group is gone
            break
        try:
            proc.wait(grace)
        except subprocess.TimeoutExpired:
            pass
    for pid in session_members(proc.pid):
        try:
            os.kill(pid, signal.SIGKILL)
        except OSError:
            pass
    proc.wait()


def run_in_group(cmd: list[str], timeout: float | None = None, **kw) -> subprocess.CompletedProcess:
    """``subprocess.run(cmd, capture_output=True, text=True)`` in a session of its own: a timeout,
    or any exception while it runs, stops the command's whole process group (its children too)."""
    proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            start_new_session=True, **kw)
    try:
        out, err = proc.communicate(timeout=timeout)
    except BaseException:   # a timeout, KeyboardInterrupt, the harness's SIGTERM: no orphans
        stop_group(proc)
        raise
    return subprocess.CompletedProcess(cmd, proc.returncode, out, err)


def build_library(name: str, sources: list[str], build_dir: Path, include_dirs: list[str], cflags: list[str],
                  cuda_cflags: list[str] | None, ldflags: list[str], lock_fd: int | None = None) -> None:
    """Compile and link the extension ``name`` into ``build_dir`` (torch's ``cpp_extension.load``, in
    a child process group); a failed build raises a RuntimeError with torch's message (the compiler's
    output). ``lock_fd``: the build lock's descriptor, held by the child as long as it lives
    (``smgs.raster.buildlock.BuildLock.fd``)."""
    spec = dict(name=name, sources=sources, extra_include_paths=include_dirs, extra_cflags=cflags,
                extra_cuda_cflags=cuda_cflags, extra_ldflags=ldflags, build_directory=str(build_dir), verbose=False)
    done = run_in_group([sys.executable, "-c", _CHILD, json.dumps(spec), str(GRACE)],
                        pass_fds=() if lock_fd is None else (lock_fd,))
    if done.returncode != 0:
        raise RuntimeError(done.stderr.strip() or f"the build process ended with status {done.returncode}")
