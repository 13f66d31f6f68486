"""Geometric queries of sim/bvh.py and sim/collision.py against brute force and analytic references.

References used here are independent of the code under test: closest distances by plane projection plus
segment distances over all triangles, inside/outside by the generalised winding number (solid angles),
barycentric coordinates by ``np.linalg.solve``, crossings by a direct 3x3 solve per (segment, triangle),
exact signed distances of an axis-aligned box, and ``trimesh.proximity.signed_distance``.
"""

import numpy as np
import pytest
import trimesh
from scipy.spatial import Delaunay

from suture_gym.sim.bvh import aabb_overlap, build_bvh, mesh_aabb, points_aabb, refit_bvh
from suture_gym.sim.collision import (
    FEATURE_EDGE_01,
    FEATURE_EDGE_12,
    FEATURE_EDGE_20,
    FEATURE_FACE,
    FEATURE_VERTEX_0,
    FEATURE_VERTEX_1,
    FEATURE_VERTEX_2,
    LAYER_INSIDE,
    LAYER_OUTSIDE,
    LAYER_RESISTANCE,
    build_triangle_surface,
    classify_layers,
    closest_point_triangle,
    closest_triangles,
    locate_points,
    segment_crossings,
    signed_distance,
)
from suture_gym.sim.mesh import box_tet_grid, surface_triangles

# ---------------------------------------------------------------------------------- references


def _segment_dist(p, a, b):
    """(M,T) distances from points p (M,1,3) to segments a->b (1,T,3)."""
    e = b - a
    ee = np.einsum("...k,...k", e, e)
    t = np.clip(np.einsum("...k,...k", p - a, e) / np.where(ee > 0, ee, 1.0), 0.0, 1.0)
    return np.linalg.norm(a + t[..., None] * e - p, axis=-1)


def brute_distance(points, tris):
    """(M,T) distances from points (M,3) to triangles (T,3,3): to the plane if the projection is inside, else
    to the nearest edge.

    A zero-area triangle has no inside (NaN comparisons are False) and falls back to its edges.
    """
    with np.errstate(divide="ignore", invalid="ignore"):
        return _brute_distance(points, tris)


def _brute_distance(points, tris):
    p = points[:, None, :]
    a, b, c = (tris[None, :, k, :] for k in range(3))
    e1, e2 = b - a, c - a
    d = p - a
    g11, g12, g22 = (np.einsum("...k,...k", x, y) for x, y in ((e1, e1), (e1, e2), (e2, e2)))
    r1, r2 = np.einsum("...k,...k", d, e1), np.einsum("...k,...k", d, e2)
    det = g11 * g22 - g12 * g12
    v = (g22 * r1 - g12 * r2) / det
    w = (g11 * r2 - g12 * r1) / det
    n = np.cross(e1, e2)
    plane = np.abs(np.einsum("...k,...k", d, n)) / np.linalg.norm(n, axis=-1)
    edges = np.minimum(np.minimum(_segment_dist(p, a, b), _segment_dist(p, b, c)), _segment_dist(p, c, a))
    return np.where((v >= 0) & (w >= 0) & (v + w <= 1), plane, edges)


def winding_number(points, tris):
    """Generalised winding number of a closed surface at each point (1 inside, 0 outside)."""
    a, b, c = (tris[None, :, k, :] - points[:, None, :] for k in range(3))
    la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
    num = np.einsum("...k,...k", a, np.cross(b, c))
    den = la * lb * lc + np.einsum("...k,...k", a, b) * lc + np.einsum("...k,...k", b, c) * la
    den += np.einsum("...k,...k", c, a) * lb
    return (2.0 * np.arctan2(num, den)).sum(axis=1) / (4.0 * np.pi)


def box_sdf(points, half):
    d = np.abs(points) - half
    return np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)


def smooth_deformation(q, rng, amplitude, wavenumber):
    """x + u(x) with |grad u| < 1 (injective): a closed surface stays closed and free of self-intersection."""
    phase = rng.uniform(0, 2 * np.pi, (3, 3))
    u = np.zeros_like(q)
    for j in range(3):
        for k in range(3):
            if k != j:
                u[:, j] += amplitude * np.sin(wavenumber * q[:, k] + phase[j, k])
    return q + u


def near_surface_points(q, tris, rng, n, spread):
    t = rng.integers(0, len(tris), n)
    bary = rng.dirichlet(np.ones(3), n)
    base = np.einsum("mk,mkj->mj", bary, q[tris[t]])
    return base + rng.normal(size=(n, 3)) * spread


