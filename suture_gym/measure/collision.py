"""Checks and benchmark of the needle/suture-tissue geometric queries (:mod:`suture_gym.sim.collision`).

Scene: the paper's two-bar wound at its Table 1 row 1 scale (6,840 tets, 2,000 vertices, 2,264 triangles):
two 85 x 35 x 30 mm bars of 17 x 7 x 6 five-tet cells (7,140 tets, 2,016 vertices, 2,104 surface triangles)
side by side with a 4 mm gap, and a 230-node strand (30-node semicircular needle of radius 8 mm through both
wound edges + 200-node suture trailing along the top surface, half of it just inside, half in the resistance
layer or outside).

Benchmark ``collision_paper_cube``: per substep, refit the surface BVH, signed distance of all 230 nodes,
refit the tet BVH and locate 10 needle nodes in the tets, while the tissue is pressed and the strand slides.
The same signed-distance query is also timed with three alternatives (surface BVH rebuilt every substep;
scipy cKDTree over triangle centroids rebuilt every substep with an exact two-stage query; brute force over
all triangles), and their answers are compared with the BVH's.
"""

from __future__ import annotations

import dataclasses
import time

import numpy as np
from numba import njit
from scipy.spatial import cKDTree

from suture_gym.measure.registry import CheckResult, benchmark, check
from suture_gym.sim.bvh import build_bvh, refit_bvh
from suture_gym.sim.collision import (
    _closest_bary,
    _pseudo_normal,
    build_triangle_surface,
    locate_points,
    segment_crossings,
    signed_distance,
)
from suture_gym.sim.mesh import box_tet_grid, surface_triangles

BAR_SIZE = (0.085, 0.035, 0.03)  # m
BAR_CELLS = (17, 7, 6)
WOUND_GAP = 0.004  # m, between the bars along y
NEEDLE_NODES = 30
SUTURE_NODES = 200
NEEDLE_RADIUS = 0.008  # m
LOCATED_NODES = slice(10, 20)  # needle nodes located in the tets each substep
DT = 1e-3  # s, substep of the scripted motion


