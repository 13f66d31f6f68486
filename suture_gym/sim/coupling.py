"""Needle/suture-tissue interaction (paper section 4), made XPBD: puncture, paths, access points and the
node-triangle, node-path and node-access constraints.

The strand
----------
The needle's arc nodes and the suture's nodes form one polyline, the *strand*, ordered from the needle tip to
the suture tail: strand node ``k < Nn`` is needle node ``k`` (node 0 is the tip, the HEAD; node ``Nn - 1`` the
swage) and strand node ``k >= Nn`` is suture node ``k - Nn + 1`` (suture node 0 sits on the swage through the
rod's attachment and is represented by the needle's swage node). Every strand node carries a material
coordinate ``sigma`` (m): its rest arc length from the tip along the polyline.

Detection (once per substep, after the prediction; :func:`coupling_detect`)
---------------------------------------------------------------------------
1. Broad phase: strand nodes outside the tissue's bounding box grown by ``broad_phase_margin`` are skipped;
   the others get their signed distance to the deformed surface with the closest triangle (BVHs refitted).
   Layers (paper Fig. 2a): inside ``s < 0``, resistance ``0 <= s < eps``, outside ``s >= eps``.
2. Matching (paper section 4.1, made continuous): each path records the strand coordinates ``sigma_entry``
   and ``sigma_exit`` of the strand points passing through its entry and exit access points, re-found every
   substep as the strand point nearest the access point within ``track_window`` of the previous value.
   A strand node with ``sigma_exit <= sigma < sigma_entry`` is IN that path. Paths are made tip first, so
   the newest path holds the front of the strand, as in the paper; unlike a per-substep re-matching of
   segments, the coordinates move continuously and cannot swap paths when two strand segments come close.
3. Puncture: while no path is open, the tip is held out of the tissue by node-triangle constraints. When the
   force they exerted on the tip region (needle nodes within ``tip_length`` of the point) against the tip's
   direction of travel in the previous substep, ``sum lambda (n . -d) / dt^2``, reaches ``puncture_force``
   the tip punctures: a new path opens whose first node and entry access point are the tip's closest surface
   point (triangle + barycentric coordinates); once the tip is through, both move to where the strand
   crosses the surface.
4. Path growth (paper section 4.3): while the path is open and the tip moves on, with ``d`` the distance from
   the tip to the last path node: no node if ``d < l``, ``floor(d / h)`` evenly spaced nodes (the last at the
   tip) if ``d > h``, one at the tip otherwise. Path nodes are tet index + barycentric coordinates located
   in the deformed mesh, so they move with the tissue.
5. Exit: once the tip has been inside and is outside again, the point where the strand crosses the surface
   becomes the exit access point and the path's last node; the path closes.
6. Release: an open path whose tip backed out (``sigma_entry <= 0`` and the tip more than ``l`` away from
   the entry) and a closed path with no strand left inside (``sigma_exit >= sigma_entry``, e.g. the thread's
   free end pulled through) are removed.
7. Constraint rows: HEAD inside an open path: none (it cuts). IN nodes: node-path (eq. 1) onto the matched
   path's polyline (nodes of an open path ahead of its last path node: none, the tip region cuts freely).
   Other nodes within ``eps + contact_margin`` of the surface (the tip too while no path is open):
   node-triangle (eq. 2), except the nodes of a strand piece through an access point. Every access point
   with the strand through it: node-access (eq. 3) on the strand piece of one segment's length centred on
   ``sigma_entry`` / ``sigma_exit`` (so the access point never sits at a piece's end, where eq. 3's gradient
   would drag the tissue along with the strand).

Projection (called by :class:`~suture_gym.sim.solver.Solver`)
--------------------------------------------------------------
* Needle rows act on the rigid needle through its generalised inverse mass (Muller et al. 2020), Gauss-Seidel
  (:func:`project_needle_rows`), with a kinetic axial friction per node inside the tissue.
* The thread is 4e-8 kg per node against 1e-4 kg tissue nodes and is solved by the rod's direct solver, so
  a plain Gauss-Seidel coupling would move only the thread: the rod pulls a taut thread straight across the
  path's bends, the node-path projection puts the node back, and the tissue never feels the tension. Hence
  suture nodes held on a path or passing an access point carry the inertia of the tissue point they are
  embedded in (:func:`embedded_inv_mass`), in their Gauss-Seidel node-path rows
  (:func:`project_suture_path_rows`) and in the rod's solve, and they slide freely along the path.
* Suture node-triangle rows are one-sided contact rows inside the rod's direct solve, made two-way with the
  tissue (:func:`suture_contact_rows`, :func:`rod_iteration_with_contacts`, :func:`apply_contact_reaction`).
* Node-access rows are Gauss-Seidel on the strand piece centred on the access point (:func:`project_access_rows`).

All rows are two-way: the tissue vertices take the reaction with their barycentric weights, so a needle pushed
against the tissue deforms it and a pulled thread closes the wound.
"""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields

import numpy as np
from numba import njit

from suture_gym.sim.bvh import BVH, build_bvh, refit_bvh
from suture_gym.sim.collision import (
    TriangleSurface,
    build_triangle_surface,
    closest_point_triangle,
    locate_points,
    segment_crossings,
    signed_distance,
)
from suture_gym.sim.quat import quat_from_rotation_vector, quat_mul, quat_normalize, quat_to_matrix
from suture_gym.sim.rod import (
    align_frames,
    apply_rod_solution,
    assemble_rod_system,
    release_contact,
    solve_block_tridiagonal,
)

#: Node states of paper section 4.1.
NODE_HEAD = 0
NODE_IN = 1
NODE_OUT = 2

#: Constraint row kinds of a strand node.
ROW_NONE = 0
ROW_TRIANGLE = 1
ROW_PATH = 2

#: Tissue vertices a node-path row touches: the two tets of the path nodes either side of the projection.
PATH_ROW_VERTICES = 8

#: Below this length (m) a direction is undefined and the constraint is skipped (degenerate geometry).
_TINY_LENGTH = 1.0e-12

#: Most re-solves per rod iteration that release suture-tissue contacts whose multiplier would pull.
CONTACT_RELEASE_PASSES = 4


def _is_real(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool)


