"""A tiny installed distribution for the plug-in tests: a package and a dist-info folder whose
entry_points.txt names its entries, put on sys.path as pip would install it."""

from __future__ import annotations

import sys
from pathlib import Path


def install(site: Path, monkeypatch, package: str, source: str, group: str, entries: dict[str, str]) -> Path:
    """``package`` (its ``__init__.py`` is ``source``) with the entry points ``entries`` (name ->
    "module:attr") in ``group``, in the folder ``site``, which goes on sys.path (undone with
    ``monkeypatch``; the test drops the imported module with ``uninstall``)."""
    pkg = site / package
    pkg.mkdir(parents=True)
    (pkg / "__init__.py").write_text(source)
    dist_name = package.replace("_", "-")
    dist = site / f"{package}-0.1.dist-info"
    dist.mkdir()
    (dist / "METADATA").write_text(f"Metadata-Version: 2.1\nName: {dist_name}\nVersion: 0.1\n")
    (dist / "entry_points.txt").write_text(f"[{group}]\n" + "".join(f"{k} = {v}\n" for k, v in entries.items()))
    monkeypatch.syspath_prepend(str(site))
    return site


def uninstall(package: str) -> None:
    sys.modules.pop(package, None)
