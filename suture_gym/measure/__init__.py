"""Physics validation checks and benchmarks behind ``scripts/validate_physics.py`` and ``scripts/bench.py``.

Checks and benchmarks register themselves with :func:`check` and :func:`benchmark`; the scripts import
the modules listed in :data:`MODULES` and run what is registered, so adding a measurement is one decorated
function in one module.
"""

from suture_gym.measure.registry import (
    BENCHMARKS,
    CHECKS,
    MODULES,
    CheckResult,
    benchmark,
    check,
    load_all,
)

__all__ = ["BENCHMARKS", "CHECKS", "MODULES", "CheckResult", "benchmark", "check", "load_all"]
