"""The just-in-time build machinery on a trivial extension (tests/data/tiny_ext, pybind11 only, a
few seconds to compile): a build cache keyed by content, a lock that survives a killed build, the
build announced and timed, a failed build that stops the caller."""

from __future__ import annotations

import json
import os
import re
import shutil
import signal
import subprocess
import sys
import time
from dataclasses import replace
from pathlib import Path

import pytest
import torch

from smgs.raster.buildcache import ExtensionSpec, build_key, source_closure
from smgs.raster.buildlock import LOCK_FILE, TORCH_LOCK_FILE, BuildLock, BuildLockTimeout
from smgs.raster.buildproc import session_members
from smgs.raster.cpu_build import cpu_extension
from smgs.raster.jit import BuildError

REPO = Path(__file__).resolve().parent.parent
TINY = Path(__file__).parent / "data" / "tiny_ext"

# one build through the same path as the real kernels (cpu_extension), in its own process
BUILD = """
import json, signal, sys
from pathlib import Path
from smgs.raster.cpu_build import cpu_extension
if sys.argv[2:] == ["harness"]:   # SIGTERM as smgs run takes it: an exception in the main thread
    from protocols.executors import on_sigterm
    signal.signal(signal.SIGTERM, on_sigterm)
src = Path(sys.argv[1])
m = cpu_extension("smgs_test_tiny", [src / "tiny.cpp"], "test kernel", [src]).module()
print(json.dumps({"answer": m.answer(), "file": m.__file__}))
"""

HOLD = """
import sys, time
from pathlib import Path
from smgs.raster.buildlock import BuildLock
with BuildLock(Path(sys.argv[1]), "held kernel"):
    print("held", flush=True)
    time.sleep(120)
"""


def checkout(tmp_path: Path, name: str, value: object) -> Path:
    """A copy of the tiny sources, as another checkout would have them."""
    d = tmp_path / name
    d.mkdir()
    shutil.copy(TINY / "tiny.cpp", d)
    (d / "value.h").write_text(f"#define VALUE {value}\n")
    return d


def build(src: Path, root: Path, timeout: float = 240) -> tuple[dict, str]:
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(root))
    p = subprocess.run([sys.executable, "-c", BUILD, str(src)], env=env, cwd=REPO, capture_output=True,
                       text=True, timeout=timeout)
    assert p.returncode == 0, p.stderr[-3000:]
    return json.loads(p.stdout.strip().splitlines()[-1]), p.stderr


def _ppid(proc: Path) -> int | None:
    try:
        return int((proc / "stat").read_text().rsplit(")", 1)[1].split()[1])
    except (OSError, ValueError, IndexError):
        return None


def dead_pid() -> int:
    p = subprocess.Popen([sys.executable, "-c", "pass"])
    p.wait()
    return p.pid


# ---- the cache key ------------------------------------------------------------------------------

def test_key_follows_the_sources_their_includes_the_flags_and_torch(tmp_path, monkeypatch):
    a, same = checkout(tmp_path, "a", 11), checkout(tmp_path, "same", 11)
    spec = ExtensionSpec("x", (a / "tiny.cpp",), include_dirs=(a,), cflags=("-O3",))
    assert source_closure(spec.sources, spec.include_dirs) == [a / "tiny.cpp", a / "value.h"]
    key = build_key(spec)
    # the same sources in another folder share the build
    assert build_key(replace(spec, sources=(same / "tiny.cpp",), include_dirs=(same,))) == key
    assert build_key(replace(spec, cflags=("-O3", "-DEXTRA=1"))) != key
    assert build_key(replace(spec, cflags=("-O2",))) != key
    assert build_key(replace(spec, target="another CPU")) != key
    (a / "value.h").write_text("#define VALUE 12\n")      # only an included header changes
    key12 = build_key(spec)
    assert key12 != key
    monkeypatch.setattr(torch, "__version__", "0.0.1")
    assert build_key(spec) != key12


def test_two_checkouts_build_apart_and_every_build_is_announced_and_timed(tmp_path):
    root = tmp_path / "ext"
    a, b = checkout(tmp_path, "a", 11), checkout(tmp_path, "b", 12)
    ra, err = build(a, root)
    assert ra["answer"] == 11
    assert "building the test kernel" in err and str(root) in err and "no earlier build" in err, err
    assert re.search(r"built the test kernel in \d+\.\d s", err), err
    rb, err = build(b, root)    # another checkout, same extension name, other sources: its own library
    assert rb["answer"] == 12 and Path(rb["file"]).parent != Path(ra["file"]).parent
    assert re.search(r"the last build of it here took \d+ s", err), err
    ra2, err = build(a, root)   # back to the first: loaded from the cache, not rebuilt
    assert ra2 == ra and "building" not in err, err
    rc, err = build(checkout(tmp_path, "c", 11), root)   # identical sources elsewhere share the build
    assert rc == ra and "building" not in err, err


# ---- the lock -----------------------------------------------------------------------------------

def test_a_stale_torch_lock_of_a_dead_builder_is_removed_and_named(tmp_path):
    d = tmp_path / "ext" / "smgs_x"
    d.mkdir(parents=True)
    pid = dead_pid()
    (d / LOCK_FILE).write_text(json.dumps({"pid": pid, "host": "h", "since": time.time(), "what": "x"}))
    (d / TORCH_LOCK_FILE).write_text("")
    said: list[str] = []
    with BuildLock(d, "x", timeout=10, say=said.append):
        assert not (d / TORCH_LOCK_FILE).exists()
        assert json.loads((d / LOCK_FILE).read_text())["pid"] == os.getpid()
    assert any(f"pid {pid}" in s and "killed build" in s for s in said), said


