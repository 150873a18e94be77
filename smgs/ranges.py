"""The values a numeric setting may take, declared beside the setting (a config dataclass's
``RANGES``): the training sections (``smgs.train.config``) and the scene formats' own configs
(``smgs.data``) refuse a value outside, naming the key, before anything runs. A run reads both through
``smgs.train.config.from_dict``, which checks them; a format made in Python
(``smgs.data.load_scene(kind, **settings)``) takes its values as given."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any


@dataclass(frozen=True)
class Range:
    """The values a numeric setting may take: a finite number between ``lo`` and ``hi`` (each bound
    open or closed, None for none); ``optional``: None is allowed too. A section lists its ranges in
    ``RANGES`` (field -> Range) and ``from_dict`` refuses a value outside, naming the key: a learning
    rate of nan, an opacity of 1 (an infinite logit) or a negative interval fails before a step runs,
    not at step 0 with the renderer's or the optimiser's words."""

    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    hi_open: bool = False
    optional: bool = False
    integer: bool = False

    def describe(self) -> str:
        kind = "a whole number" if self.integer else "a finite number"
        if self.lo is not None and self.hi is not None:
            bounds = f" in {'(' if self.lo_open else '['}{self.lo:g}, {self.hi:g}{')' if self.hi_open else ']'}"
        elif self.lo is not None:
            bounds = f" {'>' if self.lo_open else '≥'} {self.lo:g}"
        elif self.hi is not None:
            bounds = f" {'<' if self.hi_open else '≤'} {self.hi:g}"
        else:
            bounds = ""
        return kind + bounds + (" (or null)" if self.optional else "")

    def holds(self, value: Any) -> bool:
        if value is None:
            return self.optional
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
            return False
        if self.integer and not float(value).is_integer():
            return False
        lo_ok = self.lo is None or (value > self.lo if self.lo_open else value >= self.lo)
        return lo_ok and (self.hi is None or (value < self.hi if self.hi_open else value <= self.hi))


def range_problems(obj: Any, where: str = "") -> list[str]:
    """``key=value: must be …`` for every field of ``obj`` outside its section's ``RANGES`` (a
    subclass's with its bases': a densification strategy's and the densify section's shared keys')."""
    ranges: dict[str, Range] = {}
    for cls in reversed(type(obj).__mro__):
        ranges.update(vars(cls).get("RANGES", {}))
    out = []
    for name, rng in ranges.items():
        value = getattr(obj, name)
        if not rng.holds(value):
            out.append(f"{where + '.' if where else ''}{name}={value!r}: must be {rng.describe()}")
    return out
