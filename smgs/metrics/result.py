"""A metric that could not be computed, with the reason, so reports print why instead of a number."""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypeVar, Union

T = TypeVar("T")


@dataclass(frozen=True)
class Missing:
    """Stands in for a metric value that was not computed (never a made-up number)."""

    reason: str

    def __str__(self) -> str:
        return f"missing: {self.reason}"

    def to_json(self) -> dict[str, str]:
        return {"missing": self.reason}


MaybeValue = Union[T, Missing]


def is_missing(value: object) -> bool:
    return isinstance(value, Missing)


def json_value(value: object) -> object:
    """A value as results.json stores it: numbers as they are, ``Missing`` as {"missing": reason}."""
    if isinstance(value, Missing):
        return value.to_json()
    if isinstance(value, (list, tuple)):
        return [json_value(v) for v in value]
    if isinstance(value, dict):
        return {k: json_value(v) for k, v in value.items()}
    return value
