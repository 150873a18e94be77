"""The report as the last step of a run: a call in this process to the builder the config names.

protocols sit below reports (smgs <- baselines <- protocols <- reports), so the runner imports no
report code and names none: ``report_builder`` in configs/config.yaml names it (``module:function``;
the config is the one home of the default), and the runner looks it up when the sweep ends, as Hydra
looks up a ``_target_``. Any function that takes the runs directory and returns the path of what it
wrote fits.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path


class ReportFailed(RuntimeError):
    """The report builder raised; the runs are recorded and unaffected."""


def builder(spec: str | None) -> Callable[[Path], Path | str]:
    """The function ``spec`` (``module:function``) names; a spec that names none is an error saying
    what was looked for."""
    if not spec:
        raise ValueError("report_builder is not set: name the function that builds the report as module:function "
                         "(configs/config.yaml names the harness's), or report=false builds none")
    module, sep, name = spec.partition(":")
    if not sep or not module or not name:
        raise ValueError(f"report_builder={spec!r}: expected module:function (configs/config.yaml names the "
                         "harness's builder)")
    try:
        fn = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"report_builder={spec!r} names no function ({e}); configs/config.yaml names the "
                         "harness's builder, or report=false builds no report") from e
    if not callable(fn):
        raise ValueError(f"report_builder={spec!r} is not callable")
    return fn


def build_report(runs_dir: Path | str, spec: str | None = None) -> Path:
    """Build the report of every run below ``runs_dir`` with the builder ``spec`` names; returns the
    path of report.md. The builder's error becomes one ``ReportFailed`` line."""
    fn = builder(spec)
    try:
        return Path(fn(Path(runs_dir)))
    except Exception as e:
        raise ReportFailed(f"the report step failed ({type(e).__name__}: {e}); the runs are recorded, rebuild "
                           f"the report with `smgs report {runs_dir}`") from e