@pytest.fixture(scope="module")
def sphere():
    mesh = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    return np.array(mesh.vertices, dtype=np.float64), np.array(mesh.faces, dtype=np.int64)


@pytest.fixture(scope="module")
def deformed_sphere(sphere):
    q0, faces = sphere
    q = smooth_deformation(q0, np.random.default_rng(7), amplitude=0.002, wavenumber=100.0)
    return q0, q, faces


# ---------------------------------------------------------------------------------- AABB


def test_aabb_helpers():
    rng = np.random.default_rng(0)
    p = rng.normal(size=(50, 3))
    lo, hi = points_aabb(p)
    np.testing.assert_array_equal(lo, p.min(axis=0))
    np.testing.assert_array_equal(hi, p.max(axis=0))
    elements = np.array([[0, 1, 2], [2, 3, 4]])
    lo, hi = mesh_aabb(elements, p)
    np.testing.assert_array_equal(lo, p[:5].min(axis=0))
    np.testing.assert_array_equal(hi, p[:5].max(axis=0))
    a_lo, a_hi = np.zeros(3), np.ones(3)
    assert aabb_overlap(a_lo, a_hi, a_lo + 0.5, a_hi + 0.5, 0.0)
    assert aabb_overlap(a_lo, a_hi, a_lo + 1.0, a_hi + 1.0, 0.0)  # touching corner
    far_lo = np.array([1.1, 0.0, 0.0])
    assert not aabb_overlap(a_lo, a_hi, far_lo, far_lo + 1.0, 0.0)
    assert aabb_overlap(a_lo, a_hi, far_lo, far_lo + 1.0, 0.1 + 1e-12)
    assert not aabb_overlap(a_lo, a_hi, far_lo, far_lo + 1.0, 0.09)


def test_refit_matches_rebuild_and_boxes_are_tight(deformed_sphere):
    q0, q, faces = deformed_sphere
    refitted = build_bvh(faces, q0, leaf_size=4)
    refit_bvh(refitted, q)
    for node in range(len(refitted.node_child)):
        members = refitted.sorted_element[
            refitted.node_first[node] : refitted.node_first[node] + refitted.node_count[node]
        ]
        xs = q[faces[members].ravel()]
        np.testing.assert_array_equal(refitted.node_lo[node], xs.min(axis=0))
        np.testing.assert_array_equal(refitted.node_hi[node], xs.max(axis=0))
        left, right = refitted.node_child[node]
        if left >= 0:
            assert left > node and right > node
            assert refitted.node_count[left] + refitted.node_count[right] == refitted.node_count[node]
    counts = refitted.node_count[refitted.node_child[:, 0] < 0]
    assert counts.sum() == len(faces) and counts.max() <= 4
    np.testing.assert_array_equal(np.sort(refitted.sorted_element), np.arange(len(faces)))

    # Queries through the refitted and a freshly built hierarchy agree bit for bit.
    surf_refit = build_triangle_surface(faces, q0)
    refit_bvh(surf_refit.bvh, q)
    surf_fresh = build_triangle_surface(faces, q)
    pts = near_surface_points(q, faces, np.random.default_rng(1), 300, 0.003)
    for a, b in zip(signed_distance(pts, surf_refit, q), signed_distance(pts, surf_fresh, q), strict=True):
        np.testing.assert_array_equal(a, b)


# ---------------------------------------------------------------------------------- closest point


def test_closest_point_triangle_against_brute_force():
    rng = np.random.default_rng(2)
    codes_seen = set()
    for _ in range(400):
        a, b, c = rng.normal(size=(3, 3))
        p = rng.normal(size=3) * 2.0
        point, bary, feature = closest_point_triangle(p, a, b, c)
        codes_seen.add(int(feature))
        ref = brute_distance(p[None], np.array([[a, b, c]]))[0, 0]
        assert abs(np.linalg.norm(point - p) - ref) <= 1e-12 * (1 + ref)
        np.testing.assert_allclose(point, bary[0] * a + bary[1] * b + bary[2] * c, atol=1e-12)
        assert np.all(bary >= 0) and abs(bary.sum() - 1) < 1e-12
        if feature == FEATURE_FACE:
            assert np.all(bary > 0)
        elif feature in (FEATURE_VERTEX_0, FEATURE_VERTEX_1, FEATURE_VERTEX_2):
            assert bary[feature - FEATURE_VERTEX_0] == 1.0
        else:
            opposite = {FEATURE_EDGE_01: 2, FEATURE_EDGE_12: 0, FEATURE_EDGE_20: 1}[int(feature)]
            assert bary[opposite] == 0.0 and np.count_nonzero(bary) == 2
    assert codes_seen == set(range(7))


