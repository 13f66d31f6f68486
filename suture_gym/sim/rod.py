"""The suture thread as an inextensible Cosserat rod, solved with a direct block-tridiagonal XPBD solver.

Model (Kugelstadt & Schomer 2016, "Position and orientation based Cosserat rods"): nodes ``x_i`` (N, 3) and
one orientation quaternion ``q_j`` per segment (N-1, 4) whose third director ``d3(q_j)`` is the segment's
tangent. Node 0 is the end attached to the needle swage; segment j joins nodes j and j+1. Constraints:

* stretch-shear, per segment: ``C_ss = (x_{j+1} - x_j) / l_j - d3(q_j)`` (3,), world frame;
* bend-twist, per pair of segments: ``C_bt = Im(conj(q_j) q_{j+1})`` (3,) in the frame of ``q_j`` (the
  discrete Darboux vector times l/2; the sign of ``conj(q_j) q_{j+1}`` is chosen with a non-negative real
  part). The rest shape is straight and untwisted (rest Darboux vector zero);
* attachment of node 0 to the needle swage, ``C = x_0 - x_swage`` (3,), rigid and two-way: it acts on the
  needle through its generalised inverse mass (Muller et al. 2020);
* one-sided contact of each node with the closest static obstacle (plane or sphere), ``C = gap >= 0``.

Stiffness comes from the material: bending ``E I``, twist ``G J`` (``I = pi r^4 / 4``, ``J = pi r^4 / 2``);
with ``Omega = 2 C_bt / l`` the energy ``l/2 Omega^T K Omega`` gives the XPBD compliance
``alpha_bt = diag(l/(4 E I), l/(4 E I), l/(4 G J))``. Stretch and shear are rigid (compliance 0) when
``inextensible`` is set (the default: a suture must not stretch visibly under working tension); otherwise
``alpha_ss = diag(1/(G A l), 1/(G A l), 1/(E A l))`` in the segment frame.

Solver (after Deul et al. 2018, "Direct position-based solver for stiff rods"; its kernels are in
:mod:`suture_gym.sim.rod_solver`, driven by :func:`rod_solve_iteration`): every iteration linearises all
constraints of the chain at once and solves ``(J W J^T + alpha/dt^2) dlambda = -C - alpha/dt^2 lambda + J h``
exactly. Ordered per node, block i = ``[C_ss_{i-1} (3), C_bt_{i-1} (3), contact_i (1)]`` (block 0: attachment,
3 unused rows, contact_0) touches only ``x_{i-1}, x_i, q_{i-1}, q_i`` and the neighbouring blocks, so the
matrix is block tridiagonal with 7x7 blocks and one block LU sweep solves it in O(N). Unused rows carry an
identity diagonal and a zero right-hand side. Contacts use an active set: rows of penetrating (or already
pushing) nodes are in; a row whose multiplier would turn negative is released and the system re-solved.
Rigid constraints then converge like Newton's method, in one to a few iterations, whatever the mass ratios.

Frames: a segment's orientation is weighted by the transverse rotational inertia of a rigid rod segment,
``m (r^2/4 + l^2/12)`` (as Deul et al.'s rigid segments), used about all three axes, plus the geometric
stiffness of its stretch-shear rows; each frame keeps its Newton residual ``h`` (inertial minus constraint
torque) in the right-hand side, so the static solution does not depend on the iteration path or on dt. Frames
carry no angular velocity (quasi-static): their inertia resists rotation within a substep only, which damps
segment-scale bending waves (of wavelength lambda at a rate ~ (l / lambda)^2 / dt) and twist waves, and
leaves the thread's motion at larger scales to the nodes. The true twist inertia ``m r^2 / 2`` is ~30x
smaller; with it the nearly massless twist made the Newton iteration converge several times slower. At the
start of each iteration every free frame is parallel-transported (minimal rotation, twist kept) onto its
current edge, which removes the shear error that large node motions leave and keeps the linearisation valid.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, field, replace

import numpy as np
from numba import njit

from suture_gym.sim.checks import finite_array, is_real, require_non_negative, require_positive
from suture_gym.sim.needle import NeedleModel, NeedleState
from suture_gym.sim.quat import (
    quat_from_two_vectors,
)
from suture_gym.sim.rod_linalg import BLOCK, dot3
from suture_gym.sim.rod_solver import rod_iteration_kernel, tension_from_multipliers


@dataclass(frozen=True)
class SutureMaterial:
    """Elastic material of the thread. Defaults: nylon 6,6 monofilament (E ~ 2-3 GPa, nu ~ 0.39, 1140 kg/m^3).

    For a 3-0 suture (0.2 mm diameter) this gives EA ~ 80 N, EI ~ 2e-7 N m^2.
    """

    #: Young's modulus, Pa.
    youngs_modulus: float = 2.5e9
    #: Poisson ratio, in (-1, 0.5]; sets the shear modulus G = E / (2 (1 + nu)).
    poisson_ratio: float = 0.39
    #: Density, kg/m^3.
    density: float = 1140.0

    def __post_init__(self) -> None:
        require_positive("youngs_modulus", self.youngs_modulus)
        if not (is_real(self.poisson_ratio) and -1.0 < self.poisson_ratio <= 0.5):
            raise ValueError(f"poisson_ratio must be in (-1, 0.5], got {self.poisson_ratio!r}")
        require_positive("density", self.density)

    @property
    def shear_modulus(self) -> float:
        """G = E / (2 (1 + nu)), Pa."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))


