"""The rigid curved suture needle: shape and mass properties, Newton-Euler prediction, virtual coupling and
rigid-body XPBD point corrections (Muller et al. 2020, "Detailed rigid body simulation with extended
position based dynamics").

Frames
------
*Shape frame*: the needle's circle has its centre at the origin and lies in the x-y plane (normal +z). The
arc is symmetric about +y, like an upside-down U: the tip (HEAD) is at angle ``pi/2 - arc/2`` and the swage
end at ``pi/2 + arc/2`` (angles from +x about +z). For the half-circle the tip is at ``(R, 0, 0)``, the swage at
``(-R, 0, 0)`` and the crown at ``(0, R, 0)``; the tip points in -y, so the needle drives forward by turning
about -z.

*Body frame*: the shape frame translated to the centre of mass of needle + holder (axes unchanged), so the
inertia tensor is a full 3x3 matrix. The state's pose maps body to world: ``x_world = body_pos + R(body_quat)
x_body``.

Nodes: ``node_count`` points on the arc centreline, evenly spaced in angle. **Node 0 is the tip (HEAD)** and
the last node is the swage end, which carries the suture's first node.

Grip: the needle holder grasps the arc at ``grip_fraction`` of the arc length measured from the swage
(surgeons grasp one third to one half of the way from the swage). The action wrench (force N, torque N m) is
applied at the grip point, with the torque taken about the grip point. The holder is modelled as a point mass
at the grip point plus an isotropic rotational inertia about it: the effective mass/inertia of the holder's
jaws and of the haptic device that moves them.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numba import njit

from suture_gym.sim.checks import finite_array, is_real, require_non_negative, require_positive
from suture_gym.sim.quat import (
    cross3,
    quat_conj,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_rotation_vector,
    quat_to_matrix,
)
from suture_gym.sim.rigid import (
    apply_point_impulse,
    body_points_world,
    point_inv_mass,
    point_inv_mass_matrix,
    rigid_predict,
    rigid_velocities,
    world_inv_inertia,
)

#: Named arc presets: fraction of a full circle the needle spans.
ARC_PRESETS: dict[str, float] = {"1/4": 0.5 * math.pi, "3/8": 0.75 * math.pi, "1/2": math.pi, "5/8": 1.25 * math.pi}


@dataclass(frozen=True)
class NeedleShape:
    """Geometry and mass parameters of a curved needle and the holder gripping it (SI units).

    Defaults describe a 3-0 taper needle of the common 26 mm half-circle type: arc length 26 mm
    (curvature radius 26 mm / pi = 8.3 mm), wire diameter 0.6 mm, stainless steel 7850 kg/m^3, held by a
    holder whose jaws plus haptic stylus add an effective 20 g and 1e-6 kg m^2 at the grip point.
    """

    #: Arc the needle spans: a preset name from :data:`ARC_PRESETS` ("1/4", "3/8", "1/2", "5/8") or an angle
    #: in radians in (0, 2 pi].
    arc: str | float = "1/2"
    #: Radius of the needle's circle (centreline), m.
    curvature_radius: float = 0.026 / math.pi
    #: Radius of the wire cross-section, m; must be smaller than ``curvature_radius``.
    wire_radius: float = 3.0e-4
    #: Density of the needle wire, kg/m^3 (stainless steel).
    density: float = 7850.0
    #: Effective mass of the holder jaws / haptic device, a point mass at the grip point, kg (0 = bare needle).
    holder_mass: float = 0.02
    #: Effective rotational inertia of the holder about the grip point, isotropic, kg m^2 (0 = none).
    holder_inertia: float = 1.0e-6
    #: Where the holder grasps: fraction of the arc length measured from the swage end, in [0, 1].
    grip_fraction: float = 1.0 / 3.0
    #: Number of collision/coupling nodes along the arc (node 0 = tip), >= 2.
    node_count: int = 30

    def __post_init__(self) -> None:
        if isinstance(self.arc, str):
            if self.arc not in ARC_PRESETS:
                raise ValueError(f"arc preset {self.arc!r} unknown; expected one of {sorted(ARC_PRESETS)} or radians")
        elif not (is_real(self.arc) and math.isfinite(self.arc) and 0.0 < self.arc <= 2.0 * math.pi):
            raise ValueError(f"arc must be a preset name or an angle in (0, 2 pi] rad, got {self.arc!r}")
        require_positive("curvature_radius", self.curvature_radius)
        require_positive("wire_radius", self.wire_radius)
        if self.wire_radius >= self.curvature_radius:
            raise ValueError(
                f"wire_radius ({self.wire_radius}) must be smaller than curvature_radius ({self.curvature_radius})"
            )
        require_positive("density", self.density)
        require_non_negative("holder_mass", self.holder_mass)
        require_non_negative("holder_inertia", self.holder_inertia)
        if not (is_real(self.grip_fraction) and 0.0 <= self.grip_fraction <= 1.0):
            raise ValueError(f"grip_fraction must be in [0, 1], got {self.grip_fraction!r}")
        if isinstance(self.node_count, bool) or not isinstance(self.node_count, numbers.Integral):
            raise ValueError(f"node_count must be an integer >= 2, got {self.node_count!r}")
        if self.node_count < 2:
            raise ValueError(f"node_count must be >= 2, got {self.node_count}")

    @property
    def arc_angle(self) -> float:
        """Angle the arc spans, rad."""
        return ARC_PRESETS[self.arc] if isinstance(self.arc, str) else float(self.arc)

    @property
    def tip_angle(self) -> float:
        """Polar angle of the tip in the shape frame, rad."""
        return 0.5 * math.pi - 0.5 * self.arc_angle

    @property
    def swage_angle(self) -> float:
        """Polar angle of the swage end in the shape frame, rad."""
        return 0.5 * math.pi + 0.5 * self.arc_angle

    @property
    def grip_angle(self) -> float:
        """Polar angle of the grip point in the shape frame, rad."""
        return self.swage_angle - self.grip_fraction * self.arc_angle


def arc_wire_mass_properties(
    curvature_radius: float, wire_radius: float, angle_start: float, angle_end: float, density: float
) -> tuple[float, np.ndarray, np.ndarray]:
    """Exact mass properties of a round wire bent along a circular arc (a torus sector).

    The centreline is the circle of radius ``curvature_radius`` (m) about the origin in the z = 0 plane, from
    polar angle ``angle_start`` to ``angle_end`` (rad, ``angle_end > angle_start``); the wire has radius
    ``wire_radius`` (m) and ``density`` (kg/m^3). The cross-section terms are kept (a wire point at in-plane
    offset u and out-of-plane offset w from the centreline has volume element (R + u) du dw dphi).

    Returns ``(mass kg, com (3,) m, inertia (3, 3) kg m^2 about the centre of mass)`` in that frame.
    """
    R, a, rho = curvature_radius, wire_radius, density
    d = angle_end - angle_start
    area = math.pi * a * a
    mass = rho * area * R * d
    # integral over the disc of (R+u)^2 and (R+u)^3; integral of w^2 (R+u)
    m2 = rho * area * (R * R + 0.25 * a * a)
    m3 = rho * area * (R**3 + 0.75 * R * a * a)
    mw = rho * R * math.pi * a**4 / 4.0
    s0, s1 = math.sin(angle_start), math.sin(angle_end)
    c0, c1 = math.cos(angle_start), math.cos(angle_end)
    com = np.array([m2 * (s1 - s0), m2 * (c0 - c1), 0.0]) / mass
    cos2 = 0.5 * d + 0.25 * (math.sin(2.0 * angle_end) - math.sin(2.0 * angle_start))
    sin2 = 0.5 * d - 0.25 * (math.sin(2.0 * angle_end) - math.sin(2.0 * angle_start))
    sincos = 0.5 * (s1 * s1 - s0 * s0)
    second = np.array(
        [[m3 * cos2, m3 * sincos, 0.0], [m3 * sincos, m3 * sin2, 0.0], [0.0, 0.0, mw * d]]
    )  # integral of rho x x^T over the volume, about the origin
    inertia_origin = np.trace(second) * np.eye(3) - second
    inertia_com = inertia_origin - mass * (com @ com * np.eye(3) - np.outer(com, com))
    return mass, com, inertia_com


@dataclass(frozen=True)
class NeedleModel:
    """Static, derived data of a needle + holder rigid body (see the module docstring for the frames).

    Build with :meth:`NeedleModel.from_shape`. Arrays must be treated as read-only.
    """

    #: The parameters this model was built from.
    shape: NeedleShape
    #: Total mass of needle wire and holder, kg.
    body_mass: float
    #: 1 / body_mass, 1/kg.
    body_inv_mass: float
    #: (3, 3) float64, inertia tensor about the centre of mass in the body frame, kg m^2.
    body_inertia: np.ndarray
    #: (3, 3) float64, inverse of ``body_inertia``, 1/(kg m^2).
    body_inv_inertia: np.ndarray
    #: Mass of the needle wire alone, kg.
    wire_mass: float
    #: (N, 3) float64, arc nodes in the body frame, m; row 0 is the tip, row N-1 the swage end.
    node_pos_body: np.ndarray
    #: (3,) float64, grip point (where the wrench acts and the holder mass sits), body frame, m.
    grip_pos_body: np.ndarray
    #: (3,) float64, centre of the needle's circle, body frame, m.
    arc_center_body: np.ndarray
    #: (3,) float64, unit normal of the needle's plane, body frame (the needle drives tip-first about -normal).
    plane_normal_body: np.ndarray
    #: (3,) float64, unit tangent at the tip pointing the way the tip travels, body frame.
    tip_dir_body: np.ndarray
    #: Linear velocity damping rate, 1/s (v <- v / (1 + dt * rate) each substep, before forces act).
    linear_damping: float = 0.0
    #: Angular velocity damping rate, 1/s.
    angular_damping: float = 0.0
    #: If true, gravity does not act on the needle body (the haptic device compensates its weight).
    gravity_compensation: bool = False

    @property
    def node_count(self) -> int:
        """Number of arc nodes."""
        return self.node_pos_body.shape[0]

    @cached_property
    def node_reach(self) -> float:
        """Largest distance of an arc node from the centre of mass, m (a bound on a node's speed is then
        ``|v| + node_reach |omega|``)."""
        return float(np.sqrt((self.node_pos_body**2).sum(axis=1).max()))

    @property
    def tip_pos_body(self) -> np.ndarray:
        """(3,) tip (node 0) in the body frame, m."""
        return self.node_pos_body[0]

    @property
    def swage_pos_body(self) -> np.ndarray:
        """(3,) swage end (last node, where the suture attaches) in the body frame, m."""
        return self.node_pos_body[-1]

    @classmethod
    def from_shape(
        cls,
        shape: NeedleShape | None = None,
        *,
        linear_damping: float = 0.0,
        angular_damping: float = 0.0,
        gravity_compensation: bool = False,
    ) -> NeedleModel:
        """Compute mass, centre of mass, inertia and nodes of ``shape`` (default :class:`NeedleShape`)."""
        shape = NeedleShape() if shape is None else shape
        require_non_negative("linear_damping", linear_damping)
        require_non_negative("angular_damping", angular_damping)
        R = shape.curvature_radius
        wire_mass, wire_com, wire_inertia = arc_wire_mass_properties(
            R, shape.wire_radius, shape.tip_angle, shape.swage_angle, shape.density
        )
        g_ang = shape.grip_angle
        grip = np.array([R * math.cos(g_ang), R * math.sin(g_ang), 0.0])
        mass = wire_mass + shape.holder_mass
        com = (wire_mass * wire_com + shape.holder_mass * grip) / mass

        def shifted(m: float, c: np.ndarray) -> np.ndarray:
            d = c - com
            return m * (d @ d * np.eye(3) - np.outer(d, d))

        inertia = (
            wire_inertia
            + shifted(wire_mass, wire_com)
            + shape.holder_inertia * np.eye(3)
            + shifted(shape.holder_mass, grip)
        )
        inertia = 0.5 * (inertia + inertia.T)
        angles = shape.tip_angle + shape.arc_angle * np.arange(shape.node_count) / (shape.node_count - 1)
        nodes = np.stack([R * np.cos(angles), R * np.sin(angles), np.zeros_like(angles)], axis=1)
        tip = shape.tip_angle
        tip_dir = np.array([math.sin(tip), -math.cos(tip), 0.0])
        inv_inertia = np.linalg.inv(inertia)
        return cls(
            shape=shape,
            body_mass=float(mass),
            body_inv_mass=float(1.0 / mass),
            body_inertia=inertia,
            body_inv_inertia=0.5 * (inv_inertia + inv_inertia.T),
            wire_mass=float(wire_mass),
            node_pos_body=nodes - com,
            grip_pos_body=grip - com,
            arc_center_body=-com,
            plane_normal_body=np.array([0.0, 0.0, 1.0]),
            tip_dir_body=tip_dir,
            linear_damping=float(linear_damping),
            angular_damping=float(angular_damping),
            gravity_compensation=bool(gravity_compensation),
        )


@dataclass
class NeedleState:
    """Time-varying state of the needle body (world frame, SI units)."""

    #: (3,) float64, centre-of-mass position, m.
    body_pos: np.ndarray
    #: (4,) float64, unit orientation quaternion (w, x, y, z), body to world.
    body_quat: np.ndarray
    #: (3,) float64, centre-of-mass velocity, m/s.
    body_vel: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: (3,) float64, angular velocity, world frame, rad/s.
    body_omega: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: (3,) float64, position at the start of the current substep, m.
    body_pos_prev: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: (4,) float64, orientation at the start of the current substep.
    body_quat_prev: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))
    #: (3,) float64, predicted position before constraint projection this substep, m.
    body_pos_pred: np.ndarray = field(default_factory=lambda: np.zeros(3))
    #: (4,) float64, predicted orientation before constraint projection this substep.
    body_quat_pred: np.ndarray = field(default_factory=lambda: np.array([1.0, 0.0, 0.0, 0.0]))

    @classmethod
    def at_rest(cls, body_pos, body_quat) -> NeedleState:
        """A needle at rest with its centre of mass at ``body_pos`` (3,) m and orientation ``body_quat`` (4,)."""
        pos = finite_array("body_pos", body_pos, (3,)).copy()
        quat = finite_array("body_quat", body_quat, (4,))
        if np.linalg.norm(quat) == 0.0:
            raise ValueError("body_quat must be non-zero")
        quat = quat_normalize(quat)
        return cls(pos, quat, np.zeros(3), np.zeros(3), pos.copy(), quat.copy(), pos.copy(), quat.copy())

    @classmethod
    def from_grip_pose(cls, model: NeedleModel, grip_pos, body_quat) -> NeedleState:
        """A needle at rest whose grip point is at ``grip_pos`` (3,) m with orientation ``body_quat`` (4,)."""
        grip = finite_array("grip_pos", grip_pos, (3,))
        quat = quat_normalize(finite_array("body_quat", body_quat, (4,)))
        return cls.at_rest(grip - quat_rotate(quat, model.grip_pos_body), quat)

    def copy(self) -> NeedleState:
        """Deep copy (no array is shared)."""
        return NeedleState(*(np.array(getattr(self, f)) for f in self.__dataclass_fields__))


# ---------------------------------------------------------------------------------------------------------
# Phase API
# ---------------------------------------------------------------------------------------------------------


def check_wrench(wrench) -> np.ndarray:
    """Return ``wrench`` as a (6,) float64 array ``[force N, torque N m]``; ValueError if malformed/non-finite."""
    arr = np.asarray(wrench, dtype=np.float64)
    if arr.shape != (6,):
        raise ValueError(f"needle_wrench must have shape (6,) = [force (3) N, torque (3) N m], got {arr.shape}")
    if not np.isfinite(arr).all():
        raise ValueError(f"needle_wrench must be finite, got {arr.tolist()}")
    return arr


def wrench_at_com(model: NeedleModel, state: NeedleState, wrench) -> tuple[np.ndarray, np.ndarray]:
    """Convert a grip-point wrench (6,) to ``(force (3,) N, torque about the centre of mass (3,) N m)``.

    ``tau_com = tau_grip + r_grip x F`` with ``r_grip`` the world offset from the centre of mass to the grip.
    """
    return _com_wrench(state.body_quat, model.grip_pos_body, check_wrench(wrench))


@njit(cache=True)
def _com_wrench(quat, grip_body, wrench):
    """:func:`wrench_at_com`'s arithmetic for the orientation ``quat`` and the grip ``grip_body`` (body frame, m)."""
    force = wrench[:3].copy()
    return force, wrench[3:] + cross3(quat_rotate(quat, grip_body), force)


