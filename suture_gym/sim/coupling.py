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
3. Puncture: while no path is open, the tip is held out of the tissue by its *anchor*: the surface point it
   first comes within ``eps + contact_margin`` of (triangle + barycentric coordinates, a material point),
   kept while the tip stays within that band of it along the normal. The anchor row is paper eq. 2 against
   that point plus Coulomb friction (``tip_friction``): a sharp tip digs into the surface it touches and
   does not slide into the crease between two faces of the dent it makes (a node held against the
   closest face alone alternates between the faces of a crease and sinks through). A tip that slides (its
   friction at the Coulomb bound) lets go of the anchor and is anchored again where it is. When the force
   the tip region exerted on the tissue (the anchor row, and the contact rows of the needle nodes within
   ``tip_length`` of the point) against the tip's direction of travel in the previous substep reaches
   ``puncture_force``, the tip punctures: a new path opens whose first node and entry access point are the
   anchor; once the tip is through, both move to where the strand crosses the surface. Rigid faces (all
   three vertices pinned: the base, clamps) are never punctured.
4. Path growth (paper section 4.3): while the path is open and the tip moves on, with ``d`` the distance from
   the tip to the last path node: no node if ``d < l``, ``floor(d / h)`` evenly spaced nodes (the last at the
   tip) if ``d > h``, one at the tip otherwise. Path nodes are tet index + barycentric coordinates located
   in the deformed mesh, so they move with the tissue.
5. Exit: once the tip has been inside and is outside again, the point where the strand crosses the surface
   becomes the exit access point and the path's last node; the path closes. No exit through a rigid face;
   a needle whose front left the tissue without crossing its surface loses the open path.