@dataclass(frozen=True)
class SutureParams:
    """Parameters of a suture thread (SI units). Defaults: 20 cm of 3-0 nylon in 200 nodes."""

    #: Rest length of the thread, m.
    length: float = 0.2
    #: Thread radius, m (3-0 suture: 0.2 mm diameter).
    radius: float = 1.0e-4
    #: Number of nodes, >= 2 (segments = nodes - 1).
    node_count: int = 200
    #: Elastic material.
    material: SutureMaterial = field(default_factory=SutureMaterial)
    #: Rigid stretch and shear (compliance 0) if true; else the material's EA and GA.
    inextensible: bool = True
    #: Global velocity damping rate of the nodes, 1/s (v <- v / (1 + dt rate) before forces act); stands in
    #: for air drag.
    damping: float = 1.0

    def __post_init__(self) -> None:
        require_positive("length", self.length)
        require_positive("radius", self.radius)
        if isinstance(self.node_count, bool) or not isinstance(self.node_count, numbers.Integral):
            raise ValueError(f"node_count must be an integer >= 2, got {self.node_count!r}")
        if self.node_count < 2:
            raise ValueError(f"node_count must be >= 2, got {self.node_count}")
        if not isinstance(self.material, SutureMaterial):
            raise ValueError(f"material must be a SutureMaterial, got {type(self.material).__name__}")
        require_non_negative("damping", self.damping)