def needle_predict(model: NeedleModel, state: NeedleState, wrench, dt: float, gravity) -> None:
    """Predict phase: store the start pose, integrate the grip-point ``wrench`` (6,) over ``dt`` (s).

    ``gravity`` (3,) m/s^2 acts unless ``model.gravity_compensation``. Updates ``state`` in place and records
    the predicted pose in ``body_pos_pred`` / ``body_quat_pred`` (used by :func:`needle_constraint_wrench`).
    """
    require_positive("dt", dt)
    g = finite_array("gravity", gravity, (3,))
    _predict_kernel(
        model.body_inv_mass, model.body_inertia, model.body_inv_inertia, model.grip_pos_body, model.linear_damping,
        model.angular_damping, check_wrench(wrench), _NO_GRAVITY if model.gravity_compensation else g, float(dt),
        state.body_pos, state.body_quat, state.body_vel, state.body_omega, state.body_pos_prev, state.body_quat_prev,
        state.body_pos_pred, state.body_quat_pred,
    )  # fmt: skip


_NO_GRAVITY = np.zeros(3)


# The three kernels below are the phase functions' work in one compiled call each: in Python their small-array
# steps cost about 40 us of the paper cube's 1.1 ms substep. Arguments: the model's arrays and scalars, then the
# state's arrays (written in place).
@njit(cache=True)
def _predict_kernel(inv_mass, inertia, inv_inertia, grip_body, lin_damp, ang_damp, wrench, accel, dt, pos, quat, vel,
                    omega, pos_prev, quat_prev, pos_pred, quat_pred):  # fmt: skip
    """:func:`needle_predict`: the grip-point wrench moved to the centre of mass (:func:`wrench_at_com`), then
    :func:`~suture_gym.sim.rigid.rigid_predict`."""
    force, torque = _com_wrench(quat, grip_body, wrench)
    pos_prev[:] = pos
    quat_prev[:] = quat
    new_pos, new_quat, new_vel, new_omega = rigid_predict(
        pos, quat, vel, omega, inv_mass, inertia, inv_inertia, force, torque, accel, lin_damp, ang_damp, dt
    )
    pos[:] = new_pos
    quat[:] = new_quat
    vel[:] = new_vel
    omega[:] = new_omega
    pos_pred[:] = new_pos
    quat_pred[:] = new_quat