@dataclass(frozen=True)
class CouplingParams:
    """Parameters of the strand-tissue interaction (SI units).

    Attributes:
        puncture_force: force, N, the tip must exert on the surface to puncture it (default 1.0 N; measured
            suture-needle puncture forces are 0.6-0.9 N in cartilage). Scale it with the tissue: 1 N indents a
            1 kPa tissue by several centimetres before it is reached.
        tip_length: m; the tip force is the contact force of the needle nodes within this arc length of the
            point (the tapered tip: the default 2 mm spans the first three of the default needle's 30 nodes,
            which share the load once the dent is deeper than the node spacing).
        resistance_eps: ``eps`` of paper eq. 2 and Fig. 2a, m: thickness of the resistance layer, the gap the
            node-triangle constraint keeps between strand nodes and the surface.
        path_spacing_min: ``l`` of paper section 4.3, m: no path node is added closer than this to the last.
        path_spacing_max: ``h``, m: a longer step adds ``floor(d / h)`` nodes. Defaults ``l = 1.2 mm``,
            ``h = 1.7 mm`` (the paper's 1.2 / 1.7 cm scaled to a 26 mm needle): a bite through one 30 mm wound
            edge of the two-bar scene with the default half-circle needle is 10-14 mm of path, 6-11 nodes.
        tear_force: coupling force, N, above which the tissue counts as damaged (a sticky flag; tear-through
            forces of sutures are 3-4 N).
        needle_axial_friction: kinetic friction force per metre of needle inside the tissue, N/m, resisting
            the needle's motion along its path relative to the tissue (0 disables it).
        contact_margin: m; node-triangle rows are made for strand nodes closer than ``eps + contact_margin`` to
            the surface (speculative contacts: a one-sided row acts only once violated, and a node that a
            projection left exactly at ``eps`` keeps its row in the next substep instead of flickering).
        track_window: half-width, m, of the strand interval searched around the previous strand coordinate
            of each access point: the farthest the strand may slide through an access point in one substep
            (2 mm: 2 m/s at 1 ms substeps).
        broad_phase_margin: m; strand nodes farther than this outside the tissue's bounding box are skipped.
        max_paths: capacity of the path vector; a puncture with no free slot is refused and flags overflow.
        max_path_nodes: capacity of the path-node buffer shared by all paths; growth stops (overflow) when full.
    """

    puncture_force: float = 1.0
    tip_length: float = 2.0e-3
    resistance_eps: float = 3.0e-4
    path_spacing_min: float = 1.2e-3
    path_spacing_max: float = 1.7e-3
    tear_force: float = 4.0
    needle_axial_friction: float = 10.0
    contact_margin: float = 1.0e-3
    track_window: float = 2.0e-3
    broad_phase_margin: float = 5.0e-3
    max_paths: int = 16
    max_path_nodes: int = 1024

    def __post_init__(self) -> None:
        for name in (
            "puncture_force",
            "tip_length",
            "resistance_eps",
            "path_spacing_min",
            "path_spacing_max",
            "tear_force",
            "contact_margin",
            "track_window",
            "broad_phase_margin",
        ):
            value = getattr(self, name)
            if not (_is_real(value) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"CouplingParams.{name} must be a finite number > 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        value = self.needle_axial_friction
        if not (_is_real(value) and math.isfinite(value) and value >= 0.0):
            raise ValueError(f"CouplingParams.needle_axial_friction must be a finite number >= 0 N/m, got {value!r}")
        object.__setattr__(self, "needle_axial_friction", float(value))
        if self.path_spacing_min > self.path_spacing_max:
            raise ValueError(
                f"CouplingParams.path_spacing_min ({self.path_spacing_min}) must not exceed "
                f"path_spacing_max ({self.path_spacing_max})"
            )
        for name in ("max_paths", "max_path_nodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"CouplingParams.{name} must be an integer >= 1, got {value!r}")
            object.__setattr__(self, name, int(value))


# ----------------------------------------------------------------------------------------------------------
# Constraint maths: small pure functions
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def xpbd_delta_lambda(c, w_sum, alpha_tilde, lam):
    """XPBD multiplier step ``dlambda = (-C - alpha~ lambda) / (sum_i w_i |grad_i C|^2 + alpha~)``
    (Macklin et al. 2016, eq. 18). ``w_sum`` is the generalised inverse mass ``sum_i w_i |grad_i C|^2``;
    returns 0 when it and ``alpha_tilde`` are both 0 (nothing can move)."""
    denom = w_sum + alpha_tilde
    if denom <= 0.0:
        return 0.0
    return (-c - alpha_tilde * lam) / denom


@njit(cache=True)
def node_triangle_constraint(q, p1, p2, p3, eps):
    """Node-triangle constraint of paper eq. 2: ``C = (q - p1) . n - eps``, ``n = p21 x p31 / |p21 x p31|``
    (with ``p21 x p31 = (p2 - p1) x (p3 - p1)`` the outward normal of a counter-clockwise triangle).

    Yu et al. 2020, eq. 2. Inequality: satisfied while ``C >= 0``.

    Args:
        q: (3,) strand node, m. p1, p2, p3: (3,) triangle vertices, m. eps: layer thickness, m.

    Returns:
        ``(ok, C, n, b)``: ``ok`` False for a degenerate (zero-area) triangle; ``C`` in m; ``n`` (3,) the unit
        normal, which is ``grad_q C``; ``b`` (3,) the weights with ``grad_pk C = -b_k n``. Where the
        projection of ``q`` onto the plane falls inside the triangle, ``b`` are its barycentric coordinates and
        the gradient is exact; outside, ``b`` are those of the closest point of the triangle (non-negative,
        summing to 1), which keeps the reaction on the triangle's own vertices.
    """
    e1 = p2 - p1
    e2 = p3 - p1
    nrm = np.cross(e1, e2)
    area2 = math.sqrt(nrm[0] * nrm[0] + nrm[1] * nrm[1] + nrm[2] * nrm[2])
    n = np.zeros(3)
    b = np.zeros(3)
    scale = max(e1 @ e1, e2 @ e2)
    if area2 <= 1.0e-12 * scale or scale == 0.0:
        return False, 0.0, n, b
    n[:] = nrm / area2
    r = q - p1
    c = r @ n - eps
    # barycentrics of the projection of q onto the plane
    proj = r - (r @ n) * n
    d00 = e1 @ e1
    d01 = e1 @ e2
    d11 = e2 @ e2
    d20 = proj @ e1
    d21 = proj @ e2
    det = d00 * d11 - d01 * d01
    v = (d11 * d20 - d01 * d21) / det
    w = (d00 * d21 - d01 * d20) / det
    u = 1.0 - v - w
    if u >= 0.0 and v >= 0.0 and w >= 0.0:
        b[0] = u
        b[1] = v
        b[2] = w
    else:
        _, bc, _ = closest_point_triangle(q, p1, p2, p3)
        b[:] = bc
    return True, c, n, b


@njit(cache=True)
def node_path_constraint(q, p, t):
    """Node-path constraint of paper eq. 1 in scalar form: ``C = |(p - q) x t|`` for unit tangent ``t``.

    Yu et al. 2020, eq. 1: the strand node ``q`` may only move along the path tangent ``t`` through the path
    point ``p = sum_i w_i p_i``. ``|(p - q) x t|`` is the distance from ``q`` to that line; it vanishes
    exactly where eq. 1 does and, unlike the rank-2 vector form, has a well-defined XPBD step. ``t`` is held
    fixed during a substep (computed at detection).

    Args:
        q: (3,) strand node, m. p: (3,) path point, m. t: (3,) unit tangent.

    Returns:
        ``(ok, C, n)``: ``C`` in m; ``n`` (3,) unit vector from the line to ``q``, ``grad_q C = n`` and
        ``grad_p C = -n`` (so ``grad_pi C = -w_i n``). ``ok`` False when ``q`` is on the line (``C = 0``,
        nothing to correct).
    """
    r = q - p
    d = r - (r @ t) * t
    c = math.sqrt(d[0] * d[0] + d[1] * d[1] + d[2] * d[2])
    n = np.zeros(3)
    if c <= _TINY_LENGTH:
        return False, 0.0, n
    n[:] = d / c
    return True, c, n


@njit(cache=True)
def node_access_constraint(pa, pb, b, rest_length):
    """Node-access constraint of paper eq. 3: ``C = |b - pa| + |b - pb| - l``.

    Yu et al. 2020, eq. 3: the strand segment ``pa -> pb`` of rest length ``l`` must pass through the access
    point ``b``. For a segment of length ``l``, ``C >= 0`` with equality exactly when ``b`` lies on it, so it
    is projected as the inequality ``C <= 0``.

    Args:
        pa, pb: (3,) segment end nodes, m. b: (3,) access point, m. rest_length: m.

    Returns:
        ``(ok, C, ga, gb)``: ``C`` in m, ``ga = grad_pa C = (pa - b)/|pa - b|``, ``gb`` likewise, and
        ``grad_b C = -(ga + gb)``. ``ok`` False when ``b`` coincides with an end node (C's gradient is
        undefined there and ``b`` is on the segment).
    """
    ra = pa - b
    rb = pb - b
    la = math.sqrt(ra[0] * ra[0] + ra[1] * ra[1] + ra[2] * ra[2])
    lb = math.sqrt(rb[0] * rb[0] + rb[1] * rb[1] + rb[2] * rb[2])
    ga = np.zeros(3)
    gb = np.zeros(3)
    if la <= _TINY_LENGTH or lb <= _TINY_LENGTH:
        return False, 0.0, ga, gb
    ga[:] = ra / la
    gb[:] = rb / lb
    return True, la + lb - rest_length, ga, gb


@njit(cache=True)
def project_particles(c, grads, inv_mass, alpha_tilde, lam):
    """One XPBD projection of a constraint on point masses; returns ``(dlambda, dx)`` without applying them.

    Args:
        c: constraint value. grads: (k, 3) ``grad_i C`` per particle. inv_mass: (k,) 1/kg.
        alpha_tilde: compliance / dt^2. lam: multiplier accumulated so far this substep.

    Returns:
        ``dlambda`` and ``dx`` (k, 3) m with ``dx_i = w_i grad_i C dlambda`` (Macklin et al. 2016).
    """
    k = grads.shape[0]
    w_sum = 0.0
    for i in range(k):
        w_sum += inv_mass[i] * (grads[i] @ grads[i])
    dlam = xpbd_delta_lambda(c, w_sum, alpha_tilde, lam)
    dx = np.empty((k, 3))
    for i in range(k):
        dx[i] = inv_mass[i] * dlam * grads[i]
    return dlam, dx


# ----------------------------------------------------------------------------------------------------------
# Rigid-body helpers (Muller et al. 2020, "Detailed rigid body simulation with extended position based dynamics")
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def rigid_generalized_inv_mass(inv_mass, inv_inertia_world, lin, ang):
    """``w = |lin|^2 / m + ang^T I^-1 ang`` (1/kg) of a rigid body for a constraint whose gradients at body
    points ``r_i`` are ``g_i``: ``lin = sum g_i``, ``ang = sum r_i x g_i`` (world frame)."""
    return inv_mass * (lin @ lin) + ang @ (inv_inertia_world @ ang)


@njit(cache=True)
def rigid_apply(pos, quat, inv_mass, inv_inertia_world, lin, ang, dlam):
    """Rigid XPBD pose update for multiplier step ``dlam`` of a constraint with gradients (``lin``, ``ang``):
    ``x += dlam lin / m``; the orientation turns by ``dlam I^-1 ang`` (exact exponential map). Updates ``pos``
    (3,) and ``quat`` (4,) in place."""
    for i in range(3):
        pos[i] += inv_mass * dlam * lin[i]
    dtheta = dlam * (inv_inertia_world @ ang)
    quat[:] = quat_normalize(quat_mul(quat_from_rotation_vector(dtheta), quat))


@njit(cache=True)
def _world_inv_inertia(quat, inv_inertia_body):
    r = quat_to_matrix(quat)
    return r @ inv_inertia_body @ r.T


@njit(cache=True)
def _body_point(pos, quat, point_body):
    """World position (3,) of body-frame point ``point_body`` for pose (``pos``, ``quat``)."""
    r = quat_to_matrix(quat)
    return pos + r @ point_body


# ----------------------------------------------------------------------------------------------------------
# Static description and state
# ----------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CouplingModel:
    """Static data of the interaction between one strand (needle + suture) and the tissue.

    Build it with :meth:`build`. The BVH boxes inside ``surface`` and ``tet_bvh`` are scratch: every
    detection refits them to the current tissue positions before using them, so they carry no state (but one
    model must not be stepped from two threads at once).

    Attributes:
        params: the :class:`CouplingParams`.
        needle_node_count: ``Nn``, needle nodes on the strand (strand nodes ``0 .. Nn-1``).
        suture_node_count: ``Ns``, suture rod nodes (0 for a needle alone); strand nodes ``Nn .. Nn+Ns-2``
            are suture nodes ``1 .. Ns-1``.
        strand_sigma: ``(M,) float64`` material coordinate of each strand node, m: rest arc length from the tip.
        strand_seg_length: ``(M-1,) float64`` rest length of each strand segment, m.
        strand_friction: ``(M,) float64`` kinetic axial friction cap of each strand node, N
            (``needle_axial_friction`` times the node's share of needle length; 0 for suture nodes).
        tri_tet_local: ``(F, 3) int8`` local index (0-3) in its tet of each vertex of each boundary triangle.
        surface: :class:`~suture_gym.sim.collision.TriangleSurface` of the tissue boundary.
        tet_bvh: :class:`~suture_gym.sim.bvh.BVH` over the tissue tets (path-node location).
    """

    params: CouplingParams
    needle_node_count: int
    suture_node_count: int
    strand_sigma: np.ndarray
    strand_seg_length: np.ndarray
    strand_friction: np.ndarray
    tri_tet_local: np.ndarray
    surface: TriangleSurface
    tet_bvh: BVH

    @property
    def strand_node_count(self) -> int:
        """``M = Nn + max(Ns - 1, 0)``."""
        return int(self.strand_sigma.shape[0])

    @property
    def strand_length(self) -> float:
        """Rest length of the strand, m."""
        return float(self.strand_sigma[-1])

    @classmethod
    def build(cls, tissue, needle, suture=None, params: CouplingParams | None = None) -> CouplingModel:
        """Coupling data for ``tissue`` (:class:`~suture_gym.sim.model.TissueModel`), ``needle``
        (:class:`~suture_gym.sim.needle.NeedleModel`) and optional ``suture``
        (:class:`~suture_gym.sim.rod.RodModel`)."""
        params = CouplingParams() if params is None else params
        if not isinstance(params, CouplingParams):
            raise ValueError(f"params must be CouplingParams, got {type(params).__name__}")
        needle_nodes = np.asarray(needle.node_pos_body, dtype=np.float64)
        nn = needle_nodes.shape[0]
        if nn < 2:
            raise ValueError(f"the needle needs at least 2 nodes, got {nn}")
        seg = [np.linalg.norm(np.diff(needle_nodes, axis=0), axis=1)]
        ns = 0
        if suture is not None:
            ns = int(suture.node_count)
            seg.append(np.asarray(suture.seg_rest_length, dtype=np.float64))
        seg_length = np.concatenate(seg)
        if not (np.all(np.isfinite(seg_length)) and np.all(seg_length > 0.0)):
            raise ValueError("strand segment rest lengths must be finite and > 0")
        sigma = np.concatenate([[0.0], np.cumsum(seg_length)])
        friction = np.zeros(sigma.shape[0])
        share = np.zeros(nn)
        share[:-1] += 0.5 * seg_length[: nn - 1]
        share[1:] += 0.5 * seg_length[: nn - 1]
        friction[:nn] = params.needle_axial_friction * share
        tets = tissue.tet_indices
        tri = tissue.tri_indices
        local = np.argmax(tets[tissue.tri_tet][:, None, :] == tri[:, :, None], axis=2).astype(np.int8)
        if not np.all(np.take_along_axis(tets[tissue.tri_tet], local.astype(np.int64), axis=1) == tri):
            raise ValueError("tissue.tri_tet must name a tet containing each boundary triangle")
        rest = tissue.particle_rest_q
        for array in (sigma, seg_length, friction, local):
            array.flags.writeable = False
        return cls(
            params=params,
            needle_node_count=nn,
            suture_node_count=ns,
            strand_sigma=sigma,
            strand_seg_length=seg_length,
            strand_friction=friction,
            tri_tet_local=local,
            surface=build_triangle_surface(tri, rest),
            tet_bvh=build_bvh(tets, rest),
        )


@dataclass
class CouplingState:
    """Time-varying interaction state: node states, the path vector, access points and force readings.

    Paths are stored in creation order (path ``k`` is older than ``k + 1``); path ``k``'s nodes occupy slots
    ``path_first[k] .. path_first[k] + path_len[k] - 1`` of the path-node buffer. Only the newest path can be
    open. Entries beyond ``path_count`` / ``pathnode_count`` are unused.

    Attributes:
        strand_sdist: ``(M,) float64`` signed distance of each strand node at the last detection, m
            (negative inside; ``+inf`` for nodes skipped by the broad phase).
        strand_tri: ``(M,) int32`` closest surface triangle (-1 when skipped).
        strand_bary: ``(M, 3) float64`` barycentric coordinates of the closest surface point.
        strand_status: ``(M,) int8`` NODE_HEAD (node 0), NODE_IN (matched to a path) or NODE_OUT.
        strand_path: ``(M,) int32`` path each node is matched to, -1 for none.
        path_count: number of paths in the path vector.
        path_first: ``(K,) int32`` first path-node slot of each path.
        path_len: ``(K,) int32`` number of path nodes.
        path_open: ``(K,) bool`` the tip is inside and the path still grows.
        path_entered: ``(K,) bool`` the tip has been strictly inside since the puncture.
        path_entry_tri: ``(K,) int32`` entry access triangle. path_entry_bary: ``(K, 3) float64``.
        path_exit_tri: ``(K,) int32`` exit access triangle, -1 while open. path_exit_bary: ``(K, 3) float64``.
        path_sigma_entry: ``(K,) float64`` strand coordinate at the entry access point, m.
        path_sigma_exit: ``(K,) float64`` strand coordinate at the exit access point, m (``-inf`` while open).
        pathnode_count: used path-node slots.
        pathnode_tet: ``(P,) int32`` tet of each path node. pathnode_bary: ``(P, 4) float64`` its barycentrics.
        tip_force: force the tip's node-triangle constraint exerted in the last substep, N (the puncture test).
        friction_force: total axial friction force on the needle in the last substep, N.
        max_force: largest single coupling-constraint force in the last substep, N.
        punctures: number of punctures so far.
        damaged: set once any coupling force exceeded ``tear_force`` (sticky).
        overflow: set once a puncture or a path node was refused for lack of buffer space (sticky).
    """

    strand_sdist: np.ndarray
    strand_tri: np.ndarray
    strand_bary: np.ndarray
    strand_status: np.ndarray
    strand_path: np.ndarray
    path_first: np.ndarray
    path_len: np.ndarray
    path_open: np.ndarray
    path_entered: np.ndarray
    path_entry_tri: np.ndarray
    path_entry_bary: np.ndarray
    path_exit_tri: np.ndarray
    path_exit_bary: np.ndarray
    path_sigma_entry: np.ndarray
    path_sigma_exit: np.ndarray
    pathnode_tet: np.ndarray
    pathnode_bary: np.ndarray
    path_count: int = 0
    pathnode_count: int = 0
    tip_force: float = 0.0
    friction_force: float = 0.0
    max_force: float = 0.0
    punctures: int = 0
    damaged: bool = False
    overflow: bool = False

    @classmethod
    def empty(cls, model: CouplingModel) -> CouplingState:
        """State with no paths; every node OUT (the tip HEAD) and unknown distances."""
        m = model.strand_node_count
        k = model.params.max_paths
        p = model.params.max_path_nodes
        status = np.full(m, NODE_OUT, np.int8)
        status[0] = NODE_HEAD
        return cls(
            strand_sdist=np.full(m, np.inf),
            strand_tri=np.full(m, -1, np.int32),
            strand_bary=np.zeros((m, 3)),
            strand_status=status,
            strand_path=np.full(m, -1, np.int32),
            path_first=np.zeros(k, np.int32),
            path_len=np.zeros(k, np.int32),
            path_open=np.zeros(k, np.bool_),
            path_entered=np.zeros(k, np.bool_),
            path_entry_tri=np.full(k, -1, np.int32),
            path_entry_bary=np.zeros((k, 3)),
            path_exit_tri=np.full(k, -1, np.int32),
            path_exit_bary=np.zeros((k, 3)),
            path_sigma_entry=np.zeros(k),
            path_sigma_exit=np.full(k, -np.inf),
            pathnode_tet=np.full(p, -1, np.int32),
            pathnode_bary=np.zeros((p, 4)),
        )

    def copy(self) -> CouplingState:
        """Deep copy (no array shared)."""
        return CouplingState(
            **{
                f.name: (
                    getattr(self, f.name).copy()
                    if isinstance(getattr(self, f.name), np.ndarray)
                    else getattr(self, f.name)
                )
                for f in fields(self)
            }
        )

    @property
    def punctured(self) -> bool:
        """The tip is inside an open path."""
        return self.path_count > 0 and bool(self.path_open[self.path_count - 1])


class CouplingWork:
    """Per-substep scratch: the constraint rows built by the detection and their multipliers.

    Rebuilt by every :func:`coupling_detect`, so it carries no state between substeps.

    Attributes (M strand nodes, K = ``max_paths``, P = ``max_path_nodes``):
        strand_q: ``(M, 3)`` strand node positions at detection, m.
        pathnode_q: ``(P, 3)`` path node positions at detection, m. pathnode_tangent: ``(P, 3)`` unit tangents.
        row_kind: ``(M,) int8`` ROW_NONE / ROW_TRIANGLE / ROW_PATH. row_tri: ``(M,) int32`` triangle.
        row_tissue: ``(M, 8) int32`` tissue vertices of a path row; row_weight: ``(M, 8)`` their weights.
        row_tangent: ``(M, 3)`` path tangent of a path row.
        row_lambda: ``(M,)`` multiplier (kg m) of each row this substep; row_friction_lambda: ``(M,)`` axial
            friction multiplier; row_contact_normal: ``(M, 3)`` the surface normal of a needle node's
            node-triangle row at its last projection.
        access_count: rows in use. access_node: ``(2K, 4) int32`` strand nodes of the two ends of the strand
            piece through the access point (ends ``a = w0 x0 + w1 x1``, ``b = w2 x2 + w3 x3``) and
            access_weight: ``(2K, 4)`` those weights; access_rest: ``(2K,)`` rest length of the piece, m;
            access_tri: ``(2K,) int32``; access_bary: ``(2K, 3)``; access_lambda: ``(2K,)``.
        suture_inv_mass: ``(Ns,)`` inverse masses of the suture nodes used by the projections this substep,
            1/kg (:func:`embedded_inv_mass`).
        suture_contact_bary: ``(Ns, 3)`` triangle weights of the suture nodes' contact rows in the rod's solve,
            and suture_contact_w: ``(Ns,)`` their generalised inverse mass, 1/kg.
    """

    def __init__(self, model: CouplingModel):
        m = model.strand_node_count
        k = model.params.max_paths
        p = model.params.max_path_nodes
        self.strand_q = np.zeros((m, 3))
        self.pathnode_q = np.zeros((p, 3))
        self.pathnode_tangent = np.zeros((p, 3))
        self.row_kind = np.zeros(m, np.int8)
        self.row_tri = np.full(m, -1, np.int32)
        self.row_tissue = np.zeros((m, PATH_ROW_VERTICES), np.int32)
        self.row_weight = np.zeros((m, PATH_ROW_VERTICES))
        self.row_tangent = np.zeros((m, 3))
        self.row_lambda = np.zeros(m)
        self.row_friction_lambda = np.zeros(m)
        self.row_contact_normal = np.zeros((m, 3))
        self.access_count = 0
        self.access_node = np.zeros((2 * k, 4), np.int32)
        self.access_weight = np.zeros((2 * k, 4))
        self.access_rest = np.zeros(2 * k)
        self.access_tri = np.zeros(2 * k, np.int32)
        self.access_bary = np.zeros((2 * k, 3))
        self.access_lambda = np.zeros(2 * k)
        self.suture_inv_mass = np.zeros(model.suture_node_count)
        self.suture_contact_bary = np.zeros((model.suture_node_count, 3))
        self.suture_contact_w = np.zeros(model.suture_node_count)


# ----------------------------------------------------------------------------------------------------------
# Detection kernels
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def strand_positions_kernel(needle_pos, needle_quat, needle_node_body, suture_q, out):
    """Strand node positions: needle nodes from the pose, then suture nodes 1.. . Writes ``out`` (M, 3), m."""
    r = quat_to_matrix(needle_quat)
    nn = needle_node_body.shape[0]
    for k in range(nn):
        for i in range(3):
            out[k, i] = (
                needle_pos[i]
                + r[i, 0] * needle_node_body[k, 0]
                + r[i, 1] * needle_node_body[k, 1]
                + r[i, 2] * needle_node_body[k, 2]
            )
    for j in range(1, suture_q.shape[0]):
        out[nn + j - 1] = suture_q[j]


@njit(cache=True)
def path_spacing_count(d, spacing_min, spacing_max):
    """Number of path nodes to add for a tip at distance ``d`` (m) from the last path node (paper section
    4.3): 0 if ``d < l``, ``floor(d / h)`` if ``d > h``, else 1 (0 for a non-finite ``d``)."""
    if not (d >= spacing_min) or not math.isfinite(d):
        return 0
    if d > spacing_max:
        return int(math.floor(d / spacing_max))
    return 1


@njit(cache=True)
def track_sigma(strand_q, sigma, target, sigma_prev, window, lower, upper):
    """Strand coordinate (m) of the strand point nearest ``target`` (3,), searched over the strand interval
    ``[max(sigma_prev - window, lower), min(sigma_prev + window, upper)]``; ties go to the coordinate nearer
    ``sigma_prev``.

    The bounds keep the coordinates of the access points in strand order (a path's exit before its entry,
    a newer path before an older one), so a tracker cannot jump to another branch of a looping thread that
    passes close to its access point.

    Args:
        strand_q: (M, 3) strand node positions, m. sigma: (M,) their material coordinates, m.
        target: (3,) access point, m. sigma_prev: last coordinate, m. window: search half-width, m.
        lower, upper: hard bounds of the coordinate, m.

    Returns:
        ``(sigma_new, distance)``; the coordinate lies in ``[max(lower, 0), min(upper, sigma[-1])]``.
    """
    m = sigma.shape[0]
    lo = max(sigma_prev - window, lower, 0.0)
    hi = min(sigma_prev + window, upper, sigma[m - 1])
    if lo > hi:
        lo = max(min(lower, upper), 0.0)
        hi = lo
    best_s = min(max(sigma_prev, lo), hi)
    best_d2 = np.inf
    for j in range(m - 1):
        if sigma[j + 1] < lo or sigma[j] > hi:
            continue
        a = strand_q[j]
        e = strand_q[j + 1] - a
        length = sigma[j + 1] - sigma[j]
        t_lo = max((lo - sigma[j]) / length, 0.0)
        t_hi = min((hi - sigma[j]) / length, 1.0)
        ee = e @ e
        t = t_lo
        if ee > 0.0:
            t = min(max(((target - a) @ e) / ee, t_lo), t_hi)
        diff = a + t * e - target
        d2 = diff @ diff
        s = sigma[j] + t * length
        if d2 < best_d2 or (d2 == best_d2 and abs(s - sigma_prev) < abs(best_s - sigma_prev)):
            best_d2 = d2
            best_s = s
    if best_d2 == np.inf:
        return best_s, np.inf
    return best_s, math.sqrt(best_d2)


@njit(cache=True)
def path_node_kinematics(
    pathnode_tet, pathnode_bary, tet_indices, tissue_q, path_first, path_len, path_count, out_q, out_tangent
):
    """Positions (m) and unit tangents of all path nodes in the deformed mesh.

    A node's tangent is the normalised mean of the unit vectors of its adjacent path edges (paper eq. 1's
    "arithmetic mean of the adjacent edge vectors", with edges normalised so uneven spacing does not tilt
    it); a single-node path gets a zero tangent. Writes ``out_q`` and ``out_tangent`` (P, 3).
    """
    for k in range(path_count):
        first = path_first[k]
        count = path_len[k]
        for s in range(first, first + count):
            t = pathnode_tet[s]
            for i in range(3):
                acc = 0.0
                for a in range(4):
                    acc += pathnode_bary[s, a] * tissue_q[tet_indices[t, a], i]
                out_q[s, i] = acc
        for s in range(first, first + count):
            tan = np.zeros(3)
            if s > first:
                e = out_q[s] - out_q[s - 1]
                ne = math.sqrt(e @ e)
                if ne > _TINY_LENGTH:
                    tan += e / ne
            if s < first + count - 1:
                e = out_q[s + 1] - out_q[s]
                ne = math.sqrt(e @ e)
                if ne > _TINY_LENGTH:
                    tan += e / ne
            nt = math.sqrt(tan @ tan)
            if nt > _TINY_LENGTH:
                out_tangent[s] = tan / nt
            else:
                out_tangent[s] = 0.0


@njit(cache=True)
def project_onto_path(q, first, count, pathnode_q, pathnode_tangent, is_open):
    """Where strand node ``q`` (3,) meets its path's polyline: the closest point over the path's segments.

    The first segment extends backwards and the last forwards (a node beyond an end is held on the line
    through that end along its tangent), except that nothing is returned ahead of the last node of an open
    path, where the tip cuts freely.

    Returns:
        ``(ok, slot, u)``: the projection lies on segment ``slot -> slot + 1`` at parameter ``u`` in [0, 1]
        (clamped); ``ok`` False for paths with fewer than two nodes or ahead of an open path's end.
    """
    if count < 2:
        return False, 0, 0.0
    best_d2 = np.inf
    best_slot = first
    best_u = 0.0
    best_raw = 0.0
    for s in range(first, first + count - 1):
        a = pathnode_q[s]
        e = pathnode_q[s + 1] - a
        ee = e @ e
        raw = 0.0
        if ee > 0.0:
            raw = ((q - a) @ e) / ee
        u = min(max(raw, 0.0), 1.0)
        diff = a + u * e - q
        d2 = diff @ diff
        if d2 < best_d2:
            best_d2 = d2
            best_slot = s
            best_u = u
            best_raw = raw
    if is_open and best_slot == first + count - 2 and best_raw > 1.0:
        return False, best_slot, best_u
    return True, best_slot, best_u


@njit(cache=True)
def _segment_of(sigma, s):
    """Strand segment index j with ``sigma[j] <= s <= sigma[j+1]`` (clamped to valid segments)."""
    m = sigma.shape[0]
    lo = 0
    hi = m - 2
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if sigma[mid] <= s:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(cache=True)
def build_rows(
    sigma,
    strand_q,
    sdist,
    strand_tri,
    row_band,
    path_count,
    path_first,
    path_len,
    path_open,
    path_sigma_entry,
    path_sigma_exit,
    path_entry_tri,
    path_entry_bary,
    path_exit_tri,
    path_exit_bary,
    pathnode_tet,
    pathnode_bary,
    pathnode_q,
    pathnode_tangent,
    tet_indices,
    out_status,
    out_path,
    row_kind,
    row_tri,
    row_tissue,
    row_weight,
    row_tangent,
    access_node,
    access_weight,
    access_rest,
    access_tri,
    access_bary,
):
    """Node states and constraint rows of every strand node, and the node-access rows (module docstring,
    detection step 7); nodes not on a path get a node-triangle row when their signed distance is below
    ``row_band`` (m). Returns the number of access rows written.

    A node-access row acts on the strand piece of rest length ``2 h`` centred on the strand coordinate at
    the access point, with ``h`` half the rest length of the segment holding it; its ends are interpolated
    between strand nodes (clamped to the strand's ends)."""
    m = sigma.shape[0]
    total = sigma[m - 1]
    n_access = 0
    for k in range(path_count):
        for end in range(2):
            if end == 0:
                s = path_sigma_entry[k]
                tri = path_entry_tri[k]
            else:
                s = path_sigma_exit[k]
                tri = path_exit_tri[k]
            if tri < 0 or not (0.0 < s < total):
                continue
            j = _segment_of(sigma, s)
            half = 0.5 * (sigma[j + 1] - sigma[j])
            lo = max(s - half, 0.0)
            hi = min(s + half, total)
            for end_k in range(2):
                se = lo if end_k == 0 else hi
                je = _segment_of(sigma, se)
                alpha = (se - sigma[je]) / (sigma[je + 1] - sigma[je])
                access_node[n_access, 2 * end_k] = je
                access_node[n_access, 2 * end_k + 1] = je + 1
                access_weight[n_access, 2 * end_k] = 1.0 - alpha
                access_weight[n_access, 2 * end_k + 1] = alpha
            access_rest[n_access] = hi - lo
            access_tri[n_access] = tri
            if end == 0:
                access_bary[n_access] = path_entry_bary[k]
            else:
                access_bary[n_access] = path_exit_bary[k]
            n_access += 1
    for i in range(m):
        out_status[i] = NODE_HEAD if i == 0 else NODE_OUT
        out_path[i] = -1
        row_kind[i] = ROW_NONE
        row_tri[i] = -1
        if i == 0 and path_count > 0 and path_open[path_count - 1]:
            out_path[0] = path_count - 1  # the HEAD cuts its way: no row
            continue
        s = sigma[i]
        matched = -1
        for k in range(path_count):
            lo = -np.inf if path_open[k] else path_sigma_exit[k]
            if lo <= s < path_sigma_entry[k]:
                matched = k
                break
        if matched >= 0:
            out_path[i] = matched
            if i > 0:
                out_status[i] = NODE_IN
            ok, slot, u = project_onto_path(
                strand_q[i], path_first[matched], path_len[matched], pathnode_q, pathnode_tangent, path_open[matched]
            )
            if not ok:
                continue
            tan = (1.0 - u) * pathnode_tangent[slot] + u * pathnode_tangent[slot + 1]
            nt = math.sqrt(tan @ tan)
            if nt <= _TINY_LENGTH:
                continue
            row_kind[i] = ROW_PATH
            row_tangent[i] = tan / nt
            for a in range(4):
                row_tissue[i, a] = tet_indices[pathnode_tet[slot], a]
                row_weight[i, a] = (1.0 - u) * pathnode_bary[slot, a]
                row_tissue[i, 4 + a] = tet_indices[pathnode_tet[slot + 1], a]
                row_weight[i, 4 + a] = u * pathnode_bary[slot + 1, a]
            continue
        if strand_tri[i] < 0 or not (sdist[i] < row_band):
            continue
        near_access = False
        for a in range(n_access):
            for e in range(4):
                if access_node[a, e] == i and access_weight[a, e] > 0.0:
                    near_access = True
        if near_access:
            continue
        row_kind[i] = ROW_TRIANGLE
        row_tri[i] = strand_tri[i]
    return n_access


# ----------------------------------------------------------------------------------------------------------
# Projection kernels
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _tissue_point(tissue_q, idx, weight):
    p = np.zeros(3)
    for a in range(idx.shape[0]):
        p += weight[a] * tissue_q[idx[a]]
    return p


@njit(cache=True)
def project_needle_rows(
    needle_node_count,
    needle_inv_mass,
    needle_inv_inertia_body,
    needle_node_body,
    needle_pos_prev,
    needle_quat_prev,
    tissue_inv_mass,
    tissue_q_prev,
    tri_vertices,
    strand_friction,
    eps,
    dt,
    row_kind,
    row_tri,
    row_tissue,
    row_weight,
    row_tangent,
    row_lambda,
    row_friction_lambda,
    row_contact_normal,
    needle_pos,
    needle_quat,
    tissue_q,
):
    """One Gauss-Seidel pass over the rows of the needle nodes (strand nodes ``0 .. Nn-1``).

    Node-triangle rows (eq. 2, inequality ``C >= 0``, multiplier kept ``>= 0``) and node-path rows (eq. 1)
    are rigid (zero compliance) and two-way: ``dlambda = -C / (w_needle + sum_k b_k^2 w_k)`` with
    ``w_needle`` the needle's generalised inverse mass at the node along the gradient; the needle takes the
    impulse ``dlambda n`` at the node, tissue vertex ``k`` moves by ``-w_k b_k dlambda n``. After each path
    row, kinetic axial friction: the relative displacement of node and path point along the tangent since
    the start of the substep is removed up to a multiplier of ``strand_friction[i] dt^2`` in magnitude
    (static below the cap, sliding at the cap). Updates the needle pose, ``tissue_q``, the multipliers and
    ``row_contact_normal`` (the normal of each node-triangle row).
    """
    for i in range(needle_node_count):
        kind = row_kind[i]
        if kind == ROW_NONE:
            continue
        inv_inertia = _world_inv_inertia(needle_quat, needle_inv_inertia_body)
        q = _body_point(needle_pos, needle_quat, needle_node_body[i])
        r = q - needle_pos
        if kind == ROW_TRIANGLE:
            tri = row_tri[i]
            i0 = tri_vertices[tri, 0]
            i1 = tri_vertices[tri, 1]
            i2 = tri_vertices[tri, 2]
            ok, c, n, b = node_triangle_constraint(q, tissue_q[i0], tissue_q[i1], tissue_q[i2], eps)
            if not ok or (c >= 0.0 and row_lambda[i] == 0.0):
                continue
            row_contact_normal[i] = n
            w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, n, np.cross(r, n))
            w += b[0] ** 2 * tissue_inv_mass[i0] + b[1] ** 2 * tissue_inv_mass[i1] + b[2] ** 2 * tissue_inv_mass[i2]
            dlam = xpbd_delta_lambda(c, w, 0.0, row_lambda[i])
            if row_lambda[i] + dlam < 0.0:
                dlam = -row_lambda[i]
            row_lambda[i] += dlam
            rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, n, np.cross(r, n), dlam)
            tissue_q[i0] -= tissue_inv_mass[i0] * b[0] * dlam * n
            tissue_q[i1] -= tissue_inv_mass[i1] * b[1] * dlam * n
            tissue_q[i2] -= tissue_inv_mass[i2] * b[2] * dlam * n
            continue
        idx = row_tissue[i]
        wt = row_weight[i]
        t = row_tangent[i]
        p = _tissue_point(tissue_q, idx, wt)
        w_tissue = 0.0
        for a in range(idx.shape[0]):
            w_tissue += wt[a] * wt[a] * tissue_inv_mass[idx[a]]
        ok, c, n = node_path_constraint(q, p, t)
        if ok:
            w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, n, np.cross(r, n)) + w_tissue
            dlam = xpbd_delta_lambda(c, w, 0.0, row_lambda[i])
            row_lambda[i] += dlam
            rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, n, np.cross(r, n), dlam)
            for a in range(idx.shape[0]):
                tissue_q[idx[a]] -= tissue_inv_mass[idx[a]] * wt[a] * dlam * n
        cap = strand_friction[i] * dt * dt
        if cap <= 0.0:
            continue
        inv_inertia = _world_inv_inertia(needle_quat, needle_inv_inertia_body)
        q = _body_point(needle_pos, needle_quat, needle_node_body[i])
        r = q - needle_pos
        q0 = _body_point(needle_pos_prev, needle_quat_prev, needle_node_body[i])
        p = _tissue_point(tissue_q, idx, wt)
        p0 = _tissue_point(tissue_q_prev, idx, wt)
        slip = ((q - q0) - (p - p0)) @ t
        w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, t, np.cross(r, t)) + w_tissue
        dlam = xpbd_delta_lambda(slip, w, 0.0, 0.0)
        total = min(max(row_friction_lambda[i] + dlam, -cap), cap)
        dlam = total - row_friction_lambda[i]
        row_friction_lambda[i] = total
        rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, t, np.cross(r, t), dlam)
        for a in range(idx.shape[0]):
            tissue_q[idx[a]] -= tissue_inv_mass[idx[a]] * wt[a] * dlam * t


