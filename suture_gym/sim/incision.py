"""An incision in any tetrahedral mesh: a polyline on its surface cut to a depth, opened into a wound.

The cut follows the mesh's own faces: no tet is split, so the mesh keeps its quality. Given the polyline
``P_0 .. P_{K-1}`` on the surface and a depth ``d``:

1. **Frames.** The points are moved to the nearest point of the mesh's boundary. Each segment ``i`` gets a
   tangent ``T_i``, a cutting direction ``D_i`` (into the tissue: minus the area-weighted normal of the boundary
   triangles within the tolerance of its end points, made orthogonal to ``T_i``) and a side normal
   ``S_i = T_i x D_i``. The cut surface is the ribbon the segments sweep along ``D`` to depth ``d``.
2. **Cut faces.** An interior face is cut when its centroid's nearest segment (nearest across ``D``, i.e. seen
   from outside) has it within the segment's length, at a depth in ``(0, d)`` and within one of the face's
   edge lengths of the ribbon, and its two tets lie on opposite sides of the ribbon (each tet's side: the sign
   of ``S`` at its centroid in its own nearest segment's frame, a centroid on the ribbon counting as ``+``):
   the boundary between the tets on either side, a staircase at the element size where the mesh does not
   follow the ribbon (exact on a box grid cut along a grid plane).
3. **Split.** Around each vertex, the tets that still share a face through it (the cut faces no longer count)
   form one or more groups; each group beyond the first gets a copy of the vertex. Vertices where the cut
   ends inside the tissue (the crack front: the bottom of the cut and ends that do not reach the surface)
   keep one group and are not copied, so both cut faces become open wound faces that meet at the front.
   Where the split would leave a non-manifold boundary (a staircase cut touching itself or the outer surface
   along an edge or at a vertex, e.g. under a polyline over a step), the cut faces at those vertices are left
   uncut and the split redone (``dropped_faces``).
4. **Gap.** With ``gap > 0`` the wound is opened in the rest shape: the copies on either side move by
   ``-+ gap/2 * w * S`` with ``w = min(1, distance to the crack front / d')`` (a V that closes at the front;
   ``d'`` is ``d``, or the farthest copy's distance where the mesh's faces stop the cut short of ``d``),
   and every other vertex by the harmonic interpolation of those moves (graph Laplacian of the cut mesh), so
   the opening spreads into the tissue instead of squashing the tets at the cut. A cut that separates the
   mesh (``allow_split``) with no crack front moves each piece rigidly by ``-+ gap/2`` along ``S``.

The result passes :func:`~suture_gym.sim.mesh.validate_tet_mesh` (a :class:`~suture_gym.sim.mesh.TetMesh`).
Frame of the result: ``left`` is the side ``-S``. For a cut along ``+x`` into ``-z`` (``S = +y``) the left face
is at the lower ``y``, as in :func:`~suture_gym.sim.scenes.two_bar_wound`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.sparse import coo_matrix, identity
from scipy.sparse.csgraph import connected_components, laplacian
from scipy.sparse.linalg import spsolve
from scipy.spatial import cKDTree

from suture_gym.sim.mesh import TetMesh, _face_groups, surface_triangles

#: Two non-adjacent segments closer than this fraction of the on-surface tolerance cross: on a curved surface
#: the chords of two crossing cuts pass at about their sagittas' difference, not at 0.
CROSSING_TOLERANCE = 0.1
#: Sharpest turn of the polyline between two segments, rad: beyond it the segments' frames overlap.
MAX_TURN = np.pi / 2


@dataclass(frozen=True)
class Incision:
    """An incision description.

    Attributes:
        points: ``(K, 3)`` float64, K >= 2, the polyline on the tissue surface, m, in order along the cut.
        depth: depth of the cut below the polyline along the cutting direction, m (> 0).
        gap: opening of the wound at its mouth in the rest shape, m (>= 0; 0: the faces touch).
    """

    points: np.ndarray
    depth: float
    gap: float = 0.0

    def __post_init__(self) -> None:
        points = np.array(self.points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] != 3 or len(points) < 2:
            raise ValueError(f"incision points must have shape (K, 3) with K >= 2, got {points.shape}")
        if not np.all(np.isfinite(points)):
            raise ValueError("incision points must be finite coordinates in metres")
        for name in ("depth", "gap"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise ValueError(f"incision {name} must be a number in metres, got {value!r}")
        if not (np.isfinite(self.depth) and self.depth > 0):
            raise ValueError(f"incision depth must be a positive finite length in metres, got {self.depth!r}")
        if not (np.isfinite(self.gap) and self.gap >= 0):
            raise ValueError(f"incision gap must be a finite length >= 0 in metres, got {self.gap!r}")
        points.flags.writeable = False
        object.__setattr__(self, "points", points)
        object.__setattr__(self, "depth", float(self.depth))
        object.__setattr__(self, "gap", float(self.gap))


@dataclass(frozen=True)
class IncisedMesh:
    """The result of :func:`incise`.

    Attributes:
        mesh: the cut (and opened) :class:`~suture_gym.sim.mesh.TetMesh`; tets keep their order and index.
        source_vertex: ``(N',) int32``, the vertex of the input mesh each vertex copies (identity for the first
            ``N``; the copies are appended).
        left_face, right_face: ``(k,) int32`` vertices of the two wound faces (sides ``-S`` and ``+S``), the
            crack front excluded (it belongs to both).
        crack_front: ``(f,) int32`` vertices where the two faces meet (not copied).
        cut_faces: number of interior faces cut.
        dropped_faces: faces next to the ribbon left uncut because cutting them made the boundary non-manifold
            (a staircase cut touching itself or the outer surface along an edge or at a vertex).
        points: ``(K, 3) float64`` the polyline as cut, m: each point moved to the nearest point of the mesh's
            boundary (a voxel mesh's staircase lies up to a cell from the surface the points were taken on).
    """

    mesh: TetMesh
    source_vertex: np.ndarray
    left_face: np.ndarray
    right_face: np.ndarray
    crack_front: np.ndarray
    cut_faces: int
    dropped_faces: int
    points: np.ndarray


def closest_surface_points(points: np.ndarray, vertices: np.ndarray, triangles: np.ndarray) -> tuple[np.ndarray,
                                                                                                      np.ndarray]:
    """Distance from each point to each triangle (brute force, vectorised; for a few points at scene build).

    Args:
        points: ``(K, 3)`` m; vertices: ``(N, 3)`` m; triangles: ``(F, 3)`` vertex indices.

    Returns:
        ``distance (K, F)`` m, and ``normal (F, 3)`` the triangles' unit normals ``(x1 - x0) x (x2 - x0)``
        (zero for a zero-area triangle).
    """
    x = np.asarray(vertices, dtype=np.float64)[triangles]  # (F, 3, 3)
    p = np.asarray(points, dtype=np.float64)[:, None, :]  # (K, 1, 3)
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    length = np.linalg.norm(n, axis=1, keepdims=True)
    unit = np.divide(n, length, out=np.zeros_like(n), where=length > 0)
    height = np.einsum("kfj,fj->kf", p - x[None, :, 0], unit)
    foot = p - height[..., None] * unit[None]
    inside = np.ones(height.shape, dtype=bool)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        edge_normal = np.cross(x[:, b] - x[:, a], unit)  # points out of the triangle, in its plane
        inside &= np.einsum("kfj,fj->kf", foot - x[None, :, a], edge_normal) <= 0.0
    distance = np.where(inside, np.abs(height), np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        e = x[:, b] - x[:, a]
        t = np.clip(np.einsum("kfj,fj->kf", p - x[None, :, a], e) / np.maximum(np.einsum("fj,fj->f", e, e), 1e-300),
                    0.0, 1.0)
        distance = np.minimum(distance, np.linalg.norm(p - (x[None, :, a] + t[..., None] * e[None]), axis=2))
    return distance, unit


def _closest_on_triangles(p: np.ndarray, x: np.ndarray) -> np.ndarray:
    """``(K, 3)`` the closest point to each ``p[k]`` (m) on the triangle ``x[k]`` ``(K, 3, 3)``."""
    n = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    foot = p - np.einsum("kj,kj->k", p - x[:, 0], n)[:, None] * n
    inside = np.ones(len(p), dtype=bool)
    best, best_distance = foot.copy(), np.full(len(p), np.inf)
    for a, b in ((0, 1), (1, 2), (2, 0)):
        e = x[:, b] - x[:, a]
        inside &= np.einsum("kj,kj->k", foot - x[:, a], np.cross(e, n)) <= 0.0
        t = np.clip(np.einsum("kj,kj->k", p - x[:, a], e) / np.einsum("kj,kj->k", e, e), 0.0, 1.0)
        q = x[:, a] + t[:, None] * e
        d = np.linalg.norm(p - q, axis=1)
        closer = d < best_distance
        best[closer], best_distance[closer] = q[closer], d[closer]
    return np.where(inside[:, None], foot, best)


def _mean_edge(vertices: np.ndarray, triangles: np.ndarray) -> float:
    """Mean edge length (m) of the triangles ``(F, 3)`` over ``vertices`` ``(N, 3)`` (shared edges counted twice)."""
    x = vertices[triangles]
    return float(np.linalg.norm(x - np.roll(x, 1, axis=1), axis=2).mean())


def _check_polyline(points: np.ndarray, tolerance: float) -> None:
    """ValueError for a repeated point, a turn sharper than :data:`MAX_TURN`, or two non-adjacent segments that
    come within ``tolerance`` (m) of each other (cross, allowing for chords of a curved surface)."""
    seg = np.diff(points, axis=0)
    length = np.linalg.norm(seg, axis=1)
    if np.any(length <= 0.0):
        k = int(np.flatnonzero(length <= 0.0)[0])
        raise ValueError(f"incision points {k} and {k + 1} coincide at {points[k].tolist()} m")
    unit = seg / length[:, None]
    turn = np.arccos(np.clip(np.einsum("ij,ij->i", unit[:-1], unit[1:]), -1.0, 1.0))
    if np.any(turn > MAX_TURN):
        k = int(np.flatnonzero(turn > MAX_TURN)[0])
        raise ValueError(
            f"the incision polyline turns back by {np.degrees(turn[k]):.0f} deg at point {k + 1} "
            f"{points[k + 1].tolist()} m (at most {np.degrees(MAX_TURN):.0f} deg): it would cut across itself"
        )
    # Non-adjacent segments: closest approach of two segments (clamped parameters, Ericson 5.1.9).
    i, j = np.triu_indices(len(seg), k=2)
    if len(i) == 0:
        return
    d1, d2, r = seg[i], seg[j], points[i] - points[j]
    a, e = length[i] ** 2, length[j] ** 2
    b, c, f = np.einsum("ij,ij->i", d1, d2), np.einsum("ij,ij->i", d1, r), np.einsum("ij,ij->i", d2, r)
    denom = a * e - b * b
    s = np.where(denom > 1e-30 * a * e, np.clip((b * f - c * e) / np.where(denom > 0, denom, 1.0), 0.0, 1.0), 0.0)
    t = (b * s + f) / e
    s = np.where(t < 0, np.clip(-c / a, 0, 1), np.where(t > 1, np.clip((b - c) / a, 0, 1), s))
    t = np.clip(t, 0.0, 1.0)
    gap = np.linalg.norm(points[i] + s[:, None] * d1 - points[j] - t[:, None] * d2, axis=1)
    if np.any(gap < tolerance):
        k = int(np.argmin(gap))
        raise ValueError(
            f"the incision polyline crosses itself: segments {int(i[k])} and {int(j[k])} come within "
            f"{gap[k]:.3g} m of each other (tolerance {tolerance:.3g} m)"
        )


def _segment_frames(points: np.ndarray, direction: np.ndarray) -> tuple[np.ndarray, ...]:
    """``(origin (S, 3), tangent (S, 3), cut direction (S, 3), side normal (S, 3), length (S,))`` per segment,
    from the points' inward directions ``direction (K, 3)``."""
    seg = np.diff(points, axis=0)
    length = np.linalg.norm(seg, axis=1)
    tangent = seg / length[:, None]
    d = direction[:-1] + direction[1:]
    d -= np.einsum("ij,ij->i", d, tangent)[:, None] * tangent
    norm = np.linalg.norm(d, axis=1)
    if np.any(norm < 1e-9):
        k = int(np.flatnonzero(norm < 1e-9)[0])
        raise ValueError(
            f"incision segment {k} runs along the surface normal (into the tissue) instead of along the surface"
        )
    d /= norm[:, None]
    return points[:-1], tangent, d, np.cross(tangent, d), length


def _nearest_segment(x: np.ndarray, origin, tangent, cut, length) -> tuple[np.ndarray, np.ndarray]:
    """For points ``x (M, 3)``: the index of the nearest segment seen along its cutting direction, and the
    points' ``(along in segment lengths, depth, side)`` coordinates in that segment's frame, ``(M, 3)``."""
    r = x[:, None, :] - origin[None]  # (M, S, 3)
    along = np.einsum("msj,sj->ms", r, tangent)
    depth = np.einsum("msj,sj->ms", r, cut)
    lateral = r - depth[..., None] * cut[None]  # seen from outside: the cut direction projected out
    clamped = np.clip(along, 0.0, length[None])
    distance = np.linalg.norm(lateral - clamped[..., None] * tangent[None], axis=2)
    nearest = np.argmin(distance, axis=1)
    rows = np.arange(len(x))
    side = np.einsum("mj,mj->m", r[rows, nearest], np.cross(tangent, cut)[nearest])
    return nearest, np.stack([along[rows, nearest] / length[nearest], depth[rows, nearest], side], axis=1)


def incise(mesh: TetMesh, incision: Incision, tolerance: float | None = None, allow_split: bool = False) -> IncisedMesh:
    """Cut ``incision`` into ``mesh`` (see the module docstring).

    Args:
        mesh: a validated tet mesh, m.
        incision: the polyline on the surface, depth and gap.
        tolerance: how far (m) a polyline point may lie from the mesh's boundary surface; default the
            boundary's mean edge length (a voxel mesh's staircase lies up to about that far from the surface it
            approximates). Two non-adjacent segments closer than :data:`CROSSING_TOLERANCE` times it cross.
        allow_split: accept a cut that separates the mesh into more pieces (e.g. the two bars of
            :func:`~suture_gym.sim.scenes.two_bar_wound`); refused by default.

    Raises:
        ValueError: naming the problem: a point off the surface, a polyline that crosses itself or turns back,
            a cut that meets no face (depth below the element size), one that cuts the mesh in two, or a gap
            that inverts tets.
    """
    if not isinstance(mesh, TetMesh):
        raise ValueError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
    if not isinstance(incision, Incision):
        raise ValueError(f"incision must be an Incision, got {type(incision).__name__}")
    vertices, tets = mesh.vertices, mesh.tets.astype(np.int64)
    n = len(vertices)
    triangles = surface_triangles(tets)
    tri_x = vertices[triangles]
    if tolerance is None:
        tolerance = _mean_edge(vertices, triangles)
    elif not (np.isfinite(tolerance) and tolerance > 0):
        raise ValueError(f"tolerance must be a positive length in metres, got {tolerance!r}")
    points = incision.points

    distance, normal = closest_surface_points(points, vertices, triangles)
    nearest = distance.min(axis=1)
    if np.any(nearest > tolerance):
        k = int(np.argmax(nearest))
        raise ValueError(
            f"incision point {k} {points[k].tolist()} m is {nearest[k]:.3g} m from the tissue surface "
            f"(tolerance {tolerance:.3g} m): the polyline must lie on the surface"
        )
    _check_polyline(points, CROSSING_TOLERANCE * tolerance)
    points = _closest_on_triangles(points, tri_x[np.argmin(distance, axis=1)])
    area = 0.5 * np.linalg.norm(np.cross(tri_x[:, 1] - tri_x[:, 0], tri_x[:, 2] - tri_x[:, 0]), axis=1)
    near = distance <= nearest[:, None] + tolerance
    direction = -(near * area[None]) @ normal
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    origin, tangent, cut, side_normal, length = _segment_frames(points, direction)

    # Interior faces and the two tets of each.
    faces, face_tet, first = _face_groups(tets)
    counts = np.diff(np.append(first, len(faces)))
    pair = first[counts == 2]
    face_v, tet_a, tet_b = faces[pair], face_tet[pair], face_tet[pair + 1]
    fx = vertices[face_v]
    centroid = fx.mean(axis=1)
    seg, coords = _nearest_segment(centroid, origin, tangent, cut, length)
    size = np.linalg.norm(fx - np.roll(fx, 1, axis=1), axis=2).max(axis=1)
    tet_coords = _nearest_segment(vertices[tets].mean(axis=1), origin, tangent, cut, length)[1]
    tet_side = np.where(tet_coords[:, 2] < 0.0, -1, 1)
    side_a = tet_side[tet_a]
    is_cut = ((coords[:, 0] > 0.0) & (coords[:, 0] < 1.0) & (coords[:, 1] > 0.0) & (coords[:, 1] < incision.depth)
              & (np.abs(coords[:, 2]) < size) & (side_a * tet_side[tet_b] < 0))
    if not is_cut.any():
        raise ValueError(
            f"the incision cuts no face of the mesh: its depth {incision.depth:.3g} m is below the element size "
            f"near it (faces of about {np.median(size):.3g} m), or it does not run over the mesh"
        )

    # Split along the cut faces; where that leaves a non-manifold boundary (the cut's edge running along the outer
    # surface, or two parts of a staircase cut touching at a vertex), leave the cut faces there uncut and redo.
    local_a = np.argmax(tets[tet_a][:, :, None] == face_v[:, None, :], axis=1)  # (F, 3)
    local_b = np.argmax(tets[tet_b][:, :, None] == face_v[:, None, :], axis=1)
    selected = int(is_cut.sum())
    while True:
        new_tets, source_vertex = _split(tets, n, tet_a, tet_b, local_a, local_b, ~is_cut)
        bad = source_vertex[_nonmanifold_vertices(new_tets, len(source_vertex))]
        if bad.size == 0:
            break
        is_cut &= ~np.isin(face_v, bad).any(axis=1)
        if not is_cut.any():
            raise ValueError("the incision leaves no cut face that keeps the boundary a manifold: move or smooth "
                             "the polyline, or refine the mesh")
    keep = ~is_cut
    new_vertices = vertices[source_vertex]

    pieces_before = _pieces(tets, pair, tet_a, tet_b, np.ones(len(pair), dtype=bool))
    pieces_after = _pieces(tets, pair, tet_a, tet_b, keep)
    if pieces_after > pieces_before and not allow_split:
        raise ValueError(
            f"the incision (depth {incision.depth:.3g} m) cuts the mesh in two ({pieces_before} piece(s) before, "
            f"{pieces_after} after): make it shallower or shorter, or pass allow_split=True if that is meant"
        )

    # Wound faces: the copies the cut faces' tets use on either side; the crack front was not copied.
    cut_a = np.flatnonzero(is_cut)
    minus_is_a = side_a[cut_a] < 0
    minus_tet = np.where(minus_is_a, tet_a[cut_a], tet_b[cut_a])
    plus_tet = np.where(minus_is_a, tet_b[cut_a], tet_a[cut_a])
    minus_local = np.where(minus_is_a[:, None], local_a[cut_a], local_b[cut_a])
    plus_local = np.where(minus_is_a[:, None], local_b[cut_a], local_a[cut_a])
    minus = np.unique(new_tets[minus_tet[:, None], minus_local])
    plus = np.unique(new_tets[plus_tet[:, None], plus_local])
    front = np.intersect1d(minus, plus)
    left, right = np.setdiff1d(minus, front), np.setdiff1d(plus, front)
    if len(left) == 0:
        raise ValueError(
            "the incision opens no wound: every vertex of its cut lies on its edge (the cut is one element thick, "
            "or buried): make it deeper than the elements near it, or lay the polyline on the mesh's own surface"
        )

    result = TetMesh(vertices=new_vertices, tets=new_tets.astype(np.int32))
    if incision.gap > 0.0:
        frames = (origin, tangent, cut, length, side_normal)
        opened = _open(new_vertices, new_tets, left, right, front, incision, frames)
        try:
            result = TetMesh(vertices=opened, tets=result.tets)
        except ValueError as exc:
            raise ValueError(
                f"the incision's gap {incision.gap:.3g} m distorts the mesh beyond repair ({exc}): use a gap below "
                f"about the element size next to the cut ({np.median(size[is_cut]):.3g} m)"
            ) from exc
    left, right, front, source_vertex = (np.asarray(a, dtype=np.int32) for a in (left, right, front, source_vertex))
    return IncisedMesh(result, source_vertex, left, right, front, int(is_cut.sum()), selected - int(is_cut.sum()),
                       points)


def _split(tets, n, tet_a, tet_b, local_a, local_b, joined) -> tuple[np.ndarray, np.ndarray]:
    """``(tets (T, 4), source vertex (N',))`` of the mesh split along the interior faces not ``joined``: the
    corners (tet, local vertex) joined through the faces they share form components, one vertex copy each; each
    vertex's first component (by lowest corner) keeps its index, the others are appended in (vertex, corner)
    order."""
    rows = (4 * tet_a[joined, None] + local_a[joined]).ravel()
    cols = (4 * tet_b[joined, None] + local_b[joined]).ravel()
    corners = 4 * len(tets)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(corners, corners))
    _, label = connected_components(graph, directed=False)
    corner_vertex = tets.ravel()
    components = label.max() + 1
    first_corner = np.full(components, corners)
    np.minimum.at(first_corner, label, np.arange(corners))
    component_vertex = corner_vertex[first_corner]
    order = np.lexsort((first_corner, component_vertex))
    is_first = np.ones(components, dtype=bool)
    is_first[1:] = component_vertex[order][1:] != component_vertex[order][:-1]
    new_index = np.empty(components, dtype=np.int64)
    new_index[order[is_first]] = component_vertex[order[is_first]]
    extra = order[~is_first]
    new_index[extra] = n + np.arange(len(extra))
    return new_index[label].reshape(tets.shape), np.concatenate([np.arange(n), component_vertex[extra]])


