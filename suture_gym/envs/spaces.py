"""Observation layout: every component of the observation vector by index, with its unit and scale.

The layout depends on the config only through ``observation.suture_samples`` (thread samples),
``action.mode`` (``pose_delta`` adds the holder's target) and ``observation.privileged`` (the randomised
parameters), never on the randomisation's settings. :func:`observation_layout` gives the components in order;
:func:`observation_table` expands them to one row per index for the documentation (``python -m
suture_gym.envs.spaces`` prints the table of each task). Positions are relative to the centre of the current
planned arc (the "stitch frame" origin), so the same policy input means the same thing at every stitch.

Units: with ``observation.scaled`` (the default since ids v2) every entry is its SI value divided by its
field's ``scale`` (in the field's unit: :data:`LENGTH_SCALE` for lengths, the action's ``max_force`` and
``max_torque`` for forces and torques, ...) and clipped to ``[-bound, bound]``, so a policy sees O(1) numbers
in a box with finite bounds; with ``scaled: false`` it is the raw SI value (scale 1, infinite bounds). The
vector is float32.

The other ``observation.mode`` values give a ``Dict`` of camera images or a point cloud beside this vector
(:func:`sensor_spaces`, :mod:`suture_gym.envs.sensors`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import gymnasium as gym
import numpy as np

from suture_gym.envs.config import EnvConfig, default_config
from suture_gym.envs.randomization import EpisodeParams, nominal_params

#: Limit of the tip's signed distance in the observation, m (it is ``inf`` far from the tissue).
SDIST_CLIP = 0.05
#: Scale of lengths in a scaled observation, m (a stitch spans about a centimetre).
LENGTH_SCALE = 0.01
#: Scale of the needle's speed, m/s, and angular speed, rad/s.
SPEED_SCALE = 0.05
ANGULAR_SPEED_SCALE = 1.0
#: Bound of a scaled entry (in scale units) unless its field has a tighter one.
OBS_BOUND = 10.0
#: Bound of the point cloud's coordinates, m (far beyond any scene; :mod:`suture_gym.envs.sensors`).
POINT_CLOUD_BOUND = 10.0


@dataclass(frozen=True)
class ObsField:
    """One named block of the observation vector.

    Attributes:
        name: component name (``"tip_pos"``); ``start:start + size`` is its slice.
        size: number of entries.
        unit: SI unit of every entry's raw value (``"1"`` for dimensionless; ``"mixed"`` for ``params``).
        description: what it is, in which frame.
        start: index of its first entry.
        scale: ``(size,)`` raw value (in ``unit``) of one observation unit per entry (1 with ``scaled: false``).
        bound: ``(size,)`` the entries lie in ``[-bound, bound]`` (``inf`` with ``scaled: false``).
    """

    name: str
    size: int
    unit: str
    description: str
    start: int = 0
    scale: tuple[float, ...] = ()
    bound: tuple[float, ...] = ()

    @property
    def slice(self) -> slice:
        """Its slice of the observation vector."""
        return slice(self.start, self.start + self.size)


#: (name, size, unit, scale kind, bound or None for OBS_BOUND, description)
_BASE: tuple[tuple[str, int, str, str, float | None, str], ...] = (
    ("tip_pos", 3, "m", "length", None, "needle tip minus the current planned arc's centre, world axes"),
    ("tip_dir", 3, "1", "one", 1.0, "unit direction in which the tip advances"),
    ("needle_normal", 3, "1", "one", 1.0, "unit normal of the needle's plane (the tip advances clockwise about it)"),
    ("grip_pos", 3, "m", "length", None, "holder grip point minus the planned arc's centre"),
    ("needle_vel", 3, "m/s", "speed", None, "velocity of the needle body's centre of mass"),
    ("needle_omega", 3, "rad/s", "angular_speed", None, "angular velocity of the needle, world frame"),
    ("entry_rel", 3, "m", "length", None, "planned entry point minus the tip"),
    ("exit_rel", 3, "m", "length", None, "planned exit point minus the tip"),
    ("arc_progress", 1, "1", "one", None, "tip's fraction of the planned arc, 0 at entry, 1 at exit (unclamped)"),
    ("arc_distance", 1, "m", "length", None, "distance from the tip to the planned circle"),
    ("tip_sdist", 1, "m", "length", SDIST_CLIP / LENGTH_SCALE,
     f"signed distance of the tip to the tissue surface, clipped to +-{SDIST_CLIP} m"),
    ("punctured", 1, "1", "one", 1.0, "1 while the tip is inside the tissue along an open path, else 0"),
    ("stitch", 1, "1", "one", "stitches", "index of the current planned stitch"),
    ("stitch_exited", 1, "1", "one", 1.0, "1 once the current stitch's final exit happened, else 0"),
    ("tip_force", 1, "N", "force", None, "force of the tip on the surface before puncturing"),
    ("tissue_force", 1, "N", "force", None, "largest coupling-constraint force in the last substep"),
    ("haptic_force", 3, "N", "force", None, "force the constraints exert on the needle (the haptic reaction)"),
    ("haptic_torque", 3, "N m", "torque", None, "torque the constraints exert on the needle, about the grip point"),
    ("wound_gap", 1, "m", "length", None, "mean gap between the wound faces' free upper halves (0 without a wound)"),
    ("thread_through", 1, "m", "length", None, "thread pulled out of the newest exit point"),
)


def _scales(config: EnvConfig) -> dict[str, float]:
    """Raw value of one observation unit for each scale kind (all 1 with ``observation.scaled`` false)."""
    if not config.observation.scaled:
        return dict.fromkeys(("one", "length", "speed", "angular_speed", "force", "torque", "angle"), 1.0)
    return {"one": 1.0, "length": LENGTH_SCALE, "speed": SPEED_SCALE, "angular_speed": ANGULAR_SPEED_SCALE,
            "force": config.action.max_force, "torque": config.action.max_torque, "angle": 1.0}


def observation_layout(config: EnvConfig) -> tuple[ObsField, ...]:
    """The observation components of ``config``, in order, with their start indices, scales and bounds."""
    spec = list(_BASE)
    samples = config.observation.suture_samples if config.suture.node_count else 0
    if samples:
        spec.append(("suture_samples", 3 * samples, "m", "length", None,
                     f"{samples} thread nodes from the swage to the tail, minus the planned arc's centre"))
    if config.action.mode == "pose_delta":
        spec.append(("target_offset", 3, "m", "length", None, "holder target position minus the grip point"))
        spec.append(("target_rotation", 3, "rad", "angle", math.pi,
                     "rotation vector from the needle to the target orientation"))
    if config.observation.privileged:
        names = ", ".join(f"{n} ({u})" for n, u in EpisodeParams.LAYOUT)
        spec.append(("params", len(EpisodeParams.LAYOUT), "mixed", "params", None,
                     f"randomised episode parameters: {names}"))
    scales = _scales(config)
    nominal = nominal_params(config)
    params_scale = (nominal.youngs_modulus, nominal.puncture_force, nominal.gap) + (scales["length"],) * 3 + (
        scales["angle"],) * 3
    params_bound = (OBS_BOUND,) * 6 + (math.pi,) * 3
    fields_, start = [], 0
    for name, size, unit, kind, bound, description in spec:
        if kind == "params":
            scale = params_scale if config.observation.scaled else (1.0,) * size
            bounds = params_bound
        else:
            scale = (scales[kind],) * size
            limit = float(config.plan.stitches) if bound == "stitches" else OBS_BOUND if bound is None else bound
            bounds = (limit,) * size
        if not config.observation.scaled:
            bounds = (math.inf,) * size
        fields_.append(ObsField(name, size, unit, description, start, tuple(scale), tuple(bounds)))
        start += size
    return tuple(fields_)


def observation_scale(layout: tuple[ObsField, ...]) -> tuple[np.ndarray, np.ndarray]:
    """``(scale (n,), bound (n,))`` float64 of every entry: observation = clip(raw / scale, -bound, bound)."""
    return (np.array([v for f in layout for v in f.scale], dtype=np.float64),
            np.array([v for f in layout for v in f.bound], dtype=np.float64))


def observation_size(layout: tuple[ObsField, ...]) -> int:
    """Length of the observation vector."""
    return layout[-1].start + layout[-1].size


def observation_table(layout: tuple[ObsField, ...]) -> list[tuple[int, str, str, float, float, str]]:
    """One ``(index, name, unit, scale, bound, description)`` row per entry (``scale`` in ``unit`` per
    observation unit); vector components get ``_x/_y/_z`` or ``[k]``."""
    rows = []
    for f in layout:
        if f.name == "params":
            for k, (name, unit) in enumerate(EpisodeParams.LAYOUT):
                rows.append((f.start + k, f"params.{name}", unit, f.scale[k], f.bound[k],
                             "randomised episode parameter"))
            continue
        for k in range(f.size):
            suffix = "" if f.size == 1 else ("_" + "xyz"[k] if f.size == 3 else f"[{k}]")
            rows.append((f.start + k, f.name + suffix, f.unit, f.scale[k], f.bound[k], f.description))
    return rows


def point_cloud_size(config: EnvConfig) -> int:
    """Rows N of the ``point_cloud`` observation: the tissue's and the needle's points, and the thread's in a scene
    with one."""
    pc = config.observation.point_cloud
    return pc.tissue + pc.needle + (pc.suture if config.suture.node_count else 0)


def sensor_spaces(config: EnvConfig) -> dict[str, gym.spaces.Box]:
    """The spaces of the image or point-cloud keys of ``config``'s ``observation.mode`` (none for ``state``):
    ``rgb`` ``Box(0, 255, (H, W, 3), uint8)``, ``depth`` ``Box(0, far, (H, W, 1), float32)`` m and
    ``point_cloud`` ``Box(-POINT_CLOUD_BOUND, POINT_CLOUD_BOUND, (N, 3), float32)`` m."""
    mode = config.observation.mode
    cam = config.observation.camera
    spaces = {}
    if mode in ("rgb", "rgbd"):
        spaces["rgb"] = gym.spaces.Box(0, 255, (cam.height, cam.width, 3), np.uint8)
    if mode in ("depth", "rgbd"):
        spaces["depth"] = gym.spaces.Box(0.0, cam.far, (cam.height, cam.width, 1), np.float32)
    if mode == "point_cloud":
        spaces["point_cloud"] = gym.spaces.Box(-POINT_CLOUD_BOUND, POINT_CLOUD_BOUND, (point_cloud_size(config), 3),
                                               np.float32)
    return spaces


def main() -> None:
    """Print the observation table of each task's default config."""
    from suture_gym.envs.registry import registered_tasks

    for task in registered_tasks():
        layout = observation_layout(default_config(task))
        print(f"{task}: {observation_size(layout)} entries")
        for index, name, unit, scale, bound, description in observation_table(layout):
            print(f"  {index:3d}  {name:28s} {unit:7s} scale {scale:<10.4g} bound {bound:<6.4g} {description}")


if __name__ == "__main__":
    main()
