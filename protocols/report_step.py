"""The report as the last step of a run: a call in this process to the builder the config names.

protocols sit below reports (smgs <- baselines <- protocols <- reports), so the runner imports no
report code: ``report_builder`` in configs/config.yaml names it (``module:function``, by default
``reports.build:build_report``), and the runner looks it up when the sweep ends, as Hydra looks up a
``_target_``. Any function that takes the runs directory and returns the path of what it wrote fits.
"""

from __future__ import annotations

import importlib
from collections.abc import Callable
from pathlib import Path

DEFAULT_BUILDER = "reports.build:build_report"


class ReportFailed(RuntimeError):
    """The report builder raised; the runs are recorded and unaffected."""


def builder(spec: str | None) -> Callable[[Path], Path | str]:
    """The function ``spec`` (``module:function``) names; a spec that names none is an error saying
    what was looked for."""
    spec = spec or DEFAULT_BUILDER
    module, sep, name = spec.partition(":")
    if not sep or not module or not name:
        raise ValueError(f"report_builder={spec!r}: expected module:function, e.g. {DEFAULT_BUILDER}")
    try:
        fn = getattr(importlib.import_module(module), name)
    except (ImportError, AttributeError) as e:
        raise ValueError(f"report_builder={spec!r} names no function ({e}); the default is {DEFAULT_BUILDER}, "
                         "or report=false builds no report") from e
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