@njit(cache=True)
def _strand_point(node, needle_node_count, needle_pos, needle_quat, needle_node_body, suture_q):
    """World position (3,) of strand node ``node`` (needle node from the pose, or suture node)."""
    if node < needle_node_count:
        return _body_point(needle_pos, needle_quat, needle_node_body[node])
    return suture_q[node - needle_node_count + 1].copy()


@njit(cache=True)
def project_access_rows(
    access_count,
    access_node,
    access_weight,
    access_rest,
    access_tri,
    access_bary,
    needle_node_count,
    needle_inv_mass,
    needle_inv_inertia_body,
    needle_node_body,
    suture_inv_mass,
    tissue_inv_mass,
    tri_vertices,
    access_lambda,
    needle_pos,
    needle_quat,
    suture_q,
    tissue_q,
):
    """One Gauss-Seidel pass over the node-access rows (eq. 3, inequality ``C <= 0``), two-way.

    The strand piece's ends are ``pa = w0 x0 + w1 x1`` and ``pb = w2 x2 + w3 x3`` (strand nodes
    ``access_node``, weights ``access_weight``), so node ``k`` gets the gradient ``w_k ga`` or ``w_k gb``.
    Needle nodes are points of the rigid needle (their gradients add up into one body Jacobian, generalised
    inverse mass), suture nodes particles, and the access point ``b = sum_v bary_v x_v`` gives its triangle's
    vertices ``-bary_v (ga + gb)``. Updates the needle pose, ``suture_q``, ``tissue_q`` and ``access_lambda``.
    """
    nn = needle_node_count
    for a in range(access_count):
        tri = access_tri[a]
        b = np.zeros(3)
        w_tissue_scale = 0.0
        for v in range(3):
            b += access_bary[a, v] * tissue_q[tri_vertices[tri, v]]
            w_tissue_scale += access_bary[a, v] ** 2 * tissue_inv_mass[tri_vertices[tri, v]]
        ends = np.zeros((2, 3))
        points = np.zeros((4, 3))
        for e in range(4):
            points[e] = _strand_point(access_node[a, e], nn, needle_pos, needle_quat, needle_node_body, suture_q)
            ends[e // 2] += access_weight[a, e] * points[e]
        ok, c, ga, gb = node_access_constraint(ends[0], ends[1], b, access_rest[a])
        if not ok or c <= 0.0:
            continue
        gs = ga + gb
        lin = np.zeros(3)
        ang = np.zeros(3)
        w = w_tissue_scale * (gs @ gs)
        for e in range(4):
            node = access_node[a, e]
            g = access_weight[a, e] * (ga if e < 2 else gb)
            if node < nn:
                lin += g
                ang += np.cross(points[e] - needle_pos, g)
            else:
                w += suture_inv_mass[node - nn + 1] * (g @ g)
        inv_inertia = _world_inv_inertia(needle_quat, needle_inv_inertia_body)
        if lin @ lin + ang @ ang > 0.0:
            w += rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, lin, ang)
        dlam = xpbd_delta_lambda(c, w, 0.0, access_lambda[a])
        access_lambda[a] += dlam
        if lin @ lin + ang @ ang > 0.0:
            rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, lin, ang, dlam)
        for e in range(4):
            node = access_node[a, e]
            if node >= nn:
                g = access_weight[a, e] * (ga if e < 2 else gb)
                sn = node - nn + 1
                suture_q[sn] += suture_inv_mass[sn] * dlam * g
        for v in range(3):
            vi = tri_vertices[tri, v]
            tissue_q[vi] -= tissue_inv_mass[vi] * access_bary[a, v] * dlam * gs