@dataclass(frozen=True)
class RodModel:
    """Static arrays of a rod (see the module docstring for the constraints). Build with :meth:`from_params`.

    Segment frames are ``(d1, d2, d3)`` = columns of ``quat_to_matrix(seg_quat[j])``; d3 is the tangent.
    """

    #: Parameters the model was built from.
    params: SutureParams
    #: (N,) float64, lumped node masses, kg.
    node_mass: np.ndarray
    #: (N,) float64, inverse node masses, 1/kg; 0 pins a node.
    node_inv_mass: np.ndarray
    #: (N-1,) float64, segment rest lengths, m.
    seg_rest_length: np.ndarray
    #: (N-1, 3) float64, inverse rotational inertia of each segment frame about (d1, d2, d3), 1/(kg m^2)
    #: (solve weights of the quasi-static frames, see the module docstring); all zero clamps the orientation.
    seg_inv_inertia: np.ndarray
    #: (N-1, 3) float64, stretch-shear compliance along (d1, d2, d3), 1/(N m) (0 = rigid).
    seg_stretch_compliance: np.ndarray
    #: (N-2, 3) float64, bend-twist compliance about (d1, d2, d3) of segment j's frame, 1/(N m).
    bend_compliance: np.ndarray

    @property
    def node_count(self) -> int:
        """Number of nodes N."""
        return self.node_mass.shape[0]

    @property
    def radius(self) -> float:
        """Thread radius, m (used for contact)."""
        return self.params.radius

    @classmethod
    def from_params(cls, params: SutureParams | None = None, *, pinned_nodes=(), clamped_segments=()) -> RodModel:
        """Lumped masses, inertias and compliances of ``params`` (default :class:`SutureParams`).

        ``pinned_nodes``: node indices with zero inverse mass; ``clamped_segments``: segment indices whose
        orientation is fixed (zero inverse inertia).
        """
        p = SutureParams() if params is None else params
        n = p.node_count
        mat = p.material
        seg_len = np.full(n - 1, p.length / (n - 1))
        area = math.pi * p.radius**2
        i_area = 0.25 * math.pi * p.radius**4
        j_area = 0.5 * math.pi * p.radius**4
        seg_mass = mat.density * area * seg_len
        node_mass = np.zeros(n)
        node_mass[:-1] += 0.5 * seg_mass
        node_mass[1:] += 0.5 * seg_mass
        inertia = seg_mass * (0.25 * p.radius**2 + seg_len**2 / 12.0)
        seg_inv_inertia = np.stack([1.0 / inertia, 1.0 / inertia, 1.0 / inertia], axis=1)
        if p.inextensible:
            stretch = np.zeros((n - 1, 3))
        else:
            ga = mat.shear_modulus * area
            ea = mat.youngs_modulus * area
            stretch = np.stack([1.0 / (ga * seg_len), 1.0 / (ga * seg_len), 1.0 / (ea * seg_len)], axis=1)
        bend_len = 0.5 * (seg_len[:-1] + seg_len[1:])
        ei = mat.youngs_modulus * i_area
        gj = mat.shear_modulus * j_area
        bend = np.stack([bend_len / (4.0 * ei), bend_len / (4.0 * ei), bend_len / (4.0 * gj)], axis=1)
        model = cls(
            params=p,
            node_mass=node_mass,
            node_inv_mass=1.0 / node_mass,
            seg_rest_length=seg_len,
            seg_inv_inertia=seg_inv_inertia,
            seg_stretch_compliance=stretch,
            bend_compliance=bend.reshape(-1, 3),
        )
        return model.with_pins(pinned_nodes, clamped_segments)

    def with_pins(self, pinned_nodes=(), clamped_segments=()) -> RodModel:
        """A copy with ``pinned_nodes`` (zero inverse mass) and ``clamped_segments`` (zero inverse inertia)."""
        inv_mass = self.node_inv_mass.copy()
        inv_inertia = self.seg_inv_inertia.copy()
        for i in pinned_nodes:
            if not (0 <= int(i) < self.node_count):
                raise ValueError(f"pinned_nodes entry {i} out of range [0, {self.node_count})")
            inv_mass[int(i)] = 0.0
        for j in clamped_segments:
            if not (0 <= int(j) < self.node_count - 1):
                raise ValueError(f"clamped_segments entry {j} out of range [0, {self.node_count - 1})")
            inv_inertia[int(j)] = 0.0
        return replace(self, node_inv_mass=inv_mass, seg_inv_inertia=inv_inertia)


@dataclass
class RodState:
    """Time-varying state of a rod (world frame, SI units)."""

    #: (N, 3) float64, node positions, m.
    node_pos: np.ndarray
    #: (N, 3) float64, node velocities, m/s.
    node_vel: np.ndarray
    #: (N, 3) float64, node positions at the start of the current substep, m.
    node_pos_prev: np.ndarray
    #: (N-1, 4) float64, unit segment orientations (w, x, y, z); d3 = segment tangent.
    seg_quat: np.ndarray

    @classmethod
    def straight(cls, model: RodModel, start, direction) -> RodState:
        """The rod at rest on a straight line from ``start`` (3,) m along ``direction`` (3,), untwisted."""
        x0 = finite_array("start", start, (3,))
        d = finite_array("direction", direction, (3,))
        norm = float(np.linalg.norm(d))
        if norm == 0.0:
            raise ValueError("direction must be non-zero")
        d = d / norm
        s = np.concatenate([[0.0], np.cumsum(model.seg_rest_length)])
        pos = x0[None, :] + s[:, None] * d[None, :]
        q = quat_from_two_vectors(np.array([0.0, 0.0, 1.0]), d)
        quats = np.tile(q, (model.node_count - 1, 1))
        return cls(pos, np.zeros_like(pos), pos.copy(), quats)

    def copy(self) -> RodState:
        """Deep copy (no array is shared)."""
        return RodState(self.node_pos.copy(), self.node_vel.copy(), self.node_pos_prev.copy(), self.seg_quat.copy())


