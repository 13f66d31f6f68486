"""Constraint maths of the coupling rows (Yu et al. 2020 eqs. 1-3 made XPBD): small pure kernels."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.coupling.params import TINY_LENGTH
from suture_gym.sim.quat import cross3


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
    r0, r1, r2 = q[0] - p[0], q[1] - p[1], q[2] - p[2]
    along = r0 * t[0] + r1 * t[1] + r2 * t[2]
    d0, d1, d2 = r0 - along * t[0], r1 - along * t[1], r2 - along * t[2]
    c = math.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    n = np.zeros(3)
    if c <= TINY_LENGTH:
        return False, 0.0, n
    n[0], n[1], n[2] = d0 / c, d1 / c, d2 / c
    return True, c, n


@njit(cache=True, inline="always")
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
    if la <= TINY_LENGTH or lb <= TINY_LENGTH:
        return False, 0.0, ga, gb
    ga[:] = ra / la
    gb[:] = rb / lb
    return True, la + lb - rest_length, ga, gb


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
    c = -eps
    for i in range(3):  # in scalars: numba's ``@`` on (3,) arrays is a BLAS call, and each term a temporary
        c += (q[i] - (bary[0] * p1[i] + bary[1] * p2[i] + bary[2] * p3[i])) * normal[i]
    return c


@njit(cache=True)
def tissue_point(tissue_q, idx, weight):
    """The embedded tissue point ``sum_a weight[a] tissue_q[idx[a]]`` (3,) m: a path node in its tet (four
    barycentric weights) or a point of a surface triangle, from particle indices ``idx`` (K,) and weights (K,)."""
    x = y = z = 0.0
    for a in range(idx.shape[0]):  # in scalars: a row view and a temporary per term cost reference counting
        w, v = weight[a], idx[a]
        x += w * tissue_q[v, 0]
        y += w * tissue_q[v, 1]
        z += w * tissue_q[v, 2]
    p = np.empty(3)
    p[0], p[1], p[2] = x, y, z
    return p


@njit(cache=True, inline="always")
def _vertex_normal(v, tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q):
    """Area-weighted normal (3,) of surface vertex ``v`` (sum of the cross products of its triangles, not unit)."""
    nx = ny = nz = 0.0
    for s in range(vertex_tri_start[v], vertex_tri_start[v + 1]):  # in scalars: no views, no temporaries
        t = vertex_tri_index[s]
        a, b, c = tri_vertices[t, 0], tri_vertices[t, 1], tri_vertices[t, 2]
        ux, uy, uz = tissue_q[b, 0] - tissue_q[a, 0], tissue_q[b, 1] - tissue_q[a, 1], tissue_q[b, 2] - tissue_q[a, 2]
        wx, wy, wz = tissue_q[c, 0] - tissue_q[a, 0], tissue_q[c, 1] - tissue_q[a, 1], tissue_q[c, 2] - tissue_q[a, 2]
        nx += uy * wz - uz * wy
        ny += uz * wx - ux * wz
        nz += ux * wy - uy * wx
    n = np.empty(3)
    n[0], n[1], n[2] = nx, ny, nz
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
        n = cross3(tissue_q[tri_vertices[tri, 1]] - a, tissue_q[tri_vertices[tri, 2]] - a)
        length = math.sqrt(n @ n)
        if length <= 0.0:
            return np.zeros(3)
    return n / length
