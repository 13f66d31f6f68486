"""Planned stitches: the needle's own circle, turned about its centre, and where it crosses the tissue surfaces.

A curved needle of curvature radius ``R`` driven by turning it about its own centre moves its tip along its own
circle, so that circle is the ideal path (the planned arc). Its entry and exit markers are where the circle
meets the tissue's top surface on either side of the centre; over a wound it also crosses the two wound faces.

Frame of a planned arc: in-plane axes ``u`` (angle 0) and ``v = axis x u``; a point at angle ``phi`` is
``center + R (cos(phi) u + sin(phi) v)``. The tip advances counter-clockwise about ``axis`` (increasing angle),
from the entry angle to the exit angle through the bottom of the circle (angle ``-pi/2``).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def _unit(name: str, value) -> np.ndarray:
    arr = np.array(value, dtype=np.float64)
    norm = float(np.linalg.norm(arr)) if arr.shape == (3,) else 0.0
    if arr.shape != (3,) or not math.isfinite(norm) or norm == 0.0:
        raise ValueError(f"{name} must be a finite non-zero (3,) vector, got {value!r}")
    return arr / norm


@dataclass(frozen=True)
class PlannedArc:
    """One planned stitch (see the module docstring for the frame).

    Attributes:
        center: ``(3,) float64`` centre of the circle, m.
        axis: ``(3,) float64`` unit normal of its plane; the tip advances counter-clockwise about it.
        u: ``(3,) float64`` unit in-plane direction of angle 0 (``v = axis x u``).
        radius: circle radius (the needle's curvature radius), m.
        access_angles: ``(K,) float64`` increasing angles of the planned surface crossings, rad: entry first,
            exit last; over a wound ``[entry, left face, right face, exit]``.
        v: ``(3,) float64`` unit in-plane direction of angle ``pi/2``, ``axis x u`` (derived).
        access_points: ``(K, 3) float64`` those crossings, m (derived). Even indices are entries into tissue,
            odd ones exits from it.
    """

    center: np.ndarray
    axis: np.ndarray
    u: np.ndarray
    radius: float
    access_angles: np.ndarray
    v: np.ndarray = field(init=False, repr=False)
    access_points: np.ndarray = field(init=False, repr=False)

    def __post_init__(self) -> None:
        center = np.array(self.center, dtype=np.float64)
        if center.shape != (3,) or not np.all(np.isfinite(center)):
            raise ValueError(f"PlannedArc.center must be a finite (3,) point in m, got {self.center!r}")
        axis = _unit("PlannedArc.axis", self.axis)
        u = _unit("PlannedArc.u", self.u)
        if abs(float(axis @ u)) > 1e-9:
            raise ValueError("PlannedArc.u must be orthogonal to PlannedArc.axis")
        if not (math.isfinite(self.radius) and self.radius > 0.0):
            raise ValueError(f"PlannedArc.radius must be > 0 m, got {self.radius!r}")
        angles = np.array(self.access_angles, dtype=np.float64)
        if angles.ndim != 1 or len(angles) < 2 or len(angles) % 2 or np.any(np.diff(angles) <= 0.0):
            raise ValueError("PlannedArc.access_angles must be an even number (>= 2) of increasing angles in rad")
        if angles[-1] - angles[0] >= 2.0 * math.pi:
            raise ValueError("PlannedArc.access_angles must span less than a full turn")
        v = np.cross(axis, u)
        for name, value in (("center", center), ("axis", axis), ("u", u), ("v", v), ("access_angles", angles)):
            value.flags.writeable = False
            object.__setattr__(self, name, value)
        object.__setattr__(self, "radius", float(self.radius))
        points = np.stack([self.point(a) for a in angles])
        points.flags.writeable = False
        object.__setattr__(self, "access_points", points)

    @property
    def entry(self) -> np.ndarray:
        """``(3,)`` planned entry point, m."""
        return self.access_points[0]

    @property
    def exit(self) -> np.ndarray:
        """``(3,)`` planned exit point, m."""
        return self.access_points[-1]

    @property
    def entry_angle(self) -> float:
        """Angle of the entry point, rad."""
        return float(self.access_angles[0])

    @property
    def exit_angle(self) -> float:
        """Angle of the exit point, rad."""
        return float(self.access_angles[-1])

    @property
    def pull_direction(self) -> np.ndarray:
        """``(3,)`` unit direction in which to pull the thread once the needle is out: back across the wound
        and up, ``normalize(-u + 0.5 v)`` (drawing the far edge toward the near one)."""
        d = -self.u + 0.5 * self.v
        return d / np.linalg.norm(d)

    @property
    def access_progress(self) -> np.ndarray:
        """``(K,)`` fraction of the arc at each planned surface crossing (0 at the entry, 1 at the exit)."""
        return (self.access_angles - self.entry_angle) / (self.exit_angle - self.entry_angle)

    def point(self, angle: float) -> np.ndarray:
        """``(3,)`` point of the circle at ``angle`` (rad), m."""
        return self.center + self.radius * (math.cos(angle) * self.u + math.sin(angle) * self.v)

    def tangent(self, angle: float) -> np.ndarray:
        """``(3,)`` unit direction of travel at ``angle`` (rad)."""
        return -math.sin(angle) * self.u + math.cos(angle) * self.v

    def angle(self, p: np.ndarray) -> float:
        """Angle (rad) of point ``p`` (3,) m about the centre, within pi of the arc's middle angle.

        The branch cut is opposite the middle of the planned arc (above the centre), where the tip never has
        to go while it follows the arc. A point on the axis gets the middle angle.
        """
        r = np.asarray(p, dtype=np.float64) - self.center
        x, y = float(r @ self.u), float(r @ self.v)
        mid = 0.5 * (self.entry_angle + self.exit_angle)
        if x == 0.0 and y == 0.0:
            return mid
        return mid + math.remainder(math.atan2(y, x) - mid, 2.0 * math.pi)

    def progress(self, p: np.ndarray) -> float:
        """Fraction of the arc from entry (0) to exit (1) at the angle of ``p`` (3,) m; unclamped."""
        return (self.angle(p) - self.entry_angle) / (self.exit_angle - self.entry_angle)

    def distance(self, p: np.ndarray) -> float:
        """Distance (m) from ``p`` (3,) m to the circle: ``sqrt((rho - R)^2 + h^2)`` with ``rho`` the in-plane
        distance from the centre and ``h`` the offset from the plane."""
        r = np.asarray(p, dtype=np.float64) - self.center
        h = float(r @ self.axis)
        rho = math.hypot(float(r @ self.u), float(r @ self.v))
        return math.hypot(rho - self.radius, h)


def plan_stitches(
    kind: str,
    size: tuple[float, float, float],
    gap: float,
    radius: float,
    center_height: float,
    stitches: int,
) -> tuple[PlannedArc, ...]:
    """The planned arcs of a scene (geometry of :class:`~suture_gym.envs.config.SceneConfig`).

    Every arc lies in a plane ``x = size_x (i + 1) / (stitches + 1)`` with ``axis = +x`` and ``u = +y``; its
    centre is ``center_height * radius`` above the top surface ``z = size_z``, over the middle of the pad
    (``kind="pad"``) or of the wound gap (``kind="wound"``, gap between ``y = size_y`` and ``y = size_y + gap``).

    Args:
        kind: ``"pad"`` or ``"wound"``.
        size: ``(x, y, z)`` of the pad or of each bar, m.
        gap: wound gap, m (ignored for a pad).
        radius: needle curvature radius, m.
        center_height: height of the centre above the surface as a fraction of ``radius``, in (0, 1).
        stitches: number of arcs (>= 1).

    Raises:
        ValueError: when the circle does not reach the surface inside the tissue on both sides, or (wound) does
            not cross the wound faces below the surface.
    """
    if not 0.0 < center_height < 1.0:
        raise ValueError(f"center_height must lie in (0, 1), got {center_height!r}")
    sx, sy, sz = (float(s) for s in size)
    h = center_height * radius
    half_chord = math.sqrt(radius * radius - h * h)
    entry = -math.pi + math.asin(center_height)
    exit_ = -math.asin(center_height)
    if kind == "pad":
        cy = 0.5 * sy
        if half_chord >= cy:
            raise ValueError(f"the planned chord ({2 * half_chord:.4g} m) does not fit on the pad (y size {sy} m)")
        angles = [entry, exit_]
    elif kind == "wound":
        cy = sy + 0.5 * gap
        if half_chord >= sy + 0.5 * gap:
            raise ValueError(f"the planned chord ({2 * half_chord:.4g} m) reaches past the bars (y size {sy} m)")
        if 0.5 * gap >= half_chord:
            raise ValueError(f"the wound gap ({gap} m) is wider than the planned chord ({2 * half_chord:.4g} m)")
        face = math.acos(0.5 * gap / radius)
        angles = [entry, -math.pi + face, -face, exit_]
    else:
        raise ValueError(f"kind must be 'pad' or 'wound', got {kind!r}")
    arcs = []
    for i in range(stitches):
        center = np.array([sx * (i + 1) / (stitches + 1), cy, sz + h])
        arcs.append(PlannedArc(center, (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), radius, np.array(angles)))
    return tuple(arcs)


def plan_across_incision(
    points: np.ndarray,
    inside,
    radius: float,
    center_height: float,
    stitches: int,
    samples: int = 2048,
) -> tuple[PlannedArc, ...]:
    """The planned arcs across an incision on any tissue, with the crossings found on the tissue itself.

    Stitch ``i`` sits at the arc length ``L (i + 1) / (stitches + 1)`` of the incision's polyline (length ``L``):
    its circle lies in the plane normal to the polyline there (``axis`` its direction, ``u = z x axis``
    normalised, so ``u`` points to the wound's right face when the incision runs along ``+x``), centred
    ``center_height * radius`` above the polyline point along ``v = axis x u`` (up). The surface crossings are
    where ``inside`` changes along the circle's lower half (``samples`` angles, each refined by bisection to
    1e-9 rad): entry, left face, right face, exit.

    Args:
        points: ``(K, 3)`` the incision polyline on the surface, m (the middle of the wound's mouth), heading
            along ``+x`` more than along ``z`` (the needle comes from above, ``+z``).
        inside: callable ``(M, 3) m -> (M,) bool``: whether points lie inside the tissue at rest.
        radius: needle curvature radius, m; center_height: in (0, 1); stitches: >= 1.

    Raises:
        ValueError: when a circle does not cross the tissue surface exactly four times (the wound too shallow
            for the needle's arc, or the arc leaving the tissue elsewhere), naming the stitch and the crossings.
    """
    if not 0.0 < center_height < 1.0:
        raise ValueError(f"center_height must lie in (0, 1), got {center_height!r}")
    points = np.asarray(points, dtype=np.float64)
    seg = np.diff(points, axis=0)
    s = np.concatenate([[0.0], np.cumsum(np.linalg.norm(seg, axis=1))])
    phi = np.linspace(-math.pi, 0.0, samples)
    arcs = []
    for i in range(stitches):
        target = s[-1] * (i + 1) / (stitches + 1)
        k = min(int(np.searchsorted(s, target, side="right")) - 1, len(seg) - 1)
        on = points[k] + (target - s[k]) / (s[k + 1] - s[k]) * seg[k]
        axis = _unit("incision direction", seg[k])
        u = _unit("incision side", np.cross([0.0, 0.0, 1.0], axis))
        up = np.cross(axis, u)
        center = on + center_height * radius * up

        def circle(angles, center=center, u=u, up=up):
            angles = np.atleast_1d(angles)
            return center + radius * (np.cos(angles)[:, None] * u + np.sin(angles)[:, None] * up)

        state = np.asarray(inside(circle(phi)), dtype=bool)
        change = np.flatnonzero(state[1:] != state[:-1])
        if len(change) != 4 or state[0]:
            raise ValueError(
                f"stitch {i}: the needle's circle (radius {radius:.4g} m, centre {center.round(5).tolist()} m) "
                f"crosses the tissue surface {len(change)} times at rest, not 4 (in, out of the left wound face, "
                "into the right one, out): the wound is too shallow or narrow for the arc, or the arc leaves "
                "the tissue elsewhere; change plan.center_height or the incision"
            )
        angles = []
        for c in change:
            lo, hi = phi[c], phi[c + 1]
            first = state[c]
            while hi - lo > 1e-9:
                mid = 0.5 * (lo + hi)
                lo, hi = (mid, hi) if bool(inside(circle(mid))[0]) == first else (lo, mid)
            angles.append(0.5 * (lo + hi))
        arcs.append(PlannedArc(center, axis, u, radius, np.array(angles)))
    return tuple(arcs)