6. Stopper knot (optional, :meth:`CouplingModel.build`'s ``knot_tail``): the thread carries a knot at strand
   coordinate ``knot_sigma``, too big to enter a hole. The oldest path's entry coordinate is bounded by it, so
   once the knot reaches that entry the entry's node-access row holds the knot's strand piece at the access
   point (to within half a strand segment): the thread no longer slides in there, and pulling it loads the
   tissue at the entry (two-way, within ``tear_force``) as a tied first stitch does.
7. Release: an open path whose tip backed out (``sigma_entry <= 0`` and the tip more than ``l`` away from
   the entry) and a closed path with no strand left inside (``sigma_exit >= sigma_entry``, e.g. the thread's
   free end pulled through) are removed.
8. Constraint rows: HEAD inside an open path: none (it cuts). IN nodes: node-path (eq. 1) onto the matched
   path's polyline (nodes of an open path ahead of its last path node: none, the tip region cuts freely).
   Other nodes within ``eps + contact_margin`` of the surface (the tip too while no path is open, by its
   anchor): a contact row (eq. 2), except the nodes of a strand piece through an access point. Needle nodes
   inside a path with no row (the cutting front) within the band of a rigid face: a wall row, eq. 2 from
   the inside, so a needle driven through the tissue stops at the base. Rigid supports: a strand node whose
   motion this substep crosses a rigid face gets a row with that face keeping it on its side, whatever row it
   had. Every access point with the strand through it: node-access (eq. 3) on the strand piece of one
   segment's length centred on ``sigma_entry`` / ``sigma_exit`` (so the access point never sits at a piece's
   end, where eq. 3's gradient would drag the tissue along with the strand).
9. Contact frames: every contact row holds its node against a fixed surface point (the closest point, the
   anchor or the crossing) along a normal fixed for the substep, the smooth (vertex-normal blend) normal
   there (:func:`surface_normal`; the face normal of a rigid face): eq. 2 linearised at detection
   (:func:`node_surface_constraint`). Face normals flip between neighbouring faces as a node moves across
   an edge or the tissue folds, which made the heavy needle knock light surface nodes back and forth.
   The solver then bounds how far each row may push its node out this substep (:func:`contact_floors`).

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
* Suture contact rows are one-sided contact rows inside the rod's direct solve, made two-way with the
  tissue: :func:`suture_contact_rows` gives each row the triangle's share of its inverse mass, which
  :func:`~suture_gym.sim.rod.rod_iteration_kernel` adds to the row, and :func:`apply_contact_reaction` moves
  the tissue by its share.
* Node-access rows are Gauss-Seidel on the strand piece centred on the access point (:func:`project_access_rows`).
* Contact rows of a node that started the substep inside the resistance layer push it out by at most
  ``depenetration_speed * dt`` (:func:`contact_floors`): an old penetration is resolved over several
  substeps instead of launching the node.
* The rows that hold a strand in the tissue (node-path and node-access) transmit at most ``tear_force``
  each: beyond it the tissue gives way and the strand cuts through it (the damage flag is set). Without
  this bound a needle wrenched sideways drags and crushes the tissue along its path until it inverts.

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
from suture_gym.sim.checks import is_real
from suture_gym.sim.collision import (
    TriangleSurface,
    build_triangle_surface,
    locate_points,
    segment_crossings,
    signed_distance,
)
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.sim.rigid import (
    body_point,
    body_points_world,
    point_inv_mass_matrix,
    rigid_apply,
    rigid_generalized_inv_mass,
    world_inv_inertia,
)

#: Node states of paper section 4.1.
NODE_HEAD = 0
NODE_IN = 1
NODE_OUT = 2

#: Constraint row kinds of a strand node.
ROW_NONE = 0
ROW_TRIANGLE = 1
ROW_PATH = 2
ROW_ANCHOR = 3
ROW_WALL = 4

#: Tissue vertices a node-path row touches: the two tets of the path nodes either side of the projection.
PATH_ROW_VERTICES = 8

#: Below this length (m) a direction is undefined and the constraint is skipped (degenerate geometry).
_TINY_LENGTH = 1.0e-12



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
        tear_force: N, the largest force one node-path or node-access row transmits: beyond it the tissue gives
            way and the strand cuts through (tear-through forces of sutures are 3-4 N). A coupling force
            reaching it sets the sticky damage flag.
        tip_friction: Coulomb friction coefficient of the tip on the surface before puncture (>= 0): the sharp
            tip engages the surface point it first touches (the *anchor*) and slides only while the tangential
            force exceeds ``tip_friction`` times the normal force.
        depenetration_speed: m/s; a strand node that starts a substep inside a contact's resistance layer is
            moved out by at most ``depenetration_speed * dt`` per substep instead of all at once (a contact
            the prediction violates from outside is still resolved fully).
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
    tip_friction: float = 1.0
    depenetration_speed: float = 0.1
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
            "depenetration_speed",
            "contact_margin",
            "track_window",
            "broad_phase_margin",
        ):
            value = getattr(self, name)
            if not (is_real(value) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"CouplingParams.{name} must be a finite number > 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in ("needle_axial_friction", "tip_friction"):
            value = getattr(self, name)
            if not (is_real(value) and math.isfinite(value) and value >= 0.0):
                raise ValueError(f"CouplingParams.{name} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))
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
        tri_rigid: ``(F,) bool`` boundary triangles whose three vertices are pinned: faces glued to a rigid
            support (the base under the tissue, a clamp), which the strand can neither pierce nor leave through.
        surface: :class:`~suture_gym.sim.collision.TriangleSurface` of the tissue boundary.
        tet_bvh: :class:`~suture_gym.sim.bvh.BVH` over the tissue tets (path-node location).
        knot_sigma: strand coordinate of the thread's stopper knot, m (``inf`` without one; module
            docstring, detection step 6).
    """

    params: CouplingParams
    needle_node_count: int
    suture_node_count: int
    strand_sigma: np.ndarray
    strand_seg_length: np.ndarray
    strand_friction: np.ndarray
    tri_tet_local: np.ndarray
    tri_rigid: np.ndarray
    surface: TriangleSurface
    tet_bvh: BVH
    knot_sigma: float = math.inf

    @property
    def strand_node_count(self) -> int:
        """``M = Nn + max(Ns - 1, 0)``."""
        return int(self.strand_sigma.shape[0])

    @property
    def strand_length(self) -> float:
        """Rest length of the strand, m."""
        return float(self.strand_sigma[-1])

    @classmethod
    def build(
        cls, tissue, needle, suture=None, params: CouplingParams | None = None, knot_tail: float = 0.0
    ) -> CouplingModel:
        """Coupling data for ``tissue`` (:class:`~suture_gym.sim.model.TissueModel`), ``needle``
        (:class:`~suture_gym.sim.needle.NeedleModel`) and optional ``suture``
        (:class:`~suture_gym.sim.rod.RodModel`). ``knot_tail`` (m, ``0 <= knot_tail <`` the suture's length):
        a stopper knot this far from the suture's free end (0: no knot)."""
        params = CouplingParams() if params is None else params
        if not isinstance(params, CouplingParams):
            raise ValueError(f"params must be CouplingParams, got {type(params).__name__}")
        if not (is_real(knot_tail) and math.isfinite(knot_tail) and knot_tail >= 0.0):
            raise ValueError(f"knot_tail must be a finite number >= 0 m, got {knot_tail!r}")
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
        knot_sigma = math.inf
        if knot_tail > 0.0:
            suture_length = float(seg_length[nn - 1 :].sum())
            if not knot_tail < suture_length:
                raise ValueError(f"knot_tail ({knot_tail} m) must be shorter than the suture ({suture_length:.4g} m)")
            knot_sigma = float(sigma[-1] - knot_tail)
        rigid = np.all(tissue.particle_inv_mass[tri] == 0.0, axis=1)
        for array in (sigma, seg_length, friction, local, rigid):
            array.flags.writeable = False
        return cls(
            params=params,
            needle_node_count=nn,
            suture_node_count=ns,
            strand_sigma=sigma,
            strand_seg_length=seg_length,
            strand_friction=friction,
            tri_tet_local=local,
            tri_rigid=rigid,
            surface=build_triangle_surface(tri, rest),
            tet_bvh=build_bvh(tets, rest),
            knot_sigma=knot_sigma,
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
        tip_anchor_tri: surface triangle of the tip's anchor (the surface point the tip engages before puncture,
            :class:`CouplingParams` ``tip_friction``), -1 for none.
        tip_anchor_bary: ``(3,) float64`` barycentric coordinates of the anchor in that triangle.
        tip_force: force the tip region's contact rows exerted against the tip's direction of travel in the last
            substep, N (the puncture test, :func:`coupling_finish`).
        friction_force: total axial friction force on the needle in the last substep, N.
        max_force: largest single coupling-constraint force the tissue bore in the last substep, N (contacts with
            rigid faces excluded).
        punctures: number of punctures so far.
        damaged: set once any coupling force reached ``tear_force`` (sticky).
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
    tip_anchor_bary: np.ndarray
    tip_anchor_tri: int = -1
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
            tip_anchor_bary=np.zeros(3),
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
        strand_q: ``(M, 3)`` strand node positions at detection, m; strand_q_start: ``(M, 3)`` at the start of
            the substep (filled by the solver).
        pathnode_q: ``(P, 3)`` path node positions at detection, m. pathnode_tangent: ``(P, 3)`` unit tangents.
        row_kind: ``(M,) int8`` ROW_NONE / ROW_TRIANGLE (contact) / ROW_PATH / ROW_ANCHOR (the tip's contact
            with friction) / ROW_WALL (contact from the inside of a rigid face). row_tri: ``(M,) int32`` triangle.
        row_tissue: ``(M, 8) int32`` tissue vertices of a path row; row_weight: ``(M, 8)`` their weights.
        row_tangent: ``(M, 3)`` path tangent of a path row.
        row_lambda: ``(M,)`` multiplier (kg m) of each row this substep; row_friction_lambda: ``(M,)`` axial
            friction multiplier.
        row_bary: ``(M, 3)`` barycentric coordinates, in the row's triangle, of the surface point a contact row
            holds its node against, and row_contact_normal: ``(M, 3)`` the unit contact normal (the smooth
            surface normal there, :func:`surface_normal`; inward for wall rows), both fixed at detection
            (:func:`contact_frames`).
        row_floor: ``(M,)`` lower bound (m, <= 0) of ``C`` for each contact row this substep: how far inside the
            resistance layer the node may still be at the end of the substep (:func:`contact_floors`).
        tip_friction: ``(4,)`` the anchor row's accumulated tangential (friction) impulse on the tip, kg m, and the
            tangential offset its projection left, m (> 0 when the tip slides).
        access_count: rows in use. access_node: ``(2K, 4) int32`` strand nodes of the two ends of the strand
            piece through the access point (ends ``a = w0 x0 + w1 x1``, ``b = w2 x2 + w3 x3``) and
            access_weight: ``(2K, 4)`` those weights; access_rest: ``(2K,)`` rest length of the piece, m;
            access_tri: ``(2K,) int32``; access_bary: ``(2K, 3)``; access_lambda: ``(2K,)``.
        suture_inv_mass: ``(Ns,)`` inverse masses of the suture nodes used by the projections this substep,
            1/kg (:func:`embedded_inv_mass`).
        suture_contact_w: ``(Ns,)`` generalised inverse mass (1/kg) of the tissue point of each suture node's
            contact row in the rod's solve.
    """

    def __init__(self, model: CouplingModel):
        m = model.strand_node_count
        k = model.params.max_paths
        p = model.params.max_path_nodes
        self.strand_q = np.zeros((m, 3))
        self.strand_q_start = np.zeros((m, 3))
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
        self.row_floor = np.zeros(m)
        self.row_bary = np.zeros((m, 3))
        self.tip_friction = np.zeros(4)
        self.access_count = 0
        self.access_node = np.zeros((2 * k, 4), np.int32)
        self.access_weight = np.zeros((2 * k, 4))
        self.access_rest = np.zeros(2 * k)
        self.access_tri = np.zeros(2 * k, np.int32)
        self.access_bary = np.zeros((2 * k, 3))
        self.access_lambda = np.zeros(2 * k)
        self.suture_inv_mass = np.zeros(model.suture_node_count)
        self.suture_contact_w = np.zeros(model.suture_node_count)


# ----------------------------------------------------------------------------------------------------------
# Detection kernels
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def strand_positions_kernel(needle_pos, needle_quat, needle_node_body, suture_q, out):
    """Strand node positions: needle nodes from the pose, then suture nodes 1.. . Writes ``out`` (M, 3), m."""
    nn = needle_node_body.shape[0]
    body_points_world(needle_pos, needle_quat, needle_node_body, out[:nn])
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


@njit(cache=True)
def _vertex_normal(v, tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q):
    """Area-weighted normal (3,) of surface vertex ``v`` (sum of the cross products of its triangles, not unit)."""
    n = np.zeros(3)
    for s in range(vertex_tri_start[v], vertex_tri_start[v + 1]):
        t = vertex_tri_index[s]
        a = tissue_q[tri_vertices[t, 0]]
        n += np.cross(tissue_q[tri_vertices[t, 1]] - a, tissue_q[tri_vertices[t, 2]] - a)
    return n


@njit(cache=True)
def surface_normal(tri, bary, tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q):
    """Smooth unit surface normal (3,) at the surface point (``tri``, ``bary`` (3,)): the barycentric blend of
    the unit area-weighted normals of the triangle's vertices (Phong normal). It turns continuously as the
    point moves across edges, so a node in a crease or at the bottom of a dent is pushed out along the
    crease's bisector instead of alternately through one face and the other, as face normals would do.
    Falls back to the triangle's own normal where the blend vanishes; zeros for a degenerate neighbourhood."""
    n = np.zeros(3)
    for k in range(3):
        nv = _vertex_normal(tri_vertices[tri, k], tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q)
        length = math.sqrt(nv @ nv)
        if length > 0.0:
            n += bary[k] * nv / length
    length = math.sqrt(n @ n)
    if length <= 1.0e-6:
        a = tissue_q[tri_vertices[tri, 0]]
        n = np.cross(tissue_q[tri_vertices[tri, 1]] - a, tissue_q[tri_vertices[tri, 2]] - a)
        length = math.sqrt(n @ n)
        if length <= 0.0:
            return np.zeros(3)
    return n / length


@njit(cache=True)
def node_surface_constraint(q, p1, p2, p3, bary, normal, eps):
    """Contact row of a strand node against a surface point: ``C = (q - p) . n - eps`` with the material point
    ``p = sum_k b_k p_k`` of a surface triangle and the unit normal ``n`` held fixed over the substep.

    Paper eq. 2 (Yu et al. 2020) linearised at detection: the node must stay ``eps`` outside the surface at
    the point it touches; fixing ``p`` in the material and ``n`` to the smooth normal there
    (:func:`surface_normal`) keeps the row's direction from flipping between faces as the surface deforms
    within the substep. Inequality ``C >= 0``.

    Args:
        q: (3,) strand node, m. p1, p2, p3: (3,) triangle vertices, m. bary: (3,) weights ``b``.
        normal: (3,) unit ``n``. eps: layer thickness, m.

    Returns:
        ``C`` in m; ``grad_q C = n`` and ``grad_pk C = -b_k n``.
    """
    p = bary[0] * p1 + bary[1] * p2 + bary[2] * p3
    return (q - p) @ normal - eps


@njit(cache=True)
def contact_frames(
    row_kind, row_tri, row_bary, tri_rigid, tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q, row_normal
):
    """Unit contact normal of every contact row at detection, at its surface point (``row_tri``, ``row_bary``):
    the face normal of a rigid triangle (``tri_rigid``), the smooth normal (:func:`surface_normal`) of a
    deforming one; turned inward for ROW_WALL. A row whose normal is undefined (a collapsed neighbourhood)
    is dropped (ROW_NONE). Writes ``row_normal`` (M, 3); updates ``row_kind``."""
    for i in range(row_kind.shape[0]):
        kind = row_kind[i]
        if kind != ROW_TRIANGLE and kind != ROW_WALL and kind != ROW_ANCHOR:
            continue
        tri = row_tri[i]
        if tri_rigid[tri]:
            a = tissue_q[tri_vertices[tri, 0]]
            n = np.cross(tissue_q[tri_vertices[tri, 1]] - a, tissue_q[tri_vertices[tri, 2]] - a)
            length = math.sqrt(n @ n)
            if length > 0.0:
                n /= length
        else:
            n = surface_normal(tri, row_bary[i], tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q)
        if not (n[0] != 0.0 or n[1] != 0.0 or n[2] != 0.0):
            row_kind[i] = ROW_NONE
            continue
        row_normal[i] = -n if kind == ROW_WALL else n


@njit(cache=True)
def contact_floors(
    needle_node_count,
    eps,
    depenetration,
    row_kind,
    row_tri,
    row_bary,
    row_normal,
    tri_vertices,
    needle_pos_prev,
    needle_quat_prev,
    needle_node_body,
    suture_q_prev,
    tissue_q_prev,
    out_floor,
):
    """Lower bound of each contact row's ``C`` this substep, from where the node was at the start of it:
    ``floor = min(0, C_0 + depenetration)`` with ``C_0`` the row's constraint (:func:`node_surface_constraint`,
    same frame) at the start-of-substep positions and ``depenetration`` (m) the most a node may be moved out
    per substep.

    A node that starts outside the resistance layer (``C_0 >= 0``) gets ``floor = 0``: the row removes the
    whole penetration the prediction caused, as a rigid contact must. A node that starts inside by ``-C_0``
    (the tissue folded over it, a path was released around it, a detection found it late) is moved out by at
    most ``depenetration`` per substep, so resolving an old penetration never launches the node or the tissue
    (the "maximum depenetration velocity" of game physics engines). Rows of other kinds get 0. Writes
    ``out_floor`` (M,) in m.
    """
    nn = needle_node_count
    r = quat_to_matrix(needle_quat_prev)
    for i in range(row_kind.shape[0]):
        out_floor[i] = 0.0
        kind = row_kind[i]
        if kind != ROW_TRIANGLE and kind != ROW_ANCHOR and kind != ROW_WALL:
            continue
        if i < nn:
            q0 = needle_pos_prev + r @ needle_node_body[i]
        else:
            q0 = suture_q_prev[i - nn + 1]
        tri = row_tri[i]
        c0 = node_surface_constraint(
            q0,
            tissue_q_prev[tri_vertices[tri, 0]],
            tissue_q_prev[tri_vertices[tri, 1]],
            tissue_q_prev[tri_vertices[tri, 2]],
            row_bary[i],
            row_normal[i],
            eps,
        )
        out_floor[i] = min(0.0, c0 + depenetration)


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
def _project_contact(
    needle_inv_mass,
    needle_inv_inertia_body,
    node_body,
    tri,
    bary,
    normal,
    tri_vertices,
    tissue_inv_mass,
    eps,
    floor,
    lam,
    needle_pos,
    needle_quat,
    tissue_q,
):
    """A needle node's contact row (:func:`node_surface_constraint`, ``C >= floor``), rigid and two-way;
    returns the updated multiplier (``lam`` in, kept ``>= 0``).

    ``dlambda = -C / (w_needle + sum_k b_k^2 w_k)`` with ``w_needle`` the needle's generalised inverse mass at
    the node (body point ``node_body`` (3,)) along ``n``: the needle takes the impulse ``dlambda n`` at the
    node, vertex ``k`` of the triangle moves by ``-w_k b_k dlambda n``. Updates the needle pose and ``tissue_q``.
    """
    i0 = tri_vertices[tri, 0]
    i1 = tri_vertices[tri, 1]
    i2 = tri_vertices[tri, 2]
    q = body_point(needle_pos, needle_quat, node_body)
    c = node_surface_constraint(q, tissue_q[i0], tissue_q[i1], tissue_q[i2], bary, normal, eps) - floor
    if c >= 0.0 and lam == 0.0:
        return lam
    inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
    ang = np.cross(q - needle_pos, normal)
    w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, normal, ang)
    w += bary[0] ** 2 * tissue_inv_mass[i0] + bary[1] ** 2 * tissue_inv_mass[i1] + bary[2] ** 2 * tissue_inv_mass[i2]
    dlam = xpbd_delta_lambda(c, w, 0.0, lam)
    if lam + dlam < 0.0:
        dlam = -lam
    rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, normal, ang, dlam)
    for k in range(3):
        vi = tri_vertices[tri, k]
        tissue_q[vi] -= tissue_inv_mass[vi] * bary[k] * dlam * normal
    return lam + dlam