@pytest.mark.parametrize(
    "tri",
    [
        [[0, 0, 0], [1, 0, 0], [2, 0, 0]],  # collinear
        [[0, 0, 0], [0, 0, 0], [1, 1, 0]],  # two coincident vertices
        [[0.3, 0.1, 0.2]] * 3,  # a single point
        [[0, 0, 0], [1, 0, 0], [0.5, 1e-15, 0]],  # sliver below the degeneracy threshold
    ],
)
def test_closest_point_degenerate_triangle_is_finite(tri):
    a, b, c = np.array(tri, dtype=np.float64)
    rng = np.random.default_rng(3)
    for p in rng.normal(size=(50, 3)):
        point, bary, feature = closest_point_triangle(p, a, b, c)
        assert np.all(np.isfinite(point)) and np.all(np.isfinite(bary))
        ref = min(_segment_dist(p[None], x[None], y[None])[0] for x, y in ((a, b), (b, c), (c, a)))
        assert abs(np.linalg.norm(point - p) - ref) <= 1e-12
        assert feature != FEATURE_FACE


# ---------------------------------------------------------------------------------- signed distance


def test_signed_distance_box_edges_and_corners_exact():
    half = np.array([0.03, 0.02, 0.01])
    mesh = trimesh.creation.box(extents=2 * half).subdivide().subdivide()
    q, faces = np.array(mesh.vertices), np.array(mesh.faces)
    surface = build_triangle_surface(faces, q)
    rng = np.random.default_rng(4)
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=float)
    corners = signs * half
    edge_points = []
    for axis in range(3):
        for s in signs:
            e = s * half
            e[axis] = rng.uniform(-0.9, 0.9) * half[axis]
            edge_points.append(e)
    anchors = np.vstack([corners, np.array(edge_points)])
    pts = []
    for scale in (1e-7, 1e-4, 3e-3):
        dirs = rng.normal(size=(len(anchors), 20, 3))
        pts.append((anchors[:, None, :] + scale * dirs).reshape(-1, 3))
    # Bisector planes: outside points equidistant to two faces, inside points equidistant to two or three.
    for c, s in zip(corners, signs, strict=True):
        pts.append([c + 1e-3 * s * np.array([1, 1, 0]), c - 1e-3 * s * np.array([1, 1, 1])])
    pts.append(rng.uniform(-1.5, 1.5, (200, 3)) * half)
    pts = np.vstack(pts)
    sdist, tri, bary = signed_distance(pts, surface, q)
    ref = box_sdf(pts, half)
    np.testing.assert_allclose(sdist, ref, rtol=0, atol=1e-12)
    assert np.all(np.sign(sdist[np.abs(ref) > 1e-12]) == np.sign(ref[np.abs(ref) > 1e-12]))
    closest = np.einsum("mk,mkj->mj", bary, q[faces[tri]])
    np.testing.assert_allclose(np.linalg.norm(pts - closest, axis=1), np.abs(ref), atol=1e-12)


def test_signed_distance_gradient_matches_finite_differences():
    # Outside a convex surface the distance is C1 with gradient (p - c) / s, c the reported closest point.
    half = np.array([0.03, 0.02, 0.01])
    mesh = trimesh.creation.box(extents=2 * half).subdivide()
    q, faces = np.array(mesh.vertices), np.array(mesh.faces)
    surface = build_triangle_surface(faces, q)
    rng = np.random.default_rng(16)
    pts = rng.uniform(-1.5, 1.5, (400, 3)) * half
    sdist, tri, bary = signed_distance(pts, surface, q)
    pts, sdist, tri, bary = pts[sdist > 1e-3], sdist[sdist > 1e-3], tri[sdist > 1e-3], bary[sdist > 1e-3]
    assert len(pts) > 100
    closest = np.einsum("mk,mkj->mj", bary, q[faces[tri]])
    h = 1e-7
    fd = np.empty_like(pts)
    for j in range(3):
        step = np.zeros(3)
        step[j] = h
        fd[:, j] = (
            signed_distance(pts + step, surface, q)[0] - signed_distance(pts - step, surface, q)[0]
        ) / (2 * h)
    np.testing.assert_allclose(fd, (pts - closest) / sdist[:, None], atol=1e-6)


