"""Projection of the suture nodes' rows and of the node-access rows, two-way with the tissue."""

from __future__ import annotations

import numpy as np
from numba import njit

from suture_gym.sim.coupling.compliance import (
    apply_impulse,
    is_diagonal,
    move_point,
    point_compliance,
    point_inv_mass,
)
from suture_gym.sim.coupling.constraints import (
    node_access_constraint,
    node_path_constraint,
    node_surface_constraint,
    tissue_point,
    xpbd_delta_lambda,
)
from suture_gym.sim.coupling.params import PATH_ROW_VERTICES, ROW_PATH, ROW_TRIANGLE, ROW_WALL
from suture_gym.sim.quat import cross3
from suture_gym.sim.rigid import (
    body_point,
    rigid_apply,
    rigid_generalized_inv_mass,
    world_inv_inertia,
)

#: A node on a path is free along the path's tangent only while the thread there runs along it: |cos| of the
#: angle between the tangent and the thread's local direction at least this (:func:`embedded_inv_mass`).
ALIGNED_COS = 0.9


@njit(cache=True)
def embedded_inv_mass(needle_node_count, node_rows, access_rows, access_count, tri_vertices, tissue, suture_inv_mass,
                      strand_q, out):  # fmt: skip
    """Inverse masses the projections use for the suture nodes this substep, ``W_j = w_j I + a_j t_j t_j^T``
    (1/kg). A node held on a path (node-path row) is embedded in the tissue point it lies in *across* the path,
    ``w_j = min(w_node, w_point)`` with ``w_point = sum_k b_k^2 w_k`` (the point's generalised inverse mass),
    and keeps its own inertia *along* the path's tangent ``t_j`` (``a_j = w_node - w_j``) while the thread runs
    along the path there (the thread's direction at the node, from ``strand_q`` (M, 3) m, within
    ``acos(ALIGNED_COS)`` of ``t_j``; otherwise ``a_j = 0``). A node of a strand piece through an access point
    carries the access point's inertia in every direction, ``W_j = min(w_node, w_point) I``. The others keep
    their own, ``W_j = w_node I``. Writes ``out = (w (Ns,), a (Ns,), t (Ns, 3))``.

    Why embedded across: the thread is 3e-8 kg per node against 1e-4 kg tissue nodes. Projected with its own
    mass, a node on a path would take the whole of every correction: the inextensible rod's solve pulls a taut
    thread straight across the path's bends, the node-path projection puts the node back, and the tissue never
    feels the tension. Embedded, the node moves across the path with the tissue, so the solve shares the
    thread's length between the needle, the free thread and the tissue, and the node-path projection splits
    the rest evenly between node and tissue.

    Why free along: nothing but friction holds a thread from sliding along its path, so its inertia along the
    path is its own. With the tissue's inertia along the path too, the thread in a bite carried the momentum
    of the tissue it lies in: on stiff tissue (300 kPa, where ``w_point`` is 1e4 times below ``w_node``) the
    thread in a first bite coasted on as the needle slowed and fed slack into the wound gap faster than the
    needle drew it into the second bite, which then jammed (measured on SutureThrow's scripted throw; with
    the free axis it passes). Not so at an access point: the gradient of eq. 3 lies along the strand piece,
    so a piece free along itself meets the row by shortening (the inextensible solve then stretches it back;
    on SutureThrow the fight tore the tissue) instead of moving the access point onto it. Nor where the thread
    crosses its path at an angle (a crushed or kinked path): a free axis across the thread let the solve slide
    nodes far off the curved path, and the node-path rows threw the tissue back (a 1 N push through 1 kPa
    tissue diverged; with the gate it does not).

    A thread node merely touching the surface keeps its own mass: it cannot dent the tissue (an embedded mass
    there makes the contact push the surface by half of every penetration, which turned out violent).
    ``tissue`` is the compliance tuple (:mod:`~suture_gym.sim.coupling.compliance`); with the implicit one a
    point's inverse mass is the mean of its compliance block's diagonal.
    """
    row_kind, _, row_tissue, row_weight, row_tangent = node_rows
    access_node, access_weight, _, access_tri, access_bary = access_rows
    out_w, out_a, out_t = out
    nn = needle_node_count
    for j in range(suture_inv_mass.shape[0]):
        out_w[j] = suture_inv_mass[j]
        out_a[j] = 0.0
        out_t[j] = 0.0
        if j == 0:
            continue
        i = nn + j - 1
        if row_kind[i] != ROW_PATH:
            continue
        w = _isotropic_inv_mass(tissue, row_tissue[i], row_weight[i], row_tissue.shape[1])
        if w > 0.0 and w < out_w[j]:
            out_w[j] = w
            d = strand_q[min(i + 1, strand_q.shape[0] - 1)] - strand_q[i - 1]
            nd = np.sqrt(d @ d)
            if nd > 0.0 and abs(d @ row_tangent[i]) >= ALIGNED_COS * nd:
                out_a[j] = suture_inv_mass[j] - w
                out_t[j] = row_tangent[i]
    for a in range(access_count):
        w = _isotropic_inv_mass(tissue, tri_vertices[access_tri[a]], access_bary[a], access_bary.shape[1])
        if w <= 0.0:
            continue
        for e in range(4):
            node = access_node[a, e]
            if node >= nn and access_weight[a, e] > 0.0:
                j = node - nn + 1
                out_w[j] = min(w, out_w[j])
                out_a[j] = 0.0
                out_t[j] = 0.0


