"""Static coupling data (:class:`CouplingModel`), its time-varying state (:class:`CouplingState`) and the
per-substep rows (:class:`CouplingWork`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields, replace

import numpy as np

from suture_gym.sim.bvh import BVH, build_bvh
from suture_gym.sim.checks import is_real
from suture_gym.sim.collision import (
    TriangleSurface,
    build_triangle_surface,
)
from suture_gym.sim.coupling.params import (
    NODE_HEAD,
    NODE_OUT,
    PATH_ROW_VERTICES,
    TIP_PATCH_CAPACITY,
    TIP_PATCH_CELLS,
    CouplingParams,
)


@dataclass(frozen=True)
class CouplingModel:
    """Static data of the interaction between one strand (needle + suture) and the tissue.

    Build it with :meth:`build`. The BVHs inside ``surface`` and ``tet_bvh`` hold the boxes of the rest shape and
    are read-only: the detection refits copies of them held by :class:`CouplingWork`, so a model never changes.

    Attributes:
        params: the :class:`CouplingParams`.
        needle_node_count: ``Nn``, needle nodes on the strand (strand nodes ``0 .. Nn-1``).
        suture_node_count: ``Ns``, suture rod nodes (0 for a needle alone); strand nodes ``Nn .. Nn+Ns-2``
            are suture nodes ``1 .. Ns-1``.
        strand_sigma: ``(M,) float64`` material coordinate of each strand node, m: rest arc length from the tip.
        strand_seg_length: ``(M-1,) float64`` rest length of each strand segment, m.
        strand_friction: ``(M,) float64`` kinetic axial friction cap of each strand node, N
            (``needle_axial_friction`` times the node's share of needle length; for suture nodes
            ``suture_axial_friction`` times the node's share of thread length).
        tri_tet_local: ``(F, 3) int8`` local index (0-3) in its tet of each vertex of each boundary triangle.
        tri_rigid: ``(F,) bool`` boundary triangles whose three vertices are pinned: faces glued to a rigid
            support (the base under the tissue, a clamp), which the strand can neither pierce nor leave through.
        tri_on_support: ``(F,) bool`` boundary triangles lying on one of the tissue's support planes at rest
            (the bottom of a pad or bar on its base): no suture node can come between them and the base, so
            they get no node-triangle rows; the base itself is the suture's obstacle
            (:func:`~suture_gym.sim.scenes.assemble`).
        surface: :class:`~suture_gym.sim.collision.TriangleSurface` of the tissue boundary (BVH at rest).
        tet_bvh: :class:`~suture_gym.sim.bvh.BVH` over the tissue tets at rest (path-node location).
        tissue_rest_q: ``(N, 3) float64`` the tissue's rest positions, m (the tissue model's array).
        surface_vertex: ``(Vs,) int32`` the tissue vertices on the boundary; surface_vertex_area: ``(Vs,)
            float64`` their lumped rest areas (a third of each boundary triangle's), m^2: the weights of a
            uniform pressure over the tip's contact patch (:func:`~suture_gym.sim.coupling.paths.tip_patch`).
        tip_patch_radius: m, the radius of the tip's contact patch, ``max(tip_contact_radius,
            TIP_PATCH_CELLS * mean boundary edge length)`` (0 with the tip-contact model off).
        tri_tip_compliance: ``(F,) float64`` the tip's series compliance on each boundary triangle, m/N
            (:func:`tip_series_compliance` with the material of the triangle's tet; zeros with the model off).
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
    tri_on_support: np.ndarray
    surface: TriangleSurface
    tet_bvh: BVH
    tissue_rest_q: np.ndarray
    surface_vertex: np.ndarray
    surface_vertex_area: np.ndarray
    tip_patch_radius: float
    tri_tip_compliance: np.ndarray
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
        if ns:
            thread = np.zeros(sigma.shape[0] - nn)  # strand nodes nn.. are suture nodes 1..
            thread += 0.5 * seg_length[nn - 1 :]
            thread[:-1] += 0.5 * seg_length[nn:]
            friction[nn:] = params.suture_axial_friction * thread
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
        extent = float(np.ptp(tissue.particle_rest_q, axis=0).max())
        plane_dist = np.abs(tissue.particle_rest_q[tri] @ tissue.support_normal.T - tissue.support_offset)  # (F,3,S)
        on_support = np.any(np.all(plane_dist <= 1.0e-9 * extent, axis=1), axis=1)
        surface = build_triangle_surface(tri, rest)
        tet_bvh = build_bvh(tets, rest)
        surface_vertex, inverse = np.unique(tri, return_inverse=True)
        tri_area = 0.5 * np.linalg.norm(
            np.cross(rest[tri[:, 1]] - rest[tri[:, 0]], rest[tri[:, 2]] - rest[tri[:, 0]]), axis=1
        )
        vertex_area = np.bincount(
            inverse.reshape(-1), weights=np.repeat(tri_area / 3.0, 3), minlength=surface_vertex.size
        )
        patch_radius = 0.0
        compliance = np.zeros(tri.shape[0])
        if params.tip_contact_radius > 0.0:
            edges = np.concatenate([rest[tri[:, 1]] - rest[tri[:, 0]], rest[tri[:, 2]] - rest[tri[:, 1]],
                                    rest[tri[:, 0]] - rest[tri[:, 2]]])  # fmt: skip
            patch_radius = max(params.tip_contact_radius, TIP_PATCH_CELLS * float(np.linalg.norm(edges, axis=1).mean()))
            mu = tissue.tet_mu[tissue.tri_tet]
            lame = tissue.tet_lambda[tissue.tri_tet] - mu
            nu = lame / (2.0 * (lame + mu))
            compliance = tip_series_compliance(params.tip_contact_radius, patch_radius, 2.0 * mu * (1.0 + nu), nu)
            deepest = float(compliance.max()) * params.puncture_force
            if deepest > params.tip_length:
                raise ValueError(
                    f"CouplingParams.tip_length ({params.tip_length} m) must cover the tip's local dent at the "
                    f"puncture force, {deepest:.4g} m (tip_contact_radius {params.tip_contact_radius} m, "
                    f"puncture_force {params.puncture_force} N): raise tip_length or tip_contact_radius"
                )
        surface_vertex = surface_vertex.astype(np.int32)
        for array in (sigma, seg_length, friction, local, rigid, on_support, surface_vertex, vertex_area, compliance):
            array.flags.writeable = False
        for bvh in (surface.bvh, tet_bvh):
            bvh.node_lo.flags.writeable = False
            bvh.node_hi.flags.writeable = False
        return cls(
            params=params,
            needle_node_count=nn,
            suture_node_count=ns,
            strand_sigma=sigma,
            strand_seg_length=seg_length,
            strand_friction=friction,
            tri_tet_local=local,
            tri_rigid=rigid,
            tri_on_support=on_support,
            surface=surface,
            tet_bvh=tet_bvh,
            tissue_rest_q=rest,
            surface_vertex=surface_vertex,
            surface_vertex_area=vertex_area,
            tip_patch_radius=patch_radius,
            tri_tip_compliance=compliance,
            knot_sigma=knot_sigma,
        )


def tip_series_compliance(contact_radius, patch_radius, youngs_modulus, poisson_ratio):
    """The tip's local compliance the mesh cannot resolve, m/N: a rigid flat punch of radius ``a =
    contact_radius`` (m) on an elastic half-space sinks by ``F (1 - nu^2) / (2 a E)`` (Boussinesq; Johnson,
    *Contact Mechanics*, 1985, sec. 3.8), while the same force spread as a uniform pressure over a disc of radius
    ``b = patch_radius`` (m), which the mesh does resolve, moves that disc by ``16 F (1 - nu^2) / (3 pi^2 E b)``
    on average (Johnson, sec. 3.2). The row that spreads the tip's force over the patch adds the difference in
    series, so tip + mesh = the punch: ``(1 - nu^2) / E * (1 / (2 a) - 16 / (3 pi^2 b))``, clipped at 0 (a
    punch wider than the patch). ``youngs_modulus`` Pa and ``poisson_ratio`` may be arrays (one per triangle)."""
    factor = (1.0 - np.asarray(poisson_ratio) ** 2) / np.asarray(youngs_modulus)
    return np.maximum(factor * (0.5 / contact_radius - 16.0 / (3.0 * math.pi**2 * patch_radius)), 0.0)


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
        tip_anchor_inside: the anchor is an *exit anchor*: the tip inside an open path pressing on the surface
            from the inside (``exit_puncture_force``), not the entry anchor from the outside.
        exit_pierced: the tip of the open path has passed the exit threshold and may leave the tissue.
        tip_patch_count: surface vertices of the tip's contact patch (0: the anchor is one point of its
            triangle); tip_patch_vertex: ``(C,) int32`` those vertices; tip_patch_weight: ``(C,) float64`` their
            weights (sum 1); tip_patch_offset: ``(3,) float64`` m, the anchor point minus the patch's weighted
            mean at anchoring (the row holds the tip against ``sum_i w_i x_i + offset``); tip_patch_compliance:
            the row's series compliance, m/N (:func:`tip_series_compliance`).
        tip_force: force the tip region's contact rows exerted against the tip's direction of travel in the last
            substep, N (the puncture test, :func:`coupling_finish`).
        tip_slid: the tip was anchored in the last substep and slid, letting go of its anchor
            (:func:`coupling_finish`): ``tip_force`` is then its anchor spring's load, whose deflection the next
            anchor keeps (:func:`~suture_gym.sim.coupling.paths.tip_patch`).
        friction_force: total axial friction force on the needle in the last substep, N.
        cut_force: the cutting force that resisted the tip's advance in the last substep, N
            (``cutting_force`` while the tip cuts, 0 while it does not advance).
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
    tip_patch_vertex: np.ndarray
    tip_patch_weight: np.ndarray
    tip_patch_offset: np.ndarray
    tip_anchor_tri: int = -1
    tip_anchor_inside: bool = False
    exit_pierced: bool = False
    tip_patch_count: int = 0
    tip_patch_compliance: float = 0.0
    path_count: int = 0
    pathnode_count: int = 0
    tip_force: float = 0.0
    tip_slid: bool = False
    friction_force: float = 0.0
    cut_force: float = 0.0
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
            tip_patch_vertex=np.zeros(TIP_PATCH_CAPACITY, np.int32),
            tip_patch_weight=np.zeros(TIP_PATCH_CAPACITY),
            tip_patch_offset=np.zeros(3),
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


def crossing_buffers(capacity: int) -> tuple:
    """Output buffers of :func:`~suture_gym.sim.collision_kernels.crossings_kernel` for ``capacity`` crossings:
    ``(segment (C,) int32, triangle (C,) int32, bary (C, 3), t (C,), direction (C,) int8)``."""
    return (np.empty(capacity, np.int32), np.empty(capacity, np.int32), np.empty((capacity, 3)), np.empty(capacity),
            np.empty(capacity, np.int8))  # fmt: skip


class CouplingWork:
    """Per-substep scratch: the constraint rows built by the detection and their multipliers.

    Rebuilt by every :func:`coupling_detect`, so it carries no state between substeps; the solver keeps one
    per :class:`~suture_gym.sim.model.State` (never in the frozen model).

    Attributes (M strand nodes, K = ``max_paths``, P = ``max_path_nodes``):
        surface: the model's :class:`~suture_gym.sim.collision.TriangleSurface` with its own BVH boxes, and
            tet_bvh: its own copy of the model's tet BVH; every detection refits the surface's to the tissue
            positions and marks this one stale (tet_bvh_stale), refitted when a path grows (the one reader).
        crossings: the buffers of the rigid-support crossings (:func:`crossing_buffers`), grown when full.
        strand_q: ``(M, 3)`` strand node positions at detection, m; strand_q_start: ``(M, 3)`` at the start of
            the substep (filled by the solver).
        pathnode_q: ``(P, 3)`` path node positions at detection, m. pathnode_tangent: ``(P, 3)`` unit tangents.
        row_kind: ``(M,) int8`` ROW_NONE / ROW_TRIANGLE (contact) / ROW_PATH / ROW_ANCHOR (the tip's contact
            with friction) / ROW_WALL (contact from the inside of a rigid face). row_tri: ``(M,) int32`` triangle.
        row_tissue: ``(M, 8) int32`` tissue vertices of a path row; row_weight: ``(M, 8)`` their weights.
        row_tangent: ``(M, 3)`` path tangent of a path row.
        row_lambda: ``(M,)`` multiplier (kg m) of each row this substep (a needle node's path row: minus the size
            of its row_impulse); row_friction_lambda: ``(M,)`` axial friction multiplier.
        row_impulse: ``(M, 3)`` the impulse (kg m) each needle node's path row gave the needle this substep,
            summed as a vector over its projections (the tissue took the opposite).
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
        suture_inv_mass, suture_axis_inv_mass: ``(Ns,)`` 1/kg, and suture_axis: ``(Ns, 3)`` unit: the inverse
            masses ``W_j = w_j I + a_j t_j t_j^T`` of the suture nodes used by the projections this substep
            (:func:`embedded_inv_mass`), grouped as suture_mass ``(w, a, t)``.
        suture_contact_w: ``(Ns,)`` generalised inverse mass (1/kg) of the tissue point of each suture node's
            contact row in the rod's solve; suture_contact_tissue: ``(Ns,) bool``, the node's row in the rod's
            solve is its node-triangle row this iteration (not a static obstacle's).
        node_rows: the tuple ``(row_kind, row_tri, row_tissue, row_weight, row_tangent)`` and access_rows:
            ``(access_node, access_weight, access_rest, access_tri, access_bary)``, contact_rows: ``(row_kind,
            row_tri, row_bary, row_contact_normal, row_floor)`` and needle_rows: ``(row_kind,
            row_tri, row_bary, row_contact_normal, row_floor, row_tissue, row_weight, row_tangent, row_lambda,
            row_friction_lambda, tip_patch, cut_rows, row_impulse)``, built once: the kernels take these groups as
            one argument each (the same arrays, not copies).
        tip_patch: this substep's tip contact patch for the anchor row, ``(vertex (C,) int32, weight (C,),
            count (1,) int64, offset (3,) m, compliance (1,) m/N)`` (count 0: the anchor is a point of its
            triangle; :class:`CouplingState` ``tip_patch_*``).
        cut_rows: the tip's cutting row, ``(tissue (4,) int32, weight (4,), direction (3,), cap (1,) N,
            lambda (1,) kg m)``: the tissue point (the open path's last node), the tip's unit direction, the
            most force it resists the tip's advance with (0: no row) and its multiplier.
    """

    def __init__(self, model: CouplingModel):
        m = model.strand_node_count
        k = model.params.max_paths
        p = model.params.max_path_nodes
        self.surface = replace(model.surface, bvh=_writable_boxes(model.surface.bvh))
        self.tet_bvh = _writable_boxes(model.tet_bvh)
        self.tet_bvh_stale = True
        self.crossings = crossing_buffers(max(16, 2 * m))
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
        self.row_impulse = np.zeros((m, 3))
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
        self.suture_axis_inv_mass = np.zeros(model.suture_node_count)
        self.suture_axis = np.zeros((model.suture_node_count, 3))
        self.suture_mass = (self.suture_inv_mass, self.suture_axis_inv_mass, self.suture_axis)
        self.node_rows = (self.row_kind, self.row_tri, self.row_tissue, self.row_weight, self.row_tangent)
        self.access_rows = (self.access_node, self.access_weight, self.access_rest, self.access_tri, self.access_bary)
        self.contact_rows = (self.row_kind, self.row_tri, self.row_bary, self.row_contact_normal, self.row_floor)
        self.needle_rows = (
            self.row_kind, self.row_tri, self.row_bary, self.row_contact_normal, self.row_floor, self.row_tissue,
            self.row_weight, self.row_tangent, self.row_lambda, self.row_friction_lambda,
        )  # fmt: skip
        self.suture_contact_w = np.zeros(model.suture_node_count)
        self.suture_contact_tissue = np.zeros(model.suture_node_count, dtype=np.bool_)
        self.tip_patch = (
            np.zeros(TIP_PATCH_CAPACITY, np.int32), np.zeros(TIP_PATCH_CAPACITY), np.zeros(1, np.int64), np.zeros(3),
            np.zeros(1),
        )  # fmt: skip
        self.cut_rows = (np.zeros(4, np.int32), np.zeros(4), np.zeros(3), np.zeros(1), np.zeros(1))
        self.needle_rows = (*self.needle_rows, self.tip_patch, self.cut_rows, self.row_impulse)


def _writable_boxes(bvh: BVH) -> BVH:
    """A BVH sharing ``bvh``'s (read-only) topology with its own, writable copies of the boxes."""
    return replace(bvh, node_lo=bvh.node_lo.copy(), node_hi=bvh.node_hi.copy())
