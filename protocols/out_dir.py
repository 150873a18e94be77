"""Whether a sweep can write its ``out_dir``, asked before anything runs.

``smgs run`` writes below ``out_dir`` even when every cell is finished (Hydra's log in
``_hydra/``, the cells' locks, the report), so a folder it cannot write is refused in one block
before Hydra starts, naming the folder, why, and what can be done: make it writable, write
elsewhere, or read its finished cells into a report built elsewhere (``smgs report``).
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path


def unwritable(folder: Path) -> str | None:
    """Why a file cannot be made in ``folder`` (or, where it does not exist yet, in the nearest
    folder above it, where it would be made); None when one can. Tried, not inferred from the mode
    bits: root, ACLs and read-only mounts answer only to a try."""
    probe = folder
    while not probe.exists() and probe != probe.parent:
        probe = probe.parent
    if not probe.is_dir():
        return f"{probe} is a file, not a folder"
    try:
        fd, name = tempfile.mkstemp(dir=probe, prefix=".smgs-write-check-")
    except OSError as e:
        return f"{e.strerror or e} in {probe}"
    os.close(fd)
    os.unlink(name)
    return None


def out_dir_problem(out_dir: Path) -> str | None:
    """The one-block refusal of an ``out_dir`` a sweep cannot write (None when it can)."""
    out_dir = Path(out_dir).expanduser().absolute()
    why = unwritable(out_dir) or (unwritable(out_dir / "_hydra") if (out_dir / "_hydra").is_dir() else None)
    if why is None:
        return None
    problem = (f"out_dir={out_dir} cannot be written ({why}): smgs run writes there even when every cell is "
               "finished (its log, the cells' locks, the report). Make it writable, or give out_dir=DIR on a "
               "disk you can write")
    if out_dir.is_dir():
        problem += (f"; to read the cells finished there without writing to it, build their report elsewhere: "
                    f"smgs report {out_dir} --out DIR")
    return problem