def test_signed_distance_deformed_mesh_against_brute_force_and_winding(deformed_sphere):
    q0, q, faces = deformed_sphere
    surface = build_triangle_surface(faces, q0)
    refit_bvh(surface.bvh, q)
    rng = np.random.default_rng(5)
    pts = np.vstack([near_surface_points(q, faces, rng, 400, 0.002), rng.uniform(-0.03, 0.03, (200, 3))])
    sdist, tri, bary = signed_distance(pts, surface, q)
    dist = brute_distance(pts, q[faces])
    np.testing.assert_allclose(np.abs(sdist), dist.min(axis=1), rtol=1e-12, atol=1e-15)
    np.testing.assert_allclose(dist[np.arange(len(pts)), tri], dist.min(axis=1), rtol=1e-12, atol=1e-15)
    inside = winding_number(pts, q[faces]) > 0.5
    assert np.array_equal(sdist < 0, inside)
    assert np.all(bary >= 0) and np.allclose(bary.sum(axis=1), 1.0)


def test_signed_distance_sign_at_sharp_edges_and_spikes():
    # A star-shaped surface (every vertex moved radially by a random factor in [0.4, 1.6]) is closed and free
    # of self-intersection but has sharp convex and concave edges and vertices, where the face normal of the
    # closest triangle can give the wrong sign and only the pseudo-normal is right. Points cluster at vertices
    # and edges.
    mesh = trimesh.creation.icosphere(subdivisions=1, radius=0.02)
    rng = np.random.default_rng(17)
    q = np.array(mesh.vertices) * rng.uniform(0.4, 1.6, (len(mesh.vertices), 1))
    faces = np.array(mesh.faces)
    surface = build_triangle_surface(faces, q)
    edges = np.array(mesh.edges_unique)
    anchors = np.vstack([q, q[edges].mean(axis=1)])
    pts = (anchors[:, None, :] + rng.normal(size=(len(anchors), 8, 3)) * 2e-3).reshape(-1, 3)
    sdist, _, _ = signed_distance(pts, surface, q)
    np.testing.assert_allclose(
        np.abs(sdist), brute_distance(pts, q[faces]).min(axis=1), rtol=1e-12, atol=1e-16
    )
    inside = winding_number(pts, q[faces]) > 0.5
    assert inside.sum() > 200 and (~inside).sum() > 200
    np.testing.assert_array_equal(sdist < 0, inside)


def test_signed_distance_agrees_with_trimesh(deformed_sphere):
    # Compared at unit scale: trimesh resolves near-ties between candidate faces with an absolute tolerance
    # (tol.merge) that picks a farther face for millimetre-scale meshes (errors ~1e-6 m at radius 2 cm, while
    # the brute-force test above confirms our distances there).
    q0, q, faces = deformed_sphere
    rng = np.random.default_rng(6)
    for verts in (q0 / 0.02, q / 0.02):
        surface = build_triangle_surface(faces, verts)
        pts = np.vstack([near_surface_points(verts, faces, rng, 150, 0.1), rng.uniform(-1.25, 1.25, (50, 3))])
        sdist, _, _ = signed_distance(pts, surface, verts)
        theirs = trimesh.proximity.signed_distance(trimesh.Trimesh(verts, faces, process=False), pts)
        assert (sdist < 0).sum() > 50 and (sdist > 0).sum() > 50
        np.testing.assert_allclose(sdist, -theirs, rtol=0, atol=1e-12)  # trimesh: positive inside


def test_signed_distance_is_one_lipschitz(deformed_sphere):
    q0, q, faces = deformed_sphere
    surface = build_triangle_surface(faces, q)
    rng = np.random.default_rng(8)
    a = near_surface_points(q, faces, rng, 500, 0.001)
    b = a + rng.normal(size=a.shape) * 0.001
    sa, _, _ = signed_distance(a, surface, q)
    sb, _, _ = signed_distance(b, surface, q)
    assert np.all(np.abs(sa - sb) <= np.linalg.norm(a - b, axis=1) * (1 + 1e-12) + 1e-15)
    assert np.any(np.sign(sa) != np.sign(sb))  # the pairs do straddle the surface


def test_two_separate_components_and_layers():
    a = trimesh.creation.box(extents=(0.04, 0.02, 0.02))
    b = a.copy()
    b.apply_translation([0.0, 0.03, 0.0])
    q = np.vstack([a.vertices, b.vertices])
    faces = np.vstack([a.faces, b.faces + len(a.vertices)])
    surface = build_triangle_surface(faces, q)
    pts = np.array([[0, 0, 0], [0, 0.03, 0], [0, 0.015, 0], [0, 0.012, 0], [0, 0.0195, 0], [0, 0.01, 0]])
    sdist, _, _ = signed_distance(pts, surface, q)
    np.testing.assert_allclose(sdist, [-0.01, -0.01, 0.005, 0.002, 0.0005, 0.0], atol=1e-15)
    layers = classify_layers(sdist, eps=0.001)
    assert layers.tolist() == [
        LAYER_INSIDE,
        LAYER_INSIDE,
        LAYER_OUTSIDE,
        LAYER_OUTSIDE,
        LAYER_RESISTANCE,
        LAYER_RESISTANCE,
    ]


