"""How smgs builds its compiled CPU extensions (the renderer, the projection, the training loss):
compiler flags, OpenMP, the SIMD path for this host, and when a kernel is used in place of its
PyTorch path. Beside ``smgs.raster.jit`` so that the projection and the loss need not import the
renderer backend (``smgs.raster.cpu``) for its build machinery.
"""

from __future__ import annotations

import functools
import hashlib
import logging
import os
import platform
import shutil
import subprocess
import tempfile
import threading
from pathlib import Path

import torch

from smgs.raster.buildcache import ExtensionSpec, compile_and_load
from smgs.raster.buildproc import run_in_group
from smgs.raster.jit import JitExtension

log = logging.getLogger(__name__)

DISABLE = "SMGS_DISABLE_CPU_BACKEND"
# -ffp-contract=off keeps a·b + c as two roundings, as PyTorch evaluates the reference, so the
# reach tests (q <= 4.5, a >= 1/255, T < 1e-4) see the same numbers; FMAs are written explicitly
# where wanted. -fno-math-errno / -fno-trapping-math only let sqrt and selects vectorise: unlike
# -ffast-math they keep NaN/inf semantics. -Wno-psabi: the 64-byte lane vectors never cross a call.
_CFLAGS = ["-O3", "-ffp-contract=off", "-fno-math-errno", "-fno-trapping-math", "-std=c++17", "-Wno-psabi"]

ISAS = ("avx512", "avx2", "neon", "scalar")
ISA_ENV = "SMGS_CPU_ISA"


def isa_flags(isa: str) -> list[str]:
    """Compiler flags of one SIMD path of csrc/simd.h (the define selects the path; the flags let
    the compiler emit its instructions)."""
    flags = {
        "avx512": ["-march=native"],            # only chosen where the host has AVX-512 F + DQ
        "avx2": ["-mavx2", "-mfma", "-mtune=native"],   # x86-64-v3, whatever else the host has
        "neon": [],                              # Advanced SIMD is baseline on aarch64
        "scalar": [],                            # the architecture's baseline only
    }
    if isa not in flags:
        raise ValueError(f"unknown CPU SIMD path {isa!r}; choose one of {', '.join(ISAS)}")
    return flags[isa] + [f"-DSMGS_ISA_{isa.upper()}"]


@functools.lru_cache(maxsize=1)
def host_isas() -> tuple[str, ...]:
    """The SIMD paths this host CPU can run, best first (scalar always)."""
    machine = platform.machine().lower()
    feats = _cpu_features()
    if machine in ("x86_64", "amd64"):
        found = [isa for isa, need in (("avx512", {"avx512f", "avx512dq"}), ("avx2", {"avx2", "fma"}))
                 if need <= feats]
        return (*found, "scalar")
    if machine in ("aarch64", "arm64"):
        return ("neon", "scalar")
    return ("scalar",)


def _cpu_features() -> set[str]:
    """CPU feature names, lower case: /proc/cpuinfo flags (Linux), sysctl features (macOS)."""
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("flags", "Features")):
                    return set(line.split(":", 1)[1].lower().split())
    except OSError:
        pass
    try:
        out = subprocess.run(["sysctl", "-n", "machdep.cpu.features", "machdep.cpu.leaf7_features"],
                             capture_output=True, text=True, timeout=5).stdout
        return set(out.lower().split())
    except (OSError, subprocess.SubprocessError):
        return set()


def select_isa() -> str:
    """The SIMD path to build: ``$SMGS_CPU_ISA`` if set, else the best one this host runs."""
    want = os.environ.get(ISA_ENV, "").strip().lower()
    can = host_isas()
    if not want:
        return can[0]
    if want not in ISAS:
        raise ValueError(f"{ISA_ENV}={want!r} (an environment variable) is not a CPU SIMD path; it takes one of "
                         f"{', '.join(ISAS)} (this host runs {', '.join(can)}), or unset it to take the best")
    if want not in can:
        raise RuntimeError(f"{ISA_ENV}={want}: this CPU ({platform.machine()}) cannot run the {want} path; "
                           f"it runs {', '.join(can)} (unset {ISA_ENV} to take the best)")
    return want


def _cpu_tag() -> str:
    """-mtune/-march=native code must not be loaded on another CPU kind sharing the cache directory."""
    ident = platform.machine()
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                if line.startswith(("model name", "flags", "Features")):
                    ident += line
                if line.strip() == "":
                    break
    except OSError:
        ident += platform.processor()
    return hashlib.sha1(ident.encode()).hexdigest()[:10]


@functools.lru_cache(maxsize=1)
def openmp_flags() -> tuple[list[str], list[str], str]:
    """(compile flags, link flags, what) for OpenMP: ``-fopenmp`` where the compiler takes it (GCC,
    LLVM clang), ``-Xpreprocessor -fopenmp -lomp`` where libomp is found (Apple clang with Homebrew's
    libomp), else none: the kernels then run on one thread, and the log says so."""
    cxx = os.environ.get("CXX", "c++")
    candidates = [(["-fopenmp"], ["-fopenmp"], "OpenMP (-fopenmp)")]
    for prefix in ("/opt/homebrew/opt/libomp", "/usr/local/opt/libomp"):
        if Path(prefix, "include", "omp.h").exists():
            candidates.append((["-Xpreprocessor", "-fopenmp", f"-I{prefix}/include"],
                               [f"-L{prefix}/lib", "-lomp"], f"OpenMP (libomp in {prefix})"))
    src = "#include <omp.h>\nint main() { return omp_get_max_threads() > 0 ? 0 : 1; }\n"
    with tempfile.TemporaryDirectory() as tmp:
        Path(tmp, "omp.cpp").write_text(src)
        for cflags, ldflags, what in candidates:
            cmd = [cxx, *cflags, str(Path(tmp, "omp.cpp")), "-o", str(Path(tmp, "omp")), *ldflags]
            try:
                if run_in_group(cmd, timeout=120).returncode == 0:
                    return cflags, ldflags, what
            except (OSError, subprocess.SubprocessError):
                break
    log.warning("smgs: %s has no OpenMP here: the compiled projection and loss kernels run on one "
                "thread (the renderer has its own threads)", cxx)
    return [], [], "no OpenMP (one thread)"