def _nonmanifold_vertices(tets: np.ndarray, n: int) -> np.ndarray:
    """Vertices where the boundary of ``tets`` is not a manifold: on an edge of other than two boundary
    triangles, or with their boundary triangles in more than one fan (as
    :func:`~suture_gym.sim.mesh.validate_tet_mesh` checks)."""
    tri = surface_triangles(tets).astype(np.int64)
    edges = np.sort(np.concatenate([tri[:, [0, 1]], tri[:, [1, 2]], tri[:, [2, 0]]]), axis=1)
    unique, counts = np.unique(edges, axis=0, return_counts=True)
    bad = [unique[counts != 2].ravel()]
    # Fans: around each vertex, link edges join its (vertex, neighbour) pairs; one component per fan.
    centre, a, b = tri.ravel(), tri[:, [1, 2, 0]].ravel(), tri[:, [2, 0, 1]].ravel()
    nodes, inverse = np.unique(np.concatenate([centre * n + a, centre * n + b]), return_inverse=True)
    m = len(centre)
    graph = coo_matrix((np.ones(m), (inverse[:m], inverse[m:])), shape=(len(nodes), len(nodes)))
    _, labels = connected_components(graph, directed=False)
    fans = np.unique(np.stack([nodes // n, labels], axis=1), axis=0)[:, 0]
    vertex, count = np.unique(fans, return_counts=True)
    bad.append(vertex[count > 1])
    return np.unique(np.concatenate(bad))


def _pieces(tets: np.ndarray, pair: np.ndarray, tet_a: np.ndarray, tet_b: np.ndarray, joined: np.ndarray) -> int:
    """Connected pieces of the tets joined through the interior faces ``joined`` (mask over ``pair``)."""
    t = len(tets)
    graph = coo_matrix((np.ones(int(joined.sum())), (tet_a[joined], tet_b[joined])), shape=(t, t))
    return int(connected_components(graph, directed=False)[0])


def _open(vertices, tets, left, right, front, incision: Incision, frames) -> np.ndarray:
    """The vertices with the wound opened by ``incision.gap`` (module docstring, step 4)."""
    origin, tangent, cut, length, side_normal = frames
    faces = np.concatenate([left, right])
    seg, _ = _nearest_segment(vertices[faces], origin, tangent, cut, length)
    if len(front):
        reach, _ = cKDTree(vertices[front]).query(vertices[faces])
        weight = np.minimum(1.0, reach / min(incision.depth, float(reach.max())))
    else:
        weight = np.ones(len(faces))
    sign = np.concatenate([-np.ones(len(left)), np.ones(len(right))])
    prescribed = np.zeros((len(vertices), 3))
    prescribed[faces] = (0.5 * incision.gap * sign * weight)[:, None] * side_normal[seg]
    fixed = np.zeros(len(vertices), dtype=bool)
    fixed[faces] = True
    fixed[front] = True
    # Graph Laplacian of the mesh's edges; Dirichlet rows at the fixed vertices, harmonic elsewhere. A tiny
    # diagonal keeps a piece that touches no fixed vertex at rest.
    edges = tets[:, [[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]]].reshape(-1, 2)
    n = len(vertices)
    adjacency = coo_matrix((np.ones(len(edges)), (edges[:, 0], edges[:, 1])), shape=(n, n))
    adjacency = ((adjacency + adjacency.T) > 0).astype(np.float64)
    lap = laplacian(adjacency).tocsr()
    free = ~fixed
    system = lap[free][:, free] + 1e-12 * identity(int(free.sum()), format="csr")
    rhs = -lap[free][:, fixed] @ prescribed[fixed]
    displacement = prescribed.copy()
    if free.any():
        displacement[free] = spsolve(system.tocsc(), rhs).reshape(-1, 3)
    return vertices + displacement


def wound_contact_pairs(
    tissue, left: np.ndarray, right: np.ndarray, radius: float, front: np.ndarray | None = None
) -> tuple[np.ndarray, np.ndarray]:
    """The particle-triangle pairs of a wound's contact (``TissueModel.contact_vertex``, ``contact_face``): each
    free particle of one wound face against the boundary triangles of the other face whose centroids lie within
    ``radius`` (m) of it in the rest shape. A face's triangles are those with every corner on it or on the crack
    front ``front`` (where an incision's faces meet; :class:`IncisedMesh` keeps it out of both faces), at least one
    on it; the front's particles, and triangles touching a particle itself, are left out.

    Args:
        tissue: a :class:`~suture_gym.sim.model.TissueModel`.
        left, right: particle indices (or ``(N,)`` bool masks) of the two wound faces (the scenes'
            ``left_wound_face`` and ``right_wound_face`` regions).
        radius: m; a particle is paired with the facing triangles it can reach: a few cells, more than the gap.
        front: particle indices or mask of the crack front (the scenes' ``crack_front`` region); default none.

    Returns:
        ``(contact_vertex (P,) int32, contact_face (P,) int32)``, sorted by particle, then triangle.
    """
    if not radius > 0.0:
        raise ValueError(f"wound_contact_pairs needs radius > 0, got {radius!r}")
    n = tissue.particle_count
    masks = []
    for name, side in (("left", left), ("right", right), ("front", np.zeros(0, np.int64) if front is None else front)):
        side = np.asarray(side)
        mask = side.astype(bool) if side.dtype == bool else np.isin(np.arange(n), side)
        if mask.shape != (n,):
            raise ValueError(f"wound_contact_pairs: {name} must be a ({n},) mask or particle indices")
        masks.append(mask)
    crack = masks[2] | (masks[0] & masks[1])
    tri = tissue.tri_indices
    rest = tissue.particle_rest_q
    vertices, faces = [], []
    for own, other in ((masks[0] & ~crack, masks[1] & ~crack), (masks[1] & ~crack, masks[0] & ~crack)):
        facing = np.flatnonzero((other | crack)[tri].all(axis=1) & other[tri].any(axis=1))
        particles = np.flatnonzero(own & (tissue.particle_inv_mass > 0.0))
        if not (facing.size and particles.size):
            continue
        near = cKDTree(rest[tri[facing]].mean(axis=1)).query_ball_point(rest[particles], radius)
        for particle, hits in zip(particles, near, strict=True):
            for f in facing[np.asarray(hits, dtype=np.int64)]:
                if particle not in tri[f]:
                    vertices.append(particle)
                    faces.append(f)
    order = np.lexsort((np.asarray(faces), np.asarray(vertices))) if vertices else np.zeros(0, np.int64)
    return np.asarray(vertices, np.int32)[order], np.asarray(faces, np.int32)[order]


def with_wound_contact(scene, radius: float | None = None, reach: float | None = None):
    """The tissue ``scene`` (a :class:`~suture_gym.sim.scenes.Scene` without strands, with the regions
    ``left_wound_face`` and ``right_wound_face``, and ``crack_front`` where it has one) with contact between its
    wound's faces
    (:func:`wound_contact_pairs`, :func:`~suture_gym.sim.tissue.project_face_contacts`): the same tissue, state,
    regions and settings; the settings add ``wound_contact`` (pairs, radius, reach).

    Args:
        radius: m, how far apart (rest shape) a particle and a facing triangle are paired; default three mean
            boundary edges plus the widest rest gap between the faces.
        reach: m, ``TissueModel.contact_reach``; default one mean boundary edge.
    """
    from dataclasses import replace

    from suture_gym.sim.model import State, TissueState
    from suture_gym.sim.scenes import Scene

    tissue = scene.model.tissue
    if scene.model.needle is not None:
        raise ValueError("with_wound_contact takes a tissue scene without strands")
    missing = [name for name in ("left_wound_face", "right_wound_face") if name not in scene.regions]
    if missing:
        raise ValueError(f"with_wound_contact needs the scene's wound-face regions; missing {missing}")
    left, right = scene.regions["left_wound_face"], scene.regions["right_wound_face"]
    front = scene.regions.get("crack_front")
    rest = tissue.particle_rest_q
    edge = _mean_edge(rest, tissue.tri_indices)
    if radius is None:
        widest = float(cKDTree(rest[right]).query(rest[left])[0].max()) if len(left) and len(right) else 0.0
        radius = 3.0 * edge + widest
    reach = edge if reach is None else reach
    vertex, face = wound_contact_pairs(tissue, left, right, radius, front)
    rebuilt = replace(tissue, contact_vertex=vertex, contact_face=face, contact_reach=reach)
    state = State(tissue=TissueState.at_rest(rebuilt))
    state.tissue.assign(scene.state.tissue)
    settings = {**scene.settings, "wound_contact": {"pairs": int(vertex.size), "radius_m": radius, "reach_m": reach}}
    return Scene(model=replace(scene.model, tissue=rebuilt), state=state, regions=scene.regions, settings=settings)
