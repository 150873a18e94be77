"""Compile-and-load of one extension with ``torch.utils.cpp_extension.load``, cached by content.

The build directory is ``$TORCH_EXTENSIONS_DIR/<name>_<key>`` (torch's default root when unset),
where the key hashes everything that makes the library: the sources and every file they include
(``#include "..."``, followed through the include paths), the compiler flags and defines, what the
flags target (the CPU kind for ``-march=native``, the GPU archs) and the torch and Python versions.
Two checkouts, or two versions of smgs, sharing one cache therefore never load each other's
library; the same sources built twice share one.

The compilers run in a process group of their own (``smgs.raster.buildproc``): an interrupted or
killed build leaves none of them running. A finished build leaves ``smgs-build.json`` beside its
library; later processes load the library directly (well under a second). Builds are serialised
by ``BuildLock``; each is announced with the duration of the last build of that extension
(remembered in ``<root>/smgs-build-times.json``) and its own duration is logged when it ends.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
import logging
import os
import platform
import re
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Callable

import torch

from smgs.atomic import atomic_write_text
from smgs.raster.buildlock import BuildLock
from smgs.raster.buildproc import build_library

log = logging.getLogger(__name__)

MARKER = "smgs-build.json"
TIMES = "smgs-build-times.json"
_INCLUDE = re.compile(r'^\s*#\s*include\s*"([^"]+)"', re.M)


@dataclass(frozen=True)
class ExtensionSpec:
    """What to compile: ``name`` (a Python identifier; the key is appended), the sources, the
    include paths, the flags (defines included) and ``target``, what the flags compile for beyond
    their text (e.g. the CPU kind behind ``-march=native``)."""

    name: str
    sources: tuple[Path, ...]
    what: str = "compiled extension"
    include_dirs: tuple[Path, ...] = ()
    cflags: tuple[str, ...] = ()
    cuda_cflags: tuple[str, ...] = ()
    ldflags: tuple[str, ...] = ()
    target: str = ""


def source_closure(sources: tuple[Path, ...], include_dirs: tuple[Path, ...]) -> list[Path]:
    """The sources and every local file they include, transitively (sorted, no duplicates).
    Quoted includes found neither beside the includer nor in ``include_dirs`` (torch's, the
    system's) are not ours and are left out."""
    seen: dict[Path, None] = {}
    todo = [Path(s).resolve() for s in sources]
    while todo:
        p = todo.pop()
        if p in seen:
            continue
        seen[p] = None
        for inc in _INCLUDE.findall(p.read_text(errors="replace")):
            for base in (p.parent, *include_dirs):
                cand = (Path(base) / inc)
                if cand.is_file():
                    todo.append(cand.resolve())
                    break
    return sorted(seen)


def build_key(spec: ExtensionSpec) -> str:
    """Hex digest of everything that makes the library (see the module docstring)."""
    h = hashlib.sha256()

    def put(*parts: object) -> None:
        for x in parts:
            b = str(x).encode()
            h.update(len(b).to_bytes(8, "little") + b)

    put("smgs-build-1", spec.name, torch.__version__, torch.version.cuda, sys.version_info[:2],
        sys.implementation.cache_tag, platform.machine(), spec.target, os.environ.get("CXX", "c++"))
    for group in (spec.cflags, spec.cuda_cflags, spec.ldflags):
        put(len(group), *group)
    for p in source_closure(spec.sources, spec.include_dirs):
        put(p.name)
        h.update(p.read_bytes())
    return h.hexdigest()


def extensions_root() -> Path:
    from torch.utils.cpp_extension import get_default_build_root

    return Path(os.environ.get("TORCH_EXTENSIONS_DIR") or get_default_build_root())


def module_name(spec: ExtensionSpec) -> str:
    return f"{spec.name}_{build_key(spec)[:16]}"


def _library(build_dir: Path, name: str) -> Path:
    from torch.utils.cpp_extension import LIB_EXT

    return build_dir / f"{name}{LIB_EXT}"


def _import(name: str, path: Path) -> ModuleType:
    spec = importlib.util.spec_from_file_location(name, path)
    if spec is None or spec.loader is None:
        raise ImportError(f"cannot load the compiled extension {path}")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _atomic_json(path: Path, data: dict) -> None:
    atomic_write_text(path, json.dumps(data, indent=1))


def _read_json(path: Path) -> dict:
    try:
        d = json.loads(path.read_text())
        return d if isinstance(d, dict) else {}
    except (OSError, ValueError):
        return {}


def last_build_seconds(root: Path, name: str) -> float | None:
    """How long the last build of extension ``name`` took under ``root``, if one was recorded."""
    v = _read_json(root / TIMES).get(name)
    return float(v) if isinstance(v, (int, float)) else None


def _remember(root: Path, name: str, seconds: float) -> None:
    times = _read_json(root / TIMES)   # a lost update between two builds only loses an estimate
    times[name] = round(seconds, 1)
    _atomic_json(root / TIMES, times)


def _say(msg: str) -> None:
    """To the log when something will show it at info level, else to stderr: a build that runs
    for minutes must never be silent."""
    if log.isEnabledFor(logging.INFO) and log.hasHandlers():
        log.info(msg)
    else:
        print(f"smgs: {msg}", file=sys.stderr, flush=True)


def _heartbeat(what: str, expected: float | None, every_s: float, say: Callable[[str], None]) -> threading.Event:
    """Says every ``every_s`` that the build still runs (one line each: a log file can hold it)."""
    stop = threading.Event()
    start = time.monotonic()

    def run() -> None:
        while not stop.wait(every_s):
            tail = f" of ~{expected:.0f} s expected" if expected else ""
            say(f"still building the {what}: {time.monotonic() - start:.0f} s{tail}")

    threading.Thread(target=run, daemon=True, name="smgs-build-heartbeat").start()
    return stop


def compile_and_load(spec: ExtensionSpec, say: Callable[[str], None] = _say, heartbeat_s: float = 60.0) -> ModuleType:
    """The module of ``spec``: loaded from the cache when built before, else built (announced,
    timed) under the build lock. Raises what the compiler raised (torch puts its output in the
    message)."""
    name = module_name(spec)
    root = extensions_root()
    build_dir = root / name
    lib = _library(build_dir, name)
    if _read_json(build_dir / MARKER).get("module") == name and lib.is_file():
        return _import(name, lib)
    with BuildLock(build_dir, spec.what, say=say) as lock:
        if _read_json(build_dir / MARKER).get("module") == name and lib.is_file():
            return _import(name, lib)   # built by the process we waited for
        expected = last_build_seconds(root, spec.name)
        guess = (f"the last build of it here took {expected:.0f} s" if expected is not None else
                 "no earlier build of it recorded here to estimate the duration")
        say(f"building the {spec.what} ({name}) in {build_dir}; {guess}. It is built once and cached.")
        start = time.perf_counter()
        stop = _heartbeat(spec.what, expected, heartbeat_s, say)
        try:   # in a process group of its own, stopped whole if this process is interrupted
            build_library(name, [str(s) for s in spec.sources], build_dir, [str(i) for i in spec.include_dirs],
                          list(spec.cflags), list(spec.cuda_cflags) or None, list(spec.ldflags), lock.fd)
            module = _import(name, lib)
        finally:
            stop.set()
        seconds = time.perf_counter() - start
        _remember(root, spec.name, seconds)
        _atomic_json(build_dir / MARKER, {"module": name, "seconds": round(seconds, 1),
                                          "built": time.strftime("%Y-%m-%dT%H:%M:%S%z"),
                                          "sources": [str(p) for p in source_closure(spec.sources, spec.include_dirs)],
                                          "cflags": list(spec.cflags), "cuda_cflags": list(spec.cuda_cflags),
                                          "ldflags": list(spec.ldflags), "target": spec.target,
                                          "torch": torch.__version__})
        say(f"built the {spec.what} in {seconds:.1f} s")
        return module