def test_classify_layers_boundaries_and_errors():
    eps = 1e-3
    s = np.array([-1e-12, 0.0, 0.5e-3, 1e-3, 2e-3])
    assert classify_layers(s, eps).tolist() == [
        LAYER_INSIDE,
        LAYER_RESISTANCE,
        LAYER_RESISTANCE,
        LAYER_OUTSIDE,
        LAYER_OUTSIDE,
    ]
    for bad in (0.0, -1e-3, np.nan, np.inf):
        with pytest.raises(ValueError, match="eps"):
            classify_layers(s, bad)
    with pytest.raises(ValueError, match="NaN"):
        classify_layers(np.array([0.0, np.nan]), eps)


def test_closest_triangles_within_max_distance(deformed_sphere):
    q0, q, faces = deformed_sphere
    surface = build_triangle_surface(faces, q)
    rng = np.random.default_rng(9)
    pts = np.vstack([near_surface_points(q, faces, rng, 200, 0.003), [[0.5, 0.5, 0.5]]])
    max_distance = 0.002
    tri, bary, dist = closest_triangles(pts, surface, q, max_distance)
    ref = brute_distance(pts, q[faces]).min(axis=1)
    within = ref <= max_distance
    assert within.sum() > 50 and (~within).sum() > 20
    np.testing.assert_array_equal(tri < 0, ~within)
    np.testing.assert_allclose(dist[within], ref[within], rtol=1e-12)
    assert np.all(np.isinf(dist[~within])) and np.all(bary[~within] == 0)
    _, tri_all, _ = signed_distance(pts[within], surface, q)
    np.testing.assert_array_equal(tri[within], tri_all)
    with pytest.raises(ValueError, match="max_distance"):
        closest_triangles(pts, surface, q, -1.0)


# ---------------------------------------------------------------------------------- point location


def _brute_locate(points, tets, q, tol):
    x = q[tets]
    mats = np.transpose(x[:, 1:] - x[:, :1], (0, 2, 1))  # (K,3,3) columns x1-x0, x2-x0, x3-x0
    lam = np.linalg.solve(mats[None], (points[:, None, :] - x[None, :, 0])[..., None])[..., 0]
    bary = np.concatenate([1 - lam.sum(axis=-1, keepdims=True), lam], axis=-1)  # (M,K,4)
    score = bary.min(axis=-1)
    best = np.argmax(score, axis=1)  # lowest index among ties
    found = score[np.arange(len(points)), best] >= -tol
    return np.where(found, best, -1), bary[np.arange(len(points)), best]


def test_locate_points_against_brute_force():
    rng = np.random.default_rng(10)
    q0 = rng.uniform(0, 0.02, (80, 3))
    tets = Delaunay(q0).simplices
    pts = rng.uniform(-0.002, 0.022, (400, 3))
    bvh = build_bvh(tets, q0)
    tet, bary = locate_points(pts, bvh, q0)
    inside = Delaunay(q0).find_simplex(pts) >= 0
    np.testing.assert_array_equal(tet >= 0, inside)
    assert inside.sum() > 100 and (~inside).sum() > 50

    q = smooth_deformation(q0, rng, amplitude=0.0005, wavenumber=150.0)
    refit_bvh(bvh, q)
    tet, bary = locate_points(pts, bvh, q)
    ref_tet, ref_bary = _brute_locate(pts, tets, q, 1e-9)
    np.testing.assert_array_equal(tet, ref_tet)
    found = tet >= 0
    np.testing.assert_allclose(bary[found], ref_bary[found], atol=1e-9)
    np.testing.assert_allclose(
        np.einsum("mk,mkj->mj", bary[found], q[tets[tet[found]]]), pts[found], atol=1e-15
    )
    assert np.all(bary[~found] == 0)


def test_locate_points_on_vertices_and_faces():
    rng = np.random.default_rng(11)
    q = rng.uniform(0, 1, (40, 3))
    tets = Delaunay(q).simplices
    bvh = build_bvh(tets, q, leaf_size=2)
    face_points = q[tets[:, :3]].mean(axis=1)  # on a face, shared or on the hull
    tet, bary = locate_points(np.vstack([q, face_points]), bvh, q)
    assert np.all(tet >= 0)
    assert np.all(bary.min(axis=1) >= -1e-9)


# ---------------------------------------------------------------------------------- crossings


