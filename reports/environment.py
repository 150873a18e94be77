"""The environment block: what the runs recorded (``RunResult.versions``, ``render_device``) beside the
machine that builds the report."""

from __future__ import annotations

import platform
from collections import Counter
from typing import Sequence

from protocols.results import RunResult
from reports.table_model import md_text
from smgs.env import cpu_model, git_revision

ITEMS = [("smgs", "smgs"), ("torch", "torch"), ("numpy", "numpy"), ("python", "python"), ("backend", "backend"),
         ("renderer", "renderer (backend, variants)"), ("cpu_isa", "CPU SIMD path"), ("device", "device"),
         ("cpu", "CPU model"), ("gpu", "GPU"), ("git", "git revision")]


def _version(module: str) -> str:
    try:
        mod = __import__(module)
        return str(getattr(mod, "__version__", "unknown"))
    except Exception as e:  # noqa: BLE001 - report, never fail, on an import problem
        return f"not importable ({type(e).__name__})"


def this_machine(probed_backends: Sequence[str] = ()) -> dict[str, str]:
    """The machine that builds the report; ``probed_backends``: the renderer backends its stability
    battery rendered with (none: the backend row says it was not probed)."""
    env = {"smgs": _version("smgs"), "torch": _version("torch"), "numpy": _version("numpy"),
           "python": platform.python_version(), "cpu": cpu_model(), "git": git_revision(),
           "matplotlib": _version("matplotlib"), "renderer": "— (a run's: its backend as it rendered)",
           "cpu_isa": _cpu_isa()}
    try:
        import torch

        if torch.cuda.is_available():
            env["gpu"] = ", ".join(torch.cuda.get_device_name(i) for i in range(torch.cuda.device_count()))
            env["device"] = "cuda"
        else:
            env["gpu"] = "none (torch sees no CUDA device)"
            env["device"] = "cpu"
    except Exception as e:  # noqa: BLE001
        env["gpu"] = f"unknown (torch not importable: {type(e).__name__})"
    return with_probed(env, probed_backends)


def _cpu_isa() -> str:
    """The SIMD path the compiled CPU kernels would take here (nothing is built)."""
    try:
        from smgs.raster.cpu_build import isa_in_use

        return isa_in_use()
    except Exception as e:  # noqa: BLE001 - report, never fail, on an import problem
        return f"unknown ({type(e).__name__})"


def with_probed(machine: dict[str, str], probed_backends: Sequence[str] | None) -> dict[str, str]:
    """``machine`` with its backend row: the backends the stability battery rendered with, else "not
    probed" (checking the compiled backend apart from the battery could build it)."""
    out = dict(machine)
    if probed_backends:
        out["backend"] = f"{', '.join(probed_backends)} (rendered by this report's stability battery)"
    else:
        out.setdefault("backend", "not probed (the build renders nothing)")
    return out


def _runs_value(runs: list[RunResult], key: str) -> str:
    vals: Counter[str] = Counter()
    for r in runs:
        v = r.versions.get(key) if r.versions else None
        if key == "device" and r.render_device:
            v = r.render_device if not v else v
        if v:
            vals[str(v)] += 1
    if not vals:
        return "not recorded"
    if len(vals) == 1:
        return next(iter(vals))
    return "mixed: " + "; ".join(f"{v} ({n} runs)" for v, n in vals.most_common())


def environment_rows(runs: list[RunResult], machine: dict[str, str]) -> list[tuple[str, str, str]]:
    """(item, what the runs recorded, this machine) per line of the environment block."""
    rows = [(label, _runs_value(runs, key), machine.get(key, "not recorded")) for key, label in ITEMS]
    return rows + [("matplotlib", "—", machine.get("matplotlib", "unknown"))]


def environment_markdown(runs: list[RunResult], machine: dict[str, str] | None = None) -> str:
    """``machine``: ``this_machine`` of the build (its backend row from the stability battery, ``with_probed``)."""
    machine = machine if machine is not None else this_machine()
    lines = ["| | runs | this machine (report build) |", "|:--|:--|:--|"]
    for label, ran, here in environment_rows(runs, machine):
        lines.append(f"| {label} | {md_text(ran)} | {md_text(here)} |")
    devices = sorted({r.render_device for r in runs if r.render_device})
    out = ["\n".join(lines), ""]
    if devices:
        out.append(f"Render devices of the runs: {', '.join(md_text(d) for d in devices)}.")
    out.append("\"runs\" is what each results.json recorded (a value is listed with its count when runs differ); "
               "\"not recorded\" means no run stored it.")
    return "\n".join(out) + "\n"