class RodWork:
    """Scratch arrays of the direct solver for one rod (allocated once, reused every substep).

    The system has one block of :data:`BLOCK` rows per node: block 0 = ``[attachment (3), unused (3),
    contact of node 0]``, block j+1 = ``[stretch-shear_j (3), bend-twist_j (3), contact of node j+1]``.
    ``lam`` (N, 7) holds the multipliers accumulated during the current substep; :meth:`begin` resets it.
    """

    def __init__(self, model: RodModel):
        n = model.node_count
        k = BLOCK
        self.lam = np.zeros((n, k))
        self.diag = np.zeros((n, k, k))
        self.lower = np.zeros((n, k, k))
        self.rhs = np.zeros((n, k))
        self.fac = np.zeros((n, k, k))
        self.y = np.zeros((n, k))
        self.z = np.zeros((n, k))
        self.seg_rot = np.zeros((n - 1, 3, 3))
        self.seg_s = np.zeros((n - 1, 3, 3))
        self.seg_winv = np.zeros((n - 1, 3, 3))
        self.bend_b = np.zeros((max(n - 2, 0), 3, 3))
        self.seg_h = np.zeros((n - 1, 3))
        self.seg_quat_start = np.zeros((n - 1, 4))
        self.seg_tension_prev = np.zeros(n - 1)
        self.contact_gap = np.full(n, np.inf)
        self.contact_normal = np.zeros((n, 3))
        self.contact_obstacle_w = np.zeros(n)  # static obstacles only: they take no share of a contact row
        self.isotropic_axis_w = np.zeros(n)  # nodes without an axis: W_i = w_i I
        self.isotropic_axis = np.zeros((n, 3))
        self.contact_active = np.zeros(n, dtype=np.bool_)
        self.contact_push = np.zeros((n, 3))
        self.contact_cap = np.zeros(n)  # > 0: row 6 is a friction row bounded by it (kg m), else a contact
        # False: a node that penetrates without pushing yet keeps its contact row closed this iteration (the
        # solver's contact-set warm start); the standalone rod keeps all True
        self.contact_eligible = np.ones(n, dtype=np.bool_)
        self.att_r = np.zeros(3)
        self.att_winv = np.zeros((3, 3))
        # the kernels' argument groups (:mod:`suture_gym.sim.rod_solver`), the same arrays as above
        self.start = (self.seg_quat_start, self.seg_tension_prev)
        self.frames = (self.seg_rot, self.seg_s, self.seg_winv, self.bend_b, self.seg_h, self.att_r, self.att_winv)
        self.contacts = (
            self.contact_gap, self.contact_normal, self.contact_active, self.contact_push, self.contact_cap,
            self.contact_eligible,
        )  # fmt: skip
        self.system = (self.diag, self.lower, self.fac, self.rhs, self.y, self.z)

    def reset(self) -> None:
        """Forget the history (multipliers and the tension warm start), e.g. when a state is restored; two
        runs from the same state are then bit-identical."""
        self.lam[:] = 0.0
        self.seg_tension_prev[:] = 0.0

    def begin(self, state: RodState) -> None:
        """Start a projection phase: keep the last substep's segment tensions (multiplier units, kg m^2) as
        the geometric-stiffness estimate, zero the multipliers and contact pushes, and remember the frames'
        start orientations."""
        tension_from_multipliers(self.lam, self.seg_tension_prev)
        self.lam[:] = 0.0
        self.seg_quat_start[:] = state.seg_quat
        self.contact_push[:] = 0.0