# ----------------------------------------------------------------------------------------------------------
# Detection (Python orchestration of the kernels; loops here run over paths, never over nodes)
# ----------------------------------------------------------------------------------------------------------


def access_point(model: CouplingModel, tissue_q: np.ndarray, tri: int, bary: np.ndarray) -> np.ndarray:
    """World position (3,) m of the surface point (``tri``, ``bary``)."""
    v = model.surface.tri_vertices[tri]
    return bary @ tissue_q[v]


def _surface_point_tet(model: CouplingModel, tissue, tri: int, bary: np.ndarray) -> tuple[int, np.ndarray]:
    """(tet, (4,) barycentrics) of the surface point (``tri``, ``bary``) in the tet owning the triangle."""
    tet = int(tissue.tri_tet[tri])
    out = np.zeros(4)
    out[model.tri_tet_local[tri].astype(np.int64)] = bary
    return tet, out


def _append_path_nodes(state: CouplingState, model: CouplingModel, tets: np.ndarray, barys: np.ndarray) -> None:
    """Append path nodes to the newest path (the last used slots); flag overflow when the buffer is full."""
    capacity = model.params.max_path_nodes
    for tet, bary in zip(tets, barys, strict=True):
        if tet < 0:
            continue
        if state.pathnode_count >= capacity:
            state.overflow = True
            return
        slot = state.pathnode_count
        state.pathnode_tet[slot] = tet
        state.pathnode_bary[slot] = bary
        state.pathnode_count += 1
        state.path_len[state.path_count - 1] += 1


