"""The report as the last step of a run, through its command line (``python -m reports.build``).

protocols sit below reports (smgs <- baselines <- protocols <- reports), so the runner does not
import the report builder: it runs it as its own program, as a user would after the run.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

# The folder holding protocols/ and reports/, so the child imports the same tree as this process.
_ROOT = Path(__file__).resolve().parents[1]


class ReportFailed(RuntimeError):
    """The report builder exited with an error (printed by it on stderr); the runs are unaffected."""


def build_report(runs_dir: Path | str) -> Path:
    """Build the report of every run below ``runs_dir``; returns the path of report.md."""
    env = dict(os.environ)
    env["PYTHONPATH"] = os.pathsep.join(p for p in (str(_ROOT), env.get("PYTHONPATH", "")) if p)
    cmd = [sys.executable, "-m", "reports.build", str(runs_dir)]
    done = subprocess.run(cmd, env=env, stdout=subprocess.PIPE, text=True)
    lines = [ln for ln in done.stdout.splitlines() if ln.startswith("report: ")]
    if done.returncode != 0 or not lines:
        raise ReportFailed(f"the report step failed (exit status {done.returncode}; its error is printed above): "
                           f"{' '.join(cmd)}" + (f"\n{done.stdout}" if done.stdout.strip() else ""))
    for ln in done.stdout.splitlines():  # the builder's own notes, without its final path line
        if not ln.startswith("report: "):
            print(ln, flush=True)
    return Path(lines[-1][len("report: "):])
