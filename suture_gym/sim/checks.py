"""Argument checks shared by the simulator's constructors and phase functions (one definition each)."""

from __future__ import annotations

import math
import numbers

import numpy as np


def is_real(value) -> bool:
    """True for a real number that is not a bool (``numbers.Real``: Python and NumPy ints and floats)."""
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


def require_positive(name: str, value) -> None:
    """Raise ValueError unless ``value`` is a finite real number > 0 (any unit; ``name`` names it)."""
    if not (is_real(value) and math.isfinite(value) and value > 0.0):
        raise ValueError(f"{name} must be a finite number > 0, got {value!r}")


def require_non_negative(name: str, value) -> None:
    """Raise ValueError unless ``value`` is a finite real number >= 0 (any unit; ``name`` names it)."""
    if not (is_real(value) and math.isfinite(value) and value >= 0.0):
        raise ValueError(f"{name} must be a finite number >= 0, got {value!r}")


def finite_array(name: str, value, shape: tuple) -> np.ndarray:
    """``value`` as a float64 array of exactly ``shape`` with finite entries; ValueError otherwise."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != shape:
        raise ValueError(f"{name} must have shape {shape}, got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr
