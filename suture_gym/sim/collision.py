"""Geometric queries between strand nodes and the deforming tissue mesh (paper §4.1).

Per substep the solver refits two bounding volume hierarchies (:mod:`suture_gym.sim.bvh`) to the tissue
particle positions and asks:

- :func:`signed_distance` of every strand node to the closed tissue surface, with the closest surface triangle
  and its barycentric coordinates (node-triangle constraints, access points). The sign comes from the
  angle-weighted pseudo-normal of the closest feature (face, edge or vertex), after J. A. Baerentzen and
  H. Aanaes, "Signed distance computation using the angle weighted pseudonormal", IEEE TVCG 11(3), 2005: for a
  closed, consistently oriented 2-manifold, ``sign((p - c) . n)`` with ``c`` the closest point and ``n`` the
  pseudo-normal of the feature containing ``c`` is the inside/outside sign, also at edges and corners.
  :func:`classify_layers` turns the distances into the paper's three layers (Fig. 2a): inside ``s < 0``,
  resistance ``0 <= s < eps``, outside ``s >= eps``.
- :func:`closest_triangles` within a maximum distance (unsigned).
- :func:`locate_points`: the tetrahedron containing a point and its barycentric coordinates (path nodes).
- :func:`segment_crossings`: where strand segments cross the surface (entry/exit access points), as
  triangle + barycentric coordinates, with a consistent tie rule so a segment through a shared edge is
  reported by exactly one of the two triangles.

Conventions: surface triangles are oriented with outward normals ``(x1 - x0) x (x2 - x0)``; positions are
metres; a signed distance is negative inside the tissue. Queries read the BVH boxes as last refitted, so call
:func:`~suture_gym.sim.bvh.refit_bvh` with the same ``vertex_q`` first. Degenerate triangles (zero area) and
tetrahedra (zero volume) never produce NaN: a degenerate triangle is treated as its three edges and
contributes a zero normal; a degenerate tet contains no point; a degenerate triangle is never crossed.

This module checks inputs and returns results; the numba kernels are in :mod:`suture_gym.sim.collision_kernels`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suture_gym.sim.bvh import BVH, _check_elements, _check_positions, build_bvh
from suture_gym.sim.collision_kernels import (
    FEATURE_EDGE_01,
    FEATURE_EDGE_12,
    FEATURE_EDGE_20,
    FEATURE_FACE,
    FEATURE_VERTEX_0,
    FEATURE_VERTEX_1,
    FEATURE_VERTEX_2,
    closest_kernel,
    closest_point_triangle,
    crossings_kernel,
    locate_kernel,
    signed_distance_kernel,
)
from suture_gym.sim.collision_kernels import _closest_bary as _closest_bary  # used by suture_gym.measure
from suture_gym.sim.collision_kernels import _pseudo_normal as _pseudo_normal  # used by suture_gym.measure

__all__ = [
    "FEATURE_EDGE_01",
    "FEATURE_EDGE_12",
    "FEATURE_EDGE_20",
    "FEATURE_FACE",
    "FEATURE_VERTEX_0",
    "FEATURE_VERTEX_1",
    "FEATURE_VERTEX_2",
    "LAYER_INSIDE",
    "LAYER_OUTSIDE",
    "LAYER_RESISTANCE",
    "SegmentCrossings",
    "TriangleSurface",
    "build_triangle_surface",
    "classify_layers",
    "closest_point_triangle",
    "closest_triangles",
    "locate_points",
    "segment_crossings",
    "signed_distance",
]


#: Layers of paper Fig. 2a.
LAYER_INSIDE = 0
LAYER_RESISTANCE = 1
LAYER_OUTSIDE = 2


@dataclass
class TriangleSurface:
    """Closed, outward-oriented triangle surface of the tissue with its adjacency and BVH.

    Built once from topology (:func:`build_triangle_surface`); the positions live in the tissue's
    ``particle_q`` (N,3) and the BVH is refitted to them each substep.

    Attributes:
        tri_vertices: (T, 3) int32, particle indices of each triangle, counter-clockwise seen from outside.
        tri_neighbors: (T, 3) int32, triangle across edge k = (v_k, v_{k+1 mod 3}); -1 on an open boundary.
        vertex_tri_start: (N + 1,) int32, CSR offsets: triangles touching particle i are
            ``vertex_tri_index[vertex_tri_start[i] : vertex_tri_start[i + 1]]``.
        vertex_tri_index: (3T,) int32, CSR triangle indices.
        bvh: :class:`~suture_gym.sim.bvh.BVH` over the triangles (``bvh.element_vertices is tri_vertices``).
    """

    tri_vertices: np.ndarray
    tri_neighbors: np.ndarray
    vertex_tri_start: np.ndarray
    vertex_tri_index: np.ndarray
    bvh: BVH


@dataclass
class SegmentCrossings:
    """Crossings of segments with surface triangles, sorted by segment, then by position along it.

    Attributes:
        crossing_segment: (H,) int32, index of the crossing segment.
        crossing_tri: (H,) int32, surface triangle crossed.
        crossing_bary: (H, 3) float64, barycentric coordinates of the crossing in that triangle (sum 1, >= 0).
        crossing_t: (H,) float64 in [0, 1], fraction of the way from the segment's start to its end.
        crossing_q: (H, 3) float64 [m], the crossing point ``start + t (end - start)``.
        crossing_direction: (H,) int8, -1 entering (moving against the outward normal), +1 leaving.
    """

    crossing_segment: np.ndarray
    crossing_tri: np.ndarray
    crossing_bary: np.ndarray
    crossing_t: np.ndarray
    crossing_q: np.ndarray
    crossing_direction: np.ndarray

# ----------------------------------------------------------------------------------------------------------
# Python API
# ----------------------------------------------------------------------------------------------------------


def build_triangle_surface(
    tri_vertices: np.ndarray, vertex_q: np.ndarray, leaf_size: int = 4
) -> TriangleSurface:
    """Precompute the adjacency and BVH of a closed, outward-oriented triangle surface (once, from topology).

    Args:
        tri_vertices: (T, 3) int, particle indices per triangle, counter-clockwise seen from outside (as
            returned by ``sim.mesh.surface_triangles``). Several closed components are fine.
        vertex_q: (N, 3) float64 [m], particle positions (rest pose) used to build the BVH.
        leaf_size: most triangles per BVH leaf.

    Returns:
        A :class:`TriangleSurface` whose BVH is fitted to ``vertex_q``.

    Raises:
        ValueError: bad shapes or indices, a triangle repeating a vertex, an edge shared by more than two
            triangles (non-manifold), or two triangles traversing their shared edge in the same direction
            (inconsistent orientation).
    """
    q = _check_positions(vertex_q, "vertex_q")
    tv = _check_elements(tri_vertices, q.shape[0])
    if tv.shape[1] != 3:
        raise ValueError(f"tri_vertices must have shape (T, 3), got {tv.shape}")
    repeated = (tv[:, 0] == tv[:, 1]) | (tv[:, 1] == tv[:, 2]) | (tv[:, 2] == tv[:, 0])
    if repeated.any():
        bad = int(np.argmax(repeated))
        raise ValueError(f"tri_vertices row {bad} = {tv[bad].tolist()} repeats a vertex")
    n_vertices = q.shape[0]
    head = tv.ravel().astype(np.int64)
    tail = np.roll(tv, -1, axis=1).ravel().astype(np.int64)
    key = np.minimum(head, tail) * n_vertices + np.maximum(head, tail)
    order = np.argsort(key, kind="stable")
    sorted_key = key[order]
    starts = np.flatnonzero(np.r_[True, sorted_key[1:] != sorted_key[:-1]])
    sizes = np.diff(np.r_[starts, len(sorted_key)])
    if (sizes > 2).any():
        g = int(np.argmax(sizes > 2))
        u, v = divmod(int(sorted_key[starts[g]]), n_vertices)
        raise ValueError(
            f"tri_vertices: edge ({u}, {v}) is shared by {int(sizes[g])} triangles (non-manifold)"
        )
    pairs = starts[sizes == 2]
    first = order[pairs]
    second = order[pairs + 1]
    same_direction = head[first] == head[second]
    if same_direction.any():
        g = int(np.argmax(same_direction))
        raise ValueError(
            f"tri_vertices: triangles {int(first[g]) // 3} and {int(second[g]) // 3} traverse their "
            f"shared edge ({int(head[first[g]])}, {int(tail[first[g]])}) in the same direction "
            "(inconsistent orientation)"
        )
    neighbors = np.full(tv.size, -1, np.int32)
    neighbors[first] = second // 3
    neighbors[second] = first // 3
    counts = np.bincount(head, minlength=n_vertices)
    vertex_tri_start = np.zeros(n_vertices + 1, np.int32)
    np.cumsum(counts, out=vertex_tri_start[1:])
    vertex_tri_index = (np.argsort(head, kind="stable") // 3).astype(np.int32)
    bvh = build_bvh(tv, q, leaf_size)
    return TriangleSurface(
        tri_vertices=bvh.element_vertices,
        tri_neighbors=neighbors.reshape(-1, 3),
        vertex_tri_start=vertex_tri_start,
        vertex_tri_index=vertex_tri_index,
        bvh=bvh,
    )


def _check_query(points: np.ndarray, name: str) -> np.ndarray:
    p = np.ascontiguousarray(points, dtype=np.float64)
    if p.ndim != 2 or p.shape[1] != 3:
        raise ValueError(f"{name} must have shape (M, 3), got {p.shape}")
    if not np.isfinite(p).all():
        bad = int(np.argwhere(~np.isfinite(p))[0, 0])
        raise ValueError(f"{name} row {bad} is not finite: {p[bad]}")
    return p


def _check_vertices(vertex_q: np.ndarray, bvh: BVH) -> np.ndarray:
    return _check_positions(vertex_q, "vertex_q", bvh.vertex_count)


def closest_triangles(
    points: np.ndarray, surface: TriangleSurface, vertex_q: np.ndarray, max_distance: float = np.inf
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Closest surface triangle to each point, searched within ``max_distance``.

    Args:
        points: (M, 3) float64 [m] query points.
        surface: from :func:`build_triangle_surface`, BVH refitted to ``vertex_q``.
        vertex_q: (N, 3) float64 [m] current particle positions.
        max_distance: float [m] >= 0; farther triangles are ignored.

    Returns:
        ``(tri, bary, dist)``: tri (M,) int32 (-1 when no triangle is within ``max_distance``); bary (M, 3)
        float64 barycentric coordinates of the closest point (zeros when tri = -1); dist (M,) float64 [m]
        unsigned distance (inf when tri = -1). Equal distances resolve to the lower triangle index.
    """
    if not max_distance >= 0.0:
        raise ValueError(f"max_distance must be >= 0, got {max_distance!r}")
    p = _check_query(points, "points")
    q = _check_vertices(vertex_q, surface.bvh)
    tri = np.empty(p.shape[0], np.int32)
    bary = np.empty((p.shape[0], 3))
    dist = np.empty(p.shape[0])
    b = surface.bvh
    closest_kernel(
        p,
        float(max_distance) ** 2,
        b.tree,
        q,
        tri,
        bary,
        dist,
    )
    return tri, bary, dist


def signed_distance(
    points: np.ndarray, surface: TriangleSurface, vertex_q: np.ndarray, box_margin: float = np.inf
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Signed distance of each point to the closed deformed surface, with the closest triangle.

    The sign is that of ``(p - c) . n`` with ``c`` the closest surface point and ``n`` the angle-weighted
    pseudo-normal of the face, edge or vertex containing ``c`` (Baerentzen & Aanaes 2005); exact for a closed,
    consistently oriented, non-self-intersecting surface. Where the pseudo-normal vanishes (a neighbourhood of
    degenerate triangles) the point counts as outside.

    Args:
        points: (M, 3) float64 [m], e.g. strand node positions.
        surface: from :func:`build_triangle_surface`, BVH refitted to ``vertex_q``.
        vertex_q: (N, 3) float64 [m] current particle positions.
        box_margin: m, >= 0; points farther than this outside the surface's bounding box are skipped
            (``+inf``, triangle -1, zero barycentrics: a broad phase); ``inf`` (the default) skips none.

    Returns:
        ``(sdist, tri, bary)``: sdist (M,) float64 [m], negative inside; tri (M,) int32 closest triangle;
        bary (M, 3) float64 barycentric coordinates of the closest point in ``tri``.
    """
    if not box_margin >= 0.0:
        raise ValueError(f"box_margin must be >= 0, got {box_margin!r}")
    p = _check_query(points, "points")
    q = _check_vertices(vertex_q, surface.bvh)
    sdist = np.empty(p.shape[0])
    tri = np.empty(p.shape[0], np.int32)
    bary = np.empty((p.shape[0], 3))
    b = surface.bvh
    signed_distance_kernel(
        p,
        float(box_margin),
        b.tree,
        surface.tri_neighbors,
        surface.vertex_tri_start,
        surface.vertex_tri_index,
        q,
        sdist,
        tri,
        bary,
    )
    return sdist, tri, bary


def classify_layers(sdist: np.ndarray, eps: float) -> np.ndarray:
    """Layer of each signed distance (paper Fig. 2a).

    Args:
        sdist: (M,) float64 [m] signed distances (negative inside).
        eps: float [m] > 0, thickness of the resistance layer.

    Returns:
        (M,) int8: LAYER_INSIDE for s < 0, LAYER_RESISTANCE for 0 <= s < eps, LAYER_OUTSIDE for s >= eps.
    """
    if not (np.isfinite(eps) and eps > 0.0):
        raise ValueError(f"eps must be a positive finite distance in metres, got {eps!r}")
    s = np.asarray(sdist, dtype=np.float64)
    if np.isnan(s).any():
        raise ValueError(f"sdist holds NaN at index {int(np.argmax(np.isnan(s)))}")
    layer = np.full(s.shape, LAYER_RESISTANCE, np.int8)
    layer[s < 0.0] = LAYER_INSIDE
    layer[s >= eps] = LAYER_OUTSIDE
    return layer


def locate_points(
    points: np.ndarray, tet_bvh: BVH, vertex_q: np.ndarray, tolerance: float = 1e-9
) -> tuple[np.ndarray, np.ndarray]:
    """Tetrahedron containing each point and the point's barycentric coordinates in it.

    Args:
        points: (M, 3) float64 [m].
        tet_bvh: :func:`~suture_gym.sim.bvh.build_bvh` over the (K, 4) tets, refitted to ``vertex_q``.
        vertex_q: (N, 3) float64 [m] current particle positions.
        tolerance: float >= 0, a point counts as inside a tet when all its barycentric coordinates are
            >= -tolerance (so points on shared faces and on the boundary are found).

    Returns:
        ``(tet, bary)``: tet (M,) int32, -1 when no tet contains the point; bary (M, 4) float64 with
        ``p = sum_k bary[k] x_{tet[k]}`` (zeros when tet = -1). Where several tets qualify (shared faces,
        inverted or overlapping tets) the one with the largest smallest coordinate wins, then the lower index.
    """
    if tet_bvh.element_vertices.shape[1] != 4:
        raise ValueError(f"tet_bvh must be built over (K, 4) tets, got {tet_bvh.element_vertices.shape}")
    if not (np.isfinite(tolerance) and tolerance >= 0.0):
        raise ValueError(f"tolerance must be a finite number >= 0, got {tolerance!r}")
    p = _check_query(points, "points")
    q = _check_vertices(vertex_q, tet_bvh)
    tet = np.empty(p.shape[0], np.int32)
    bary = np.empty((p.shape[0], 4))
    b = tet_bvh
    locate_kernel(
        p,
        float(tolerance),
        b.tree,
        q,
        tet,
        bary,
    )
    return tet, bary


def segment_crossings(
    seg_start: np.ndarray,
    seg_end: np.ndarray,
    surface: TriangleSurface,
    vertex_q: np.ndarray,
    check_finite: bool = True,
) -> SegmentCrossings:
    """Every crossing of the segments ``seg_start[i] -> seg_end[i]`` with the surface triangles.

    For a strand with node positions x (M, 3), pass ``x[:-1], x[1:]``. A segment passing exactly through an
    edge shared by two triangles is reported once (canonical tie rule on exact zeros); exactly through a
    vertex it may be reported by none or several of the triangles around it. Segments lying in a triangle's
    plane and degenerate triangles report no crossing.

    Args:
        seg_start, seg_end: (S, 3) float64 [m] segment end points.
        surface: from :func:`build_triangle_surface`, BVH refitted to ``vertex_q``.
        vertex_q: (N, 3) float64 [m] current particle positions.
        check_finite: validate the three arrays (shapes, finite values; ValueError naming the bad one). The
            solver's detection passes False: its C-contiguous float64 positions were checked finite just before.

    Returns:
        :class:`SegmentCrossings`, sorted by segment, then ``t``, then triangle.
    """
    if check_finite:
        a = _check_query(seg_start, "seg_start")
        b_end = _check_query(seg_end, "seg_end")
        q = _check_vertices(vertex_q, surface.bvh)
    else:
        a, b_end, q = seg_start, seg_end, vertex_q
    if a.shape != b_end.shape:
        raise ValueError(f"seg_start {a.shape} and seg_end {b_end.shape} must have the same shape")
    b = surface.bvh
    capacity = max(16, 2 * a.shape[0])
    while True:
        seg = np.empty(capacity, np.int32)
        tri = np.empty(capacity, np.int32)
        bary = np.empty((capacity, 3))
        t = np.empty(capacity)
        direction = np.empty(capacity, np.int8)
        count = crossings_kernel(
            a,
            b_end,
            b.tree,
            q,
            seg,
            tri,
            bary,
            t,
            direction,
        )
        if count <= capacity:
            break
        capacity = count
    if count == 0:  # the common case in the solver's detection: no sort, no copies
        return SegmentCrossings(seg[:0], tri[:0], bary[:0], t[:0], np.empty((0, 3)), direction[:0])
    order = np.lexsort((tri[:count], t[:count], seg[:count]))
    seg = seg[order]
    t = t[order]
    return SegmentCrossings(
        crossing_segment=seg,
        crossing_tri=tri[order],
        crossing_bary=bary[order],
        crossing_t=t,
        crossing_q=a[seg] + t[:, None] * (b_end[seg] - a[seg]),
        crossing_direction=direction[order],
    )