@njit(cache=True)
def node_inv_mass_along(mass, j, g) -> float:
    """``g^T W_j g`` (1/kg times |g|^2): suture node ``j``'s inverse mass ``mass = (w, a, t)``
    (:func:`embedded_inv_mass`) along the gradient ``g`` (3,)."""
    w, a, t = mass
    tg = t[j, 0] * g[0] + t[j, 1] * g[1] + t[j, 2] * g[2]
    return w[j] * (g @ g) + a[j] * tg * tg


@njit(cache=True)
def move_node(mass, j, g, dlam, q):
    """``q[j] += W_j g dlam``: suture node ``j`` (``mass = (w, a, t)``, :func:`embedded_inv_mass`) takes the
    impulse ``g dlam`` (kg m). Updates ``q`` (Ns, 3)."""
    w, a, t = mass
    q[j] += w[j] * dlam * g
    if a[j] != 0.0:
        q[j] += a[j] * dlam * (t[j, 0] * g[0] + t[j, 1] * g[1] + t[j, 2] * g[2]) * t[j]


@njit(cache=True)
def _isotropic_inv_mass(tissue, idx, weight, count) -> float:
    """``sum_a b_a^2 w_a`` (1/kg) with the diagonal compliance; the mean diagonal of the point's compliance
    block otherwise."""
    if is_diagonal(tissue):
        w = tissue[0]
        total = 0.0
        for a in range(count):
            total += weight[a] ** 2 * w[idx[a]]
        return total
    k = np.empty((3, 3))
    point_compliance(tissue, idx, weight, count, k)
    return (k[0, 0] + k[1, 1] + k[2, 2]) / 3.0


@njit(cache=True)
def project_suture_path_rows(
    needle_node_count,
    row_kind,
    row_tissue,
    row_weight,
    row_tangent,
    suture_mass,
    tissue,
    force_cap,
    row_lambda,
    suture_q,
    tissue_q,
):
    """One Gauss-Seidel pass over the suture nodes' node-path rows (eq. 1, ``C = |(p - q) x t|``), rigid and
    two-way between the node (its embedded inverse mass ``suture_mass``, :func:`embedded_inv_mass`) and the
    path point's tissue vertices, each multiplier kept within ``force_cap`` (kg m, the tear force times
    ``dt^2``) in magnitude. Updates ``suture_q``, ``tissue_q`` and ``row_lambda``."""
    nn = needle_node_count
    for j in range(1, suture_q.shape[0]):
        i = nn + j - 1
        if row_kind[i] != ROW_PATH:
            continue
        idx = row_tissue[i]
        wt = row_weight[i]
        p = tissue_point(tissue_q, idx, wt)
        ok, c, n = node_path_constraint(suture_q[j], p, row_tangent[i])
        if not ok:
            continue
        w = node_inv_mass_along(suture_mass, j, n)
        if is_diagonal(tissue):
            tissue_inv_mass = tissue[0]
            for a in range(PATH_ROW_VERTICES):
                w += wt[a] * wt[a] * tissue_inv_mass[idx[a]]
        else:
            w += point_inv_mass(tissue, idx, wt, idx.shape[0], n)
        dlam = xpbd_delta_lambda(c, w, 0.0, row_lambda[i])
        dlam = max(row_lambda[i] + dlam, -force_cap) - row_lambda[i]
        row_lambda[i] += dlam
        move_node(suture_mass, j, n, dlam, suture_q)
        move_point(tissue, idx, wt, dlam, n, tissue_q)


