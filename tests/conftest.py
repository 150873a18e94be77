"""Shared fixtures: the compiled CPU kernels' SIMD paths."""

from __future__ import annotations

import pytest

from smgs.raster import cpu_build


@pytest.fixture(params=cpu_build.ISAS)
def cpu_isa(request, monkeypatch) -> str:
    """Runs the test once per SIMD path of the compiled CPU kernels (``SMGS_CPU_ISA``), skipping
    the paths this host's CPU cannot execute. A module opts in with
    ``pytestmark = pytest.mark.usefixtures("cpu_isa")``."""
    isa = request.param
    if isa not in cpu_build.host_isas():
        pytest.skip(f"this CPU cannot run the {isa} path (it runs {', '.join(cpu_build.host_isas())})")
    monkeypatch.setenv(cpu_build.ISA_ENV, isa)
    return isa
