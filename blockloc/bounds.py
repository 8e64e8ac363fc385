"""Ranges a parameter must lie in, declared beside the parameter (ground floor: the core's
parameter dataclasses and ``blockloc.config`` both use them; the config checks every loaded value
against a field's ``bounds`` metadata)."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Bounds:
    """The range a config value must lie in: ``low`` / ``high`` (None: unbounded), each open
    (excluded) or closed. Tuples are checked value by value."""

    low: float | None = None
    high: float | None = None
    low_open: bool = False
    high_open: bool = False

    def contains(self, value: float) -> bool:
        if self.low is not None and (value <= self.low if self.low_open else value < self.low):
            return False
        return not (self.high is not None and (value >= self.high if self.high_open else value > self.high))

    def __str__(self) -> str:
        if self.high is None:
            return f"{'>' if self.low_open else '>='} {self.low:g}"
        return (f"in {'(' if self.low_open else '['}{self.low:g}, {self.high:g}"
                f"{')' if self.high_open else ']'}")


POSITIVE = Bounds(0.0, low_open=True)  # sizes, rates, noise densities
NON_NEGATIVE = Bounds(0.0)  # distances where 0 switches a feature off, retries, extra levels
COUNT = Bounds(1.0)  # integer counts of at least one
PROBABILITY = Bounds(0.0, 1.0, low_open=True, high_open=True)
FRACTION = Bounds(0.0, 1.0)
ANGLE_WINDOW = Bounds(0.0, 360.0, low_open=True)  # degrees


def bounded(default: Any, bounds: Bounds):
    """A dataclass field with ``default`` whose loaded values must lie in ``bounds``."""
    return field(default=default, metadata={"bounds": bounds})
