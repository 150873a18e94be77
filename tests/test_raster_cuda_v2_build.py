"""The opt-in CUDA kernels (csrc/projection_cuda.cu, csrc/cuda_v2_kernel.cu) compile, warnings as
errors, on a machine without a GPU, with the flags their extensions are built with; what ptxas and
the PTX say about them holds (tools/ptxas_report.py prints the full table, kept in docs/cuda.md):

* no spills and no stack in the v2 backward and the projection kernels (the v2 backward's launch
  bounds are chosen for that);
* the v2 softmax backward reads and writes its head records as float4 (whole 32-byte records);
* the v2 kernels use the hardware reciprocal, the default kernels never (the opt-in leaves the
  default build alone), and the reach arithmetic is explicitly unfused (mul.rn);
* the projection's PTX has no FMA: built as the CPU projection is, the two give the same bits;
* the per-pixel order's key (peak_depth) is unfused where cuda_pixel.cu contracts the rest.

The torch bindings are checked by the host compiler against this torch's headers (~30 s for both,
side by side, on two cores: in the default run, as the v2 binding once went uncompilable for weeks
when it was marked slow). Skipped, with the reason, where nvcc or a C++ compiler is missing. Nothing here
runs CUDA code: tests/test_raster_cuda_v2.py and tests/test_raster_projection_cuda.py (marked gpu) do.
"""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import sysconfig
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tools"))

import ptxas_report  # noqa: E402

CSRC = ptxas_report.CSRC
TIMEOUT_S = 900   # a shared 2-core machine under load; normally ~30 s


def _nvcc_or_skip() -> str:
    nv = ptxas_report.nvcc()
    if nv is None:
        pytest.skip("nvcc not found (PATH, CUDA_HOME, /usr/local/cuda): the CUDA kernels cannot be compiled here")
    release = re.search(r"release (\d+)\.", subprocess.run([nv, "--version"], capture_output=True, text=True).stdout)
    if release is None or int(release.group(1)) < 12:
        pytest.skip(f"{nv} is not CUDA >= 12")
    if shutil.which("g++") is None and shutil.which("c++") is None:
        pytest.skip("no host C++ compiler for nvcc")
    return nv


def _ptx_functions(ptx: str) -> dict[str, str]:
    """Entry name -> body of each kernel in a PTX file."""
    parts = re.split(r"\n(?:\.visible )?\.entry ", ptx)
    return {p.split("(", 1)[0]: p for p in parts[1:]}