def needle_update_velocities(state: NeedleState, dt: float) -> None:
    """Velocity phase: ``v = (x - x_prev) / dt`` and ``omega`` from the orientation change, in place."""
    _velocities_kernel(state.body_pos, state.body_quat, state.body_pos_prev, state.body_quat_prev, float(dt),
                       state.body_vel, state.body_omega)  # fmt: skip


@njit(cache=True)
def _velocities_kernel(pos, quat, pos_prev, quat_prev, dt, vel, omega):
    """:func:`needle_update_velocities` (:func:`~suture_gym.sim.rigid.rigid_velocities`)."""
    new_vel, new_omega = rigid_velocities(pos, quat, pos_prev, quat_prev, dt)
    vel[:] = new_vel
    omega[:] = new_omega


def needle_constraint_wrench(
    model: NeedleModel, state: NeedleState, dt: float, out: np.ndarray | None = None
) -> np.ndarray:
    """Wrench (6,) ``[force N, torque about the grip point N m]`` the constraints exerted on the needle.

    From the projection's pose change this substep: ``F = m (x - x_pred) / dt^2`` and
    ``tau_com = I_world dtheta / dt^2`` with ``dtheta = log(q conj(q_pred))``. This is the haptic reaction;
    the device feels its opposite. Written into ``out`` (6,) if given.
    """
    if out is None:
        out = np.empty(6)
    _constraint_wrench_kernel(model.body_mass, model.body_inertia, model.grip_pos_body, float(dt), state.body_pos,
                              state.body_pos_pred, state.body_quat, state.body_quat_pred, out)  # fmt: skip
    return out


