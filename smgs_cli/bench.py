"""``smgs bench NAME [ARGS...]``: the benchmarks of bench/, run in this process as
``python -m bench.NAME`` from the checkout would run them.

bench/ is part of the source checkout, not of the installed packages (it reads benchmark scenes
beside the checkout and times trees of it), so the command finds it next to the installed sources,
as ``pip install -e .`` leaves them, and says so where it is missing."""

from __future__ import annotations

import runpy
import sys
from pathlib import Path

import protocols



def bench_dir() -> Path:
    return Path(protocols.__file__).resolve().parents[1] / "bench"


def benchmarks() -> list[str]:
    """The benchmark scripts of the checkout's bench/ (none where it is not there): the modules that
    run as a script, not the helpers they import (gpu_stages, gpu_report)."""
    return sorted(p.stem for p in bench_dir().glob("*.py")
                  if not p.stem.startswith("_") and 'if __name__ == "__main__"' in p.read_text())


def run_bench(args: list[str]) -> int:
    names = ", ".join(benchmarks()) or "none (bench/ is not there)"
    if not args or args[0] in ("-h", "--help"):
        print(f"usage: smgs bench NAME [ARGS...]  (smgs bench NAME --help: its options)\nbenchmarks: {names}")
        return 0 if args else 2
    name = args[0].replace("-", "_")
    script = bench_dir() / f"{name}.py"
    if name not in benchmarks() and script.parent.is_dir():
        print(f"smgs bench: unknown benchmark {args[0]!r}; the benchmarks are {names}", file=sys.stderr)
        return 2
    if not script.is_file():
        print(f"smgs bench: {script} is not there: the benchmarks run from a source checkout "
              "(git clone, then pip install --no-build-isolation -e .)", file=sys.stderr)
        return 2
    saved = sys.argv, list(sys.path)
    sys.argv = [str(script), *args[1:]]
    sys.path.insert(0, str(script.parent.parent))   # as `python -m bench.NAME` from the checkout
    try:
        runpy.run_module(f"bench.{name}", run_name="__main__", alter_sys=True)
    except SystemExit as e:  # the benchmarks end with sys.exit(main()) or SystemExit("why")
        if e.code is None or isinstance(e.code, int):
            return e.code or 0
        print(e.code, file=sys.stderr)   # as Python prints it for `python -m bench.NAME`
        return 1
    finally:
        sys.argv, sys.path[:] = saved[0], saved[1]
    return 0