def _brute_crossings(a, b, q, faces):
    hits = {}
    x = q[faces]
    d = b - a
    for s in range(len(a)):
        mats = np.stack(
            [-np.broadcast_to(d[s], (len(faces), 3)), x[:, 1] - x[:, 0], x[:, 2] - x[:, 0]], axis=2
        )
        sol = np.linalg.solve(mats, (a[s] - x[:, 0])[..., None])[..., 0]
        t, u, v = sol.T
        ok = (t >= 0) & (t <= 1) & (u >= 0) & (v >= 0) & (u + v <= 1)
        for f in np.flatnonzero(ok):
            hits[(s, int(f))] = (t[f], np.array([1 - u[f] - v[f], u[f], v[f]]))
    return hits


def test_signed_distance_box_margin_skips_only_points_outside_the_box(deformed_sphere):
    q0, q, faces = deformed_sphere
    surface = build_triangle_surface(faces, q0)
    refit_bvh(surface.bvh, q)
    rng = np.random.default_rng(8)
    pts = np.vstack([near_surface_points(q, faces, rng, 100, 0.002), rng.uniform(-0.05, 0.05, (300, 3))])
    margin = 0.004
    lo, hi = q.min(axis=0) - margin, q.max(axis=0) + margin
    near = np.all((pts >= lo) & (pts <= hi), axis=1)
    assert 100 < near.sum() < len(pts)  # both kinds present
    full = signed_distance(pts, surface, q)
    sdist, tri, bary = signed_distance(pts, surface, q, box_margin=margin)
    assert np.array_equal(sdist[near], full[0][near]) and np.array_equal(tri[near], full[1][near])
    assert np.array_equal(bary[near], full[2][near])
    assert np.all(np.isposinf(sdist[~near])) and np.all(tri[~near] == -1) and np.all(bary[~near] == 0.0)
    with pytest.raises(ValueError, match="box_margin"):
        signed_distance(pts, surface, q, box_margin=-1.0)


def test_segment_crossings_against_brute_force(deformed_sphere):
    q0, q, faces = deformed_sphere
    surface = build_triangle_surface(faces, q0)
    refit_bvh(surface.bvh, q)
    rng = np.random.default_rng(12)
    a = near_surface_points(q, faces, rng, 300, 0.003)
    b = a + rng.normal(size=a.shape) * 0.004
    got = segment_crossings(a, b, surface, q)
    ref = _brute_crossings(a, b, q, faces)
    assert len(ref) > 60
    unchecked = segment_crossings(a, b, surface, q, check_finite=False)  # the solver's path: same crossings
    for name in ("crossing_segment", "crossing_tri", "crossing_bary", "crossing_t", "crossing_q", "crossing_direction"):
        assert np.array_equal(getattr(unchecked, name), getattr(got, name)), name
    assert set(zip(got.crossing_segment.tolist(), got.crossing_tri.tolist(), strict=True)) == set(ref)
    for s, f, t, bary in zip(
        got.crossing_segment, got.crossing_tri, got.crossing_t, got.crossing_bary, strict=True
    ):
        rt, rbary = ref[(s, f)]
        assert abs(t - rt) < 1e-9
        np.testing.assert_allclose(bary, rbary, atol=1e-9)
    np.testing.assert_allclose(
        got.crossing_q, np.einsum("hk,hkj->hj", got.crossing_bary, q[faces[got.crossing_tri]]), atol=1e-12
    )
    # Parity and direction against inside/outside of the end points.
    inside_a = winding_number(a, q[faces]) > 0.5
    inside_b = winding_number(b, q[faces]) > 0.5
    n_cross = np.bincount(got.crossing_segment, minlength=len(a))
    np.testing.assert_array_equal(n_cross % 2 == 1, inside_a != inside_b)
    order_ok = np.all(np.diff(got.crossing_segment) >= 0)
    assert order_ok
    first = np.r_[True, np.diff(got.crossing_segment) > 0]
    expected_first = np.where(inside_a[got.crossing_segment[first]], 1, -1)
    np.testing.assert_array_equal(got.crossing_direction[first], expected_first)


