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

Solver (after Deul et al. 2018, "Direct position-based solver for stiff rods"): every iteration linearises all
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
    quat_to_matrix,
    quat_to_matrix_into,
    quat_turn_into,
)

#: A pivot of the block solve below this fraction of its row's diagonal marks the row as redundant.
_PIVOT_TOL = 1.0e-12
#: Rows per block of the direct solve: 3 stretch-shear (or attachment), 3 bend-twist, 1 contact.
BLOCK = 7
#: Weight of the frames' Newton residual |h| (rad) in the convergence measure. Measured on a 200-node thread
#: dragged over the ground: once |h| <= 1e-3 rad the nodes are within ~3e-8 m (3e-5 of a segment) of the fully
#: converged solve, so a tolerance of 1e-6 on the weighted value stops there.
_FRAME_RESIDUAL_WEIGHT = 1.0e-3
#: Most re-solves per iteration for releasing contacts that would pull (a thread peeling off the ground or the
#: tissue releases about one node per pass; the rest follow in the next iterations).
_MAX_RELEASE_PASSES = 4


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
        self.dinv = np.zeros((n, k, k))
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
        self.contact_active = np.zeros(n, dtype=np.bool_)
        self.contact_push = np.zeros((n, 3))
        self.att_r = np.zeros(3)
        self.att_winv = np.zeros((3, 3))

    def reset(self) -> None:
        """Forget the history (multipliers and the tension warm start), e.g. when a state is restored; two
        runs from the same state are then bit-identical."""
        self.lam[:] = 0.0
        self.seg_tension_prev[:] = 0.0

    def begin(self, state: RodState) -> None:
        """Start a projection phase: keep the last substep's segment tensions (multiplier units, kg m^2) as
        the geometric-stiffness estimate, zero the multipliers and contact pushes, and remember the frames'
        start orientations."""
        _tension_from_multipliers(self.lam, self.seg_tension_prev)
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
# Constraint maths
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _dot3(a, b):
    """Dot product of two 3-vectors."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True)
def _ab_into(a, b, out):
    """``out[:] = a @ b`` for small matrices, by loops (no BLAS call, no allocation)."""
    for i in range(a.shape[0]):
        for j in range(b.shape[1]):
            t = 0.0
            for k in range(a.shape[1]):
                t += a[i, k] * b[k, j]
            out[i, j] = t


@njit(cache=True)
def _abt_acc(a, b, scale, out):
    """``out += scale * a @ b.T`` for small matrices, by loops."""
    for i in range(a.shape[0]):
        for j in range(b.shape[0]):
            t = 0.0
            for k in range(a.shape[1]):
                t += a[i, k] * b[j, k]
            out[i, j] += scale * t


@njit(cache=True)
def _mv_acc(a, v, scale, out):
    """``out += scale * a @ v``."""
    for i in range(a.shape[0]):
        t = 0.0
        for k in range(a.shape[1]):
            t += a[i, k] * v[k]
        out[i] += scale * t


@njit(cache=True)
def _mtv_acc(a, v, scale, out):
    """``out += scale * a.T @ v``."""
    for k in range(a.shape[0]):
        vk = scale * v[k]
        for i in range(a.shape[1]):
            out[i] += a[k, i] * vk


@njit(cache=True)
def _rot_diag_into(r, d, scale, out):
    """``out[:] = scale * R diag(d) R^T`` (3, 3) for rotation ``r`` (3, 3) and diagonal ``d`` (3,)."""
    for i in range(3):
        for j in range(3):
            out[i, j] = scale * (r[i, 0] * d[0] * r[j, 0] + r[i, 1] * d[1] * r[j, 1] + r[i, 2] * d[2] * r[j, 2])


@njit(cache=True)
def _skew_into(x, y, z, out):
    """Write ``[(x, y, z)]x`` into ``out`` (3, 3)."""
    out[0, 0] = 0.0
    out[0, 1] = -z
    out[0, 2] = y
    out[1, 0] = z
    out[1, 1] = 0.0
    out[1, 2] = -x
    out[2, 0] = -y
    out[2, 1] = x
    out[2, 2] = 0.0


@njit(cache=True)
def stretch_shear_constraint(x0, x1, q, rest_length):
    """Stretch-shear ``C = (x1 - x0) / l - d3(q)`` (3,) of one segment (Kugelstadt & Schomer 2016).

    ``x0, x1`` (3,) m, ``q`` (4,) unit, ``rest_length`` m. Gradients: ``dC/dx1 = I/l``, ``dC/dx0 = -I/l`` and,
    for a world rotation-vector perturbation ``q <- exp(dtheta/2) q``, ``dC/dtheta = [d3]x``
    (:func:`stretch_shear_jacobian`).
    """
    r = quat_to_matrix(q)
    out = np.empty(3)
    for i in range(3):
        out[i] = (x1[i] - x0[i]) / rest_length - r[i, 2]
    return out


@njit(cache=True)
def stretch_shear_jacobian(q):
    """``dC_ss / dtheta = [d3(q)]x`` (3, 3) for a world rotation vector ``dtheta`` applied to ``q``."""
    r = quat_to_matrix(q)
    s = np.zeros((3, 3))
    _skew_into(r[0, 2], r[1, 2], r[2, 2], s)
    return s


@njit(cache=True)
def _darboux(q0, q1):
    """``r = conj(q0) q1`` as a tuple (w, x, y, z), sign chosen so that ``w >= 0`` (same rotation)."""
    w = q0[0] * q1[0] + q0[1] * q1[1] + q0[2] * q1[2] + q0[3] * q1[3]
    x = q0[0] * q1[1] - q0[1] * q1[0] - q0[2] * q1[3] + q0[3] * q1[2]
    y = q0[0] * q1[2] + q0[1] * q1[3] - q0[2] * q1[0] - q0[3] * q1[1]
    z = q0[0] * q1[3] - q0[1] * q1[2] + q0[2] * q1[1] - q0[3] * q1[0]
    if w < 0.0:
        return -w, -x, -y, -z
    return w, x, y, z


@njit(cache=True)
def bend_twist_constraint(q0, q1):
    """Bend-twist ``C = Im(conj(q0) q1)`` (3,) in q0's frame, rest shape straight (Kugelstadt & Schomer 2016).

    ``C ~ (l/2) Omega`` with Omega the discrete Darboux vector (curvatures about d1, d2 and twist about d3);
    the sign of ``conj(q0) q1`` is chosen with a non-negative real part.
    """
    _, x, y, z = _darboux(q0, q1)
    out = np.empty(3)
    out[0] = x
    out[1] = y
    out[2] = z
    return out


@njit(cache=True)
def _bend_twist_jacobian_into(q0, q1, r0, out):
    """Write ``B = 1/2 (r_w I - [r_v]x) R0^T`` into ``out`` (3, 3); ``r0`` (3, 3) is ``R(q0)``."""
    w, x, y, z = _darboux(q0, q1)
    m = np.empty((3, 3))
    _skew_into(-x, -y, -z, m)
    for i in range(3):
        m[i, i] = w
    for i in range(3):
        for j in range(3):
            out[i, j] = 0.5 * (m[i, 0] * r0[j, 0] + m[i, 1] * r0[j, 1] + m[i, 2] * r0[j, 2])


@njit(cache=True)
def bend_twist_jacobian(q0, q1):
    """``B = dC_bt / dtheta1 = 1/2 (r_w I - [r_v]x) R(q0)^T`` (3, 3); ``dC_bt / dtheta0 = -B``.

    ``r = conj(q0) q1`` (sign as in :func:`bend_twist_constraint`), ``dtheta`` world rotation vectors.
    """
    out = np.empty((3, 3))
    _bend_twist_jacobian_into(q0, q1, quat_to_matrix(q0), out)
    return out


# ---------------------------------------------------------------------------------------------------------
# Direct block-tridiagonal solve
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True)
def guarded_inverse(a, lmat, d, out):
    """Inverse of a symmetric positive semi-definite :data:`BLOCK` x :data:`BLOCK` matrix ``a`` by LDL^T.

    ``lmat`` (7, 7) and ``d`` (7,) are scratch; the inverse goes to ``out`` (7, 7). A row whose pivot falls
    below ``1e-12`` of its diagonal (a redundant or fully pinned constraint) is dropped: its rows and columns
    of ``out`` are zero, so it receives no multiplier. (Fixed size so that the loops compile unrolled.)
    """
    n = BLOCK
    for j in range(n):
        for i in range(n):
            lmat[i, j] = 0.0
        lmat[j, j] = 1.0
        s = a[j, j]
        for k in range(j):
            s -= lmat[j, k] * lmat[j, k] * d[k]
        if a[j, j] <= 0.0 or s <= _PIVOT_TOL * a[j, j]:
            d[j] = 0.0
            continue
        d[j] = s
        for i in range(j + 1, n):
            t = a[i, j]
            for k in range(j):
                t -= lmat[i, k] * lmat[j, k] * d[k]
            lmat[i, j] = t / s
    # lmat <- its inverse (unit lower triangular) in place: column j, rows top-down, uses the new rows above
    # and the old entries of later columns
    for j in range(n):
        for i in range(j + 1, n):
            t = lmat[i, j]
            for k in range(j + 1, i):
                t += lmat[i, k] * lmat[k, j]
            lmat[i, j] = -t
    for i in range(n):
        for j in range(i, n):
            t = 0.0
            for k in range(j, n):
                if d[k] > 0.0:
                    t += lmat[k, i] * lmat[k, j] / d[k]
            out[i, j] = t
            out[j, i] = t


@njit(cache=True)
def solve_block_tridiagonal(diag, lower, rhs, dinv, y, z):
    """Solve ``A z = rhs`` for symmetric block-tridiagonal ``A`` by a block LU sweep, O(number of blocks).

    ``diag`` (B, 7, 7) are the diagonal blocks ``A[b, b]``, ``lower`` (B, 7, 7) the blocks ``A[b, b-1]``
    (``lower[0]`` unused), ``rhs`` (B, 7). Scratch: ``dinv`` (B, 7, 7), ``y`` (B, 7). Output ``z`` (B, 7).
    """
    k7 = BLOCK
    nb = rhs.shape[0]
    lmat = np.empty((k7, k7))
    dvec = np.empty(k7)
    lfac = np.empty((k7, k7))
    schur = np.empty((k7, k7))
    tv = np.empty(k7)
    guarded_inverse(diag[0], lmat, dvec, dinv[0])
    y[0] = rhs[0]
    for b in range(1, nb):
        for i in range(k7):
            for j in range(k7):
                t = 0.0
                for k in range(k7):
                    t += lower[b, i, k] * dinv[b - 1, k, j]
                lfac[i, j] = t
        for i in range(k7):
            for j in range(k7):
                t = diag[b, i, j]
                for k in range(k7):
                    t -= lfac[i, k] * lower[b, j, k]
                schur[i, j] = t
        guarded_inverse(schur, lmat, dvec, dinv[b])
        for i in range(k7):
            t = rhs[b, i]
            for k in range(k7):
                t -= lfac[i, k] * y[b - 1, k]
            y[b, i] = t
    for i in range(k7):
        t = 0.0
        for k in range(k7):
            t += dinv[nb - 1, i, k] * y[nb - 1, k]
        z[nb - 1, i] = t
    for b in range(nb - 2, -1, -1):
        for i in range(k7):
            t = y[b, i]
            for k in range(k7):
                t -= lower[b + 1, k, i] * z[b + 1, k]
            tv[i] = t
        for i in range(k7):
            t = 0.0
            for k in range(k7):
                t += dinv[b, i, k] * tv[k]
            z[b, i] = t


@njit(cache=True)
def align_frames(node_pos, seg_inv_inertia, seg_quat):
    """Parallel-transport each free segment frame so that d3 points along its edge (minimal rotation).

    Clamped segments (zero inverse inertia) and zero-length edges are left alone. Updates ``seg_quat``.
    """
    theta = np.empty(3)
    for j in range(seg_quat.shape[0]):
        if seg_inv_inertia[j, 0] == 0.0 and seg_inv_inertia[j, 1] == 0.0 and seg_inv_inertia[j, 2] == 0.0:
            continue
        ex = node_pos[j + 1, 0] - node_pos[j, 0]
        ey = node_pos[j + 1, 1] - node_pos[j, 1]
        ez = node_pos[j + 1, 2] - node_pos[j, 2]
        en = np.sqrt(ex * ex + ey * ey + ez * ez)
        if en == 0.0:
            continue
        w, x, y, z = seg_quat[j, 0], seg_quat[j, 1], seg_quat[j, 2], seg_quat[j, 3]
        dx, dy, dz = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)  # d3(q)
        ex, ey, ez = ex / en, ey / en, ez / en
        cx, cy, cz = dy * ez - dz * ey, dz * ex - dx * ez, dx * ey - dy * ex  # d3 x edge
        s = np.sqrt(cx * cx + cy * cy + cz * cz)
        c = dx * ex + dy * ey + dz * ez
        if s < 1.0e-15 and c > 0.0:
            continue
        if s < 1.0e-15:  # antiparallel: half turn about an axis perpendicular to d3
            ax, ay, az = (dz, 0.0, -dx) if abs(dy) > 0.5 else (-dy, dx, 0.0)
            an = np.sqrt(ax * ax + ay * ay + az * az)
            theta[0], theta[1], theta[2] = np.pi * ax / an, np.pi * ay / an, np.pi * az / an
        else:
            angle = np.arctan2(s, c) / s
            theta[0], theta[1], theta[2] = cx * angle, cy * angle, cz * angle
        quat_turn_into(seg_quat[j], theta, seg_quat[j])


@njit(cache=True)
def _relative_rotation_vector(q, q0, out):
    """Write the rotation vector (rad, world) of ``q conj(q0)`` into ``out`` (3,), the short way."""
    w = q[0] * q0[0] + q[1] * q0[1] + q[2] * q0[2] + q[3] * q0[3]
    x = -q[0] * q0[1] + q[1] * q0[0] - q[2] * q0[3] + q[3] * q0[2]
    y = -q[0] * q0[2] + q[1] * q0[3] + q[2] * q0[0] - q[3] * q0[1]
    z = -q[0] * q0[3] - q[1] * q0[2] + q[2] * q0[1] + q[3] * q0[0]
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = np.sqrt(x * x + y * y + z * z)
    if s < 1.0e-300:
        out[0], out[1], out[2] = 0.0, 0.0, 0.0
        return
    f = 2.0 * np.arctan2(s, w) / s
    out[0], out[1], out[2] = x * f, y * f, z * f


@njit(cache=True)
def assemble_rod_system(
    node_pos,
    seg_quat,
    node_inv_mass,
    seg_rest_length,
    seg_inv_inertia,
    seg_stretch_compliance,
    bend_compliance,
    seg_quat_start,
    seg_tension_prev,
    contact_gap,
    contact_normal,
    lam,
    dt,
    has_needle,
    needle_pos,
    needle_quat,
    needle_inv_mass,
    needle_inv_inertia_body,
    swage_body,
    seg_rot,
    seg_s,
    seg_winv,
    bend_b,
    seg_h,
    att_r,
    att_winv,
    contact_active,
    diag,
    lower,
    rhs,
):
    """Linearise all rod constraints at the current configuration into the block-tridiagonal XPBD system.

    Rows (see :class:`RodWork`): attachment ``C = x_0 - (p_needle + R s_swage)`` (rigid), stretch-shear and
    bend-twist per segment, and a one-sided contact ``C = gap_i`` along ``contact_normal[i]`` for node i,
    active while the node penetrates (``contact_gap[i] < 0``) or already pushes (``lam[i, 6] > 0``). Unused
    rows carry an identity diagonal and a zero right-hand side.

    Outputs: Jacobian pieces ``seg_rot``, ``seg_s`` (= [d3]x), ``seg_winv`` (N-1, 3, 3), ``bend_b`` (N-2, 3, 3),
    frame residuals ``seg_h`` (N-1, 3), ``att_r`` (3,), ``att_winv`` (3, 3), ``contact_active`` (N,), and
    ``diag``, ``lower`` (N, 7, 7), ``rhs`` (N, 7) = ``-C - alpha~ lambda + J_theta h``, ``alpha~ = alpha/dt^2``.

    Frame "mass": the frames are nearly massless, so their block uses inertia plus the geometric stiffness of
    the stretch-shear rows, ``|lambda_ss| (I - d3 d3^T)`` (a bound on the lambda-weighted Hessian of
    ``-d3(theta)``; the previous substep's value stands in while this substep's multipliers build up), and
    keeps their Newton residual ``h = W (I dtheta - J_theta^T lambda)`` in the right-hand side, so the
    stiffness shapes the steps but not the solution. Without it Newton steps on the frames diverge under load.

    Returns the largest residual before the solve, dimensionless: ``|C + alpha~ lambda|`` (strain for
    stretch-shear, half-angle for bend-twist, gap / segment length for attachment and contacts) and
    ``1e-3 |h|`` (h in rad, see :data:`_FRAME_RESIDUAL_WEIGHT`).
    """
    n = node_pos.shape[0]
    nseg = n - 1
    inv_dt2 = 1.0 / (dt * dt)
    diag[:] = 0.0
    lower[:] = 0.0
    rhs[:] = 0.0
    residual = 0.0
    tmp = np.empty((3, 3))
    tmp2 = np.empty((3, 3))
    tmp3 = np.empty((3, 3))
    inertia = np.empty(3)
    winv_mod = np.empty(3)
    g = np.empty(3)
    dth = np.empty(3)
    for j in range(nseg):
        quat_to_matrix_into(seg_quat[j], seg_rot[j])
        _skew_into(seg_rot[j, 0, 2], seg_rot[j, 1, 2], seg_rot[j, 2, 2], seg_s[j])
    for j in range(nseg - 1):
        _bend_twist_jacobian_into(seg_quat[j], seg_quat[j + 1], seg_rot[j], bend_b[j])

    # frame inverse "mass" W_j and Newton residual h_j = W_j (I_j dtheta_j - (J_theta^T lambda)_j)
    _frame_torque(lam, seg_s, bend_b, seg_h)
    for j in range(nseg):
        rj = seg_rot[j]
        if not (seg_inv_inertia[j, 0] > 0.0 and seg_inv_inertia[j, 1] > 0.0 and seg_inv_inertia[j, 2] > 0.0):
            seg_winv[j] = 0.0
            seg_h[j] = 0.0
            continue
        stiff = max(np.sqrt(lam[j + 1, 0] ** 2 + lam[j + 1, 1] ** 2 + lam[j + 1, 2] ** 2), seg_tension_prev[j])
        for i in range(3):
            inertia[i] = 1.0 / seg_inv_inertia[j, i]
        winv_mod[0] = 1.0 / (inertia[0] + stiff)
        winv_mod[1] = 1.0 / (inertia[1] + stiff)
        winv_mod[2] = seg_inv_inertia[j, 2]
        _rot_diag_into(rj, winv_mod, 1.0, seg_winv[j])
        _rot_diag_into(rj, inertia, 1.0, tmp)
        _relative_rotation_vector(seg_quat[j], seg_quat_start[j], dth)
        for i in range(3):
            g[i] = -seg_h[j, i]
        _mv_acc(tmp, dth, 1.0, g)
        seg_h[j] = 0.0
        _mv_acc(seg_winv[j], g, 1.0, seg_h[j])
        residual = max(residual, _FRAME_RESIDUAL_WEIGHT * max(abs(seg_h[j, 0]), abs(seg_h[j, 1]), abs(seg_h[j, 2])))

    # block 0: attachment to the needle swage (rows 0-2), unused rows 3-5
    if has_needle:
        rn = np.empty((3, 3))
        quat_to_matrix_into(needle_quat, rn)
        _ab_into(rn, needle_inv_inertia_body, tmp)
        att_winv[:] = 0.0
        _abt_acc(tmp, rn, 1.0, att_winv)
        att_r[:] = 0.0
        _mv_acc(rn, swage_body, 1.0, att_r)
        _skew_into(att_r[0], att_r[1], att_r[2], tmp2)
        _ab_into(tmp2, att_winv, tmp)
        _abt_acc(tmp, tmp2, 1.0, diag[0, :3, :3])
        for i in range(3):
            diag[0, i, i] += node_inv_mass[0] + needle_inv_mass
            rhs[0, i] = -(node_pos[0, i] - needle_pos[i] - att_r[i])
            residual = max(residual, abs(rhs[0, i]) / seg_rest_length[0])
    else:
        for i in range(3):
            diag[0, i, i] = 1.0
    for i in range(3, 6):
        diag[0, i, i] = 1.0

    for j in range(nseg):
        b = j + 1
        l = seg_rest_length[j]
        s = seg_s[j]
        winv = seg_winv[j]
        rj = seg_rot[j]
        # stretch-shear rows
        _rot_diag_into(rj, seg_stretch_compliance[j], inv_dt2, tmp3)  # alpha~_ss, world frame
        _ab_into(s, winv, tmp)  # tmp = [d3]x W_j
        d_ss = diag[b, :3, :3]
        _abt_acc(tmp, s, 1.0, d_ss)
        w_sum = (node_inv_mass[j] + node_inv_mass[j + 1]) / (l * l)
        for i in range(3):
            val = -((node_pos[j + 1, i] - node_pos[j, i]) / l - rj[i, 2])
            hterm = 0.0
            d_ss[i, i] += w_sum
            for k in range(3):
                d_ss[i, k] += tmp3[i, k]
                val -= tmp3[i, k] * lam[b, k]
                hterm += s[i, k] * seg_h[j, k]
            rhs[b, i] = val + hterm
            residual = max(residual, abs(val))
        # bend-twist rows
        if j < nseg - 1:
            bj = bend_b[j]
            for i in range(3):
                for k in range(3):
                    tmp2[i, k] = winv[i, k] + seg_winv[j + 1, i, k]
            _ab_into(bj, tmp2, tmp3)
            _abt_acc(tmp3, bj, 1.0, diag[b, 3:6, 3:6])
            _abt_acc(tmp, bj, -1.0, diag[b, :3, 3:6])
            c_bt = bend_twist_constraint(seg_quat[j], seg_quat[j + 1])
            for i in range(3):
                a_i = bend_compliance[j, i] * inv_dt2
                diag[b, 3 + i, 3 + i] += a_i
                val = -c_bt[i] - a_i * lam[b, 3 + i]
                hterm = 0.0
                for k in range(3):
                    hterm += bj[i, k] * (seg_h[j + 1, k] - seg_h[j, k])
                    diag[b, 3 + i, k] = diag[b, k, 3 + i]
                rhs[b, 3 + i] = val + hterm
                residual = max(residual, abs(val))
        else:
            for i in range(3, 6):
                diag[b, i, i] = 1.0
        # coupling with the previous block through x_j (and q_j)
        if j == 0:
            if has_needle:
                for i in range(3):
                    lower[1, i, i] = -node_inv_mass[0] / l
        else:
            lp = seg_rest_length[j - 1]
            for i in range(3):
                lower[b, i, i] = -node_inv_mass[j] / (l * lp)
            bp = bend_b[j - 1]
            _abt_acc(tmp, bp, 1.0, lower[b, :3, 3:6])
            if j < nseg - 1:
                _ab_into(bend_b[j], winv, tmp2)
                _abt_acc(tmp2, bp, -1.0, lower[b, 3:6, 3:6])

    # contact rows: row 6 of block i belongs to node i
    for i in range(n):
        w = node_inv_mass[i]
        gap = contact_gap[i]
        active = w > 0.0 and np.isfinite(gap) and (gap < 0.0 or lam[i, 6] > 0.0)
        contact_active[i] = active
        if not active:
            diag[i, 6, 6] = 1.0
            continue
        nrm = contact_normal[i]
        diag[i, 6, 6] = w
        rhs[i, 6] = -gap
        scale = seg_rest_length[i - 1] if i >= 1 else seg_rest_length[0]
        residual = max(residual, abs(gap) / scale)
        if i >= 1:  # stretch-shear of segment i-1 (same block): dC_ss/dx_i = I / l_{i-1}
            for k in range(3):
                diag[i, 6, k] = w * nrm[k] / seg_rest_length[i - 1]
                diag[i, k, 6] = diag[i, 6, k]
        elif has_needle:  # attachment: dC_att/dx_0 = I
            for k in range(3):
                diag[0, 6, k] = w * nrm[k]
                diag[0, k, 6] = diag[0, 6, k]
        if i < nseg:  # stretch-shear of segment i (next block): dC_ss/dx_i = -I / l_i
            for k in range(3):
                lower[i + 1, k, 6] = -w * nrm[k] / seg_rest_length[i]
    return residual


@njit(cache=True)
def _frame_torque(mult, seg_s, bend_b, out):
    """``out[j] = (J_theta^T mult)_j`` (N-1, 3): generalised torque impulse of multipliers ``mult`` (N, 7) on
    each segment frame, from its stretch-shear rows and the bend-twist rows on either side."""
    nseg = out.shape[0]
    out[:] = 0.0
    for j in range(nseg):
        _mtv_acc(seg_s[j], mult[j + 1, :3], 1.0, out[j])
        if j < nseg - 1:
            _mtv_acc(bend_b[j], mult[j + 1, 3:6], -1.0, out[j])
        if j >= 1:
            _mtv_acc(bend_b[j - 1], mult[j, 3:6], 1.0, out[j])


@njit(cache=True)
def release_contact(i, lam_c, contact_active, diag, lower, rhs):
    """Take node i's contact row out of the system with its step fixed at ``-lam_c`` (its whole push undone).

    The fixed step's effect on the coupled stretch-shear/attachment rows moves to their right-hand side, then
    the row becomes an identity row with right-hand side ``-lam_c``. Updates ``contact_active``, ``diag``,
    ``lower``, ``rhs``.
    """
    contact_active[i] = False
    for k in range(6):
        rhs[i, k] += diag[i, k, 6] * lam_c
        diag[i, k, 6] = 0.0
        diag[i, 6, k] = 0.0
    if i + 1 < diag.shape[0]:
        for k in range(7):
            rhs[i + 1, k] += lower[i + 1, k, 6] * lam_c
            lower[i + 1, k, 6] = 0.0
    diag[i, 6, 6] = 1.0
    rhs[i, 6] = -lam_c


@njit(cache=True)
def apply_rod_solution(
    node_inv_mass,
    seg_rest_length,
    seg_s,
    seg_winv,
    bend_b,
    seg_h,
    has_needle,
    needle_inv_mass,
    att_r,
    att_winv,
    contact_active,
    contact_normal,
    z,
    lam,
    node_pos,
    seg_quat,
    needle_pos,
    needle_quat,
    contact_push,
):
    """Apply multiplier steps ``z`` (N, 7): ``dx = M^-1 J^T z`` to nodes, ``dtheta = W J^T z - h`` to frames
    (exact exponential map), and the attachment impulse ``-z[0, :3]`` to the needle (rigid XPBD).

    ``z`` is added to ``lam``. Updates ``node_pos`` (N, 3), ``seg_quat`` (N-1, 4), ``needle_pos`` (3,),
    ``needle_quat`` (4,), and adds contact pushes (m) to ``contact_push``.
    """
    n = node_pos.shape[0]
    nseg = n - 1
    lam += z
    for i in range(n):
        w = node_inv_mass[i]
        if w == 0.0:
            continue
        for k in range(3):
            dx = z[i, 6] * contact_normal[i, k]
            contact_push[i, k] += w * dx
            if i == 0 and has_needle:
                dx += z[0, k]
            if i >= 1:
                dx += z[i, k] / seg_rest_length[i - 1]
            if i < nseg:
                dx -= z[i + 1, k] / seg_rest_length[i]
            node_pos[i, k] += w * dx
    t = np.empty((nseg, 3))
    _frame_torque(z, seg_s, bend_b, t)
    dtheta = np.empty(3)
    for j in range(nseg):
        dtheta[:] = -seg_h[j]
        _mv_acc(seg_winv[j], t[j], 1.0, dtheta)
        if dtheta[0] != 0.0 or dtheta[1] != 0.0 or dtheta[2] != 0.0:  # clamped frames stay bit-exact
            quat_turn_into(seg_quat[j], dtheta, seg_quat[j])
    if has_needle:
        p = -z[0, :3]
        needle_pos += needle_inv_mass * p
        dtheta[:] = 0.0
        _mv_acc(att_winv, np.cross(att_r, p), 1.0, dtheta)
        quat_turn_into(needle_quat, dtheta, needle_quat)


@njit(cache=True)
def rod_iteration_kernel(
    node_inv_mass,
    seg_rest_length,
    seg_inv_inertia,
    seg_stretch_compliance,
    bend_compliance,
    dt,
    tolerance,
    has_needle,
    needle_inv_mass,
    needle_inv_inertia_body,
    swage_body,
    seg_quat_start,
    seg_tension_prev,
    contact_gap,
    contact_normal,
    contact_obstacle_w,
    seg_rot,
    seg_s,
    seg_winv,
    bend_b,
    seg_h,
    att_r,
    att_winv,
    contact_active,
    diag,
    lower,
    rhs,
    dinv,
    y,
    z,
    lam,
    node_pos,
    seg_quat,
    needle_pos,
    needle_quat,
    contact_push,
):
    """One direct XPBD iteration: align frames, assemble; if the residual exceeds ``tolerance``, solve and
    apply. Returns the residual before the solve (see :func:`assemble_rod_system`).

    ``contact_obstacle_w`` (N,) is the obstacle's share of each contact row's generalised inverse mass,
    ``J M^-1 J^T``: 0 for static obstacles; for a deformable one (a tissue triangle, see
    :func:`~suture_gym.sim.coupling.suture_contact_rows`) it makes the contact multiplier the two-way XPBD one,
    and the caller moves the obstacle by its share afterwards.
    """
    align_frames(node_pos, seg_inv_inertia, seg_quat)
    residual = assemble_rod_system(
        node_pos,
        seg_quat,
        node_inv_mass,
        seg_rest_length,
        seg_inv_inertia,
        seg_stretch_compliance,
        bend_compliance,
        seg_quat_start,
        seg_tension_prev,
        contact_gap,
        contact_normal,
        lam,
        dt,
        has_needle,
        needle_pos,
        needle_quat,
        needle_inv_mass,
        needle_inv_inertia_body,
        swage_body,
        seg_rot,
        seg_s,
        seg_winv,
        bend_b,
        seg_h,
        att_r,
        att_winv,
        contact_active,
        diag,
        lower,
        rhs,
    )
    if residual <= tolerance:
        return residual
    for i in range(node_pos.shape[0]):
        if contact_active[i]:
            diag[i, 6, 6] += contact_obstacle_w[i]
    # active-set refinement: contacts whose multiplier would turn negative (pull) are released and the system
    # re-solved; contacts still pulling after the last pass stay in for this iteration (the solution remains
    # consistent) and are released by the next iteration's activation rule.
    solve_block_tridiagonal(diag, lower, rhs, dinv, y, z)
    for _ in range(_MAX_RELEASE_PASSES):
        released = False
        for i in range(node_pos.shape[0]):
            if contact_active[i] and lam[i, 6] + z[i, 6] < 0.0:
                release_contact(i, lam[i, 6], contact_active, diag, lower, rhs)
                released = True
        if not released:
            break
        solve_block_tridiagonal(diag, lower, rhs, dinv, y, z)
    apply_rod_solution(
        node_inv_mass,
        seg_rest_length,
        seg_s,
        seg_winv,
        bend_b,
        seg_h,
        has_needle,
        needle_inv_mass,
        att_r,
        att_winv,
        contact_active,
        contact_normal,
        z,
        lam,
        node_pos,
        seg_quat,
        needle_pos,
        needle_quat,
        contact_push,
    )
    return residual


@njit(cache=True)
def _tension_from_multipliers(lam, out):
    """``out[j] = |lam[j+1, :3]|`` (N-1,): size of the stretch-shear multipliers (kg m^2) of segment j."""
    for j in range(out.shape[0]):
        out[j] = np.sqrt(lam[j + 1, 0] ** 2 + lam[j + 1, 1] ** 2 + lam[j + 1, 2] ** 2)


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
        node_pos_prev[i] = node_pos[i]
        w = node_inv_mass[i]
        if w == 0.0:
            node_vel[i] = 0.0
            continue
        node_vel[i] = node_vel[i] * scale + dt * (gravity + w * node_force[i])
        node_pos[i] += dt * node_vel[i]


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
    for i in range(node_pos.shape[0]):
        contact_gap[i] = np.inf
        if node_inv_mass[i] == 0.0:
            continue
        for k in range(plane_point.shape[0]):
            gap = _dot3(node_pos[i] - plane_point[k], plane_normal[k]) - radius
            if gap < contact_gap[i]:
                contact_gap[i] = gap
                contact_normal[i] = plane_normal[k]
        for k in range(sphere_center.shape[0]):
            d = node_pos[i] - sphere_center[k]
            dist = np.sqrt(_dot3(d, d))
            gap = dist - sphere_radius[k] - radius
            if dist > 0.0 and gap < contact_gap[i]:
                contact_gap[i] = gap
                contact_normal[i] = d / dist


@njit(cache=True)
def friction_kernel(contact_push, friction, dt, node_vel):
    """Coulomb friction at velocity level (as in Muller et al. 2020): a node pushed out by ``p`` (3,) m
    this substep loses up to ``mu |p| / dt`` of its tangential velocity. Updates ``node_vel`` (N, 3)."""
    for i in range(node_vel.shape[0]):
        push = np.sqrt(_dot3(contact_push[i], contact_push[i]))
        if push == 0.0:
            continue
        n = contact_push[i] / push
        vt = node_vel[i] - _dot3(node_vel[i], n) * n
        speed = np.sqrt(_dot3(vt, vt))
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


def _obstacle_arrays(obstacles: StaticObstacles | None) -> tuple:
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
        state.node_pos, model.node_inv_mass, model.radius, *_obstacle_arrays(obstacles), work.contact_gap,
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
) -> float:
    """One direct-solver iteration (:func:`rod_iteration_kernel`) over all rod constraints, the contact rows in
    ``work.contact_gap`` / ``work.contact_normal`` and (if a needle is given) the two-way swage attachment.

    Call ``work.begin(state)`` once per substep before the first iteration. ``node_inv_mass`` (N,) 1/kg replaces
    the model's node inverse masses for this iteration (the coupling's embedded masses) and ``contact_w`` (N,)
    1/kg gives the obstacle's share of each contact row (default ``work.contact_obstacle_w``: static obstacles).
    Returns the largest residual before this iteration's solve (dimensionless, see :func:`assemble_rod_system`);
    if it is <= ``tolerance`` the solve is skipped and nothing moves except the frame alignment.
    """
    if needle_model is not None and needle_state is not None:
        n_args = (True, needle_model.body_inv_mass, needle_model.body_inv_inertia, needle_model.swage_pos_body)
        n_pos, n_quat = needle_state.body_pos, needle_state.body_quat
    else:
        n_args = (False, 0.0, _NO_INERTIA, _NO_VECTOR)
        n_pos, n_quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    return rod_iteration_kernel(
        model.node_inv_mass if node_inv_mass is None else node_inv_mass, model.seg_rest_length,
        model.seg_inv_inertia, model.seg_stretch_compliance, model.bend_compliance, float(dt), float(tolerance),
        *n_args, work.seg_quat_start, work.seg_tension_prev, work.contact_gap, work.contact_normal,
        work.contact_obstacle_w if contact_w is None else contact_w, work.seg_rot, work.seg_s, work.seg_winv,
        work.bend_b, work.seg_h, work.att_r, work.att_winv, work.contact_active, work.diag, work.lower, work.rhs,
        work.dinv, work.y, work.z, work.lam, state.node_pos, state.seg_quat, n_pos, n_quat, work.contact_push,
    )  # fmt: skip


#: Needle arguments of :func:`rod_iteration_kernel` for a rod without a needle (never read).
_NO_INERTIA = np.zeros((3, 3))
_NO_VECTOR = np.zeros(3)


def segment_strain(model: RodModel, state: RodState) -> np.ndarray:
    """(N-1,) axial strain ``|x_{j+1} - x_j| / l_j - 1`` of every segment (dimensionless)."""
    edges = np.diff(state.node_pos, axis=0)
    return np.linalg.norm(edges, axis=1) / model.seg_rest_length - 1.0