@njit(cache=True)
def _constraint_wrench_kernel(mass, inertia, grip_body, dt, pos, pos_pred, quat, quat_pred, out):
    """:func:`needle_constraint_wrench` into ``out`` (6,)."""
    force = mass * (pos - pos_pred) / (dt * dt)
    dtheta = quat_rotation_vector(quat_mul(quat, quat_conj(quat_pred)))
    r = quat_to_matrix(quat)
    torque_com = r @ inertia @ r.T @ dtheta / (dt * dt)
    out[:3] = force
    out[3:] = torque_com - cross3(quat_rotate(quat, grip_body), force)


def needle_node_positions(model: NeedleModel, state: NeedleState, out: np.ndarray | None = None) -> np.ndarray:
    """World positions (N, 3) m of the arc nodes (row 0 = tip, last = swage); written into ``out`` if given."""
    if out is None:
        out = np.empty_like(model.node_pos_body)
    body_points_world(state.body_pos, state.body_quat, model.node_pos_body, out)
    return out


def needle_point_world(model: NeedleModel, state: NeedleState, point_body) -> np.ndarray:
    """World position (3,) m of a body-frame point ``point_body`` (3,)."""
    return state.body_pos + quat_rotate(state.body_quat, np.asarray(point_body, dtype=np.float64))