def _release_path(state: CouplingState, k: int) -> None:
    """Remove path ``k`` and its nodes from the buffers, keeping the order of the others."""
    first, length = int(state.path_first[k]), int(state.path_len[k])
    end = state.pathnode_count
    state.pathnode_tet[first : end - length] = state.pathnode_tet[first + length : end]
    state.pathnode_bary[first : end - length] = state.pathnode_bary[first + length : end]
    state.pathnode_tet[end - length : end] = -1
    state.pathnode_bary[end - length : end] = 0.0
    state.pathnode_count -= length
    n = state.path_count
    for name in (
        "path_first",
        "path_len",
        "path_open",
        "path_entered",
        "path_entry_tri",
        "path_entry_bary",
        "path_exit_tri",
        "path_exit_bary",
        "path_sigma_entry",
        "path_sigma_exit",
    ):
        array = getattr(state, name)
        array[k : n - 1] = array[k + 1 : n]
    state.path_first[k : n - 1] -= length
    state.path_open[n - 1] = False
    state.path_entered[n - 1] = False
    state.path_len[n - 1] = 0
    state.path_entry_tri[n - 1] = -1
    state.path_exit_tri[n - 1] = -1
    state.path_sigma_exit[n - 1] = -np.inf
    state.path_count -= 1


