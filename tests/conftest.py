"""Shared fixtures: the compiled CPU renderer, its SIMD paths; no LPIPS download on first use."""

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


@pytest.fixture
def cpu_backend():
    """The compiled CPU renderer module, or a skip naming why it cannot be used here (no compiler or
    ninja, or ``SMGS_DISABLE_CPU_BACKEND=1``); a failed build raises. tests/test_raster_cpu.py
    asserts that it is available, so where it is expected, its absence fails there."""
    from smgs.raster import cpu

    if not cpu.is_available():
        pytest.skip(f"cpu backend unavailable: {cpu.unavailable_reason()}")
    return cpu


@pytest.fixture(autouse=True)
def _own_live_cell_registry(tmp_path_factory, monkeypatch):
    """Each test counts only the cells it runs itself (``protocols.live_cells``), not those of other
    test sessions or sweeps on the same machine."""
    from protocols.live_cells import ENV

    monkeypatch.setenv(ENV, str(tmp_path_factory.mktemp("live_cells")))


@pytest.fixture(autouse=True, scope="session")
def _no_lpips_download():
    """No test fetches LPIPS weights on first use (``SMGS_LPIPS_AUTO=0``, inherited by the runs the
    tests start as subprocesses); the tests that want weights set them up from their own cache."""
    import os

    from smgs.metrics.lpips_weights import AUTO_ENV

    old = os.environ.get(AUTO_ENV)
    os.environ[AUTO_ENV] = "0"
    yield
    if old is None:
        os.environ.pop(AUTO_ENV, None)
    else:
        os.environ[AUTO_ENV] = old