def test_segment_through_shared_edges_is_reported_once():
    # Power-of-two sizes make every edge midpoint exact, so the edge volumes of the shared edge are exactly 0
    # and only the tie rule decides which of the two triangles reports the crossing.
    h = 2.0**-6  # m
    mesh = trimesh.creation.box(extents=(4 * h, 4 * h, 2 * h)).subdivide().subdivide()
    q, faces = np.array(mesh.vertices), np.array(mesh.faces)
    surface = build_triangle_surface(faces, q)
    edges = np.array(mesh.edges_unique)
    top = np.all(q[edges][:, :, 2] == h, axis=1)
    mid = q[edges[top]].mean(axis=1)
    interior = (np.abs(mid[:, 0]) < 2 * h) & (np.abs(mid[:, 1]) < 2 * h)
    mid = mid[interior]
    assert len(mid) > 20
    start = mid + [0, 0, h]
    end = mid - [0, 0, 3 * h]
    got = segment_crossings(start, end, surface, q)
    np.testing.assert_array_equal(np.bincount(got.crossing_segment, minlength=len(mid)), 2)
    first = got.crossing_direction[0::2]
    second = got.crossing_direction[1::2]
    assert np.all(first == -1) and np.all(second == 1)
    np.testing.assert_allclose(got.crossing_t[0::2], 0.25, atol=1e-15)
    np.testing.assert_allclose(got.crossing_t[1::2], 0.75, atol=1e-15)
    assert np.all(np.min(got.crossing_bary[0::2], axis=1) == 0.0)  # the top hit lies on an edge


def test_polyline_touching_the_surface_counts_consistently():
    mesh = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    q, faces = np.array(mesh.vertices), np.array(mesh.faces)
    surface = build_triangle_surface(faces, q)
    # A polyline from outside through a node lying exactly on the top face (z = 0.01) and back out.
    nodes = np.array([[0.002, 0.003, 0.02], [0.002, 0.003, 0.01], [0.004, 0.003, 0.02]])
    got = segment_crossings(nodes[:-1], nodes[1:], surface, q)
    assert len(got.crossing_segment) % 2 == 0
    # Passing through the plane at a node: counted exactly once.
    nodes = np.array([[0.002, 0.003, 0.02], [0.002, 0.003, 0.01], [0.002, 0.003, 0.0]])
    got = segment_crossings(nodes[:-1], nodes[1:], surface, q)
    assert len(got.crossing_segment) == 1 and got.crossing_direction[0] == -1


# ---------------------------------------------------------------------------------- degenerate / errors


def test_degenerate_elements_never_produce_nan(sphere):
    q0, faces = sphere
    q = q0.copy()
    v = faces[0, 0]
    q[faces[0, 1]] = q[v]  # collapse an edge: every triangle on that edge has zero area
    surface = build_triangle_surface(faces, q)
    rng = np.random.default_rng(13)
    pts = np.vstack([q[v] + rng.normal(size=(100, 3)) * 1e-3, near_surface_points(q, faces, rng, 100, 0.002)])
    sdist, tri, bary = signed_distance(pts, surface, q)
    assert np.all(np.isfinite(sdist)) and np.all(np.isfinite(bary)) and np.all(tri >= 0)
    np.testing.assert_allclose(np.abs(sdist), brute_distance(pts, q[faces]).min(axis=1), atol=1e-12)
    far = np.abs(sdist) > 2e-4  # away from the collapsed corner the sign is still right
    inside = winding_number(pts, q[faces]) > 0.5
    np.testing.assert_array_equal((sdist < 0)[far], inside[far])
    crossings = segment_crossings(pts, pts[::-1].copy(), surface, q)
    assert np.all(np.isfinite(crossings.crossing_bary)) and np.all(np.isfinite(crossings.crossing_t))

    tq = rng.uniform(0, 1, (30, 3))
    tets = Delaunay(tq).simplices
    tq[tets[0, 3]] = tq[tets[0, :3]].mean(axis=0)  # flatten one tet
    bvh = build_bvh(tets, tq)
    tet, tbary = locate_points(rng.uniform(0, 1, (200, 3)), bvh, tq)
    assert np.all(np.isfinite(tbary)) and not np.any(tet == 0)


