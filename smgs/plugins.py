"""What every registry of plug-ins shares (methods: baselines.registry; scene formats and datasets:
smgs.data.registry): entries named as ``"module:attr"`` strings and imported on use, and third-party
entries from a Python entry-point group, never allowed to shadow a built-in."""

from __future__ import annotations

import importlib
import warnings
from collections.abc import Iterable
from importlib import metadata
from typing import Any


def entry_points(group: str, builtins: Iterable[str], what: str) -> dict[str, metadata.EntryPoint]:
    """The installed plugins of ``group`` by name (the first of a name wins); one named as a
    built-in is left out with a warning that calls it a ``what`` (e.g. "plugin method")."""
    taken = set(builtins)
    eps: dict[str, metadata.EntryPoint] = {}
    for ep in metadata.entry_points(group=group):
        if ep.name in taken:
            warnings.warn(f"{what} {ep.name!r} ({ep.value}) is shadowed by the built-in of that name", stacklevel=4)
            continue
        eps.setdefault(ep.name, ep)
    return eps


def source_of(ep: metadata.EntryPoint) -> str:
    """``plugin <distribution>`` (or the entry point's target where no distribution is known)."""
    dist = getattr(ep, "dist", None)
    return f"plugin {dist.name if dist else ep.value}"


def load_target(target: str, what: str) -> Any:
    """The object a ``"module:attr"`` string names (``attr`` may be dotted), imported now."""
    module, _, attr = target.partition(":")
    if not module or not attr:
        raise ValueError(f"{what} target must be 'module:attr', got {target!r}")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj
