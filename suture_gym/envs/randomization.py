"""Seeded domain randomisation: the per-episode physical parameters and how they are sampled.

:func:`sample_params` draws every parameter from the env's generator in one fixed order, whatever the config
enables (a disabled range has ``lo == hi`` and returns its nominal value exactly), so the same seed gives the
same parameters and the same random stream after them.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from suture_gym.envs.config import EnvConfig


@dataclass(frozen=True)
class EpisodeParams:
    """Physical parameters of one episode.

    Attributes:
        youngs_modulus: tissue Young's modulus, Pa.
        puncture_force: tip force that pierces the surface, N.
        gap: wound gap at rest, m (the scene's nominal value for a pad, where it is unused).
        needle_position_offset: ``(3,) float64`` offset of the needle's start position from the plan, m.
        needle_rotation_offset: ``(3,) float64`` rotation vector applied to the planned start orientation
            (about the needle's grip point, world frame), rad.
    """

    youngs_modulus: float
    puncture_force: float
    gap: float
    needle_position_offset: np.ndarray
    needle_rotation_offset: np.ndarray

    def __post_init__(self) -> None:
        for name in ("youngs_modulus", "puncture_force", "gap"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float)) or not (
                math.isfinite(value) and value > 0.0
            ):
                raise ValueError(f"EpisodeParams.{name} must be a finite number > 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("needle_position_offset", "needle_rotation_offset"):
            arr = np.array(getattr(self, name), dtype=np.float64)
            if arr.shape != (3,) or not np.all(np.isfinite(arr)):
                raise ValueError(f"EpisodeParams.{name} must be three finite numbers, got {getattr(self, name)!r}")
            arr.flags.writeable = False
            object.__setattr__(self, name, arr)

    #: Names of the components of :meth:`as_array`, with units.
    LAYOUT = (
        ("youngs_modulus", "Pa"),
        ("puncture_force", "N"),
        ("gap", "m"),
        ("needle_position_offset_x", "m"),
        ("needle_position_offset_y", "m"),
        ("needle_position_offset_z", "m"),
        ("needle_rotation_offset_x", "rad"),
        ("needle_rotation_offset_y", "rad"),
        ("needle_rotation_offset_z", "rad"),
    )

    def as_array(self) -> np.ndarray:
        """``(9,) float64`` in the order of :attr:`LAYOUT`."""
        return np.concatenate(
            [[self.youngs_modulus, self.puncture_force, self.gap], self.needle_position_offset,
             self.needle_rotation_offset]
        )

    def to_dict(self) -> dict:
        """Plain-data copy (lists for the vectors)."""
        return {f.name: (v.tolist() if isinstance(v := getattr(self, f.name), np.ndarray) else v)
                for f in fields(self)}

    def physics_key(self) -> tuple[float, float, float]:
        """The parameters that change the physical model (the needle offsets only move the start pose)."""
        return (self.youngs_modulus, self.puncture_force, self.gap)

    def with_overrides(self, overrides: dict) -> EpisodeParams:
        """A copy with the named fields replaced; unknown names raise ValueError naming them."""
        if not isinstance(overrides, dict):
            raise ValueError(f"options['params'] must be a mapping, got {type(overrides).__name__}")
        known = {f.name for f in fields(self)}
        unknown = sorted(str(k) for k in overrides if k not in known)
        if unknown:
            raise ValueError(f"unknown episode parameter(s) {unknown}; known: {sorted(known)}")
        return replace(self, **overrides)


def nominal_params(config: EnvConfig) -> EpisodeParams:
    """The parameters of ``config`` without randomisation."""
    return EpisodeParams(
        youngs_modulus=config.tissue.youngs_modulus,
        puncture_force=config.coupling.puncture_force,
        gap=config.scene.gap,
        needle_position_offset=np.zeros(3),
        needle_rotation_offset=np.zeros(3),
    )


def _log_uniform(rng: np.random.Generator, bounds: tuple[float, float]) -> float:
    lo, hi = bounds
    return math.exp(rng.uniform(math.log(lo), math.log(hi)))


def sample_params(config: EnvConfig, rng: np.random.Generator) -> EpisodeParams:
    """Draw one episode's parameters from ``rng``, in the order: Young's modulus factor, puncture force factor,
    gap factor, position offset (x, y, z), rotation offset (x, y, z); with ``randomization.enabled`` false the
    draws are made all the same and the nominal parameters returned. A scene without a wound (``pad``) keeps
    its nominal gap, which it does not use."""
    r = config.randomization
    nominal = nominal_params(config)
    e_scale = _log_uniform(rng, r.youngs_modulus_scale)
    f_scale = _log_uniform(rng, r.puncture_force_scale)
    g_scale = _log_uniform(rng, r.gap_scale)
    position = rng.uniform(-r.needle_position_noise, r.needle_position_noise, size=3)
    rotation = rng.uniform(-r.needle_rotation_noise, r.needle_rotation_noise, size=3)
    if not r.enabled:
        return nominal
    return EpisodeParams(
        youngs_modulus=nominal.youngs_modulus * e_scale,
        puncture_force=nominal.puncture_force * f_scale,
        gap=nominal.gap * (g_scale if config.scene.kind != "pad" else 1.0),
        needle_position_offset=position,
        needle_rotation_offset=rotation,
    )