@njit(cache=True)
def suture_contact_rows(needle_node_count, eps, contact_rows, tri_vertices, tissue_q, tissue, suture_q, out_gap,
                        out_normal, out_tissue_w, out_is_tissue):  # fmt: skip
    """The suture nodes' contact rows (:func:`node_surface_constraint` in the row's frame) as the rod's
    one-sided contact rows: ``gap = C - floor`` (``row_floor``, :func:`contact_floors`) at the current
    positions, ``normal = n``, and the generalised inverse mass of the surface point ``sum_v b_v^2 w_v`` (1/kg)
    in ``out_tissue_w``. Nodes without a contact row (and node 0, on the swage) keep their ``out_gap`` and
    ``out_normal`` (+inf, or a static obstacle's, :func:`~suture_gym.sim.rod.rod_detect_contacts`) and get
    ``out_tissue_w = 0``; so does a node whose static obstacle's gap is the smaller one (a node has one
    contact row: the more violated constraint takes it, e.g. the base under a wound rather than the wound
    face beside it). Writes ``out_gap`` (Ns,), ``out_normal`` (Ns, 3), ``out_tissue_w`` (Ns,) and
    ``out_is_tissue`` (Ns,) bool, whether the node's row is its node-triangle row."""
    row_kind, row_tri, row_bary, row_contact_normal, row_floor = contact_rows
    nn = needle_node_count
    for j in range(suture_q.shape[0]):
        out_tissue_w[j] = 0.0
        out_is_tissue[j] = False
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
        if not c - row_floor[i] < out_gap[j]:
            continue
        out_is_tissue[j] = True
        out_gap[j] = c - row_floor[i]
        out_normal[j] = row_contact_normal[i]
        if is_diagonal(tissue):
            for v in range(3):
                out_tissue_w[j] += b[v] * b[v] * tissue[0][tri_vertices[tri, v]]
        else:
            out_tissue_w[j] = point_inv_mass(tissue, tri_vertices[tri], b, b.shape[0], row_contact_normal[i])


@njit(cache=True)
def apply_contact_reaction(needle_node_count, contact_rows, tri_vertices, contact_normal, z, is_tissue, tissue,
                           row_lambda, tissue_q):  # fmt: skip
    """Give the tissue the reaction of the rod's contact steps ``z[j, 6]`` (kg m) on suture nodes whose row
    in the solve is their node-triangle row (``is_tissue`` (Ns,), :func:`suture_contact_rows`): triangle vertex
    ``v`` moves by ``-w_v b_v z normal``, so the exchange conserves momentum. Adds each step to
    ``row_lambda``. Updates ``tissue_q``."""
    row_kind, row_tri, row_bary = contact_rows[:3]
    nn = needle_node_count
    for j in range(1, z.shape[0]):
        i = nn + j - 1
        dlam = z[j, 6]
        if not is_tissue[j] or (row_kind[i] != ROW_TRIANGLE and row_kind[i] != ROW_WALL) or dlam == 0.0:
            continue
        row_lambda[i] += dlam
        move_point(tissue, tri_vertices[row_tri[i]], row_bary[i], dlam, contact_normal[j], tissue_q)


