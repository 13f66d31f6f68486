"""Numba kernels of the geometric queries of :mod:`suture_gym.sim.collision`: closest points on triangles,
angle-weighted pseudo-normals, and the BVH traversals behind ``signed_distance``, ``closest_triangles``,
``locate_points`` and ``segment_crossings`` (conventions in that module's docstring; positions in metres).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Closest-point feature codes: the triangle's interior, one of its vertices, or one of its edges.
FEATURE_FACE = 0
FEATURE_VERTEX_0 = 1
FEATURE_VERTEX_1 = 2
FEATURE_VERTEX_2 = 3
FEATURE_EDGE_01 = 4
FEATURE_EDGE_12 = 5
FEATURE_EDGE_20 = 6


# A triangle is degenerate when |(x1-x0) x (x2-x0)| <= 1e-12 * (longest edge)^2 (sine of its largest angle
# below ~1e-12); a tet when |det| <= 1e-12 * (longest edge from x0)^3.
_DEGENERATE_REL = 1e-12

# ----------------------------------------------------------------------------------------------------------
# Triangle primitives
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _segment_closest(px, py, pz, ax, ay, az, bx, by, bz):
    """(t, squared distance) of the point a + t (b - a), t in [0, 1], closest to p; t = 0 if a == b."""
    ex = bx - ax
    ey = by - ay
    ez = bz - az
    ee = ex * ex + ey * ey + ez * ez
    t = 0.0
    if ee > 0.0:
        t = ((px - ax) * ex + (py - ay) * ey + (pz - az) * ez) / ee
        t = min(max(t, 0.0), 1.0)
    dx = ax + t * ex - px
    dy = ay + t * ey - py
    dz = az + t * ez - pz
    return t, dx * dx + dy * dy + dz * dz


@njit(cache=True, inline="always")
def _closest_bary_degenerate(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Closest point on a zero-area triangle: the nearest of its three edges (first wins ties)."""
    t0, d0 = _segment_closest(px, py, pz, ax, ay, az, bx, by, bz)
    t1, d1 = _segment_closest(px, py, pz, bx, by, bz, cx, cy, cz)
    t2, d2 = _segment_closest(px, py, pz, cx, cy, cz, ax, ay, az)
    if d0 <= d1 and d0 <= d2:
        feature = FEATURE_VERTEX_0 if t0 == 0.0 else (FEATURE_VERTEX_1 if t0 == 1.0 else FEATURE_EDGE_01)
        return 1.0 - t0, t0, 0.0, feature
    if d1 <= d2:
        feature = FEATURE_VERTEX_1 if t1 == 0.0 else (FEATURE_VERTEX_2 if t1 == 1.0 else FEATURE_EDGE_12)
        return 0.0, 1.0 - t1, t1, feature
    feature = FEATURE_VERTEX_2 if t2 == 0.0 else (FEATURE_VERTEX_0 if t2 == 1.0 else FEATURE_EDGE_20)
    return t2, 0.0, 1.0 - t2, feature