@dataclass(frozen=True)
class StaticObstacles:
    """Obstacles the thread cannot enter (it keeps ``radius`` away), with Coulomb friction.

    Planes are half-spaces ``(x - point) . normal >= 0``; spheres are solid balls (e.g. the holder's jaws,
    moved by the caller between substeps).
    """

    #: (P, 3) float64, a point on each plane, m.
    plane_point: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: (P, 3) float64, unit outward normals.
    plane_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: (S, 3) float64, sphere centres, m.
    sphere_center: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    #: (S,) float64, sphere radii, m.
    sphere_radius: np.ndarray = field(default_factory=lambda: np.zeros(0))
    #: Coulomb friction coefficient (applied to velocities after the projection), >= 0.
    friction: float = 0.3

    def __post_init__(self) -> None:
        pp = np.asarray(self.plane_point, dtype=np.float64).reshape(-1, 3)
        pn = np.asarray(self.plane_normal, dtype=np.float64).reshape(-1, 3)
        if pp.shape != pn.shape:
            raise ValueError(f"plane_point {pp.shape} and plane_normal {pn.shape} must have the same shape")
        norms = np.linalg.norm(pn, axis=1)
        if np.any(norms == 0.0) or not np.all(np.isfinite(pn)) or not np.all(np.isfinite(pp)):
            raise ValueError("plane_normal must be finite and non-zero and plane_point finite")
        sc = np.asarray(self.sphere_center, dtype=np.float64).reshape(-1, 3)
        sr = np.asarray(self.sphere_radius, dtype=np.float64).reshape(-1)
        if sc.shape[0] != sr.shape[0]:
            raise ValueError(f"sphere_center ({sc.shape[0]}) and sphere_radius ({sr.shape[0]}) counts differ")
        if not (np.all(np.isfinite(sc)) and np.all(np.isfinite(sr)) and np.all(sr > 0.0)):
            raise ValueError("sphere_center must be finite and sphere_radius finite and > 0")
        require_non_negative("friction", self.friction)
        object.__setattr__(self, "plane_point", pp)
        object.__setattr__(self, "plane_normal", pn / norms[:, None])
        object.__setattr__(self, "sphere_center", sc)
        object.__setattr__(self, "sphere_radius", sr)

    @classmethod
    def ground(cls, height: float = 0.0, normal=(0.0, 0.0, 1.0), friction: float = 0.3) -> StaticObstacles:
        """A single ground plane through ``height * normal`` with unit ``normal``."""
        n = np.asarray(normal, dtype=np.float64)
        n = n / np.linalg.norm(n)
        return cls(plane_point=(height * n)[None, :], plane_normal=n[None, :], friction=friction)


# ---------------------------------------------------------------------------------------------------------
# Prediction, obstacles, velocities
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True)
def rod_predict_kernel(node_inv_mass, gravity, node_force, damping, dt, node_pos, node_vel, node_pos_prev):
    """Semi-implicit Euler prediction of the nodes: ``v <- v / (1 + dt c) + dt (g + f/m)``, ``x += dt v``.

    The damping acts on the old velocity only, so a static load gives the same equilibrium for any dt.

    ``gravity`` (3,) m/s^2, ``node_force`` (N, 3) N, ``damping`` 1/s. Pinned nodes keep position, zero
    velocity. Stores the start positions in ``node_pos_prev`` and updates ``node_pos``, ``node_vel``.
    """
    scale = 1.0 / (1.0 + dt * damping)
    for i in range(node_pos.shape[0]):
        w = node_inv_mass[i]
        for k in range(3):  # in scalars: a row expression allocates its temporaries, per node and substep
            node_pos_prev[i, k] = node_pos[i, k]
            if w == 0.0:
                node_vel[i, k] = 0.0
                continue
            node_vel[i, k] = node_vel[i, k] * scale + dt * (gravity[k] + w * node_force[i, k])
            node_pos[i, k] += dt * node_vel[i, k]


