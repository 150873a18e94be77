"""The just-in-time extension holder shared by the compiled backends."""

import pytest
import torch

from smgs.raster import constants as K
from smgs.raster import cpu, resolve_backend
from smgs.raster.jit import BuildError, JitExtension


def test_missing_prerequisite_is_unavailable_with_the_reason():
    jit = JitExtension("x", build=lambda s, d: pytest.fail("must not build"), precheck=lambda: "no toolchain")
    assert not jit.is_available()
    assert jit.unavailable_reason() == "no toolchain"
    with pytest.raises(RuntimeError, match="no toolchain"):
        jit.module()


def test_failed_build_raises_with_the_fix_and_is_not_retried():
    calls = []

    def build(suffix, defines):
        calls.append(suffix)
        raise OSError("compiler crashed")

    jit = JitExtension("x", build=build, precheck=lambda: None, disable="SMGS_DISABLE_X")
    for _ in range(2):
        with pytest.raises(BuildError, match="compiler crashed(.|\n)*SMGS_DISABLE_X=1"):
            jit.is_available()
    assert calls == [""] and "compiler crashed" in jit.unavailable_reason()


def test_auto_backend_stops_on_a_build_failure_and_falls_back_only_without_a_toolchain(monkeypatch):
    """A lock race once made ``auto`` render with the 100-1000x slower reference, silently."""
    def broken(suffix, defines):
        raise FileNotFoundError("[Errno 2] No such file or directory: '.../smgs_raster_cpu_x/lock'")

    for precheck, expect in ((lambda: None, BuildError), (lambda: "no C++ compiler", "reference")):
        jit = JitExtension("cpu", build=broken, precheck=precheck, disable="SMGS_DISABLE_CPU_BACKEND")
        monkeypatch.setattr(cpu, "_JIT", jit)
        monkeypatch.setattr(cpu, "is_available", jit.is_available)
        if expect is BuildError:
            with pytest.raises(BuildError, match="lock"):
                resolve_backend("auto", "cpu", torch.float32)
        else:
            assert resolve_backend("auto", "cpu", torch.float32) == "reference"


def test_one_build_per_threshold():
    built = []

    def build(suffix, defines):
        built.append((suffix, defines))
        return object()

    jit = JitExtension("x", build=build, precheck=lambda: None)
    default = jit.module()
    assert jit.module(K.T_MIN) is default
    zero = jit.module(0.0)
    assert jit.module(0.0) is zero and zero is not default
    assert built == [("", ()), ("_tmin0p000e00", ("-DSMGS_T_MIN=0.0",))]