@njit(cache=True)
def _project_anchor(
    needle_inv_mass,
    needle_inv_inertia_body,
    node_body,
    tri,
    bary,
    normal,
    tri_vertices,
    tissue_inv_mass,
    eps,
    floor,
    friction,
    lam,
    friction_out,
    needle_pos,
    needle_quat,
    tissue_q,
):
    """The tip's anchor row: the tip held ``eps`` above its anchor ``p = sum_k b_k x_k`` (eq. 2 with the
    contact point fixed in the material, ``C_n = (q - p) . n - eps >= floor``) and over it across the normal,
    within a Coulomb cone; returns the updated normal multiplier (``lam`` in, kept ``>= 0``).

    The tip is a point of a rigid body whose generalised inverse mass is a full 3 x 3 matrix
    (``K = I/m - [r]x I^-1 [r]x``, :func:`~suture_gym.sim.needle.point_inv_mass_matrix`, plus the anchor's
    ``sum_k b_k^2 w_k``): an impulse across the normal also moves the tip along it and sideways, so the
    normal and friction rows are solved together as one point constraint: the impulse ``P = K^-1 (t - q)``
    that puts the tip on its target ``t = p + (eps + floor) n``. If the accumulated tangential impulse
    (``friction_out[:3]``, kg m) would leave the cone ``|P_t| <= friction * P_n``, it is scaled back onto it
    and the normal part re-solved with it fixed, so the tip slides; ``friction_out[3]`` gets the tangential
    offset left, m (0 while the tip sticks). The needle takes ``P`` at the tip, vertex ``k`` moves by
    ``-w_k b_k P``. Updates the needle pose, ``tissue_q`` and ``friction_out`` (4,).
    """
    i0 = tri_vertices[tri, 0]
    i1 = tri_vertices[tri, 1]
    i2 = tri_vertices[tri, 2]
    w_tissue = (
        bary[0] ** 2 * tissue_inv_mass[i0] + bary[1] ** 2 * tissue_inv_mass[i1] + bary[2] ** 2 * tissue_inv_mass[i2]
    )
    q = body_point(needle_pos, needle_quat, node_body)
    p = bary[0] * tissue_q[i0] + bary[1] * tissue_q[i1] + bary[2] * tissue_q[i2]
    d = p + (eps + floor) * normal - q
    friction_out[3] = 0.0
    if d @ normal <= 0.0 and lam == 0.0:  # clear of the surface: no load, the tip slides freely
        offset = d - (d @ normal) * normal
        friction_out[3] = math.sqrt(offset @ offset)
        return lam
    inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
    r = q - needle_pos
    k = point_inv_mass_matrix(needle_inv_mass, inv_inertia, r)
    for a in range(3):
        k[a, a] += w_tissue
    impulse = np.linalg.solve(k, d)
    p_n = impulse @ normal
    if lam + p_n < 0.0:  # the tissue would have to pull the tip: the contact lets go
        p_n = -lam
        impulse = p_n * normal - (friction_out[:3])
    else:
        tangential = friction_out[:3] + impulse - p_n * normal
        size = math.sqrt(tangential @ tangential)
        cap = friction * (lam + p_n)
        if size > cap:
            tangential *= cap / size
            push_t = tangential - friction_out[:3]
            kn = k @ normal
            p_n = (d @ normal - (k @ push_t) @ normal) / (normal @ kn)
            if lam + p_n < 0.0:
                p_n = -lam
            impulse = p_n * normal + push_t
            moved = k @ impulse - d
            offset = moved - (moved @ normal) * normal
            friction_out[3] = max(math.sqrt(offset @ offset), _TINY_LENGTH)
    friction_out[:3] += impulse - (impulse @ normal) * normal
    rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, impulse, np.cross(r, impulse), 1.0)
    for a in range(3):
        vi = tri_vertices[tri, a]
        tissue_q[vi] -= tissue_inv_mass[vi] * bary[a] * impulse
    return lam + (impulse @ normal)


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
    tip_friction,
    tear_force,
    row_kind,
    row_tri,
    row_bary,
    row_contact_normal,
    row_floor,
    row_tissue,
    row_weight,
    row_tangent,
    row_lambda,
    row_friction_lambda,
    tip_friction_out,
    needle_pos,
    needle_quat,
    tissue_q,
):
    """One Gauss-Seidel pass over the rows of the needle nodes (strand nodes ``0 .. Nn-1``).

    Contact rows (ROW_TRIANGLE, ROW_WALL, ROW_ANCHOR: :func:`node_surface_constraint` in the row's frame,
    ``C >= row_floor``, multiplier kept ``>= 0``) and node-path rows (eq. 1) are rigid (zero compliance) and
    two-way (:func:`_project_contact`): ``dlambda = -C / (w_needle + sum_k b_k^2 w_k)`` with ``w_needle`` the
    needle's generalised inverse mass at the node along the gradient; the needle takes the impulse
    ``dlambda n`` at the node, tissue vertex ``k`` moves by ``-w_k b_k dlambda n``. The tip's anchor row adds
    Coulomb friction with coefficient ``tip_friction`` (:func:`_project_anchor`; its tangential impulse and
    slip in ``tip_friction_out`` (4,)). A node-path multiplier is kept within ``tear_force dt^2`` in magnitude (the
    tissue gives way beyond it). After each path row, kinetic axial friction: the relative displacement of
    node and path point along the tangent since the start of the substep is removed up to a multiplier of
    ``strand_friction[i] dt^2`` in magnitude (static below the cap, sliding at the cap). Updates the needle
    pose, ``tissue_q`` and the multipliers.
    """
    for i in range(needle_node_count):
        kind = row_kind[i]
        if kind == ROW_NONE:
            continue
        if kind == ROW_ANCHOR:
            row_lambda[i] = _project_anchor(
                needle_inv_mass, needle_inv_inertia_body, needle_node_body[i], row_tri[i], row_bary[i],
                row_contact_normal[i], tri_vertices, tissue_inv_mass, eps, row_floor[i], tip_friction,
                row_lambda[i], tip_friction_out, needle_pos, needle_quat, tissue_q,
            )  # fmt: skip
            continue
        if kind != ROW_PATH:
            row_lambda[i] = _project_contact(
                needle_inv_mass, needle_inv_inertia_body, needle_node_body[i], row_tri[i], row_bary[i],
                row_contact_normal[i], tri_vertices, tissue_inv_mass, eps, row_floor[i], row_lambda[i],
                needle_pos, needle_quat, tissue_q,
            )  # fmt: skip
            continue
        inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
        q = body_point(needle_pos, needle_quat, needle_node_body[i])
        r = q - needle_pos
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
            dlam = max(row_lambda[i] + dlam, -tear_force * dt * dt) - row_lambda[i]
            row_lambda[i] += dlam
            rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, n, np.cross(r, n), dlam)
            for a in range(idx.shape[0]):
                tissue_q[idx[a]] -= tissue_inv_mass[idx[a]] * wt[a] * dlam * n
        cap = strand_friction[i] * dt * dt
        if cap <= 0.0:
            continue
        inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
        q = body_point(needle_pos, needle_quat, needle_node_body[i])
        r = q - needle_pos
        q0 = body_point(needle_pos_prev, needle_quat_prev, needle_node_body[i])
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
        return body_point(needle_pos, needle_quat, needle_node_body[node])
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
    force_cap,
    access_lambda,
    needle_pos,
    needle_quat,
    suture_q,
    tissue_q,
):
    """One Gauss-Seidel pass over the node-access rows (eq. 3, inequality ``C <= 0``), two-way, each
    multiplier kept within ``force_cap`` (kg m, the tear force times ``dt^2``) in magnitude.

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
        inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
        if lin @ lin + ang @ ang > 0.0:
            w += rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, lin, ang)
        dlam = xpbd_delta_lambda(c, w, 0.0, access_lambda[a])
        dlam = max(access_lambda[a] + dlam, -force_cap) - access_lambda[a]
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


def _rigid_crossings(model: CouplingModel, work: CouplingWork, tissue_q, strand_q_start, strand_q) -> None:
    """Rigid supports (module docstring, detection step 7): a strand node whose motion this substep,
    ``strand_q_start -> strand_q``, crosses a rigid face gets a contact row with that face at the crossing
    point that keeps it on the side it came from (outside: ROW_TRIANGLE, inside: ROW_WALL), whatever row it
    had; so neither a needle dragging the tissue down nor a tip cutting through it passes the base."""
    hits = segment_crossings(strand_q_start, strand_q, model.surface, tissue_q)
    done = np.zeros(strand_q.shape[0], dtype=bool)
    for h in np.flatnonzero(model.tri_rigid[hits.crossing_tri]):
        i = hits.crossing_segment[h]
        if done[i]:
            continue
        done[i] = True
        work.row_kind[i] = ROW_TRIANGLE if hits.crossing_direction[h] < 0 else ROW_WALL
        work.row_tri[i] = hits.crossing_tri[h]
        work.row_bary[i] = hits.crossing_bary[h]


def coupling_detect(
    model: CouplingModel,
    state: CouplingState,
    work: CouplingWork,
    tissue,
    tissue_q: np.ndarray,
    strand_q: np.ndarray,
    strand_q_start: np.ndarray | None = None,
) -> None:
    """Detection phase (module docstring, steps 1-7) for strand positions ``strand_q`` (M, 3) m against the
    tissue (:class:`~suture_gym.sim.model.TissueModel` ``tissue``, positions ``tissue_q`` (N, 3) m).
    ``strand_q_start`` (M, 3) m, the positions at the start of the substep, enables the rigid-support rows
    (:func:`_rigid_crossings`).

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
        upper = state.path_sigma_exit[k - 1] if k > 0 else min(total, model.knot_sigma)
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
    _update_tip_anchor(model, state, tissue_q, tip)
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
    nn = model.needle_node_count
    tri = state.strand_tri[:nn]
    band = params.resistance_eps + params.contact_margin
    wall = (
        (work.row_kind[:nn] == ROW_NONE)
        & (state.strand_path[:nn] >= 0)
        & (tri >= 0)
        & (state.strand_sdist[:nn] > -band)
    )
    wall[wall] = model.tri_rigid[tri[wall]]
    work.row_kind[:nn][wall] = ROW_WALL
    work.row_tri[:nn][wall] = tri[wall]
    if state.tip_anchor_tri >= 0 and work.row_kind[0] != ROW_PATH:
        in_access = np.any((work.access_node[: work.access_count] == 0) & (work.access_weight[: work.access_count] > 0))
        if not in_access:
            work.row_kind[0] = ROW_ANCHOR
            work.row_tri[0] = state.tip_anchor_tri
    work.row_bary[:] = state.strand_bary
    if work.row_kind[0] == ROW_ANCHOR:
        work.row_bary[0] = state.tip_anchor_bary
    if strand_q_start is not None and model.tri_rigid.any():
        _rigid_crossings(model, work, tissue_q, strand_q_start, strand_q)
    contact_frames(
        work.row_kind, work.row_tri, work.row_bary, model.tri_rigid, model.surface.tri_vertices,
        model.surface.vertex_tri_start, model.surface.vertex_tri_index, tissue_q, work.row_contact_normal,
    )  # fmt: skip
    work.row_lambda[:] = 0.0
    work.row_friction_lambda[:] = 0.0
    work.access_lambda[:] = 0.0
    work.tip_friction[:] = 0.0