def needle_point_velocity(model: NeedleModel, state: NeedleState, point_body) -> np.ndarray:
    """World velocity (3,) m/s of a body-frame point: ``v + omega x r``."""
    r = quat_rotate(state.body_quat, np.asarray(point_body, dtype=np.float64))
    return state.body_vel + cross3(state.body_omega, r)


def needle_point_inv_mass(model: NeedleModel, state: NeedleState, point_world, direction) -> float:
    """Generalised inverse mass (1/kg) of world point ``point_world`` (3,) on the needle along ``direction``."""
    n = finite_array("direction", direction, (3,))
    norm = np.linalg.norm(n)
    if norm == 0.0:
        raise ValueError("direction must be non-zero")
    r = finite_array("point_world", point_world, (3,)) - state.body_pos
    return float(
        point_inv_mass(model.body_inv_mass, world_inv_inertia(state.body_quat, model.body_inv_inertia), r, n / norm)
    )


def needle_apply_impulse(model: NeedleModel, state: NeedleState, point_world, impulse) -> None:
    """Apply a positional impulse ``impulse`` (3,) kg m at world point ``point_world`` (3,) to the pose, in place.

    This is how contact and path constraints on needle nodes act on the rigid body: a constraint with
    gradient ``n`` at the node and multiplier step ``dlambda`` passes ``impulse = dlambda n``.
    """
    p = finite_array("impulse", impulse, (3,))
    r = finite_array("point_world", point_world, (3,)) - state.body_pos
    pos, quat = apply_point_impulse(
        state.body_pos,
        state.body_quat,
        model.body_inv_mass,
        world_inv_inertia(state.body_quat, model.body_inv_inertia),
        r,
        p,
    )
    state.body_pos[:] = pos
    state.body_quat[:] = quat