@njit(cache=True)
def detect_contacts_kernel(
    node_pos,
    node_inv_mass,
    radius,
    plane_point,
    plane_normal,
    sphere_center,
    sphere_radius,
    contact_gap,
    contact_normal,
):
    """Closest obstacle of every free node: gap ``(x - p) . n - radius`` to planes and ``|x - c| - R - radius``
    to spheres. Writes the smallest gap (m; +inf if none or pinned) to ``contact_gap`` (N,) and its unit
    outward normal to ``contact_normal`` (N, 3)."""
    for i in range(node_pos.shape[0]):  # in scalars: no temporaries and no views, per node and iteration
        contact_gap[i] = np.inf
        if node_inv_mass[i] == 0.0:
            continue
        x, y, z = node_pos[i, 0], node_pos[i, 1], node_pos[i, 2]
        for k in range(plane_point.shape[0]):
            nx, ny, nz = plane_normal[k, 0], plane_normal[k, 1], plane_normal[k, 2]
            gap = (x - plane_point[k, 0]) * nx + (y - plane_point[k, 1]) * ny + (z - plane_point[k, 2]) * nz - radius
            if gap < contact_gap[i]:
                contact_gap[i] = gap
                contact_normal[i, 0], contact_normal[i, 1], contact_normal[i, 2] = nx, ny, nz
        for k in range(sphere_center.shape[0]):
            dx, dy, dz = x - sphere_center[k, 0], y - sphere_center[k, 1], z - sphere_center[k, 2]
            dist = np.sqrt(dx * dx + dy * dy + dz * dz)
            gap = dist - sphere_radius[k] - radius
            if dist > 0.0 and gap < contact_gap[i]:
                contact_gap[i] = gap
                contact_normal[i, 0], contact_normal[i, 1], contact_normal[i, 2] = dx / dist, dy / dist, dz / dist


@njit(cache=True)
def friction_kernel(contact_push, friction, dt, node_vel):
    """Coulomb friction at velocity level (as in Muller et al. 2020): a node pushed out by ``p`` (3,) m
    this substep loses up to ``mu |p| / dt`` of its tangential velocity. Updates ``node_vel`` (N, 3)."""
    for i in range(node_vel.shape[0]):
        push = np.sqrt(dot3(contact_push[i], contact_push[i]))
        if push == 0.0:
            continue
        n = contact_push[i] / push
        vt = node_vel[i] - dot3(node_vel[i], n) * n
        speed = np.sqrt(dot3(vt, vt))
        limit = friction * push / dt
        if speed <= limit:
            node_vel[i] -= vt
        else:
            node_vel[i] -= vt * (limit / speed)


# ---------------------------------------------------------------------------------------------------------
# Phase API
# ---------------------------------------------------------------------------------------------------------


def rod_predict(model: RodModel, state: RodState, dt: float, gravity, node_force=None) -> None:
    """Predict phase: store start positions, integrate gravity (3,) m/s^2 and ``node_force`` (N, 3) N."""
    require_positive("dt", dt)
    g = finite_array("gravity", gravity, (3,))
    n = model.node_count
    f = np.zeros((n, 3)) if node_force is None else finite_array("node_force", node_force, (n, 3))
    rod_predict_kernel(
        model.node_inv_mass, g, f, model.params.damping, dt, state.node_pos, state.node_vel, state.node_pos_prev
    )


_NO_OBSTACLES = (np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0, 3)), np.zeros(0))


def obstacle_arrays(obstacles: StaticObstacles | None) -> tuple:
    """The obstacle arrays of :func:`detect_contacts_kernel`, ``(plane_point (P, 3), plane_normal (P, 3),
    sphere_center (S, 3), sphere_radius (S,))`` (empty without obstacles)."""
    if obstacles is None:
        return _NO_OBSTACLES
    return obstacles.plane_point, obstacles.plane_normal, obstacles.sphere_center, obstacles.sphere_radius


def rod_detect_contacts(model: RodModel, state: RodState, work: RodWork, obstacles: StaticObstacles | None) -> None:
    """Collision detection for the thread: closest obstacle gap and normal of each node into
    ``work.contact_gap`` / ``work.contact_normal``, which the direct solve turns into one-sided contact rows.

    Every node's gap is reset (+inf without an obstacle in reach); the solver then lets the tissue contact rows
    of the coupling overwrite theirs (:func:`~suture_gym.sim.coupling.suture_contact_rows`).
    """
    detect_contacts_kernel(
        state.node_pos, model.node_inv_mass, model.radius, *obstacle_arrays(obstacles), work.contact_gap,
        work.contact_normal,
    )  # fmt: skip