@njit(cache=True)
def suture_friction_rows(needle_node_count, friction_rows, tissue_q, tissue, suture_q, out_gap, out_normal,
                         out_tissue_w, out_cap):  # fmt: skip
    """Kinetic friction of the thread in its paths, as friction rows of the rod's solve: a suture node with a
    node-path row and a friction cap ``strand_friction > 0`` (N) gets row 6 of its block along the path's
    tangent ``t``, ``C = t . ((x - x_start) - (p - p_start))`` (the slip of node against path point ``p``
    since the substep began, m), held at 0 while its multiplier stays within ``strand_friction dt^2`` (the
    thread sticks) and at that bound otherwise (it slides against a constant force). ``out_tissue_w`` gets the
    path point's inverse mass along ``t`` (1/kg) and ``out_cap`` the bound (kg m); nodes without such a row get
    ``out_cap = 0``. A friction row, once made, stays for the substep's later iterations; a node without one
    whose static obstacle's contact row is violated (``out_gap < 0``, from
    :func:`~suture_gym.sim.rod.rod_detect_contacts`) keeps that row instead. A static obstacle gives every free
    node a finite gap however far it is (the base under a pad: the node's height), so a finite gap alone must
    not keep the friction row out: it did, and with the base as the thread's obstacle the thread had no
    friction at all.

    The friction has to be in the rod's solve: the thread node is 3e-8 kg along its path, so a friction
    impulse applied outside the solve is undone by the solve's inextensibility at no cost to the needle, and
    the pull never feels it.

    Args:
        friction_rows: ``(strand_friction (M,) N, row_kind (M,), row_tissue (M, 8), row_weight (M, 8),
            row_tangent (M, 3), suture_q_start (Ns, 3) m, tissue_q_start (N, 3) m, dt s)``.
        tissue_q: ``(N, 3)`` m. tissue: the compliance tuple. suture_q: ``(Ns, 3)`` m.
        out_gap, out_normal, out_tissue_w, out_cap: the rod's contact arrays, ``(Ns,)``, ``(Ns, 3)``, ``(Ns,)``,
            ``(Ns,)``, written.
    """
    strand_friction, row_kind, row_tissue, row_weight, row_tangent, suture_q_start, tissue_q_start, dt = (
        friction_rows
    )
    nn = needle_node_count
    for j in range(1, suture_q.shape[0]):
        i = nn + j - 1
        was_friction = out_cap[j] > 0.0
        out_cap[j] = 0.0
        if row_kind[i] != ROW_PATH or strand_friction[i] <= 0.0 or (out_gap[j] < 0.0 and not was_friction):
            if was_friction:
                out_gap[j] = np.inf
            continue
        t = row_tangent[i]
        idx = row_tissue[i]
        wt = row_weight[i]
        path_moved = tissue_point(tissue_q, idx, wt) - tissue_point(tissue_q_start, idx, wt)
        slip = (suture_q[j] - suture_q_start[j]) - path_moved
        out_gap[j] = slip @ t
        out_normal[j] = t
        if is_diagonal(tissue):
            out_tissue_w[j] = 0.0
            for a in range(PATH_ROW_VERTICES):
                out_tissue_w[j] += wt[a] * wt[a] * tissue[0][idx[a]]
        else:
            out_tissue_w[j] = point_inv_mass(tissue, idx, wt, idx.shape[0], t)
        out_cap[j] = strand_friction[i] * dt * dt


@njit(cache=True)
def apply_friction_reaction(needle_node_count, friction_rows, contact_cap, contact_normal, z, tissue,
                            row_friction_lambda, tissue_q):  # fmt: skip
    """Give the tissue the reaction of the rod's friction steps ``z[j, 6]`` (kg m) on suture nodes with a
    friction row (``contact_cap[j] > 0``, :func:`suture_friction_rows`): the path point takes ``-z t``, so
    the exchange conserves momentum. Adds each step to ``row_friction_lambda``. Updates ``tissue_q``."""
    row_tissue, row_weight = friction_rows[2], friction_rows[3]
    nn = needle_node_count
    for j in range(1, z.shape[0]):
        dlam = z[j, 6]
        if contact_cap[j] <= 0.0 or dlam == 0.0:
            continue
        i = nn + j - 1
        row_friction_lambda[i] += dlam
        move_point(tissue, row_tissue[i], row_weight[i], dlam, contact_normal[j], tissue_q)


