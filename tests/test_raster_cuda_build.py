"""The CUDA backend's sources compile, warnings as errors, on a machine without a GPU.

nvcc compiles csrc/cuda_kernel.cu (kernels, launchers, cub binning; no torch headers) to an object
file for one architecture (sm_80), with the flags smgs/raster/cuda.py gives the JIT build. The torch
binding (csrc/cuda_binding.cpp) is checked by the host compiler against this torch's headers and the
CUDA toolkit's headers (-fsyntax-only: a CPU build of torch has no CUDA libraries to link). Both
compile at once to keep the test short. Skipped, with the reason, where nvcc or a C++ compiler is
missing. Nothing here runs CUDA code: tests/test_raster_cuda.py (marked gpu) does.
"""

import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

from smgs.raster import cuda as cuda_backend

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tools"))
from ptxas_report import nvcc as _nvcc  # noqa: E402   (where nvcc is: PATH, CUDA_HOME, /usr/local/cuda)

CSRC = Path(cuda_backend.__file__).parent / "csrc"
TIMEOUT_S = 600   # a shared 2-core machine under load; normally ~20 s and ~50 s


def _cuda_include(nvcc: str) -> Path | None:
    """The toolkit's include directory (nvcc may be a copy outside the toolkit, as on this machine)."""
    homes = [Path(nvcc).resolve().parent.parent, os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"),
             "/usr/local/cuda"]
    for home in homes:
        if home and (Path(home) / "include" / "cuda_runtime_api.h").is_file():
            return Path(home) / "include"
    return None


def _run_all(cmds: dict[str, list[str]]) -> dict[str, subprocess.CompletedProcess]:
    procs = {k: subprocess.Popen(c, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for k, c in cmds.items()}
    out = {}
    for k, p in procs.items():
        try:
            text, _ = p.communicate(timeout=TIMEOUT_S)
        except subprocess.TimeoutExpired:
            p.kill()
            text, _ = p.communicate()
        out[k] = subprocess.CompletedProcess(cmds[k], p.returncode, text)
    return out


def test_cuda_sources_compile_without_warnings(tmp_path):
    nvcc = _nvcc()
    if nvcc is None:
        pytest.skip("nvcc not found (PATH, CUDA_HOME, /usr/local/cuda): the CUDA kernel cannot be compiled here")
    release = re.search(r"release (\d+)\.(\d+)", subprocess.run([nvcc, "--version"], capture_output=True,
                                                                   text=True).stdout)
    if release is None or int(release.group(1)) < 12:
        pytest.skip(f"{nvcc} is not CUDA >= 12 (what a torch 2.13 CUDA build needs, and C++20)")
    if shutil.which("g++") is None and shutil.which("c++") is None:
        pytest.skip("no host C++ compiler for nvcc")
    cmds = {"kernel": [nvcc, "-c", "-arch=sm_80", "-std=c++20", *cuda_backend.CUDA_CFLAGS,
                       "-Werror", "all-warnings", "-Xcompiler", "-Wall,-Wextra,-Werror", f"-I{CSRC}",
                       str(CSRC / "cuda_kernel.cu"), "-o", str(tmp_path / "cuda_kernel.o")]}
    cxx = shutil.which(os.environ.get("CXX", "c++"))
    cuda_include = _cuda_include(nvcc)
    binding_checked = cxx is not None and cuda_include is not None
    if binding_checked:
        from torch.utils.cpp_extension import include_paths

        # the cmake-generated c10/cuda macros header ships only with CUDA builds of torch
        cmds["binding"] = [cxx, "-std=c++20", "-fsyntax-only", "-Wall", "-Werror",
                           "-DC10_CUDA_NO_CMAKE_CONFIGURE_FILE", "-DTORCH_EXTENSION_NAME=smgs_raster_cuda_check",
                           *[f"-I{p}" for p in include_paths()], f"-I{sysconfig.get_paths()['include']}",
                           f"-I{cuda_include}", f"-I{CSRC}", str(CSRC / "cuda_binding.cpp")]
    res = _run_all(cmds)
    for name, r in res.items():
        assert r.returncode == 0, f"{name}: {' '.join(r.args)}\n{r.stdout[-6000:]}"
    obj = tmp_path / "cuda_kernel.o"
    assert obj.stat().st_size > 0
    if not binding_checked:
        pytest.skip("kernel compiled; the torch binding was not checked (no C++ compiler or CUDA headers)")


def test_cuda_kernel_takes_the_per_splat_math_from_the_shared_header():
    """splat_math.h is the only place of the forward step and its adjoint: the kernel includes it
    and defines none of its functions or types again."""
    header = (CSRC / "splat_math.h").read_text()
    kernel = (CSRC / "cuda_kernel.cu").read_text()
    assert re.search(r'^#include "splat_math.h"', kernel, re.M)
    names = set(re.findall(r"^SMGS_HD inline [\w<>:, ]+?\b(\w+)\(", header, re.M))
    names |= set(re.findall(r"^struct (\w+)", header, re.M))
    assert {"softmax_fwd", "softmax_bwd", "splat_quad", "splat_absorb", "splat_kernel_bwd", "vanilla_coef",
            "vanilla_coef_bwd", "SoftFwd", "Coef"} <= names
    for name in names:
        definition = re.compile(rf"^(?!\s*//).*(\bstruct\s+{name}\b|^\S.*\b{name}\s*\([^;]*$)", re.M)
        hits = [m.group(0) for m in definition.finditer(kernel) if "=" not in m.group(0)]
        assert not hits, f"cuda_kernel.cu redefines {name}: {hits}"
    for call in ("softmax_fwd(", "softmax_bwd(", "splat_quad(", "splat_absorb<", "splat_kernel_bwd<",
                 "vanilla_coef(", "vanilla_coef_bwd("):
        assert call in kernel, f"the kernel does not use {call}"
