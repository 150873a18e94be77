"""The SIMD layer of the compiled CPU kernels (smgs/raster/csrc/simd.h): accuracy of exp, log,
reciprocal and square root against float64 on every path this host runs, the path selection, and an
aarch64 (NEON) cross-compile of the layer and the compositing core."""

from __future__ import annotations

import os
import shutil
import subprocess
from pathlib import Path

import pytest

from smgs.raster import cpu, cpu_build

CSRC = Path(cpu.__file__).parent / "csrc"
CHECK = Path(__file__).parent / "simd_check.cpp"
FLAGS = ["-O2", "-std=c++17", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-Wno-psabi"]
# max ulp against float64, as simd.h states them
BOUNDS = {"vexp": 1.5, "vexp_kernel": 1.5, "vlog": 1.5, "vrcp": 1.0, "vrcp_unit": 1.0, "vsqrt_pos": 1.0,
          "vsqrt": 0.5}
CROSS = "aarch64-linux-gnu-g++"


def _cxx() -> str:
    cxx = os.environ.get("CXX", "c++")
    if shutil.which(cxx) is None:
        pytest.skip(f"no C++ compiler ({cxx!r} not on PATH)")
    return cxx


def test_simd_accuracy_and_lanes(cpu_isa, tmp_path):
    exe = tmp_path / "simd_check"
    subprocess.run([_cxx(), *FLAGS, *cpu_build.isa_flags(cpu_isa), f"-I{CSRC}", str(CHECK), "-o", str(exe)],
                   check=True, capture_output=True, text=True)
    out = subprocess.run([str(exe)], check=True, capture_output=True, text=True).stdout
    got = dict(line.split() for line in out.splitlines())
    assert got.pop("isa") == cpu_isa
    for name, bound in BOUNDS.items():
        assert float(got[name]) <= bound, (cpu_isa, name, got[name])
    assert got["special"] == "1" and got["masks"] == "1" and got["reduce16"] == "1", got


def test_isa_selection_errors(monkeypatch):
    with pytest.raises(ValueError, match="unknown CPU SIMD path"):
        cpu_build.isa_flags("sse9")
    monkeypatch.setenv(cpu_build.ISA_ENV, "sse9")
    with pytest.raises(ValueError, match="not a CPU SIMD path.*avx512, avx2, neon, scalar"):
        cpu_build.select_isa()
    foreign = next((i for i in cpu_build.ISAS if i not in cpu_build.host_isas()), None)
    if foreign is None:
        pytest.skip("this host runs every path")
    monkeypatch.setenv(cpu_build.ISA_ENV, foreign)
    with pytest.raises(RuntimeError, match=f"cannot run the {foreign} path"):
        cpu_build.select_isa()
    assert not cpu.is_available() and "cannot run" in cpu.unavailable_reason()
    monkeypatch.delenv(cpu_build.ISA_ENV)
    assert cpu_build.select_isa() == cpu_build.host_isas()[0]


def test_renderer_reports_its_path(cpu_isa):
    if not cpu.is_available():
        pytest.skip(f"cpu backend unavailable: {cpu.unavailable_reason()}")
    assert cpu.isa() == cpu_isa


def test_neon_cross_compiles(tmp_path):
    """The NEON path and the compositing core compile for aarch64 (without torch headers or
    OpenMP); -O1 for the core keeps the default suite short: the code is the same at -O3."""
    if shutil.which(CROSS) is None:
        pytest.skip(f"{CROSS} not installed (Debian: apt-get install g++-aarch64-linux-gnu)")
    flags = [*FLAGS, "-Wall", "-Werror", *cpu_build.isa_flags("neon"), f"-I{CSRC}", "-c"]
    jobs = [[CROSS, *flags, str(CHECK), "-o", str(tmp_path / "check.o")]]
    jobs += [[CROSS, *flags, "-O1", str(CSRC / f), "-o", str(tmp_path / f"{f}.o")]
             for f in ("cpu_fwd.cpp", "cpu_bwd.cpp", "cpu_bwd_soft.cpp")]
    procs = [subprocess.Popen(j, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True) for j in jobs]
    for j, p in zip(jobs, procs):
        out = p.communicate()[0]
        assert p.returncode == 0, f"{' '.join(j)}\n{out[-3000:]}"
    nm = shutil.which("aarch64-linux-gnu-nm") or shutil.which("nm")
    syms = subprocess.run([nm, "-C", str(tmp_path / "cpu_fwd.cpp.o")], capture_output=True, text=True).stdout
    assert "smgs::forward_tiles" in syms and "simd_isa" in syms