@pytest.fixture(scope="module")
def compiled(tmp_path_factory):
    nv = _nvcc_or_skip()
    out = tmp_path_factory.mktemp("cuda_v2_build")
    flags = dict(ptxas_report.sources())
    procs = {}
    for src in ("projection_cuda.cu", "cuda_v2_kernel.cu", "cuda_pixel.cu"):
        procs[src] = subprocess.Popen(ptxas_report.compile_command(nv, src, flags[src], "sm_90", out),
                                      stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    logs = {}
    for src, p in procs.items():
        try:
            logs[src] = p.communicate(timeout=TIMEOUT_S)[0]
        except subprocess.TimeoutExpired:
            p.kill()
            logs[src] = p.communicate()[0]
        assert p.returncode == 0, f"{src} failed to compile:\n{logs[src][-6000:]}"
    kernels = [k for src, text in logs.items() for k in ptxas_report.parse(src, text)]
    ptx = {src: _ptx_functions((out / (Path(src).stem + ".ptx")).read_text()) for src in procs}
    return kernels, ptx


def test_v2_backward_and_projection_kernels_do_not_spill(compiled):
    kernels, _ = compiled
    names = {(k.source, k.name) for k in kernels}
    for deg in range(-1, 4):
        assert ("projection_cuda.cu", f"project_fwd_kernel<{deg}>") in names
        assert ("projection_cuda.cu", f"project_bwd_kernel<{deg}>") in names
    bwd = [k for k in kernels if k.source == "cuda_v2_kernel.cu" and k.name.startswith("bwd_kernel<")]
    assert len(bwd) == 8 and len([k for k in kernels if k.source == "cuda_v2_kernel.cu"
                                  and k.name.startswith("fwd_kernel<")]) == 8
    for k in bwd + [k for k in kernels if k.source == "projection_cuda.cu"]:
        assert (k.spill_stores, k.spill_loads, k.stack) == (0, 0, 0), k
    for k in bwd:   # the launch bounds' occupancy: 3 blocks of 256 without softmax, 2 with
        soft = k.name.split(",")[1].strip() == "true"
        assert k.blocks_per_sm() >= (2 if soft else 3), k


def test_v2_ptx_has_the_record_layout_and_the_arithmetic_diet(compiled):
    _, ptx = compiled
    v2 = ptx["cuda_v2_kernel.cu"]
    bwd = {n: b for n, b in v2.items() if "bwd_kernel" in n}
    soft = [b for n, b in bwd.items() if re.search(r"bwd_kernelILb[01]ELb1E", n)]
    assert len(bwd) == 8 and len(soft) == 4
    for body in soft:
        assert "st.global.v4.f32" in body and "ld.global.v4.f32" in body
        assert "rcp.approx.f32" in body and "sqrt.approx.f32" in body
    for name, body in v2.items():
        if "fwd_kernel" in name or "bwd_kernel" in name:
            assert body.count("mul.rn.f32") >= 5, name   # splat_quad's unfused products
            assert "fma.rn.f32" in body, name


def test_per_pixel_kernels_compile_and_keep_their_window_in_local_memory(compiled):
    """cuda_pixel.cu: every mode's forward and backward; the window (32 entries of 5 words per
    thread) is the only stack, the backward does not spill, and its step records are written as
    float4 (and read so where every field is used: softmax)."""
    kernels, ptx = compiled
    px = [k for k in kernels if k.source == "cuda_pixel.cu"]
    assert len([k for k in px if k.name.startswith("fwd_kernel<")]) == 8
    bwd = [k for k in px if k.name.startswith("bwd_kernel<")]
    assert len(bwd) == 8
    for k in px:
        assert 640 <= k.stack <= 640 + 64, k
    for k in bwd:
        assert (k.spill_stores, k.spill_loads) == (0, 0), k
    for name, body in ptx["cuda_pixel.cu"].items():
        if "bwd_kernel" in name:
            assert "st.global.v4" in body, name
            if re.search(r"bwd_kernelILb[01]ELb1E", name):   # softmax reads every field back
                assert "ld.global.v4.f32" in body, name


def test_projection_ptx_has_no_fma(compiled):
    _, ptx = compiled
    for name, body in ptx["projection_cuda.cu"].items():
        assert "fma.rn.f32" not in body and "rcp.approx" not in body and "div.approx" not in body, name
        assert "div.rn.f32" in body, name


def test_the_peak_depth_key_is_not_contracted_where_the_per_pixel_kernels_are(tmp_path):
    """cuda_pixel.cu is built with FMA contraction (the v2 flags); the CPU window without. The key
    that orders each pixel's splats (splat_math.h's peak_depth) is written unfused, so both order
    alike to the bit: its PTX alone has no fma and every product and sum rounds on its own."""
    nv = _nvcc_or_skip()
    probe = tmp_path / "probe.cu"
    probe.write_text('#include "splat_math.h"\n'
                     'extern "C" __global__ void probe(const float* c, float* out) {\n'
                     '  out[threadIdx.x] = smgs::peak_depth(c[9], c[10], c, c[11]);\n}\n')
    flags = dict(ptxas_report.sources())["cuda_pixel.cu"]
    assert "--fmad=true" in flags
    done = subprocess.run([nv, "-ptx", "-arch=sm_90", *flags, f"-I{CSRC}", str(probe), "-o", str(tmp_path / "p.ptx")],
                          capture_output=True, text=True, timeout=TIMEOUT_S)
    assert done.returncode == 0, done.stderr[-3000:]
    ptx = (tmp_path / "p.ptx").read_text()
    assert "fma.rn.f32" not in ptx
    assert ptx.count("mul.rn.f32") == 14 and ptx.count("add.rn.f32") == 9, ptx   # as written, no fewer
    assert "div.rn.f32" in ptx


def test_bindings_compile_against_this_torch():
    _nvcc_or_skip()
    cxx = shutil.which(os.environ.get("CXX", "c++"))
    cuda_include = next((Path(h) / "include" for h in (os.environ.get("CUDA_HOME"), os.environ.get("CUDA_PATH"),
                                                        Path(ptxas_report.nvcc()).resolve().parent.parent,
                                                        "/usr/local/cuda")
                         if h and (Path(h) / "include" / "cuda_runtime_api.h").is_file()), None)
    if cxx is None or cuda_include is None:
        pytest.skip("no C++ compiler or no CUDA headers for the bindings")
    from torch.utils.cpp_extension import include_paths

    base = [cxx, "-std=c++20", "-fsyntax-only", "-Wall", "-Werror", "-DC10_CUDA_NO_CMAKE_CONFIGURE_FILE",
            "-DTORCH_EXTENSION_NAME=smgs_check", *[f"-I{p}" for p in include_paths()],
            f"-I{sysconfig.get_paths()['include']}", f"-I{cuda_include}", f"-I{CSRC}"]
    procs = {f: subprocess.Popen(base + [str(CSRC / f)], stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
             for f in ("projection_cuda_binding.cpp", "cuda_v2_binding.cpp")}
    for f, p in procs.items():
        text = p.communicate(timeout=TIMEOUT_S)[0]
        assert p.returncode == 0, f"{f}:\n{text[-6000:]}"