def needle_move_point(model: NeedleModel, state: NeedleState, point_world, displacement) -> None:
    """Rigid XPBD projection moving body point ``point_world`` (3,) by ``displacement`` (3,) m, other side static.

    The three rows ``C = x_point - x_target`` are solved together: impulse ``p = K^-1 dx`` with ``K`` the
    point's generalised inverse mass matrix (:func:`point_inv_mass_matrix`), so the point moves by
    ``displacement`` up to second order in the rotation. A zero displacement does nothing.
    """
    dx = finite_array("displacement", displacement, (3,))
    if not np.any(dx):
        return
    point = finite_array("point_world", point_world, (3,))
    k = point_inv_mass_matrix(
        model.body_inv_mass, world_inv_inertia(state.body_quat, model.body_inv_inertia), point - state.body_pos
    )
    needle_apply_impulse(model, state, point, np.linalg.solve(k, dx))


@dataclass(frozen=True)
class VirtualCoupling:
    """Spring-damper between a target grip pose (the haptic device) and the needle's grip point.

    ``F = k (x_target - x_grip) + c (v_target - v_grip)``,
    ``tau = k_w log(q_target conj(q)) + c_w (omega_target - omega)`` (about the grip point).
    The defaults are near critically damped (damping ratio ~0.95) at ~160 rad/s for the default needle
    (mass 20 g, inertia ~1e-6 kg m^2); the semi-implicit step keeps ``omega_n dt`` well below 1 for dt <= 2 ms.
    """

    #: Translational stiffness, N/m.
    linear_stiffness: float = 500.0
    #: Translational damping, N s/m.
    linear_damping: float = 6.0
    #: Rotational stiffness, N m/rad.
    angular_stiffness: float = 0.025
    #: Rotational damping, N m s/rad.
    angular_damping: float = 3.0e-4

    def __post_init__(self) -> None:
        for name in ("linear_stiffness", "linear_damping", "angular_stiffness", "angular_damping"):
            require_non_negative(name, getattr(self, name))

    def wrench(
        self,
        model: NeedleModel,
        state: NeedleState,
        target_pos,
        target_quat,
        target_vel=(0.0, 0.0, 0.0),
        target_omega=(0.0, 0.0, 0.0),
    ) -> np.ndarray:
        """Grip-point wrench (6,) ``[force N, torque N m]`` pulling the needle toward the target grip pose.

        ``target_pos`` (3,) m is where the grip point should be, ``target_quat`` (4,) the body orientation,
        ``target_vel`` (3,) m/s and ``target_omega`` (3,) rad/s the target's velocities.
        """
        xt = finite_array("target_pos", target_pos, (3,))
        qt = finite_array("target_quat", target_quat, (4,))
        vt = finite_array("target_vel", target_vel, (3,))
        wt = finite_array("target_omega", target_omega, (3,))
        grip = needle_point_world(model, state, model.grip_pos_body)
        v_grip = needle_point_velocity(model, state, model.grip_pos_body)
        force = self.linear_stiffness * (xt - grip) + self.linear_damping * (vt - v_grip)
        err = quat_rotation_vector(quat_mul(quat_normalize(qt), quat_conj(state.body_quat)))
        torque = self.angular_stiffness * err + self.angular_damping * (wt - state.body_omega)
        return np.concatenate([force, torque])
