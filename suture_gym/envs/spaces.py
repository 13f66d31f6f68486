"""Observation layout: every component of the observation vector by index, with its unit.

The layout depends on the config only through ``observation.suture_samples`` (thread samples),
``action.mode`` (``pose_delta`` adds the holder's target) and ``observation.privileged`` (the randomised
parameters). :func:`observation_layout` gives the components in order; :func:`observation_table` expands
them to one row per index for the documentation (``python -m suture_gym.envs.spaces`` prints the table of
each task). Positions are relative to the centre of the current planned arc (the "stitch frame" origin), so
the same policy input means the same thing at every stitch. Everything is SI; the vector is float32.
"""

from __future__ import annotations

from dataclasses import dataclass

from suture_gym.envs.config import EnvConfig, default_config
from suture_gym.envs.randomization import EpisodeParams

#: Limit of the tip's signed distance in the observation, m (it is ``inf`` far from the tissue).
SDIST_CLIP = 0.05


@dataclass(frozen=True)
class ObsField:
    """One named block of the observation vector.

    Attributes:
        name: component name (``"tip_pos"``); ``start:start + size`` is its slice.
        size: number of entries.
        unit: SI unit of every entry (``"1"`` for dimensionless).
        description: what it is, in which frame.
        start: index of its first entry.
    """

    name: str
    size: int
    unit: str
    description: str
    start: int = 0

    @property
    def slice(self) -> slice:
        """Its slice of the observation vector."""
        return slice(self.start, self.start + self.size)


_BASE: tuple[tuple[str, int, str, str], ...] = (
    ("tip_pos", 3, "m", "needle tip minus the current planned arc's centre, world axes"),
    ("tip_dir", 3, "1", "unit direction in which the tip advances"),
    ("needle_normal", 3, "1", "unit normal of the needle's plane (the tip advances clockwise about it)"),
    ("grip_pos", 3, "m", "holder grip point minus the planned arc's centre"),
    ("needle_vel", 3, "m/s", "velocity of the needle body's centre of mass"),
    ("needle_omega", 3, "rad/s", "angular velocity of the needle, world frame"),
    ("entry_rel", 3, "m", "planned entry point minus the tip"),
    ("exit_rel", 3, "m", "planned exit point minus the tip"),
    ("arc_progress", 1, "1", "tip's fraction of the planned arc, 0 at entry, 1 at exit (unclamped)"),
    ("arc_distance", 1, "m", "distance from the tip to the planned circle"),
    ("tip_sdist", 1, "m", f"signed distance of the tip to the tissue surface, clipped to +-{SDIST_CLIP}"),
    ("punctured", 1, "1", "1 while the tip is inside the tissue along an open path, else 0"),
    ("stitch", 1, "1", "index of the current planned stitch"),
    ("stitch_exited", 1, "1", "1 once the current stitch's final exit happened, else 0"),
    ("tip_force", 1, "N", "force of the tip on the surface before puncturing"),
    ("tissue_force", 1, "N", "largest coupling-constraint force in the last substep"),
    ("haptic_force", 3, "N", "force the constraints exert on the needle (the haptic reaction)"),
    ("haptic_torque", 3, "N m", "torque the constraints exert on the needle, about the grip point"),
    ("wound_gap", 1, "m", "mean gap between the wound faces' free upper halves (0 without a wound)"),
    ("thread_through", 1, "m", "thread pulled out of the newest exit point"),
)


def observation_layout(config: EnvConfig) -> tuple[ObsField, ...]:
    """The observation components of ``config``, in order, with their start indices."""
    spec = list(_BASE)
    samples = config.observation.suture_samples if config.suture.node_count else 0
    if samples:
        spec.append(("suture_samples", 3 * samples, "m",
                     f"{samples} thread nodes from the swage to the tail, minus the planned arc's centre"))
    if config.action.mode == "pose_delta":
        spec.append(("target_offset", 3, "m", "holder target position minus the grip point"))
        spec.append(("target_rotation", 3, "rad", "rotation vector from the needle to the target orientation"))
    if config.observation.privileged:
        names = ", ".join(f"{n} ({u})" for n, u in EpisodeParams.LAYOUT)
        spec.append(("params", len(EpisodeParams.LAYOUT), "mixed", f"randomised episode parameters: {names}"))
    fields_, start = [], 0
    for name, size, unit, description in spec:
        fields_.append(ObsField(name, size, unit, description, start))
        start += size
    return tuple(fields_)


def observation_size(layout: tuple[ObsField, ...]) -> int:
    """Length of the observation vector."""
    return layout[-1].start + layout[-1].size


def observation_table(layout: tuple[ObsField, ...]) -> list[tuple[int, str, str, str]]:
    """One ``(index, name, unit, description)`` row per entry; vector components get ``_x/_y/_z`` or ``[k]``."""
    rows = []
    for f in layout:
        if f.name == "params":
            for k, (name, unit) in enumerate(EpisodeParams.LAYOUT):
                rows.append((f.start + k, f"params.{name}", unit, "randomised episode parameter"))
            continue
        for k in range(f.size):
            suffix = "" if f.size == 1 else ("_" + "xyz"[k] if f.size == 3 else f"[{k}]")
            rows.append((f.start + k, f.name + suffix, f.unit, f.description))
    return rows


def main() -> None:
    """Print the observation table of each task's default config."""
    from suture_gym.envs.registry import registered_tasks

    for task in registered_tasks():
        layout = observation_layout(default_config(task))
        print(f"{task}: {observation_size(layout)} entries")
        for index, name, unit, description in observation_table(layout):
            print(f"  {index:3d}  {name:28s} {unit:7s} {description}")


if __name__ == "__main__":
    main()