@njit(cache=True, inline="always")
def _strand_point(node, needle_node_count, needle_pos, needle_quat, needle_node_body, suture_q):
    """World position (3,) of strand node ``node`` (needle node from the pose, or suture node)."""
    if node < needle_node_count:
        return body_point(needle_pos, needle_quat, needle_node_body[node])
    return suture_q[node - needle_node_count + 1].copy()


@njit(cache=True)
def project_access_rows(access, access_count, needle, suture_mass, tissue, tri_vertices, force_cap, access_lambda,
                        needle_pos, needle_quat, suture_q, tissue_q):  # fmt: skip
    """One Gauss-Seidel pass over the first ``access_count`` node-access rows (eq. 3, inequality ``C <= 0``),
    two-way, each multiplier kept within ``force_cap`` (kg m, the tear force times ``dt^2``) in magnitude.

    The strand piece's ends are ``pa = w0 x0 + w1 x1`` and ``pb = w2 x2 + w3 x3`` (strand nodes
    ``access_node``, weights ``access_weight``), so node ``k`` gets the gradient ``w_k ga`` or ``w_k gb``.
    Needle nodes are points of the rigid needle (their gradients add up into one body Jacobian, generalised
    inverse mass), suture nodes particles, and the access point ``b = sum_v bary_v x_v`` gives its triangle's
    vertices ``-bary_v (ga + gb)``. Updates the needle pose, ``suture_q``, ``tissue_q`` and ``access_lambda``.

    Args:
        access: ``CouplingWork.access_rows``: ``(access_node (2K, 4), access_weight (2K, 4), access_rest (2K,) m,
            access_tri (2K,), access_bary (2K, 3))``.
        needle: ``(Nn, inv_mass 1/kg, inv_inertia_body (3, 3), node_body (Nn, 3) m)``.
        suture_mass: the suture nodes' inverse masses ``(w, a, t)`` (:func:`embedded_inv_mass`).
        tissue: the compliance tuple (:mod:`~suture_gym.sim.coupling.compliance`).
        tri_vertices: ``(F, 3)``.
        access_lambda: ``(2K,)`` kg m. needle_pos: ``(3,)`` m. needle_quat: ``(4,)``. suture_q: ``(Ns, 3)`` m.
        tissue_q: ``(N, 3)`` m.
    """
    access_node, access_weight, access_rest, access_tri, access_bary = access
    needle_node_count, needle_inv_mass, needle_inv_inertia_body, needle_node_body = needle
    nn = needle_node_count
    for a in range(access_count):
        tri = access_tri[a]
        b = np.zeros(3)
        w_tissue_scale = 0.0
        for v in range(3):
            b += access_bary[a, v] * tissue_q[tri_vertices[tri, v]]
            w_tissue_scale += access_bary[a, v] ** 2 * tissue[0][tri_vertices[tri, v]]
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
        if is_diagonal(tissue):
            w = w_tissue_scale * (gs @ gs)
        else:
            w = point_inv_mass(tissue, tri_vertices[tri], access_bary[a], access_bary.shape[1], gs)
        for e in range(4):
            node = access_node[a, e]
            g = access_weight[a, e] * (ga if e < 2 else gb)
            if node < nn:
                lin += g
                ang += cross3(points[e] - needle_pos, g)
            else:
                w += node_inv_mass_along(suture_mass, node - nn + 1, g)
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
                move_node(suture_mass, node - nn + 1, g, dlam, suture_q)
        if is_diagonal(tissue):
            for v in range(3):
                vi = tri_vertices[tri, v]
                tissue_q[vi] -= tissue[0][vi] * access_bary[a, v] * dlam * gs
        else:
            apply_impulse(tissue, tri_vertices[tri], access_bary[a], access_bary.shape[1], dlam * gs, tissue_q)
