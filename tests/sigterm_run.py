"""A sweep started as the command line starts it and sent SIGTERM once its first progress line
(``marker``) shows that training has begun: for the tests of the clean stop."""

from __future__ import annotations

import signal
import subprocess
import sys
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def terminate_when_training(args: list[str], marker: str) -> tuple[int, str, str]:
    """(exit status, stdout, stderr) of ``python -m protocols.run ARGS`` sent SIGTERM after ``marker``."""
    p = subprocess.Popen([sys.executable, "-m", "protocols.run", *args], cwd=REPO, stdout=subprocess.PIPE,
                         stderr=subprocess.PIPE, text=True)
    lines = []
    for line in p.stderr:
        lines.append(line)
        if marker in line:
            break
    p.send_signal(signal.SIGTERM)
    out, err = p.communicate(timeout=120)
    return p.returncode, out, "".join(lines) + err