def _precheck() -> str | None:
    """A missing toolchain (or the switch) is "unavailable"; any other build failure is an error."""
    if os.environ.get(DISABLE, "") not in ("", "0"):
        return f"disabled by {DISABLE}"
    if shutil.which(os.environ.get("CXX", "c++")) is None:
        return f"no C++ compiler ({os.environ.get('CXX', 'c++')!r} not on PATH)"
    from torch.utils.cpp_extension import is_ninja_available

    if not is_ninja_available():
        return "no ninja build tool (pip install ninja)"
    return None


class CpuExtension:
    """A compiled CPU extension of smgs, one build per SIMD path (``isa_flags``; the path is part of
    the build name, so the paths never share a binary), chosen by ``select_isa()`` at each use: the
    renderer here, the projection and the training loss elsewhere. Each path is a ``JitExtension``,
    built just in time on first use."""

    def __init__(self, name: str, sources: list[Path], what: str, include: list[Path] | None = None):
        self.name, self.sources, self.what, self.include = name, sources, what, include or []
        self._paths: dict[str, JitExtension] = {}
        self._lock = threading.Lock()

    def jit(self, isa: str | None = None) -> JitExtension:
        isa = isa or select_isa()
        with self._lock:
            if isa not in self._paths:
                self._paths[isa] = JitExtension("cpu", self._builder(isa), _precheck, what=self.what,
                                                disable=DISABLE)
            return self._paths[isa]

    def _builder(self, isa: str):
        def build(suffix: str, defines: tuple[str, ...]):
            omp_c, omp_l, omp_what = openmp_flags()
            log.info("smgs: the compiled CPU %s: %s path, %s", self.what, isa, omp_what)
            # the cache key (smgs.raster.buildcache) covers the sources, every flag and the CPU kind
            return compile_and_load(ExtensionSpec(
                name=f"{self.name}_{isa}{suffix}", sources=tuple(self.sources), what=self.what,
                include_dirs=tuple(self.include), cflags=tuple(_CFLAGS + omp_c + isa_flags(isa)) + tuple(defines),
                ldflags=tuple(omp_l), target=_cpu_tag()))
        return build

    @property
    def kind(self) -> str:
        return "cpu"

    def is_available(self) -> bool:
        """Whether the path in use builds; a failed build (``BuildError``) propagates, and so does an
        ``SMGS_CPU_ISA`` that names no path (a ValueError: a typo must not fall back to the 100-1000x
        slower reference renderer, as an unknown ``renderer.kernels`` does not)."""
        try:
            isa = select_isa()   # its ValueError (no such path) propagates
        except RuntimeError as exc:   # an SMGS_CPU_ISA this host cannot run
            log.warning("smgs cpu %s unavailable: %s", self.what, exc)
            return False
        return self.jit(isa).is_available()

    def unavailable_reason(self) -> str | None:
        try:
            isa = select_isa()
        except (ValueError, RuntimeError) as exc:
            return str(exc)
        return self.jit(isa).unavailable_reason()

    def module(self):
        return self.jit().module()

    def loaded(self):
        """The module of the path in use where this process has loaded it already, else None: never
        builds (for work that may use a kernel but must not cost a build, e.g. an input check)."""
        try:
            isa = select_isa()
        except (ValueError, RuntimeError):
            return None
        with self._lock:
            path = self._paths.get(isa)
        return None if path is None else path.loaded()


def cpu_extension(name: str, sources: list[Path], what: str, include: list[Path] | None = None) -> CpuExtension:
    """A compiled CPU extension of smgs (``_CFLAGS``, OpenMP where the compiler has it, one build
    per SIMD path), built just in time on first use."""
    return CpuExtension(name, sources, what, include)


class UnsupportedInput(ValueError, RuntimeError):
    """Inputs a compiled CPU kernel does not take, where it was required (``fused=True``): a bad
    argument (ValueError), and like the kernel's other refusals a RuntimeError."""


def use_cpu_kernel(ext: CpuExtension, fused: bool | None, tensors: tuple[torch.Tensor, ...], takes: str) -> bool:
    """Whether to run a compiled CPU kernel (the projection, the training loss) rather than its
    PyTorch path: ``fused`` None = wherever it applies (float32 CPU ``tensors``) and builds; True =
    required (UnsupportedInput naming what it takes, RuntimeError naming why it cannot build);
    False = never."""
    if fused is False:
        return False
    applies = all(t.device.type == "cpu" and t.dtype == torch.float32 for t in tensors)
    if fused is True:
        if not applies:
            got = ", ".join(f"{t.dtype} on {t.device}" for t in tensors)
            raise UnsupportedInput(f"the compiled {ext.what} takes float32 CPU {takes}; got {got}")
        if not ext.is_available():
            raise RuntimeError(f"the compiled {ext.what} is unavailable: {ext.unavailable_reason()}")
        return True
    return applies and ext.is_available()


def isa_in_use() -> str:
    """The SIMD path this process's compiled CPU kernels use (or were refused: the reason), without
    building anything: for results' version records."""
    try:
        return select_isa()
    except (ValueError, RuntimeError) as exc:
        return f"none ({exc})"
