"""Registers, spills and stack of every CUDA kernel of smgs, from ptxas (no GPU needed).

    python tools/ptxas_report.py [--arch sm_90] [--keep DIR]

Compiles each CUDA source with the flags its extension is built with (smgs/raster/cuda.py,
cuda_v2.py, projection_cuda.py) plus ``-Xptxas -v`` and prints one markdown row per kernel
instantiation: registers, spill stores/loads (bytes), stack frame (bytes), and the blocks of its
launch size a multiprocessor holds by registers alone (65536 registers, allocated per warp in
units of 256). docs/cuda.md keeps the table; tests/test_raster_cuda_v2_build.py uses the same
parser to hold the spill-free kernels to it. ``--keep DIR`` leaves the PTX there.
"""

from __future__ import annotations

import argparse
import os
import re
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
CSRC = ROOT / "smgs" / "raster" / "csrc"


@dataclass(frozen=True)
class Kernel:
    source: str
    name: str          # demangled, namespaces and anonymous namespaces dropped
    registers: int
    spill_stores: int
    spill_loads: int
    stack: int

    def blocks_per_sm(self, threads: int = 256) -> int:
        """Blocks of ``threads`` a multiprocessor holds by registers alone (sm_80/sm_90: 64K
        registers, per-warp allocation rounded up to 256)."""
        per_warp = -(-max(self.registers, 1) * 32 // 256) * 256
        return min(65536 // (per_warp * -(-threads // 32)), 2048 // threads)


def sources() -> list[tuple[str, list[str]]]:
    """(source file, nvcc flags of its extension) for every CUDA source."""
    import sys

    sys.path.insert(0, str(ROOT))
    from smgs.raster import cuda, cuda_v2, projection_cuda

    return [("cuda_kernel.cu", list(cuda.CUDA_CFLAGS)), ("cuda_v2_kernel.cu", list(cuda_v2.CUDA_CFLAGS)),
            ("cuda_pixel.cu", list(cuda_v2.CUDA_CFLAGS)), ("projection_cuda.cu", list(projection_cuda.CUDA_CFLAGS))]


def nvcc() -> str | None:
    found = shutil.which("nvcc")
    if found:
        return found
    for home in (os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"), "/usr/local/cuda"):
        if home and (Path(home) / "bin" / "nvcc").is_file():
            return str(Path(home) / "bin" / "nvcc")
    return None


def compile_command(nv: str, source: str, flags: list[str], arch: str, out_dir: Path) -> list[str]:
    """nvcc to an object file with ptxas's report, warnings as errors, the PTX kept in out_dir."""
    return [nv, "-c", f"-arch={arch}", "-std=c++20", *flags, "-Xptxas", "-v", "-Werror", "all-warnings",
            "-Xcompiler", "-Wall,-Wextra,-Werror", "-keep", "-keep-dir", str(out_dir), f"-I{CSRC}",
            str(CSRC / source), "-o", str(out_dir / (Path(source).stem + ".o"))]


def _demangle(names: list[str]) -> list[str]:
    filt = shutil.which("c++filt")
    if filt is None:
        return names
    out = subprocess.run([filt], input="\n".join(names), capture_output=True, text=True).stdout.splitlines()
    return out if len(out) == len(names) else names


def _short(name: str) -> str:
    name = re.sub(r"\(anonymous namespace\)::|smgs::(cuda::)?((v2|pixel)::)?", "", name)
    name = re.sub(r"\(.*\)$", "", name)   # parameter list
    return name.replace("void ", "")


def parse(source: str, text: str) -> list[Kernel]:
    """The kernels of one ptxas -v report."""
    rows: list[tuple[str, int, int, int, int]] = []
    current = None
    spills = (0, 0, 0)
    for line in text.splitlines():
        m = re.search(r"Compiling entry function '(\w+)'", line)
        if m:
            current = m.group(1)
            spills = (0, 0, 0)
            continue
        m = re.search(r"(\d+) bytes stack frame, (\d+) bytes spill stores, (\d+) bytes spill loads", line)
        if m and current:
            spills = (int(m.group(2)), int(m.group(3)), int(m.group(1)))
            continue
        m = re.search(r"Used (\d+) registers", line)
        if m and current:
            rows.append((current, int(m.group(1)), *spills))
            current = None
    names = _demangle([r[0] for r in rows])
    return [Kernel(source, _short(n), r, ss, sl, st) for n, (_, r, ss, sl, st) in zip(names, rows)]


def report(arch: str = "sm_90", keep: Path | None = None) -> tuple[list[Kernel], dict[str, str]]:
    """Every kernel of every source, and each source's compiler output (for errors)."""
    nv = nvcc()
    if nv is None:
        raise RuntimeError("nvcc not found (PATH, CUDA_HOME, /usr/local/cuda)")
    with tempfile.TemporaryDirectory() as tmp:
        out_dir = keep or Path(tmp)
        out_dir.mkdir(parents=True, exist_ok=True)
        procs = {src: subprocess.Popen(compile_command(nv, src, flags, arch, out_dir), stdout=subprocess.PIPE,
                                       stderr=subprocess.STDOUT, text=True) for src, flags in sources()}
        logs = {src: p.communicate()[0] for src, p in procs.items()}
        for src, p in procs.items():
            if p.returncode != 0:
                raise RuntimeError(f"{src} failed to compile:\n{logs[src][-4000:]}")
    return [k for src in logs for k in parse(src, logs[src])], logs


def markdown(kernels: list[Kernel]) -> str:
    lines = ["| source | kernel | registers | spill stores / loads (B) | stack (B) | blocks of 256 / SM by registers |",
             "|---|---|--:|--:|--:|--:|"]
    for k in kernels:
        if k.name.startswith("cub::"):   # the library's binning kernels
            continue
        lines.append(f"| {k.source} | `{k.name}` | {k.registers} | {k.spill_stores} / {k.spill_loads} | {k.stack} | "
                     f"{k.blocks_per_sm()} |")
    return "\n".join(lines)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--arch", default="sm_90")
    ap.add_argument("--keep", type=Path, default=None, help="folder to keep the PTX in")
    args = ap.parse_args()
    kernels, _ = report(args.arch, args.keep)
    print(markdown(kernels))


if __name__ == "__main__":
    main()