def rod_solve_iteration(
    model: RodModel,
    state: RodState,
    work: RodWork,
    dt: float,
    needle_model: NeedleModel | None = None,
    needle_state: NeedleState | None = None,
    tolerance: float = 0.0,
    node_inv_mass: np.ndarray | None = None,
    contact_w: np.ndarray | None = None,
    axis_inv_mass: np.ndarray | None = None,
    axis: np.ndarray | None = None,
) -> float:
    """One direct-solver iteration (:func:`~suture_gym.sim.rod_solver.rod_iteration_kernel`) over all rod
    constraints, the contact rows in ``work.contact_gap`` / ``work.contact_normal`` and (if a needle is given)
    the two-way swage attachment.

    Call ``work.begin(state)`` once per substep before the first iteration. ``node_inv_mass`` (N,) 1/kg replaces
    the model's node inverse masses for this iteration (the coupling's embedded masses); with ``axis_inv_mass``
    (N,) 1/kg and unit ``axis`` (N, 3) node ``i``'s inverse mass is the matrix ``node_inv_mass[i] I +
    axis_inv_mass[i] axis[i] axis[i]^T`` (a node embedded in the tissue across a path but free along it;
    default: isotropic). ``contact_w`` (N,) 1/kg gives the obstacle's share of each contact row (default
    ``work.contact_obstacle_w``: static obstacles).
    Returns the largest residual before this iteration's solve (dimensionless, see
    :func:`~suture_gym.sim.rod_solver.assemble_rod_system`); if it is <= ``tolerance`` the solve is skipped and
    nothing moves except the frame alignment.
    """
    rod, needle, n_pos, n_quat = rod_kernel_args(
        model, work, needle_model, needle_state, node_inv_mass, contact_w, axis_inv_mass, axis
    )
    return rod_iteration_kernel(
        rod, needle, work.start, work.frames, work.contacts, work.system, work.lam, state.node_pos, state.seg_quat,
        n_pos, n_quat, float(dt), float(tolerance), True,
    )  # fmt: skip


def rod_kernel_args(
    model: RodModel,
    work: RodWork,
    needle_model: NeedleModel | None = None,
    needle_state: NeedleState | None = None,
    node_inv_mass: np.ndarray | None = None,
    contact_w: np.ndarray | None = None,
    axis_inv_mass: np.ndarray | None = None,
    axis: np.ndarray | None = None,
) -> tuple:
    """The argument groups ``(rod, needle, needle_pos, needle_quat)`` of
    :func:`~suture_gym.sim.rod_solver.rod_iteration_kernel` (see :mod:`suture_gym.sim.rod_solver`) for the
    arguments of :func:`rod_solve_iteration` (same meaning and defaults). Without a needle the needle group is
    marked absent and the pose is a placeholder; with one, ``needle_pos`` and ``needle_quat`` are the state's own
    arrays, which the solve updates in place."""
    if needle_model is not None and needle_state is not None:
        needle = (True, needle_model.body_inv_mass, needle_model.body_inv_inertia, needle_model.swage_pos_body)
        n_pos, n_quat = needle_state.body_pos, needle_state.body_quat
    else:
        needle = (False, 0.0, _NO_INERTIA, _NO_VECTOR)
        n_pos, n_quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    rod = (
        model.node_inv_mass if node_inv_mass is None else node_inv_mass, model.seg_rest_length,
        model.seg_inv_inertia, model.seg_stretch_compliance, model.bend_compliance,
        work.contact_obstacle_w if contact_w is None else contact_w,
        work.isotropic_axis_w if axis_inv_mass is None else axis_inv_mass,
        work.isotropic_axis if axis is None else axis,
    )  # fmt: skip
    return rod, needle, n_pos, n_quat


#: Needle arguments of :func:`~suture_gym.sim.rod_solver.rod_iteration_kernel` for a rod without a needle (never read).
_NO_INERTIA = np.zeros((3, 3))
_NO_VECTOR = np.zeros(3)


def segment_strain(model: RodModel, state: RodState) -> np.ndarray:
    """(N-1,) axial strain ``|x_{j+1} - x_j| / l_j - 1`` of every segment (dimensionless)."""
    edges = np.diff(state.node_pos, axis=0)
    return np.linalg.norm(edges, axis=1) / model.seg_rest_length - 1.0
