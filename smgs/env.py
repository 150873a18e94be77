"""The machine and the software versions, recorded with every result and printed in reports."""

from __future__ import annotations

import platform
import subprocess
from pathlib import Path

import torch

ROOT = Path(__file__).resolve().parent.parent


def cpu_model() -> str:
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or "unknown"


def gpu_model() -> str:
    if torch.cuda.is_available():
        return ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
    return "none"


def git_revision(root: Path = ROOT) -> str:
    """Short revision of the checkout that holds this package (with "+ uncommitted changes" when
    dirty), or "unknown" outside a git checkout of this project."""
    def git(*args: str) -> subprocess.CompletedProcess:
        return subprocess.run(["git", *args], cwd=root, capture_output=True, text=True, timeout=10)
    try:
        top = git("rev-parse", "--show-toplevel")
        if top.returncode != 0 or Path(top.stdout.strip()).resolve() != root.resolve():
            return "unknown"
        rev = git("rev-parse", "--short", "HEAD").stdout.strip()
        dirty = git("status", "--porcelain", "--untracked-files=no").stdout.strip()
        return (rev + (" + uncommitted changes" if dirty else "")) if rev else "unknown"
    except (OSError, subprocess.SubprocessError):
        return "unknown"


def versions(backend: str, device: str) -> dict[str, str]:
    """What a result records about where it was computed."""
    import numpy

    from smgs.version import __version__

    return {"smgs": __version__, "torch": torch.__version__, "numpy": numpy.__version__,
            "python": platform.python_version(), "backend": backend, "device": device,
            "cpu": cpu_model(), "gpu": gpu_model(), "git": git_revision()}