def coupling_detect(
    model: CouplingModel, state: CouplingState, work: CouplingWork, tissue, tissue_q: np.ndarray, strand_q: np.ndarray
) -> None:
    """Detection phase (module docstring, steps 1-7) for strand positions ``strand_q`` (M, 3) m against the
    tissue (:class:`~suture_gym.sim.model.TissueModel` ``tissue``, positions ``tissue_q`` (N, 3) m).

    Updates ``state`` (distances, node states, paths, access points, puncture) and fills ``work``'s rows with
    zeroed multipliers. Uses ``state.tip_force`` from the previous substep for the puncture test.
    """
    params = model.params
    m = model.strand_node_count
    if strand_q.shape != (m, 3):
        raise ValueError(f"strand_q must have shape ({m}, 3), got {strand_q.shape}")
    work.strand_q[:] = strand_q
    refit_bvh(model.surface.bvh, tissue_q)
    refit_bvh(model.tet_bvh, tissue_q)

    lo = model.surface.bvh.node_lo[0] - params.broad_phase_margin
    hi = model.surface.bvh.node_hi[0] + params.broad_phase_margin
    near = np.flatnonzero(np.all((strand_q >= lo) & (strand_q <= hi), axis=1))
    state.strand_sdist[:] = np.inf
    state.strand_tri[:] = -1
    state.strand_bary[:] = 0.0
    if near.size:
        sdist, tri, bary = signed_distance(strand_q[near], model.surface, tissue_q)
        state.strand_sdist[near] = sdist
        state.strand_tri[near] = tri
        state.strand_bary[near] = bary

    sigma = model.strand_sigma
    window = params.track_window
    total = model.strand_length
    for k in range(state.path_count - 1, -1, -1):  # newest (front of the strand) first
        upper = state.path_sigma_exit[k - 1] if k > 0 else total
        newer_entry = state.path_sigma_entry[k + 1] if k + 1 < state.path_count else 0.0
        if not state.path_open[k]:
            b = access_point(model, tissue_q, state.path_exit_tri[k], state.path_exit_bary[k])
            state.path_sigma_exit[k] = track_sigma(
                strand_q, sigma, b, state.path_sigma_exit[k], window, newer_entry, state.path_sigma_entry[k]
            )[0]
            lower = state.path_sigma_exit[k]
        else:
            lower = 0.0
        b = access_point(model, tissue_q, state.path_entry_tri[k], state.path_entry_bary[k])
        state.path_sigma_entry[k] = track_sigma(strand_q, sigma, b, state.path_sigma_entry[k], window, lower, upper)[0]

    tip = strand_q[0]
    for k in range(state.path_count - 1, -1, -1):
        if state.path_open[k]:
            b = access_point(model, tissue_q, state.path_entry_tri[k], state.path_entry_bary[k])
            release = state.path_sigma_entry[k] <= 0.0 and np.linalg.norm(tip - b) > params.path_spacing_min
        else:
            release = state.path_sigma_exit[k] >= state.path_sigma_entry[k]
        if release:
            _release_path(state, k)

    path_node_kinematics(
        state.pathnode_tet,
        state.pathnode_bary,
        tissue.tet_indices,
        tissue_q,
        state.path_first,
        state.path_len,
        state.path_count,
        work.pathnode_q,
        work.pathnode_tangent,
    )
    _tip_events(model, state, work, tissue, tissue_q, tip)
    path_node_kinematics(
        state.pathnode_tet,
        state.pathnode_bary,
        tissue.tet_indices,
        tissue_q,
        state.path_first,
        state.path_len,
        state.path_count,
        work.pathnode_q,
        work.pathnode_tangent,
    )

    work.access_count = build_rows(
        sigma,
        strand_q,
        state.strand_sdist,
        state.strand_tri,
        params.resistance_eps + params.contact_margin,
        state.path_count,
        state.path_first,
        state.path_len,
        state.path_open,
        state.path_sigma_entry,
        state.path_sigma_exit,
        state.path_entry_tri,
        state.path_entry_bary,
        state.path_exit_tri,
        state.path_exit_bary,
        state.pathnode_tet,
        state.pathnode_bary,
        work.pathnode_q,
        work.pathnode_tangent,
        tissue.tet_indices,
        state.strand_status,
        state.strand_path,
        work.row_kind,
        work.row_tri,
        work.row_tissue,
        work.row_weight,
        work.row_tangent,
        work.access_node,
        work.access_weight,
        work.access_rest,
        work.access_tri,
        work.access_bary,
    )
    work.row_lambda[:] = 0.0
    work.row_friction_lambda[:] = 0.0
    work.access_lambda[:] = 0.0