def _update_tip_anchor(model: CouplingModel, state: CouplingState, tissue_q, tip) -> None:
    """Keep, release or set the tip's anchor (module docstring, detection step 3) for the tip at ``tip`` (3,)
    m: while no path is open, the tip engages the surface point it first comes within the contact band of and
    keeps it until it moves off the surface (its gap along the anchor normal exceeds the band) or slides
    (:func:`coupling_finish`)."""
    params = model.params
    band = params.resistance_eps + params.contact_margin
    surface = model.surface
    if state.punctured:
        state.tip_anchor_tri = -1
    if state.tip_anchor_tri >= 0:
        n = surface_normal(
            state.tip_anchor_tri, state.tip_anchor_bary, surface.tri_vertices, surface.vertex_tri_start,
            surface.vertex_tri_index, tissue_q,
        )  # fmt: skip
        p = access_point(model, tissue_q, state.tip_anchor_tri, state.tip_anchor_bary)
        if not n.any() or float((tip - p) @ n) > band:
            state.tip_anchor_tri = -1
    if state.tip_anchor_tri < 0 and not state.punctured and state.strand_tri[0] >= 0 and state.strand_sdist[0] < band:
        state.tip_anchor_tri = int(state.strand_tri[0])
        state.tip_anchor_bary[:] = state.strand_bary[0]