def test_invalid_inputs_raise_value_error(sphere):
    q, faces = sphere
    with pytest.raises(ValueError, match="vertex_q"):
        build_triangle_surface(faces, q[:, :2])
    with pytest.raises(ValueError, match="element_vertices row"):
        build_triangle_surface(np.vstack([faces, [[0, 1, len(q)]]]), q)
    with pytest.raises(ValueError, match="repeats a vertex"):
        build_triangle_surface(np.vstack([faces, [[0, 0, 1]]]), q)
    with pytest.raises(ValueError, match="non-manifold"):
        build_triangle_surface(np.vstack([faces, faces[:1][:, ::-1], faces[:1]]), q)
    with pytest.raises(ValueError, match="inconsistent orientation"):
        build_triangle_surface(np.vstack([faces[:-1], faces[-1:, ::-1]]), q)
    surface = build_triangle_surface(faces, q)
    bad = q.copy()
    bad[5, 1] = np.nan
    with pytest.raises(ValueError, match="vertex_q row 5"):
        refit_bvh(surface.bvh, bad)
    with pytest.raises(ValueError, match="rows"):
        signed_distance(np.zeros((1, 3)), surface, q[:-1])
    with pytest.raises(ValueError, match="points row 1"):
        signed_distance(np.array([[0.0, 0, 0], [np.inf, 0, 0]]), surface, q)
    with pytest.raises(ValueError, match="points must have shape"):
        signed_distance(np.zeros(3), surface, q)
    with pytest.raises(ValueError, match="tet_bvh"):
        locate_points(np.zeros((1, 3)), surface.bvh, q)
    with pytest.raises(ValueError, match="same shape"):
        segment_crossings(np.zeros((2, 3)), np.zeros((3, 3)), surface, q)
    with pytest.raises(ValueError, match="leaf_size"):
        build_bvh(faces, q, leaf_size=0)
    with pytest.raises(ValueError, match="empty"):
        build_bvh(np.zeros((0, 3), np.int64), q)


def test_empty_queries_return_empty_arrays(sphere):
    q, faces = sphere
    surface = build_triangle_surface(faces, q)
    sdist, tri, bary = signed_distance(np.zeros((0, 3)), surface, q)
    assert sdist.shape == (0,) and tri.shape == (0,) and bary.shape == (0, 3)
    got = segment_crossings(np.zeros((0, 3)), np.zeros((0, 3)), surface, q)
    assert got.crossing_q.shape == (0, 3)
    far = np.full((4, 3), 10.0)  # segments that cross nothing
    got = segment_crossings(far, far + 1.0, surface, q, check_finite=False)
    assert got.crossing_segment.shape == (0,) and got.crossing_bary.shape == (0, 3) and got.crossing_q.shape == (0, 3)


def test_determinism_bit_identical(deformed_sphere):
    q0, q, faces = deformed_sphere
    rng = np.random.default_rng(14)
    pts = near_surface_points(q, faces, rng, 200, 0.003)
    runs = []
    for _ in range(2):
        surface = build_triangle_surface(faces, q0)
        refit_bvh(surface.bvh, q)
        out = signed_distance(pts, surface, q)
        cross = segment_crossings(pts[:-1], pts[1:], surface, q)
        runs.append(
            [*out, surface.bvh.node_lo, surface.bvh.sorted_element, cross.crossing_bary, cross.crossing_tri]
        )
    for a, b in zip(*runs, strict=True):
        assert a.dtype == b.dtype and a.tobytes() == b.tobytes()


# ---------------------------------------------------------------------------------- tet grids


@pytest.mark.parametrize("scheme", ["five", "six"])
def test_box_tet_grid_surface_and_point_location(scheme):
    size = np.array([0.03, 0.02, 0.01])
    grid = box_tet_grid(size, (6, 4, 2), origin=-size / 2, scheme=scheme)
    q0, tets = np.array(grid.vertices), np.array(grid.tets)
    surface = build_triangle_surface(surface_triangles(tets), q0)
    rng = np.random.default_rng(15)
    pts = rng.uniform(-0.7, 0.7, (300, 3)) * size
    sdist, _, _ = signed_distance(pts, surface, q0)
    np.testing.assert_allclose(sdist, box_sdf(pts, size / 2), atol=1e-12)

    bvh = build_bvh(tets, q0)
    tet, bary = locate_points(pts, bvh, q0)
    inside = np.all(np.abs(pts) < size / 2, axis=1)
    np.testing.assert_array_equal(tet >= 0, inside)
    np.testing.assert_allclose(
        np.einsum("mk,mkj->mj", bary[inside], q0[tets[tet[inside]]]), pts[inside], atol=1e-15
    )

    q = smooth_deformation(q0, rng, amplitude=0.0005, wavenumber=200.0)
    refit_bvh(bvh, q)
    tet, bary = locate_points(pts, bvh, q)
    ref_tet, ref_bary = _brute_locate(pts, tets, q, 1e-9)
    np.testing.assert_array_equal(tet, ref_tet)
    np.testing.assert_allclose(bary[tet >= 0], ref_bary[tet >= 0], atol=1e-9)
    refit_bvh(surface.bvh, q)
    sdist, _, _ = signed_distance(pts, surface, q)
    tris = q[surface.tri_vertices]
    np.testing.assert_array_equal(sdist < 0, winding_number(pts, tris) > 0.5)
    np.testing.assert_array_equal(sdist < 0, tet >= 0)  # inside the surface <=> inside some tet