def _tip_events(model, state, work, tissue, tissue_q, tip) -> None:
    """Puncture, path growth and exit of the tip (module docstring, steps 3-5)."""
    params = model.params
    n = state.path_count
    open_k = n - 1 if n > 0 and state.path_open[n - 1] else -1
    tip_sdist = state.strand_sdist[0]
    if open_k < 0:
        if state.tip_force >= params.puncture_force and state.strand_tri[0] >= 0:
            if n >= params.max_paths or state.pathnode_count >= params.max_path_nodes:
                state.overflow = True
                return
            tri = int(state.strand_tri[0])
            bary = state.strand_bary[0].copy()
            state.path_first[n] = state.pathnode_count
            state.path_len[n] = 0
            state.path_open[n] = True
            state.path_entered[n] = False
            state.path_entry_tri[n] = tri
            state.path_entry_bary[n] = bary
            state.path_exit_tri[n] = -1
            state.path_exit_bary[n] = 0.0
            state.path_sigma_entry[n] = 0.0
            state.path_sigma_exit[n] = -np.inf
            state.path_count = n + 1
            state.punctures += 1
            tet, tet_bary = _surface_point_tet(model, tissue, tri, bary)
            _append_path_nodes(state, model, np.array([tet]), tet_bary[None, :])
        return
    if tip_sdist < 0.0 and not state.path_entered[open_k]:
        # the tip is through: the entry is where the strand crosses the surface (the puncture recorded the
        # tip's closest point from just outside)
        state.path_entered[open_k] = True
        tri, bary = _tip_crossing(model, state, tissue_q, work.strand_q)
        state.path_entry_tri[open_k] = tri
        state.path_entry_bary[open_k] = bary
        slot = state.path_first[open_k]
        state.pathnode_tet[slot], state.pathnode_bary[slot] = _surface_point_tet(model, tissue, tri, bary)
        return
    if state.path_entered[open_k] and tip_sdist > 0.0 and state.strand_tri[0] >= 0:
        tri, bary = _tip_crossing(model, state, tissue_q, work.strand_q)
        state.path_open[open_k] = False
        state.path_exit_tri[open_k] = tri
        state.path_exit_bary[open_k] = bary
        state.path_sigma_exit[open_k] = 0.0
        tet, tet_bary = _surface_point_tet(model, tissue, tri, bary)
        _append_path_nodes(state, model, np.array([tet]), tet_bary[None, :])
        return
    last = state.path_first[open_k] + state.path_len[open_k] - 1
    p_last = work.pathnode_q[last]
    step = tip - p_last
    d = float(np.linalg.norm(step))
    count = path_spacing_count(d, params.path_spacing_min, params.path_spacing_max)
    if count == 0:
        return
    free = params.max_path_nodes - state.pathnode_count
    if count > free:
        state.overflow = True
        count = free
        if count == 0:
            return
    if state.path_len[open_k] >= 2:
        forward = float(step @ (p_last - work.pathnode_q[last - 1])) > 0.0
    else:
        forward = tip_sdist < 0.0
    if not forward:
        return
    points = p_last + np.arange(1, count + 1)[:, None] / count * step
    tets, barys = locate_points(points, model.tet_bvh, tissue_q, tolerance=1e-6)
    _append_path_nodes(state, model, tets, barys)


def coupling_finish(
    model: CouplingModel, state: CouplingState, work: CouplingWork, dt: float, tip_direction: np.ndarray
) -> None:
    """Force readings after the projection: the tip force, the total axial friction, the largest coupling force
    and the sticky damage flag (``max_force > tear_force``).

    The tip force (N), the puncture test of the next substep, is the force the tissue's node-triangle rows
    exert against the tip's direction of travel ``tip_direction`` (3,) (unit, world) on the needle nodes within
    ``tip_length`` of the point, ``sum_i lambda_i (n_i . -d) / dt^2``, clipped at 0: the load that drives
    the cut. (In a dent the surface normals tilt, and the lateral part of the contact force is carried by the
    holder, not by the cutting edge.)
    """
    inv_dt2 = 1.0 / (dt * dt)
    nn = model.needle_node_count
    tip = model.strand_sigma[:nn] <= model.params.tip_length
    touching = tip & (work.row_kind[:nn] == ROW_TRIANGLE)
    axial = -(work.row_contact_normal[:nn][touching] @ np.asarray(tip_direction, dtype=np.float64))
    state.tip_force = max(0.0, float(work.row_lambda[:nn][touching] @ axial) * inv_dt2)
    state.friction_force = float(np.abs(work.row_friction_lambda).sum() * inv_dt2)
    largest = float(np.abs(work.row_lambda).max(initial=0.0))
    if work.access_count:
        largest = max(largest, float(np.abs(work.access_lambda[: work.access_count]).max()))
    state.max_force = largest * inv_dt2
    if state.max_force > model.params.tear_force:
        state.damaged = True


