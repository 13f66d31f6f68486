"""The fast part of the physics validation, in the test suite.

``scripts/validate_physics.py`` runs every registered check (minutes); the checks named here take a few seconds
each and run with every ``pytest``, so a change that breaks an analytic reference fails CI, not only a later
``make validate``. Each check's verdict is computed by :class:`~suture_gym.measure.registry.CheckResult` from its
own numbers and tolerance; the test asserts it and prints the figures on failure.
"""

from __future__ import annotations

import pytest

from suture_gym.measure import CHECKS, load_all

#: Checks that take under about three seconds each on one core (wall times of ``validate_physics.py --json``).
FAST_CHECKS = (
    "hanging_bar",
    "volume_compression",
    "dt_independence",
    "residual_decrease",
    "needle_free_flight",
    "suture_stretch_pull",
    "suture_pull_jitter",
    "rod_cantilever",
    "rod_dt_independence",
    "thread_extension_sweeps",
    "tip_force_profile",
    "env_needle_insert_scripted_accuracy",
)

load_all()


def test_fast_checks_are_registered():
    missing = [name for name in FAST_CHECKS if name not in CHECKS]
    assert not missing, f"fast checks not registered: {missing}"


@pytest.mark.parametrize("name", FAST_CHECKS)
def test_physics_check_passes(name):
    result = CHECKS[name]()
    assert result.name == name
    assert result.passed, (
        f"{name}: measured {result.measured!r} {result.unit} vs reference {result.reference!r} "
        f"(tolerance {result.tolerance!r}, {result.comparison}); settings {result.settings}"
    )
