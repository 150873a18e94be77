"""The just-in-time extension holder shared by the compiled backends."""

import pytest

from smgs.raster import constants as K
from smgs.raster.jit import JitExtension


def test_missing_prerequisite_is_unavailable_with_the_reason():
    jit = JitExtension("x", build=lambda s, d: pytest.fail("must not build"), precheck=lambda: "no toolchain")
    assert not jit.is_available()
    assert jit.unavailable_reason() == "no toolchain"
    with pytest.raises(RuntimeError, match="no toolchain"):
        jit.module()


def test_failed_build_is_unavailable_and_not_retried():
    calls = []

    def build(suffix, defines):
        calls.append(suffix)
        raise OSError("compiler crashed")

    jit = JitExtension("x", build=build, precheck=lambda: None)
    assert not jit.is_available() and not jit.is_available()
    assert calls == [""] and "compiler crashed" in jit.unavailable_reason()


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
