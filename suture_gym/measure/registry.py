"""Registries of physics checks and benchmarks.

A check is a function ``() -> CheckResult`` comparing a simulated quantity with an analytic reference.
A benchmark is a function ``() -> dict`` returning the fields of the measurement contract
(``scene, tets, particles, strand_nodes, substep_ms, substeps_per_s, collision_fraction,
solver_fraction``, or ``env_steps_per_s`` for environments).
"""

from __future__ import annotations

import importlib
import math
from collections.abc import Callable
from dataclasses import asdict, dataclass, field

#: Modules that define checks and benchmarks; imported by :func:`load_all`.
MODULES: tuple[str, ...] = (
    "suture_gym.measure.tissue",
    "suture_gym.measure.tissue_stiff",
    "suture_gym.measure.strands",
    "suture_gym.measure.interaction",
    "suture_gym.measure.puncture",
    "suture_gym.measure.support",
    "suture_gym.measure.insertion",
    "suture_gym.measure.friction",
    "suture_gym.measure.collision",
    "suture_gym.measure.render",
    "suture_gym.measure.envs",
    "suture_gym.measure.anatomy",
)

CHECKS: dict[str, Callable[[], CheckResult]] = {}
BENCHMARKS: dict[str, Callable[[], dict]] = {}


@dataclass
class CheckResult:
    """Outcome of one validation check.

    ``passed`` is computed from the numbers, never set by hand: by default
    ``|measured - reference| <= tolerance``; a check whose criterion is one-sided (a bound such as
    "stretch under 0.5 %") passes ``comparison="<="`` and then ``measured <= reference + tolerance``.
    ``settings`` records every parameter the check used (mesh, material, dt, iterations...), so a result
    can be reproduced from its JSON alone.
    """

    name: str
    measured: float
    reference: float
    tolerance: float
    unit: str
    comparison: str = "abs"
    settings: dict = field(default_factory=dict)
    details: dict = field(default_factory=dict)

    @property
    def passed(self) -> bool:
        if not (math.isfinite(self.measured) and math.isfinite(self.reference)):
            return False
        if self.comparison == "abs":
            return abs(self.measured - self.reference) <= self.tolerance
        if self.comparison == "rel":
            return abs(self.measured - self.reference) <= self.tolerance * abs(self.reference)
        if self.comparison == "<=":
            return self.measured <= self.reference + self.tolerance
        if self.comparison == ">=":
            return self.measured >= self.reference - self.tolerance
        raise ValueError(f"unknown comparison {self.comparison!r}; expected 'abs', 'rel', '<=' or '>='")

    def to_dict(self) -> dict:
        out = asdict(self)
        out["passed"] = self.passed
        return out


def _register(table: dict, kind: str, name: str) -> Callable:
    def deco(fn: Callable) -> Callable:
        if name in table:
            raise ValueError(f"{kind} {name!r} is registered twice")
        table[name] = fn
        return fn

    return deco


def check(name: str) -> Callable:
    """Register a validation check under ``name`` (the ``name`` field of its JSON entry)."""
    return _register(CHECKS, "check", name)


def benchmark(name: str) -> Callable:
    """Register a benchmark under ``name`` (the ``scene`` field of its JSON entry)."""
    return _register(BENCHMARKS, "benchmark", name)


def load_all() -> None:
    """Import every module in :data:`MODULES` so that their checks and benchmarks register."""
    for module in MODULES:
        importlib.import_module(module)
