"""Fill ``.gpu/`` (ignored by git) with what the GPU check (bench/gpu_check.py) needs on a GPU
machine that has no internet and lacks some of the project's packages: their wheels for the GPU
machine's Python, unpacked into ``.gpu/site`` (put on PYTHONPATH by the check), and copies of the
benchmark scenes and the fox scene in ``.gpu/shared``. Run it here, where there is a package
registry, then carry ``.gpu/site`` and ``.gpu/shared`` with the checkout (docs/gpu/README.md).

    python tools/gpu_bundle.py                         # download, unpack, copy, print the sizes
    python tools/gpu_bundle.py --skip-download         # unpack what is in .gpu/wheels again

The packages are pinned to the versions installed here (what the tests ran with), else to the
versions the project was run with before. ``antlr4-python3-runtime`` 4.9.3 (omegaconf's parser) has
no wheel on the index: it is built here from its source release. Any other wheel put into
``.gpu/wheels`` (e.g. gsplat's, for the side-by-side timing) is unpacked with them.
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
from importlib import metadata
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
# what the GPU machine lacks (its torch, numpy, scipy, opencv, pillow, ... are there), with the
# versions used before where this machine has none installed
WHEELS = {"hydra-core": "1.3.2", "omegaconf": "2.3.0", "plyfile": "1.1", "flip-evaluator": "1.6", "submitit": "1.5.2"}
FROM_SOURCE = {"antlr4-python3-runtime": "4.9.3"}
PLATFORMS = ("manylinux_2_28_x86_64", "manylinux_2_17_x86_64", "manylinux2014_x86_64", "linux_x86_64")
CARRY_LIMIT_MIB = 64


def pinned(name: str, fallback: str) -> str:
    try:
        return f"{name}=={metadata.version(name)}"
    except metadata.PackageNotFoundError:
        return f"{name}=={fallback}"


def target_flags(python: str) -> list[str]:
    plats = [f"--platform={p}" for p in PLATFORMS]
    return ["--python-version", python, "--implementation", "cp", *plats, "--only-binary=:all:", "--no-deps"]


def pip(*args: str) -> None:
    cmd = [sys.executable, "-m", "pip", *args]
    print("+", " ".join(cmd), flush=True)
    subprocess.run(cmd, check=True)


def download(wheels: Path, python: str) -> None:
    wheels.mkdir(parents=True, exist_ok=True)
    pip("download", "-d", str(wheels), *target_flags(python), *(pinned(n, v) for n, v in WHEELS.items()))
    for name, version in FROM_SOURCE.items():   # sdist only: a pure-Python wheel built here
        pip("wheel", "--no-deps", "-w", str(wheels), f"{name}=={version}")


def unpack(wheels: Path, site: Path, python: str) -> None:
    """Every wheel in ``wheels`` installed into the plain folder ``site`` for the target Python."""
    found = sorted(wheels.glob("*.whl"))
    if not found:
        raise SystemExit(f"no wheels in {wheels}: run without --skip-download first")
    if site.exists():
        shutil.rmtree(site)
    pip("install", "--no-index", "--no-compile", "--target", str(site), *target_flags(python), *map(str, found))


def copy_shared(shared: Path, dest: Path) -> None:
    for part in ("bench", "data/fox"):
        src = shared / part
        if not src.is_dir():
            raise SystemExit(f"{src} is missing: the GPU check needs it (give --shared, the folder with "
                             "bench/ and data/fox)")
        shutil.copytree(src, dest / part, dirs_exist_ok=True)


def size_mib(path: Path) -> float:
    return sum(f.stat().st_size for f in path.rglob("*") if f.is_file()) / 2**20


def check_size(paths: list[Path], limit_mib: float = CARRY_LIMIT_MIB) -> float:
    """Total MiB of ``paths``; a SystemExit naming each where they exceed what travels with the checkout."""
    sizes = {p: size_mib(p) for p in paths}
    total = sum(sizes.values())
    if total > limit_mib:
        parts = ", ".join(f"{p.name} {s:.1f} MiB" for p, s in sizes.items())
        raise SystemExit(f"the bundle is {total:.1f} MiB ({parts}), over the {limit_mib} MiB that travel with the "
                         "checkout: leave out a wheel or the fox images")
    return total


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--out", type=Path, default=ROOT / ".gpu")
    ap.add_argument("--shared", type=Path, default=ROOT.parent / "shared")
    ap.add_argument("--python", default="3.12", help="the GPU machine's Python (default 3.12)")
    ap.add_argument("--skip-download", action="store_true")
    args = ap.parse_args(argv)
    wheels, site, shared = args.out / "wheels", args.out / "site", args.out / "shared"
    if not args.skip_download:
        download(wheels, args.python)
    unpack(wheels, site, args.python)
    copy_shared(args.shared, shared)
    total = check_size([site, shared])
    for p in (wheels, site, shared):
        print(f"{p}: {size_mib(p):.1f} MiB")
    print(f"to carry: {site.relative_to(ROOT) if site.is_relative_to(ROOT) else site} and "
          f"{shared.relative_to(ROOT) if shared.is_relative_to(ROOT) else shared}, {total:.1f} MiB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
