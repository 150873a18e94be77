"""What the registries of plug-ins share: entries named as ``"module:attr"`` strings and imported on
use, and third-party entries from a Python entry-point group, never allowed to shadow a built-in.
Scene formats and datasets (smgs.data.registry) and densification strategies
(smgs.train.strategies.registry) are each a ``Registry``; methods (baselines.registry), whose
built-ins are ``MethodSpec`` records rather than targets, use its functions (``entry_points``,
``load_target``, ``source_of``)."""

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


def target_doc(target: str) -> str:
    """The docstring of the class a ``"module:Class"`` target names, read from the module's source
    without importing it (a listing imports nothing: no torch for ``smgs list``); "" where none."""
    import ast
    import importlib.util
    from pathlib import Path

    module, _, attr = target.partition(":")
    spec = importlib.util.find_spec(module)
    if spec is None or not spec.origin or not spec.origin.endswith(".py"):
        return ""
    for node in ast.parse(Path(spec.origin).read_text()).body:
        if isinstance(node, ast.ClassDef) and node.name == attr:
            return ast.get_docstring(node) or ""
    return ""


def load_target(target: str, what: str) -> Any:
    """The object a ``"module:attr"`` string names (``attr`` may be dotted), imported now."""
    module, _, attr = target.partition(":")
    if not module or not attr:
        raise ValueError(f"{what} target must be 'module:attr', got {target!r}")
    obj = importlib.import_module(module)
    for part in attr.split("."):
        obj = getattr(obj, part)
    return obj


class Registry:
    """Entries by name of one kind of plug-in, looked up in this order: those registered in this
    process (``register``: tests, notebooks), the built-ins (``"module:attr"`` strings), then the
    plugins of the entry-point group ``group``. Listing imports nothing; ``get`` imports the entry."""

    def __init__(self, group: str, builtins: dict[str, str], what: str) -> None:
        self.group, self.builtins, self.what = group, builtins, what
        self._registered: dict[str, Any] = {}

    def register(self, name: str, entry: Any, overwrite: bool = False) -> None:
        """Register ``entry`` as ``name`` in this process; it overrides a built-in or plugin of that name."""
        if name in self._registered and not overwrite:
            raise ValueError(f"{self.what} {name!r} is already registered")
        self._registered[name] = entry

    def unregister(self, name: str) -> None:
        self._registered.pop(name, None)

    def entry_points(self) -> dict[str, metadata.EntryPoint]:
        return entry_points(self.group, self.builtins, f"plugin {self.what}")

    def names(self) -> list[str]:
        """Every name known here (built-ins, registered, plugins), sorted."""
        return sorted(set(self.builtins) | set(self._registered) | set(self.entry_points()))

    def plugin_source(self, name: str) -> str | None:
        """``plugin <distribution>`` for an entry from the entry-point group, None for the others."""
        if name in self._registered or name in self.builtins:
            return None
        ep = self.entry_points().get(name)
        return None if ep is None else source_of(ep)

    def get(self, name: str) -> Any:
        """The entry registered as ``name`` (imported now); a KeyError where there is none."""
        if name in self._registered:
            return self._registered[name]
        if name in self.builtins:
            return load_target(self.builtins[name], self.what)
        ep = self.entry_points().get(name)
        if ep is None:
            raise KeyError(name)
        return ep.load()