def _tip_events(model, state, work, tissue, tissue_q, tip) -> None:
    """Puncture, path growth and exit of the tip (module docstring, steps 3-5)."""
    params = model.params
    n = state.path_count
    open_k = n - 1 if n > 0 and state.path_open[n - 1] else -1
    tip_sdist = state.strand_sdist[0]
    if open_k < 0:
        if state.tip_anchor_tri >= 0:
            tri, bary = int(state.tip_anchor_tri), state.tip_anchor_bary.copy()
        else:
            tri, bary = int(state.strand_tri[0]), state.strand_bary[0].copy()
        if state.tip_force >= params.puncture_force and tri >= 0 and not model.tri_rigid[tri]:
            if n >= params.max_paths or state.pathnode_count >= params.max_path_nodes:
                state.overflow = True
                return
            state.tip_anchor_tri = -1
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
    if state.path_entered[open_k] and tip_sdist > 0.0:
        tri, bary = _tip_crossing(model, state, tissue_q, work.strand_q)
        if tri < 0:  # the needle's front left the tissue without crossing its surface: the bite is lost
            _release_path(state, open_k)
            return
        if model.tri_rigid[tri]:
            return
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
    the tissue bore (rows against rigid faces, the base or a clamp, do not count) and the sticky damage flag
    (``max_force >= tear_force``); and the anchor's release when the tip slid.

    The tip force (N), the puncture test of the next substep, is the force the tissue's contact rows exert
    against the tip's direction of travel ``tip_direction`` (3,) (unit, world) on the needle nodes within
    ``tip_length`` of the point: ``sum_i lambda_i (n_i . -d) / dt^2`` over their node-triangle rows, plus the
    anchor row's normal and friction force along ``-d``, clipped at 0: the load that drives the cut. (In a
    dent the surface normals tilt, and the lateral part of the contact force is carried by the holder, not by
    the cutting edge.) A tip that slid this substep (its friction at the Coulomb bound) lets go of its anchor;
    the next detection anchors it where it is.
    """
    inv_dt2 = 1.0 / (dt * dt)
    nn = model.needle_node_count
    d = np.asarray(tip_direction, dtype=np.float64)
    kind = work.row_kind[:nn]
    tip = model.strand_sigma[:nn] <= model.params.tip_length
    touching = tip & (kind == ROW_TRIANGLE)
    axial = -(work.row_contact_normal[:nn][touching] @ d)
    load = float(work.row_lambda[:nn][touching] @ axial)
    anchored = kind[0] == ROW_ANCHOR
    if anchored:
        load -= work.row_lambda[0] * float(work.row_contact_normal[0] @ d) + float(work.tip_friction[:3] @ d)
        if work.tip_friction[3] > 0.0:
            state.tip_anchor_tri = -1
    state.tip_force = max(0.0, load * inv_dt2)
    state.friction_force = float(np.abs(work.row_friction_lambda).sum() * inv_dt2)
    on_support = (work.row_kind != ROW_NONE) & (work.row_kind != ROW_PATH) & model.tri_rigid[work.row_tri]
    largest = float(np.abs(np.where(on_support, 0.0, work.row_lambda)).max(initial=0.0))
    if anchored and not on_support[0]:
        largest = max(largest, math.hypot(work.row_lambda[0], float(np.linalg.norm(work.tip_friction[:3]))))
    if work.access_count:
        largest = max(largest, float(np.abs(work.access_lambda[: work.access_count]).max()))
    state.max_force = largest * inv_dt2
    if state.max_force >= (1.0 - 1.0e-9) * model.params.tear_force:  # a row held at its cap reads tear_force
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
    force_cap,
    row_lambda,
    suture_q,
    tissue_q,
):
    """One Gauss-Seidel pass over the suture nodes' node-path rows (eq. 1, ``C = |(p - q) x t|``), rigid and
    two-way between the node (its embedded inverse mass, :func:`embedded_inv_mass`) and the path point's tissue
    vertices, each multiplier kept within ``force_cap`` (kg m, the tear force times ``dt^2``) in magnitude.
    Updates ``suture_q``, ``tissue_q`` and ``row_lambda``."""
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
        dlam = max(row_lambda[i] + dlam, -force_cap) - row_lambda[i]
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
    row_bary,
    row_contact_normal,
    row_floor,
    tri_vertices,
    tissue_q,
    tissue_inv_mass,
    suture_q,
    out_gap,
    out_normal,
    out_tissue_w,
):
    """The suture nodes' contact rows (:func:`node_surface_constraint` in the row's frame) as the rod's
    one-sided contact rows: ``gap = C - floor`` (``row_floor``, :func:`contact_floors`) at the current
    positions, ``normal = n``, and the generalised inverse mass of the surface point ``sum_v b_v^2 w_v`` (1/kg)
    in ``out_tissue_w``. Nodes without a contact row (and node 0, on the swage) get ``gap = +inf``. Writes
    ``out_gap`` (Ns,), ``out_normal`` (Ns, 3), ``out_tissue_w`` (Ns,)."""
    nn = needle_node_count
    for j in range(suture_q.shape[0]):
        out_gap[j] = np.inf
        out_tissue_w[j] = 0.0
        if j == 0:
            continue
        i = nn + j - 1
        if row_kind[i] != ROW_TRIANGLE and row_kind[i] != ROW_WALL:
            continue
        tri = row_tri[i]
        b = row_bary[i]
        c = node_surface_constraint(
            suture_q[j],
            tissue_q[tri_vertices[tri, 0]],
            tissue_q[tri_vertices[tri, 1]],
            tissue_q[tri_vertices[tri, 2]],
            b,
            row_contact_normal[i],
            eps,
        )
        out_gap[j] = c - row_floor[i]
        out_normal[j] = row_contact_normal[i]
        for v in range(3):
            out_tissue_w[j] += b[v] * b[v] * tissue_inv_mass[tri_vertices[tri, v]]


@njit(cache=True)
def apply_contact_reaction(
    needle_node_count,
    row_kind,
    row_tri,
    row_bary,
    tri_vertices,
    contact_normal,
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
        if (row_kind[i] != ROW_TRIANGLE and row_kind[i] != ROW_WALL) or dlam == 0.0:
            continue
        row_lambda[i] += dlam
        for v in range(3):
            vi = tri_vertices[row_tri[i], v]
            tissue_q[vi] -= tissue_inv_mass[vi] * row_bary[i, v] * dlam * contact_normal[j]


def _tip_crossing(
    model: CouplingModel, state: CouplingState, tissue_q: np.ndarray, strand_q: np.ndarray
) -> tuple[int, np.ndarray]:
    """(triangle, barycentrics) where the strand nearest the tip crosses the surface, searched over the first
    four strand segments, then over the whole needle; the tip's closest surface point when none crosses
    (triangle -1 when the tip is beyond the broad phase)."""
    nn = model.needle_node_count
    for k in (min(4, strand_q.shape[0] - 1), nn - 1):
        hits = segment_crossings(strand_q[:k], strand_q[1 : k + 1], model.surface, tissue_q)
        if hits.crossing_tri.size:
            return int(hits.crossing_tri[0]), hits.crossing_bary[0].copy()
    return int(state.strand_tri[0]), state.strand_bary[0].copy()
