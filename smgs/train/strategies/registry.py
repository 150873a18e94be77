"""Densification strategies by name, imported lazily (the way methods register, ``baselines.registry``);
docs/adding-a-strategy.md.

A strategy is a dataclass subclassing ``smgs.train.strategies.Strategy``: its fields are the densify
section's keys, its methods the trainer's hooks. Lookup order: strategies registered in this process
(``register``), the built-ins, then third-party plugins from the entry-point group
``smgs.strategies``, declared in their own package metadata::

    [project.entry-points."smgs.strategies"]
    my_strategy = "my_pkg.densify:MyStrategy"

A run picks one with ``densify.strategy`` (``+method.train.densify.strategy=NAME`` on the command
line), or through its budget's kind (``smgs.train.config.BUDGETS``). Listing never imports a
strategy's module; it is imported when a run uses it.
"""

from __future__ import annotations

import dataclasses
from typing import Any

from smgs.plugins import Registry
from smgs.train.sections import DensifyConfig

ENTRY_POINT_GROUP = "smgs.strategies"

BUILTINS: dict[str, str] = {
    "default": "smgs.train.strategies.default:DefaultStrategy",
    "mcmc": "smgs.train.strategies.mcmc:MCMCStrategy",
}

_REGISTRY = Registry(ENTRY_POINT_GROUP, BUILTINS, "densification strategy")


def register(name: str, cls: type, overwrite: bool = False) -> None:
    """Register a strategy class in this process (tests, notebooks); it overrides a built-in or a
    plugin of that name."""
    _REGISTRY.register(name, cls, overwrite)


def unregister(name: str) -> None:
    _REGISTRY.unregister(name)


def list_strategies() -> list[str]:
    """Every strategy name known here (built-ins, registered, plugins), sorted."""
    return _REGISTRY.names()


def plugin_source(name: str) -> str | None:
    """``plugin <distribution>`` for a strategy from the entry-point group, None for the others."""
    return _REGISTRY.plugin_source(name)


def strategy_class(name: str) -> type:
    """The strategy class registered as ``name`` (imported now), checked to be a ``Strategy``
    dataclass; a ValueError lists the known names."""
    from smgs.train.strategies.base import Strategy

    try:
        cls = _REGISTRY.get(name)
    except KeyError:
        raise ValueError(f"unknown densification strategy {name!r} (densify.strategy); known: "
                         f"{', '.join(list_strategies())} (docs/adding-a-strategy.md)") from None
    if not (isinstance(cls, type) and issubclass(cls, Strategy) and dataclasses.is_dataclass(cls)):
        raise _REGISTRY.wrong_kind(name, cls, "a dataclass subclassing smgs.train.strategies.Strategy (its fields "
                                   "are its config)", "docs/adding-a-strategy.md")
    return cls


def builtin_keys() -> dict[str, Any]:
    """Every key of the built-in strategies with its default (the first strategy's where two share
    one): the densify section's form before strategies had their own configs."""
    out: dict[str, Any] = {}
    for name in reversed(BUILTINS):
        out.update(dataclasses.asdict(strategy_class(name)()))
    return out


def start_strategy(section: DensifyConfig, run: Any) -> Any:
    """The strategy a run's densify section names, started for ``run`` (``Strategy.start``): a
    ``FixedCount`` where densification is off."""
    from smgs.train.strategies.base import FixedCount

    if not section.enabled:
        return FixedCount(**{f.name: getattr(section, f.name) for f in dataclasses.fields(DensifyConfig)}).start(run)
    cls = strategy_class(section.strategy)
    if type(section) is not cls:
        raise TypeError(f"densify.strategy={section.strategy!r} is {cls.__qualname__}, but the section is a "
                        f"{type(section).__qualname__}: make it with smgs.train.densify_config or from_dict")
    return section.start(run)