@njit(cache=True)
def _closest_bary(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz):
    """Barycentric coordinates (u, v, w) and feature code of the point of triangle abc closest to p.

    Voronoi-region walk over the vertices, edges and face of the triangle (the classic construction, e.g.
    C. Ericson, Real-Time Collision Detection, 2005, §5.1.5); zero-area triangles go to the edge-only version.
    """
    abx = bx - ax
    aby = by - ay
    abz = bz - az
    acx = cx - ax
    acy = cy - ay
    acz = cz - az
    nx = aby * acz - abz * acy
    ny = abz * acx - abx * acz
    nz = abx * acy - aby * acx
    lab = abx * abx + aby * aby + abz * abz
    lac = acx * acx + acy * acy + acz * acz
    lbc = (cx - bx) ** 2 + (cy - by) ** 2 + (cz - bz) ** 2
    lmax = max(lab, lac, lbc)
    if nx * nx + ny * ny + nz * nz <= (_DEGENERATE_REL * lmax) ** 2:
        return _closest_bary_degenerate(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
    apx = px - ax
    apy = py - ay
    apz = pz - az
    d1 = abx * apx + aby * apy + abz * apz
    d2 = acx * apx + acy * apy + acz * apz
    if d1 <= 0.0 and d2 <= 0.0:
        return 1.0, 0.0, 0.0, FEATURE_VERTEX_0
    bpx = px - bx
    bpy = py - by
    bpz = pz - bz
    d3 = abx * bpx + aby * bpy + abz * bpz
    d4 = acx * bpx + acy * bpy + acz * bpz
    if d3 >= 0.0 and d4 <= d3:
        return 0.0, 1.0, 0.0, FEATURE_VERTEX_1
    vc = d1 * d4 - d3 * d2
    if vc <= 0.0 and d1 >= 0.0 and d3 <= 0.0:
        v = d1 / (d1 - d3)
        return 1.0 - v, v, 0.0, FEATURE_EDGE_01
    cpx = px - cx
    cpy = py - cy
    cpz = pz - cz
    d5 = abx * cpx + aby * cpy + abz * cpz
    d6 = acx * cpx + acy * cpy + acz * cpz
    if d6 >= 0.0 and d5 <= d6:
        return 0.0, 0.0, 1.0, FEATURE_VERTEX_2
    vb = d5 * d2 - d1 * d6
    if vb <= 0.0 and d2 >= 0.0 and d6 <= 0.0:
        w = d2 / (d2 - d6)
        return 1.0 - w, 0.0, w, FEATURE_EDGE_20
    va = d3 * d6 - d5 * d4
    if va <= 0.0 and d4 - d3 >= 0.0 and d5 - d6 >= 0.0:
        w = (d4 - d3) / ((d4 - d3) + (d5 - d6))
        return 0.0, 1.0 - w, w, FEATURE_EDGE_12
    denom = 1.0 / (va + vb + vc)
    v = vb * denom
    w = vc * denom
    return 1.0 - v - w, v, w, FEATURE_FACE


@njit(cache=True)
def closest_point_triangle(p, a, b, c):
    """Point of triangle abc closest to p.

    Args:
        p, a, b, c: (3,) float64 [m].

    Returns:
        ``(point, bary, feature)``: point (3,) float64 [m]; bary (3,) float64, weights of a, b, c (>= 0,
        sum 1); feature: FEATURE_FACE, FEATURE_VERTEX_k or FEATURE_EDGE_ij (int). A zero-area triangle is
        treated as its three edges.
    """
    u, v, w, feature = _closest_bary(p[0], p[1], p[2], a[0], a[1], a[2], b[0], b[1], b[2], c[0], c[1], c[2])
    bary = np.array([u, v, w])
    point = u * a + v * b + w * c
    return point, bary, feature


@njit(cache=True)
def _tri_unit_normal(vertex_q, i0, i1, i2):
    """Unit normal (x1 - x0) x (x2 - x0) / |.|, or zero for a degenerate triangle."""
    ax = vertex_q[i1, 0] - vertex_q[i0, 0]
    ay = vertex_q[i1, 1] - vertex_q[i0, 1]
    az = vertex_q[i1, 2] - vertex_q[i0, 2]
    bx = vertex_q[i2, 0] - vertex_q[i0, 0]
    by = vertex_q[i2, 1] - vertex_q[i0, 1]
    bz = vertex_q[i2, 2] - vertex_q[i0, 2]
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    cx = vertex_q[i2, 0] - vertex_q[i1, 0]
    cy = vertex_q[i2, 1] - vertex_q[i1, 1]
    cz = vertex_q[i2, 2] - vertex_q[i1, 2]
    lmax = max(ax * ax + ay * ay + az * az, bx * bx + by * by + bz * bz, cx * cx + cy * cy + cz * cz)
    n2 = nx * nx + ny * ny + nz * nz
    if n2 <= (_DEGENERATE_REL * lmax) ** 2:
        return 0.0, 0.0, 0.0
    inv = 1.0 / np.sqrt(n2)
    return nx * inv, ny * inv, nz * inv


@njit(cache=True, inline="always")
def _corner_angle(vertex_q, i0, i1, i2):
    """Interior angle [rad] at x0 of triangle (x0, x1, x2); 0 when an edge has zero length."""
    ax = vertex_q[i1, 0] - vertex_q[i0, 0]
    ay = vertex_q[i1, 1] - vertex_q[i0, 1]
    az = vertex_q[i1, 2] - vertex_q[i0, 2]
    bx = vertex_q[i2, 0] - vertex_q[i0, 0]
    by = vertex_q[i2, 1] - vertex_q[i0, 1]
    bz = vertex_q[i2, 2] - vertex_q[i0, 2]
    cx = ay * bz - az * by
    cy = az * bx - ax * bz
    cz = ax * by - ay * bx
    return np.arctan2(np.sqrt(cx * cx + cy * cy + cz * cz), ax * bx + ay * by + az * bz)


@njit(cache=True)
def _pseudo_normal(tri, feature, tri_vertices, tri_neighbors, vertex_tri_start, vertex_tri_index, vertex_q):
    """Angle-weighted pseudo-normal (Baerentzen & Aanaes 2005) of a feature of triangle ``tri`` (not unit).

    Face: the face's unit normal. Edge: sum of the unit normals of its two triangles (each weighted by pi).
    Vertex: sum over incident triangles of (corner angle) x (unit normal).
    """
    if feature == FEATURE_FACE:
        return _tri_unit_normal(vertex_q, tri_vertices[tri, 0], tri_vertices[tri, 1], tri_vertices[tri, 2])
    if feature >= FEATURE_EDGE_01:
        nx, ny, nz = _tri_unit_normal(
            vertex_q, tri_vertices[tri, 0], tri_vertices[tri, 1], tri_vertices[tri, 2]
        )
        other = tri_neighbors[tri, feature - FEATURE_EDGE_01]
        if other >= 0:
            mx, my, mz = _tri_unit_normal(
                vertex_q, tri_vertices[other, 0], tri_vertices[other, 1], tri_vertices[other, 2]
            )
            nx += mx
            ny += my
            nz += mz
        return nx, ny, nz
    vertex = tri_vertices[tri, feature - FEATURE_VERTEX_0]
    nx = 0.0
    ny = 0.0
    nz = 0.0
    for s in range(vertex_tri_start[vertex], vertex_tri_start[vertex + 1]):
        t = vertex_tri_index[s]
        k = 0
        while tri_vertices[t, k] != vertex:
            k += 1
        i0 = tri_vertices[t, k]
        i1 = tri_vertices[t, (k + 1) % 3]
        i2 = tri_vertices[t, (k + 2) % 3]
        angle = _corner_angle(vertex_q, i0, i1, i2)
        mx, my, mz = _tri_unit_normal(vertex_q, tri_vertices[t, 0], tri_vertices[t, 1], tri_vertices[t, 2])
        nx += angle * mx
        ny += angle * my
        nz += angle * mz
    return nx, ny, nz


# ----------------------------------------------------------------------------------------------------------
# BVH traversals
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _box_dist2(px, py, pz, node_lo, node_hi, node):
    """Squared distance [m^2] from p to the box of ``node`` (0 inside)."""
    d2 = 0.0
    x = node_lo[node, 0] - px
    if x > 0.0:
        d2 += x * x
    else:
        x = px - node_hi[node, 0]
        if x > 0.0:
            d2 += x * x
    x = node_lo[node, 1] - py
    if x > 0.0:
        d2 += x * x
    else:
        x = py - node_hi[node, 1]
        if x > 0.0:
            d2 += x * x
    x = node_lo[node, 2] - pz
    if x > 0.0:
        d2 += x * x
    else:
        x = pz - node_hi[node, 2]
        if x > 0.0:
            d2 += x * x
    return d2


@njit(cache=True)
def _nearest_triangle(
    px,
    py,
    pz,
    max_d2,
    tree,
    vertex_q,
    stack,
    stack_d2,
):
    """Closest triangle to p with squared distance <= max_d2, nearest child first, boxes pruned.

    Returns (tri, u, v, w, feature, d2); tri = -1 when none is that close. Equal distances go to the lower
    triangle index, so the answer does not depend on the traversal order. ``tree`` is the surface BVH's
    :attr:`~suture_gym.sim.bvh.BVH.tree`.
    """
    node_lo, node_hi, node_child, node_first, node_count, sorted_tri, tri_vertices = tree
    best_tri = -1
    best_d2 = max_d2
    best_u = 0.0
    best_v = 0.0
    best_w = 0.0
    best_feature = -1
    stack[0] = 0
    root_d2 = _box_dist2(px, py, pz, node_lo, node_hi, stack[0])
    if root_d2 > best_d2:
        return best_tri, best_u, best_v, best_w, best_feature, best_d2
    stack_d2[0] = root_d2
    top = 1
    while top > 0:
        top -= 1
        node = stack[top]
        if stack_d2[top] > best_d2:
            continue
        left = node_child[node, 0]
        if left < 0:
            for s in range(node_first[node], node_first[node] + node_count[node]):
                t = sorted_tri[s]
                i0 = tri_vertices[t, 0]
                i1 = tri_vertices[t, 1]
                i2 = tri_vertices[t, 2]
                ax = vertex_q[i0, 0]
                ay = vertex_q[i0, 1]
                az = vertex_q[i0, 2]
                bx = vertex_q[i1, 0]
                by = vertex_q[i1, 1]
                bz = vertex_q[i1, 2]
                cx = vertex_q[i2, 0]
                cy = vertex_q[i2, 1]
                cz = vertex_q[i2, 2]
                u, v, w, feature = _closest_bary(px, py, pz, ax, ay, az, bx, by, bz, cx, cy, cz)
                dx = u * ax + v * bx + w * cx - px
                dy = u * ay + v * by + w * cy - py
                dz = u * az + v * bz + w * cz - pz
                d2 = dx * dx + dy * dy + dz * dz
                if d2 < best_d2 or (d2 == best_d2 and (best_tri < 0 or t < best_tri)):
                    best_tri = t
                    best_d2 = d2
                    best_u = u
                    best_v = v
                    best_w = w
                    best_feature = feature
            continue
        right = node_child[node, 1]
        dl = _box_dist2(px, py, pz, node_lo, node_hi, left)
        dr = _box_dist2(px, py, pz, node_lo, node_hi, right)
        if dl <= dr:
            near, d_near, far, d_far = left, dl, right, dr
        else:
            near, d_near, far, d_far = right, dr, left, dl
        if d_far <= best_d2:
            stack[top] = far
            stack_d2[top] = d_far
            top += 1
        if d_near <= best_d2:
            stack[top] = near
            stack_d2[top] = d_near
            top += 1
    return best_tri, best_u, best_v, best_w, best_feature, best_d2


@njit(cache=True)
def closest_kernel(
    points,
    max_d2,
    tree,
    vertex_q,
    out_tri,
    out_bary,
    out_dist,
):
    node_lo, node_hi, node_child, node_first, node_count, sorted_tri, tri_vertices = tree
    stack = np.empty(node_child.shape[0] + 1, np.int32)
    stack_d2 = np.empty(node_child.shape[0] + 1)
    for i in range(points.shape[0]):
        t, u, v, w, feature, d2 = _nearest_triangle(
            points[i, 0],
            points[i, 1],
            points[i, 2],
            max_d2,
            tree,
            vertex_q,
            stack,
            stack_d2,
        )
        out_tri[i] = t
        if t < 0:
            out_bary[i, 0] = 0.0
            out_bary[i, 1] = 0.0
            out_bary[i, 2] = 0.0
            out_dist[i] = np.inf
        else:
            out_bary[i, 0] = u
            out_bary[i, 1] = v
            out_bary[i, 2] = w
            out_dist[i] = np.sqrt(d2)


@njit(cache=True)
def signed_distance_kernel(
    points,
    box_margin,
    tree,
    tri_neighbors,
    vertex_tri_start,
    vertex_tri_index,
    vertex_q,
    out_sdist,
    out_tri,
    out_bary,
):
    """Signed distances of ``points`` (M, 3) within ``box_margin`` (m; ``inf``: all of them) of the surface's
    box; the points outside it get ``inf``, triangle -1 and zero barycentrics."""
    node_lo, node_hi, node_child, node_first, node_count, sorted_tri, tri_vertices = tree
    stack = np.empty(node_child.shape[0] + 1, np.int32)
    stack_d2 = np.empty(node_child.shape[0] + 1)
    lo_x, lo_y, lo_z = node_lo[0, 0] - box_margin, node_lo[0, 1] - box_margin, node_lo[0, 2] - box_margin
    hi_x, hi_y, hi_z = node_hi[0, 0] + box_margin, node_hi[0, 1] + box_margin, node_hi[0, 2] + box_margin
    for i in range(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        if not (lo_x <= px <= hi_x and lo_y <= py <= hi_y and lo_z <= pz <= hi_z):
            out_sdist[i] = np.inf
            out_tri[i] = -1
            out_bary[i, 0] = 0.0
            out_bary[i, 1] = 0.0
            out_bary[i, 2] = 0.0
            continue
        t, u, v, w, feature, d2 = _nearest_triangle(
            px,
            py,
            pz,
            np.inf,
            tree,
            vertex_q,
            stack,
            stack_d2,
        )
        out_tri[i] = t
        out_bary[i, 0] = u
        out_bary[i, 1] = v
        out_bary[i, 2] = w
        i0 = tri_vertices[t, 0]
        i1 = tri_vertices[t, 1]
        i2 = tri_vertices[t, 2]
        cx = u * vertex_q[i0, 0] + v * vertex_q[i1, 0] + w * vertex_q[i2, 0]
        cy = u * vertex_q[i0, 1] + v * vertex_q[i1, 1] + w * vertex_q[i2, 1]
        cz = u * vertex_q[i0, 2] + v * vertex_q[i1, 2] + w * vertex_q[i2, 2]
        nx, ny, nz = _pseudo_normal(
            t, feature, tri_vertices, tri_neighbors, vertex_tri_start, vertex_tri_index, vertex_q
        )
        dist = np.sqrt(d2)
        if (px - cx) * nx + (py - cy) * ny + (pz - cz) * nz < 0.0:
            out_sdist[i] = -dist
        else:
            out_sdist[i] = dist


@njit(cache=True)
def _tet_bary(vertex_q, i0, i1, i2, i3, px, py, pz):
    """(ok, l0, l1, l2, l3): barycentric coordinates of p in tet (x0..x3); ok False for a degenerate tet."""
    ax = vertex_q[i1, 0] - vertex_q[i0, 0]
    ay = vertex_q[i1, 1] - vertex_q[i0, 1]
    az = vertex_q[i1, 2] - vertex_q[i0, 2]
    bx = vertex_q[i2, 0] - vertex_q[i0, 0]
    by = vertex_q[i2, 1] - vertex_q[i0, 1]
    bz = vertex_q[i2, 2] - vertex_q[i0, 2]
    cx = vertex_q[i3, 0] - vertex_q[i0, 0]
    cy = vertex_q[i3, 1] - vertex_q[i0, 1]
    cz = vertex_q[i3, 2] - vertex_q[i0, 2]
    rx = px - vertex_q[i0, 0]
    ry = py - vertex_q[i0, 1]
    rz = pz - vertex_q[i0, 2]
    # det = a . (b x c); Cramer's rule for r = l1 a + l2 b + l3 c.
    bcx = by * cz - bz * cy
    bcy = bz * cx - bx * cz
    bcz = bx * cy - by * cx
    det = ax * bcx + ay * bcy + az * bcz
    lmax = max(ax * ax + ay * ay + az * az, bx * bx + by * by + bz * bz, cx * cx + cy * cy + cz * cz)
    if abs(det) <= _DEGENERATE_REL * lmax * np.sqrt(lmax):
        return False, 0.0, 0.0, 0.0, 0.0
    inv = 1.0 / det
    l1 = (rx * bcx + ry * bcy + rz * bcz) * inv
    rcx = ry * cz - rz * cy
    rcy = rz * cx - rx * cz
    rcz = rx * cy - ry * cx
    l2 = (ax * rcx + ay * rcy + az * rcz) * inv
    brx = by * rz - bz * ry
    bry = bz * rx - bx * rz
    brz = bx * ry - by * rx
    l3 = (ax * brx + ay * bry + az * brz) * inv
    return True, 1.0 - l1 - l2 - l3, l1, l2, l3


@njit(cache=True)
def locate_kernel(
    points,
    tolerance,
    tree,
    vertex_q,
    out_tet,
    out_bary,
):
    """For each point, the tet maximising its smallest barycentric coordinate among those >= -tolerance.

    A tet with all coordinates >= -tolerance lies inside its box grown by 3 tolerance x (box extent) per axis,
    so boxes are tested with that margin. Equal scores go to the lower tet index.
    """
    node_lo, node_hi, node_child, node_first, node_count, sorted_tet, tet_vertices = tree
    stack = np.empty(node_child.shape[0] + 1, np.int32)
    grow = 3.0 * tolerance
    for i in range(points.shape[0]):
        px = points[i, 0]
        py = points[i, 1]
        pz = points[i, 2]
        best_tet = -1
        best_score = -tolerance
        b0 = 0.0
        b1 = 0.0
        b2 = 0.0
        b3 = 0.0
        stack[0] = 0
        top = 1
        while top > 0:
            top -= 1
            node = stack[top]
            outside = False
            for j in range(3):
                lo = node_lo[node, j]
                hi = node_hi[node, j]
                m = grow * (hi - lo)
                x = points[i, j]
                if x < lo - m or x > hi + m:
                    outside = True
            if outside:
                continue
            left = node_child[node, 0]
            if left >= 0:
                stack[top] = node_child[node, 1]
                stack[top + 1] = left
                top += 2
                continue
            for s in range(node_first[node], node_first[node] + node_count[node]):
                e = sorted_tet[s]
                ok, l0, l1, l2, l3 = _tet_bary(
                    vertex_q,
                    tet_vertices[e, 0],
                    tet_vertices[e, 1],
                    tet_vertices[e, 2],
                    tet_vertices[e, 3],
                    px,
                    py,
                    pz,
                )
                if not ok:
                    continue
                score = min(min(l0, l1), min(l2, l3))
                if score > best_score or (score == best_score and (best_tet < 0 or e < best_tet)):
                    best_tet = e
                    best_score = score
                    b0 = l0
                    b1 = l1
                    b2 = l2
                    b3 = l3
        out_tet[i] = best_tet
        out_bary[i, 0] = b0
        out_bary[i, 1] = b1
        out_bary[i, 2] = b2
        out_bary[i, 3] = b3


@njit(cache=True)
def _edge_volume(p0x, p0y, p0z, dx, dy, dz, iu, iv, vertex_q):
    """((x_u - p0) x (x_v - p0)) . d for the directed edge u -> v, evaluated in a canonical vertex order.

    Evaluating with the lower vertex index first and negating otherwise makes the two triangles sharing an
    edge see exactly opposite values, which is what makes the crossing test watertight.
    """
    if iu < iv:
        a = iu
        b = iv
        sign = 1.0
    else:
        a = iv
        b = iu
        sign = -1.0
    ax = vertex_q[a, 0] - p0x
    ay = vertex_q[a, 1] - p0y
    az = vertex_q[a, 2] - p0z
    bx = vertex_q[b, 0] - p0x
    by = vertex_q[b, 1] - p0y
    bz = vertex_q[b, 2] - p0z
    return sign * ((ay * bz - az * by) * dx + (az * bx - ax * bz) * dy + (ax * by - ay * bx) * dz)


@njit(cache=True)
def _edge_admits(volume, sigma, iu, iv):
    """The line passes on the inner side of edge u -> v; an exact zero counts only for the edge with u < v."""
    return volume * sigma > 0.0 or (volume == 0.0 and iu < iv)


@njit(cache=True, inline="always")
def _segment_triangle(p0x, p0y, p0z, p1x, p1y, p1z, i0, i1, i2, vertex_q):
    """Crossing of segment p0 -> p1 with triangle (x0, x1, x2).

    The segment crosses when its end points lie on different sides of the triangle's plane (half-open: a point
    on the plane counts as the negative side, so a polyline touching the plane is counted consistently) and
    its line passes through the triangle: the three edge volumes share the sign of their sum. Returns
    (hit, t, b0, b1, b2, direction) with the crossing point p0 + t (p1 - p0) = b0 x0 + b1 x1 + b2 x2.
    """
    ax = vertex_q[i1, 0] - vertex_q[i0, 0]
    ay = vertex_q[i1, 1] - vertex_q[i0, 1]
    az = vertex_q[i1, 2] - vertex_q[i0, 2]
    bx = vertex_q[i2, 0] - vertex_q[i0, 0]
    by = vertex_q[i2, 1] - vertex_q[i0, 1]
    bz = vertex_q[i2, 2] - vertex_q[i0, 2]
    nx = ay * bz - az * by
    ny = az * bx - ax * bz
    nz = ax * by - ay * bx
    s0 = (p0x - vertex_q[i0, 0]) * nx + (p0y - vertex_q[i0, 1]) * ny + (p0z - vertex_q[i0, 2]) * nz
    s1 = (p1x - vertex_q[i0, 0]) * nx + (p1y - vertex_q[i0, 1]) * ny + (p1z - vertex_q[i0, 2]) * nz
    if (s0 > 0.0) == (s1 > 0.0):
        return False, 0.0, 0.0, 0.0, 0.0, 0
    dx = p1x - p0x
    dy = p1y - p0y
    dz = p1z - p0z
    e01 = _edge_volume(p0x, p0y, p0z, dx, dy, dz, i0, i1, vertex_q)
    e12 = _edge_volume(p0x, p0y, p0z, dx, dy, dz, i1, i2, vertex_q)
    e20 = _edge_volume(p0x, p0y, p0z, dx, dy, dz, i2, i0, vertex_q)
    total = e01 + e12 + e20
    if total == 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0
    sigma = 1.0 if total > 0.0 else -1.0
    if not (
        _edge_admits(e01, sigma, i0, i1)
        and _edge_admits(e12, sigma, i1, i2)
        and _edge_admits(e20, sigma, i2, i0)
    ):
        return False, 0.0, 0.0, 0.0, 0.0, 0
    t = s0 / (s0 - s1)
    direction = 1 if s1 > s0 else -1
    return True, t, e12 / total, e20 / total, e01 / total, direction


@njit(cache=True)
def crossings_kernel(
    seg_start,
    seg_end,
    tree,
    vertex_q,
    out_segment,
    out_tri,
    out_bary,
    out_t,
    out_direction,
):
    """Write up to len(out_segment) crossings; return the total number found (may exceed the capacity)."""
    node_lo, node_hi, node_child, node_first, node_count, sorted_tri, tri_vertices = tree
    capacity = out_segment.shape[0]
    stack = np.empty(node_child.shape[0] + 1, np.int32)
    count = 0
    for s in range(seg_start.shape[0]):
        p0x = seg_start[s, 0]
        p0y = seg_start[s, 1]
        p0z = seg_start[s, 2]
        p1x = seg_end[s, 0]
        p1y = seg_end[s, 1]
        p1z = seg_end[s, 2]
        lox = min(p0x, p1x)
        loy = min(p0y, p1y)
        loz = min(p0z, p1z)
        hix = max(p0x, p1x)
        hiy = max(p0y, p1y)
        hiz = max(p0z, p1z)
        stack[0] = 0
        top = 1
        while top > 0:
            top -= 1
            node = stack[top]
            if (
                lox > node_hi[node, 0]
                or hix < node_lo[node, 0]
                or loy > node_hi[node, 1]
                or hiy < node_lo[node, 1]
                or loz > node_hi[node, 2]
                or hiz < node_lo[node, 2]
            ):
                continue
            left = node_child[node, 0]
            if left >= 0:
                stack[top] = node_child[node, 1]
                stack[top + 1] = left
                top += 2
                continue
            for k in range(node_first[node], node_first[node] + node_count[node]):
                tri = sorted_tri[k]
                hit, t, b0, b1, b2, direction = _segment_triangle(
                    p0x,
                    p0y,
                    p0z,
                    p1x,
                    p1y,
                    p1z,
                    tri_vertices[tri, 0],
                    tri_vertices[tri, 1],
                    tri_vertices[tri, 2],
                    vertex_q,
                )
                if not hit:
                    continue
                if count < capacity:
                    out_segment[count] = s
                    out_tri[count] = tri
                    out_bary[count, 0] = b0
                    out_bary[count, 1] = b1
                    out_bary[count, 2] = b2
                    out_t[count] = t
                    out_direction[count] = direction
                count += 1
    return count