def _two_bar_scene() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(vertex_q (N,3) m, tets (K,4), surface triangles (T,3)) of the two bars."""
    a = box_tet_grid(BAR_SIZE, BAR_CELLS)
    b = box_tet_grid(BAR_SIZE, BAR_CELLS, origin=(0.0, BAR_SIZE[1] + WOUND_GAP, 0.0))
    q = np.vstack([a.vertices, b.vertices])
    tets = np.vstack([a.tets, b.tets + a.vertex_count]).astype(np.int32)
    return q, tets, surface_triangles(tets)


def _pressed_tissue(q0: np.ndarray, time_s: float) -> np.ndarray:
    """Tissue pressed down near the wound by up to 2 mm plus a 0.3 mm lateral sway, at time ``time_s``."""
    centre = np.array([0.5 * BAR_SIZE[0], BAR_SIZE[1] + 0.5 * WOUND_GAP])
    r2 = ((q0[:, :2] - centre) ** 2).sum(axis=1)
    depth = 0.002 * (0.5 + 0.5 * np.sin(2 * np.pi * 2.0 * time_s))
    q = q0.copy()
    q[:, 2] -= depth * np.exp(-r2 / 0.02**2) * (q0[:, 2] / BAR_SIZE[2])
    q[:, 1] += 0.0003 * np.sin(2 * np.pi * 1.0 * time_s + 60.0 * q0[:, 0])
    return q


def _strand(time_s: float) -> np.ndarray:
    """(230, 3) strand nodes at time ``time_s``: needle arc through both wound edges, then the suture."""
    top = BAR_SIZE[2]
    x_needle = 0.04 + 0.01 * np.sin(2 * np.pi * 0.5 * time_s)
    y_mid = BAR_SIZE[1] + 0.5 * WOUND_GAP
    theta = np.linspace(0.0, np.pi, NEEDLE_NODES)
    needle = np.column_stack(
        [
            np.full(NEEDLE_NODES, x_needle),
            y_mid + NEEDLE_RADIUS * np.cos(theta),
            top + 0.001 - NEEDLE_RADIUS * np.sin(theta),
        ]
    )
    s = np.linspace(0.0, 1.0, SUTURE_NODES + 1)[1:]
    suture = np.column_stack(
        [
            x_needle - 0.035 * s,
            needle[0, 1] + 0.01 * np.sin(3 * np.pi * s),
            top + 0.001 + 0.003 * np.sin(8 * np.pi * s + time_s),
        ]
    )
    return np.vstack([needle, suture])


@njit(cache=True)
def _candidate_signed_distance(
    points,
    cand_start,
    cand_index,
    tri_vertices,
    tri_neighbors,
    vertex_tri_start,
    vertex_tri_index,
    vertex_q,
    out_sdist,
):
    """Signed distance from each point to the closest of its candidate triangles (CSR lists)."""
    for i in range(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        best = np.inf
        best_tri = -1
        bf = 0
        sx = 0.0
        sy = 0.0
        sz = 0.0
        for s in range(cand_start[i], cand_start[i + 1]):
            t = cand_index[s]
            a = tri_vertices[t, 0]
            b = tri_vertices[t, 1]
            c = tri_vertices[t, 2]
            u, v, w, f = _closest_bary(
                px,
                py,
                pz,
                vertex_q[a, 0],
                vertex_q[a, 1],
                vertex_q[a, 2],
                vertex_q[b, 0],
                vertex_q[b, 1],
                vertex_q[b, 2],
                vertex_q[c, 0],
                vertex_q[c, 1],
                vertex_q[c, 2],
            )
            dx = u * vertex_q[a, 0] + v * vertex_q[b, 0] + w * vertex_q[c, 0] - px
            dy = u * vertex_q[a, 1] + v * vertex_q[b, 1] + w * vertex_q[c, 1] - py
            dz = u * vertex_q[a, 2] + v * vertex_q[b, 2] + w * vertex_q[c, 2] - pz
            d2 = dx * dx + dy * dy + dz * dz
            if d2 < best or (d2 == best and t < best_tri):
                best = d2
                best_tri = t
                bf = f
                sx, sy, sz = -dx, -dy, -dz
        nx, ny, nz = _pseudo_normal(
            best_tri, bf, tri_vertices, tri_neighbors, vertex_tri_start, vertex_tri_index, vertex_q
        )
        dist = np.sqrt(best)
        out_sdist[i] = -dist if sx * nx + sy * ny + sz * nz < 0.0 else dist


def _csr(lists) -> tuple[np.ndarray, np.ndarray]:
    lengths = np.fromiter((len(x) for x in lists), np.int64, len(lists))
    start = np.zeros(len(lists) + 1, np.int64)
    np.cumsum(lengths, out=start[1:])
    index = np.concatenate([np.asarray(x, np.int64) for x in lists]) if start[-1] else np.zeros(0, np.int64)
    return start, index


def _ckdtree_signed_distance(points, surface, vertex_q, k: int = 4) -> np.ndarray:
    """Exact signed distance through a cKDTree of triangle centroids, rebuilt from ``vertex_q``.

    Stage 1: the k nearest centroids give an upper bound ub on the distance. Stage 2: every triangle within ub
    has its centroid within ub + (largest centroid-to-vertex distance), so a ball query with that radius
    returns a candidate set that surely holds the closest triangle.
    """
    corners = vertex_q[surface.tri_vertices]
    centroid = corners.mean(axis=1)
    reach = np.sqrt(((corners - centroid[:, None, :]) ** 2).sum(axis=2).max())
    tree = cKDTree(centroid)
    _, nearest = tree.query(points, k=k)
    start = np.arange(0, k * len(points) + 1, k)
    upper = np.empty(len(points))
    args = (
        surface.tri_vertices,
        surface.tri_neighbors,
        surface.vertex_tri_start,
        surface.vertex_tri_index,
        vertex_q,
    )
    _candidate_signed_distance(points, start, nearest.ravel(), *args, upper)
    lists = tree.query_ball_point(points, np.abs(upper) + reach)
    start, index = _csr(lists)
    sdist = np.empty(len(points))
    _candidate_signed_distance(points, start, index, *args, sdist)
    return sdist


def _brute_force_signed_distance(points, surface, vertex_q) -> np.ndarray:
    n_tri = len(surface.tri_vertices)
    start = np.arange(0, n_tri * len(points) + 1, n_tri)
    index = np.tile(np.arange(n_tri), len(points))
    sdist = np.empty(len(points))
    _candidate_signed_distance(
        points,
        start,
        index,
        surface.tri_vertices,
        surface.tri_neighbors,
        surface.vertex_tri_start,
        surface.vertex_tri_index,
        vertex_q,
        sdist,
    )
    return sdist


def _median_ms(samples) -> float:
    return float(np.median(samples) * 1e3)


@benchmark("collision_paper_cube")
def bench_collision_paper_cube(substeps: int = 300, warmup: int = 20, alt_substeps: int = 40) -> dict:
    """Per-substep collision queries at the paper's cube scale; see the module docstring."""
    q0, tets, tris = _two_bar_scene()
    surface = build_triangle_surface(tris, q0)
    tet_bvh = build_bvh(tets, q0)
    parts = {"refit_surface": [], "signed_distance": [], "refit_tets": [], "locate": [], "crossings": []}
    totals = []
    inside_nodes = []
    for step in range(warmup + substeps):
        q = _pressed_tissue(q0, step * DT)
        nodes = _strand(step * DT)
        t0 = time.perf_counter()
        refit_bvh(surface.bvh, q)
        t1 = time.perf_counter()
        sdist, _, _ = signed_distance(nodes, surface, q)
        t2 = time.perf_counter()
        refit_bvh(tet_bvh, q)
        t3 = time.perf_counter()
        locate_points(nodes[LOCATED_NODES], tet_bvh, q)
        t4 = time.perf_counter()
        segment_crossings(nodes[:-1], nodes[1:], surface, q)
        t5 = time.perf_counter()
        if step >= warmup:
            for name, dt in zip(parts, (t1 - t0, t2 - t1, t3 - t2, t4 - t3, t5 - t4), strict=True):
                parts[name].append(dt)
            totals.append(t4 - t0)
            inside_nodes.append(int((sdist < 0).sum()))

    # Alternatives for "surface structure update + signed distance of all nodes", checked against the BVH.
    def rebuilt_bvh(nodes, q):
        fresh = dataclasses.replace(surface, bvh=build_bvh(surface.tri_vertices, q))
        return signed_distance(nodes, fresh, q)[0]

    def refit_bvh_query(nodes, q):
        refit_bvh(surface.bvh, q)
        return signed_distance(nodes, surface, q)[0]

    alternatives = {
        "bvh_refit": refit_bvh_query,
        "bvh_rebuild": rebuilt_bvh,
        "ckdtree_centroids": lambda nodes, q: _ckdtree_signed_distance(nodes, surface, q),
        "brute_force": lambda nodes, q: _brute_force_signed_distance(nodes, surface, q),
    }
    alt_ms = {}
    alt_diff = {}
    for name, fn in alternatives.items():
        samples = []
        worst = 0.0
        for step in range(2 + alt_substeps):
            q = _pressed_tissue(q0, step * DT)
            nodes = _strand(step * DT)
            t0 = time.perf_counter()
            got = fn(nodes, q)
            elapsed = time.perf_counter() - t0
            if step >= 2:
                samples.append(elapsed)
                refit_bvh(surface.bvh, q)
                worst = max(worst, float(np.abs(got - signed_distance(nodes, surface, q)[0]).max()))
        alt_ms[name] = _median_ms(samples)
        alt_diff[name] = worst

    substep_ms = _median_ms(totals)
    return {
        "tets": int(len(tets)),
        "particles": int(len(q0)),
        "strand_nodes": NEEDLE_NODES + SUTURE_NODES,
        "substep_ms": substep_ms,
        "substeps_per_s": 1e3 / substep_ms,
        "collision_fraction": 1.0,
        "solver_fraction": 0.0,
        "surface_triangles": int(len(tris)),
        "located_nodes": LOCATED_NODES.stop - LOCATED_NODES.start,
        "median_inside_nodes": int(np.median(inside_nodes)),
        "p90_substep_ms": float(np.percentile(totals, 90) * 1e3),
        "refit_surface_ms": _median_ms(parts["refit_surface"]),
        "signed_distance_ms": _median_ms(parts["signed_distance"]),
        "refit_tets_ms": _median_ms(parts["refit_tets"]),
        "locate_ms": _median_ms(parts["locate"]),
        "crossings_229_segments_ms": _median_ms(parts["crossings"]),
        "target_ms": 0.5,
        "surface_bvh_nodes": int(len(surface.bvh.node_child)),
        "surface_bvh_depth": surface.bvh.depth,
        "alt_surface_update_plus_signed_distance_ms": alt_ms,
        "alt_max_abs_diff_vs_bvh_m": alt_diff,
        "substeps": substeps,
    }


