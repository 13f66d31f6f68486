"""Validation helpers of the config sections: each check raises ValueError naming the dotted key it checks."""

from __future__ import annotations

import functools
import math
import typing
from dataclasses import fields
from typing import Any, ClassVar


def _fail(path: str, message: str) -> None:
    raise ValueError(f"{path} {message}")


def _real(path: str, value: Any, *, low: float | None = None, high: float | None = None, strict_low: bool = False,
          strict_high: bool = False) -> None:
    """Check that ``value`` is a finite real number in the given bounds; ValueError naming ``path`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        _fail(path, f"must be a finite number, got {value!r}")
    if low is not None and (value <= low if strict_low else value < low):
        _fail(path, f"must be {'>' if strict_low else '>='} {low}, got {value!r}")
    if high is not None and (value >= high if strict_high else value > high):
        _fail(path, f"must be {'<' if strict_high else '<='} {high}, got {value!r}")


def _count(path: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        _fail(path, f"must be an integer >= {low}, got {value!r}")


def _choice(path: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        _fail(path, f"must be one of {list(choices)}, got {value!r}")


def _range(path: str, value: tuple[float, float], *, low: float, strict_low: bool = True) -> None:
    """A ``(lo, hi)`` sampling range with ``low < lo <= hi`` (or ``low <= lo`` when not strict)."""
    for k, v in enumerate(value):
        _real(f"{path}[{k}]", v, low=low, strict_low=strict_low)
    if value[0] > value[1]:
        _fail(path, f"must satisfy lo <= hi, got {list(value)}")


class _Section:
    """Base of the config sections: validated on construction, errors named ``<section>.<field>``."""

    SECTION: ClassVar[str] = ""

    def __post_init__(self) -> None:
        self.validate(self.SECTION)

    def validate(self, path: str) -> None:
        """Raise ValueError naming ``<path>.<field>`` for the first invalid field; every section defines it."""


def sim_fields(section: Any, sim_cls: type) -> dict:
    """The values of ``section`` for the fields of the simulator dataclass ``sim_cls`` (its base class), as
    keyword arguments of ``sim_cls``."""
    return {f.name: getattr(section, f.name) for f in fields(sim_cls) if f.init}


def _point(path: str, value: tuple[float, ...], *, optional: bool) -> None:
    """A point or vector: three finite numbers (or, when ``optional``, none: the empty tuple)."""
    if optional and not value:
        return
    if len(value) != 3:
        _fail(path, f"must be {'empty or ' if optional else ''}a list of 3 numbers (x, y, z), got {list(value)}")
    for k, v in enumerate(value):
        _real(f"{path}[{k}]", v)


@functools.cache
def _field_types(cls) -> dict[str, Any]:
    """Resolved types of the dataclass fields of ``cls`` (class variables excluded)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)}