def test_a_waiter_names_the_live_owner_and_proceeds_when_it_dies(tmp_path):
    d = tmp_path / "ext" / "smgs_x"
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(d)], cwd=REPO, stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        said: list[str] = []
        with pytest.raises(BuildLockTimeout, match=f"pid {holder.pid} .*held kernel"):
            with BuildLock(d, "x", timeout=0.5, say=said.append, poll_s=0.05):
                pass
        assert said and f"pid {holder.pid}" in said[0] and "waiting" in said[0]
        holder.send_signal(signal.SIGKILL)   # the OS releases its lock
        with BuildLock(d, "x", timeout=30, say=said.append, poll_s=0.05):
            pass
    finally:
        holder.kill()
        holder.wait()


def test_a_build_killed_midway_does_not_block_the_next(tmp_path):
    root, a = tmp_path / "ext", checkout(tmp_path, "a", 11)
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(root))
    # a build killed with its compiler (Ctrl-C, a killed sweep cell), while torch's lock file exists
    p = subprocess.Popen([sys.executable, "-c", BUILD, str(a)], env=env, cwd=REPO, start_new_session=True,
                         stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 120
    while not list(root.glob(f"*/{TORCH_LOCK_FILE}")):
        assert p.poll() is None, "the build ended before it could be killed"
        assert time.monotonic() < deadline, "the build never started"
        time.sleep(0.02)
    # the build's own process and its compilers' session with it (all killed at once: kill -9 of
    # everything, the OOM killer), so that nothing cleans up after it
    builders = [int(d.name) for d in Path("/proc").glob("[0-9]*") if _ppid(d) == p.pid]
    os.killpg(p.pid, signal.SIGKILL)
    for _ in range(2):
        for pid in [m for b in builders for m in session_members(b)]:
            os.kill(pid, signal.SIGKILL)
    p.wait()
    assert list(root.glob(f"*/{TORCH_LOCK_FILE}")), "the killed build should have left torch's lock"
    # the next build must proceed: a hang here (waiting on that lock) fails by the timeout
    r, err = build(a, root, timeout=180)
    assert r["answer"] == 11
    assert f"pid {p.pid}" in err and "killed build" in err, err
    assert not list(root.glob(f"*/{TORCH_LOCK_FILE}"))


# A header that keeps the compiler busy for minutes (a constexpr loop): a build that is stopped must
# stop it, not wait for it.
SLOW_VALUE = """#define VALUE 11
constexpr long smgs_slow() {
    long s = 0;
    for (long i = 0; i < 100000; ++i)
        for (long j = 0; j < 100000; ++j) s += (i ^ j) & 1;
    return s;
}
static_assert(smgs_slow() >= 0, "keeps the compiler busy");
"""


def _builders(src: Path, but: int) -> dict[int, str]:
    """pid -> (name, command line) of every process but ``but`` whose command line names ``src``."""
    out = {}
    for proc in Path("/proc").glob("[0-9]*"):
        try:
            cmd = (proc / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
            name = (proc / "comm").read_text().strip()
        except OSError:
            continue
        if str(src) in cmd and int(proc.name) != but:
            out[int(proc.name)] = f"{name}: {cmd[:120]}"
    return out


@pytest.mark.skipif(not Path("/proc/self/cmdline").exists(), reason="finds the compilers in /proc")
@pytest.mark.parametrize("handler", ["harness", "default"])
def test_sigterm_while_the_compilers_run_leaves_none_of_them_running(tmp_path, handler):
    """SIGTERM to a process building a kernel (``smgs run`` turns it into an exception; a plain
    script dies of it) stops the build's compilers too: none is left orphaned."""
    root, src = tmp_path / "ext", checkout(tmp_path, "slow", 11)
    (src / "value.h").write_text(SLOW_VALUE)
    env = dict(os.environ, TORCH_EXTENSIONS_DIR=str(root))
    p = subprocess.Popen([sys.executable, "-c", BUILD, str(src), handler], env=env, cwd=REPO,
                         stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 180
        while not any(v.startswith("cc1plus") for v in _builders(src, p.pid).values()):
            assert p.poll() is None, p.stderr.read()[-3000:]
            assert time.monotonic() < deadline, "the compiler never started"
            time.sleep(0.02)
        p.send_signal(signal.SIGTERM)
        p.wait(60)
        deadline = time.monotonic() + 5   # the build's child notices its parent gone within 0.5 s
        while _builders(src, p.pid) and time.monotonic() < deadline:
            time.sleep(0.05)
        assert _builders(src, p.pid) == {}, "left running after SIGTERM"
    finally:
        for pid in _builders(src, p.pid):   # what a build without the fix leaves
            os.kill(pid, signal.SIGKILL)
        p.kill()
        p.wait()


# ---- failures -----------------------------------------------------------------------------------

def test_a_failed_build_raises_with_the_compiler_output_and_the_fix(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_EXTENSIONS_DIR", str(tmp_path / "ext"))
    src = checkout(tmp_path, "bad", "undeclared_name_xyz")
    ext = cpu_extension("smgs_test_tiny", [src / "tiny.cpp"], "test kernel", [src])
    with pytest.raises(BuildError, match="undeclared_name_xyz") as e:
        ext.is_available()
    assert "SMGS_DISABLE_CPU_BACKEND=1" in str(e.value)
    with pytest.raises(BuildError):   # not retried, the same error again
        ext.module()


def test_no_compiler_means_unavailable_not_an_error(monkeypatch):
    monkeypatch.setenv("CXX", "no-such-compiler-xyz")
    ext = cpu_extension("smgs_test_tiny", [TINY / "tiny.cpp"], "test kernel", [TINY])
    assert not ext.is_available()
    assert "no C++ compiler" in ext.unavailable_reason()