# ------------------------------------------------------------------------------------------------ checks


def _winding_inside(points: np.ndarray, triangles: np.ndarray) -> np.ndarray:
    """Inside test by the generalised winding number (sum of signed solid angles / 4 pi > 1/2)."""
    inside = np.empty(len(points), bool)
    for lo in range(0, len(points), 256):
        p = points[lo : lo + 256]
        a, b, c = (triangles[None, :, k, :] - p[:, None, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        num = np.einsum("...k,...k", a, np.cross(b, c))
        den = la * lb * lc + np.einsum("...k,...k", a, b) * lc + np.einsum("...k,...k", b, c) * la
        den += np.einsum("...k,...k", c, a) * lb
        inside[lo : lo + 256] = (2.0 * np.arctan2(num, den)).sum(axis=1) / (4.0 * np.pi) > 0.5
    return inside


@check("collision_sdf_box_exact")
def check_sdf_box_exact() -> CheckResult:
    """Signed distance to one bar's tet-grid surface vs the box SDF, near corners/edges and at random."""
    half = 0.5 * np.asarray(BAR_SIZE)
    grid = box_tet_grid(BAR_SIZE, BAR_CELLS, origin=-half)
    surface = build_triangle_surface(surface_triangles(grid.tets), grid.vertices)
    rng = np.random.default_rng(0)
    signs = np.array([[x, y, z] for x in (-1, 1) for y in (-1, 1) for z in (-1, 1)], dtype=float)
    anchors = np.vstack(
        [signs * half, signs * half * [0.3, 1, 1], signs * half * [1, 0.4, 1], signs * half * [1, 1, 0.2]]
    )
    near = (anchors[:, None, :] + rng.normal(size=(len(anchors), 50, 3)) * 1e-3).reshape(-1, 3)
    points = np.vstack([near, rng.uniform(-1.3, 1.3, (2000, 3)) * half])
    sdist, _, _ = signed_distance(points, surface, np.asarray(grid.vertices))
    d = np.abs(points) - half
    exact = np.linalg.norm(np.maximum(d, 0.0), axis=1) + np.minimum(d.max(axis=1), 0.0)
    error = float(np.abs(sdist - exact).max())
    return CheckResult(
        name="collision_sdf_box_exact",
        measured=error,
        reference=0.0,
        tolerance=1e-12,
        unit="m",
        settings={
            "bar_size_m": list(BAR_SIZE),
            "cells": list(BAR_CELLS),
            "scheme": "five",
            "points": len(points),
            "near_corner_edge_points": len(near),
            "seed": 0,
        },
        details={
            "inside_points": int((exact < 0).sum()),
            "sign_mismatches": int((np.sign(sdist) != np.sign(exact)).sum()),
        },
    )


@check("collision_sign_deformed_two_bar")
def check_sign_deformed_two_bar() -> CheckResult:
    """Inside/outside by pseudo-normals vs the winding number, near the pressed two-bar wound's surface."""
    q0, _, tris = _two_bar_scene()
    q = _pressed_tissue(q0, 0.125)  # deepest press
    surface = build_triangle_surface(tris, q0)
    refit_bvh(surface.bvh, q)
    rng = np.random.default_rng(1)
    pick = rng.integers(0, len(tris), 3000)
    bary = rng.dirichlet(np.ones(3), len(pick))
    points = np.einsum("mk,mkj->mj", bary, q[tris[pick]]) + rng.normal(size=(len(pick), 3)) * 5e-4
    sdist, _, _ = signed_distance(points, surface, q)
    inside = _winding_inside(points, q[tris])
    mismatches = int(((sdist < 0) != inside).sum())
    return CheckResult(
        name="collision_sign_deformed_two_bar",
        measured=float(mismatches),
        reference=0.0,
        tolerance=0.0,
        unit="points",
        settings={
            "bar_size_m": list(BAR_SIZE),
            "cells": list(BAR_CELLS),
            "gap_m": WOUND_GAP,
            "points": len(points),
            "offset_std_m": 5e-4,
            "press_time_s": 0.125,
            "seed": 1,
        },
        details={"inside_points": int(inside.sum()), "surface_triangles": int(len(tris))},
    )