@njit(cache=True)
def embedded_inv_mass(
    needle_node_count,
    row_kind,
    row_tissue,
    row_weight,
    access_count,
    access_node,
    access_weight,
    access_tri,
    access_bary,
    tri_vertices,
    tissue_inv_mass,
    suture_inv_mass,
    out,
):
    """Inverse masses (1/kg) the projections use for the suture nodes this substep: a node held on a path
    (node-path row) carries the inertia of the tissue point it is embedded in, ``min(w_node, sum_k b_k^2 w_k)``,
    and a node of a strand piece through an access point that of the access point,
    ``min(w_node, sum_v bary_v^2 w_v)``; the others keep their own. Writes ``out`` (Ns,).

    Why: the thread is 3e-8 kg per node against 1e-4 kg tissue nodes. Projected with its own mass, a node on a
    path would take the whole of every correction: the inextensible rod's solve pulls a taut thread straight
    across the path's bends, the node-path projection puts the node back, and the tissue never feels the
    tension. Embedded in the tissue, the node moves across the path with the tissue, so the solve shares the
    thread's length between the needle, the free thread and the tissue, and the node-path projection splits
    the rest evenly between node and tissue. It slides along the path freely (no row along the tangent); the
    same holds for the thread in the hole at an access point. A thread node merely touching the surface
    keeps its own mass: it cannot dent the tissue (an embedded mass there makes the contact push the surface
    by half of every penetration, which turned out violent).
    """
    nn = needle_node_count
    for j in range(suture_inv_mass.shape[0]):
        out[j] = suture_inv_mass[j]
        if j == 0:
            continue
        i = nn + j - 1
        if row_kind[i] != ROW_PATH:
            continue
        w = 0.0
        for a in range(PATH_ROW_VERTICES):
            w += row_weight[i, a] ** 2 * tissue_inv_mass[row_tissue[i, a]]
        if w > 0.0 and w < out[j]:
            out[j] = w
    for a in range(access_count):
        w = 0.0
        for v in range(3):
            w += access_bary[a, v] ** 2 * tissue_inv_mass[tri_vertices[access_tri[a], v]]
        if w <= 0.0:
            continue
        for e in range(4):
            node = access_node[a, e]
            if node >= nn and access_weight[a, e] > 0.0:
                j = node - nn + 1
                if w < out[j]:
                    out[j] = w


@njit(cache=True)
def project_suture_path_rows(
    needle_node_count,
    row_kind,
    row_tissue,
    row_weight,
    row_tangent,
    suture_inv_mass,
    tissue_inv_mass,
    row_lambda,
    suture_q,
    tissue_q,
):
    """One Gauss-Seidel pass over the suture nodes' node-path rows (eq. 1, ``C = |(p - q) x t|``), rigid and
    two-way between the node (its embedded inverse mass, :func:`embedded_inv_mass`) and the path point's tissue
    vertices. Updates ``suture_q``, ``tissue_q`` and ``row_lambda``."""
    nn = needle_node_count
    for j in range(1, suture_q.shape[0]):
        i = nn + j - 1
        if row_kind[i] != ROW_PATH:
            continue
        idx = row_tissue[i]
        wt = row_weight[i]
        p = _tissue_point(tissue_q, idx, wt)
        ok, c, n = node_path_constraint(suture_q[j], p, row_tangent[i])
        if not ok:
            continue
        w = suture_inv_mass[j]
        for a in range(PATH_ROW_VERTICES):
            w += wt[a] * wt[a] * tissue_inv_mass[idx[a]]
        dlam = xpbd_delta_lambda(c, w, 0.0, row_lambda[i])
        row_lambda[i] += dlam
        suture_q[j] += suture_inv_mass[j] * dlam * n
        for a in range(PATH_ROW_VERTICES):
            tissue_q[idx[a]] -= tissue_inv_mass[idx[a]] * wt[a] * dlam * n


@njit(cache=True)
def suture_contact_rows(
    needle_node_count,
    eps,
    row_kind,
    row_tri,
    tri_vertices,
    tissue_q,
    tissue_inv_mass,
    suture_q,
    out_gap,
    out_normal,
    out_bary,
    out_tissue_w,
):
    """The suture nodes' node-triangle rows (eq. 2) as the rod's one-sided contact rows: ``gap = C`` and
    ``normal = n`` at the current positions, the weights ``b`` of the triangle's vertices in ``out_bary`` and
    their generalised inverse mass ``sum_v b_v^2 w_v`` (1/kg) in ``out_tissue_w``. Nodes without a
    node-triangle row (and node 0, on the swage) get ``gap = +inf``. Writes ``out_gap`` (Ns,), ``out_normal``
    (Ns, 3), ``out_bary`` (Ns, 3), ``out_tissue_w`` (Ns,)."""
    nn = needle_node_count
    for j in range(suture_q.shape[0]):
        out_gap[j] = np.inf
        out_tissue_w[j] = 0.0
        if j == 0:
            continue
        i = nn + j - 1
        if row_kind[i] != ROW_TRIANGLE:
            continue
        tri = row_tri[i]
        ok, c, n, b = node_triangle_constraint(
            suture_q[j],
            tissue_q[tri_vertices[tri, 0]],
            tissue_q[tri_vertices[tri, 1]],
            tissue_q[tri_vertices[tri, 2]],
            eps,
        )
        if ok:
            out_gap[j] = c
            out_normal[j] = n
            out_bary[j] = b
            for v in range(3):
                out_tissue_w[j] += b[v] * b[v] * tissue_inv_mass[tri_vertices[tri, v]]


@njit(cache=True)
def rod_iteration_with_contacts(
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
    contact_tissue_w,
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
    """One direct XPBD iteration of the suture (the rod's :func:`~suture_gym.sim.rod.rod_iteration_kernel`)
    whose contact rows are two-way with the tissue.

    The rod's solve treats a contact as a static obstacle; a tissue triangle is not: its vertices weigh about
    1e-4 kg against the 20 g needle that a thread pressed onto the tissue can transmit. So each active
    contact row's diagonal gets the triangle point's generalised inverse mass ``contact_tissue_w`` (the
    tissue's share of ``J M^-1 J^T``), which makes the multiplier the two-way XPBD one; the caller moves the
    tissue by its share afterwards (:func:`apply_contact_reaction`). Contacts whose multiplier would pull are
    released and the system re-solved (at most :data:`CONTACT_RELEASE_PASSES` times), as in the rod's kernel.
    Returns the residual before the solve.
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
            diag[i, 6, 6] += contact_tissue_w[i]
    solve_block_tridiagonal(diag, lower, rhs, dinv, y, z)
    for _ in range(CONTACT_RELEASE_PASSES):
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
def apply_contact_reaction(
    needle_node_count,
    row_kind,
    row_tri,
    tri_vertices,
    contact_normal,
    contact_bary,
    z,
    tissue_inv_mass,
    row_lambda,
    tissue_q,
):
    """Give the tissue the reaction of the rod's contact steps ``z[j, 6]`` (kg m) on suture nodes with a
    node-triangle row: triangle vertex ``v`` moves by ``-w_v b_v z normal``, so the exchange conserves
    momentum. Adds each step to ``row_lambda``. Updates ``tissue_q``."""
    nn = needle_node_count
    for j in range(1, z.shape[0]):
        i = nn + j - 1
        dlam = z[j, 6]
        if row_kind[i] != ROW_TRIANGLE or dlam == 0.0:
            continue
        row_lambda[i] += dlam
        for v in range(3):
            vi = tri_vertices[row_tri[i], v]
            tissue_q[vi] -= tissue_inv_mass[vi] * contact_bary[j, v] * dlam * contact_normal[j]


def _tip_crossing(
    model: CouplingModel, state: CouplingState, tissue_q: np.ndarray, strand_q: np.ndarray
) -> tuple[int, np.ndarray]:
    """(triangle, barycentrics) where the strand nearest the tip crosses the surface, searched over the first
    four strand segments; the tip's closest surface point when none crosses."""
    k = min(4, strand_q.shape[0] - 1)
    hits = segment_crossings(strand_q[:k], strand_q[1 : k + 1], model.surface, tissue_q)
    if hits.crossing_tri.size:
        return int(hits.crossing_tri[0]), hits.crossing_bary[0].copy()
    return int(state.strand_tri[0]), state.strand_bary[0].copy()
