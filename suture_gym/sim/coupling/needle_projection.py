"""Projection of the needle nodes' rows on the rigid needle, two-way with the tissue."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.coupling.compliance import (
    apply_impulse,
    is_diagonal,
    move_point,
    point_compliance,
    point_inv_mass,
    weighted_inv_mass,
)
from suture_gym.sim.coupling.constraints import (
    node_path_constraint,
    node_surface_constraint,
    tissue_point,
    xpbd_delta_lambda,
)
from suture_gym.sim.coupling.params import ROW_ANCHOR, ROW_EXIT, ROW_NONE, ROW_PATH, TINY_LENGTH
from suture_gym.sim.quat import cross3
from suture_gym.sim.rigid import (
    body_point,
    point_inv_mass_matrix,
    rigid_apply,
    rigid_generalized_inv_mass,
    world_inv_inertia,
)


@njit(cache=True, inline="always")
def _project_contact(
    needle_inv_mass,
    needle_inv_inertia_body,
    node_body,
    tri,
    bary,
    normal,
    tri_vertices,
    tissue,
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
    ang = cross3(q - needle_pos, normal)
    w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, normal, ang)
    tissue_w = tissue[0]
    if is_diagonal(tissue):
        w += bary[0] ** 2 * tissue_w[i0] + bary[1] ** 2 * tissue_w[i1] + bary[2] ** 2 * tissue_w[i2]
    else:
        w += point_inv_mass(tissue, tri_vertices[tri], bary, bary.shape[0], normal)
    dlam = xpbd_delta_lambda(c, w, 0.0, lam)
    if lam + dlam < 0.0:
        dlam = -lam
    rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, normal, ang, dlam)
    if is_diagonal(tissue):
        for k in range(3):
            vi = tri_vertices[tri, k]
            tissue_q[vi] -= tissue_w[vi] * bary[k] * dlam * normal
    else:
        apply_impulse(tissue, tri_vertices[tri], bary, bary.shape[0], dlam * normal, tissue_q)
    return lam + dlam


@njit(cache=True, inline="always")
def _anchor_point(tri, bary, tri_vertices, tissue_q, tissue, patch):
    """The tissue point ``p`` (3,) m an anchor row holds the tip against and its generalised inverse mass
    ``(3, 3)`` (1/kg): ``sum_k c_k^2 w_k I`` with the diagonal compliance, the point's compliance block
    otherwise (:mod:`~suture_gym.sim.coupling.compliance`). The point is the patch's ``sum_i c_i x_i +
    offset`` (:class:`CouplingWork` ``tip_patch``) when it has vertices, else ``sum_k b_k x_k`` of ``tri``."""
    vertex, weight, count, offset, _ = patch
    k_tissue = np.zeros((3, 3))
    if count[0] == 0:
        i0 = tri_vertices[tri, 0]
        i1 = tri_vertices[tri, 1]
        i2 = tri_vertices[tri, 2]
        p = bary[0] * tissue_q[i0] + bary[1] * tissue_q[i1] + bary[2] * tissue_q[i2]
        if is_diagonal(tissue):
            w = tissue[0]
            w_tissue = bary[0] ** 2 * w[i0] + bary[1] ** 2 * w[i1] + bary[2] ** 2 * w[i2]
            for a in range(3):
                k_tissue[a, a] = w_tissue
        else:
            point_compliance(tissue, tri_vertices[tri], bary, bary.shape[0], k_tissue)
        return p, k_tissue
    p = offset.copy()
    w_tissue = 0.0
    for a in range(count[0]):
        p += weight[a] * tissue_q[vertex[a]]
        w_tissue += weight[a] ** 2 * tissue[0][vertex[a]]
    if is_diagonal(tissue):
        for a in range(3):
            k_tissue[a, a] = w_tissue
    else:
        point_compliance(tissue, vertex, weight, count[0], k_tissue)
    return p, k_tissue


@njit(cache=True, inline="always")
def _project_anchor(
    needle_inv_mass,
    needle_inv_inertia_body,
    node_body,
    tri,
    bary,
    normal,
    tri_vertices,
    tissue,
    eps,
    floor,
    friction,
    lam,
    friction_out,
    patch,
    dt,
    needle_pos,
    needle_quat,
    tissue_q,
):
    """The tip's anchor row: the tip held ``eps`` above its anchor ``p`` (eq. 2 with the contact point fixed in
    the material, ``C_n = (q - p) . n - eps >= floor``) and over it across the normal, within a Coulomb cone;
    returns the updated normal multiplier (``lam`` in, kept ``>= 0``). ``p`` is the point ``sum_k b_k x_k`` of
    the anchor triangle, or, with the tip-contact model, the tip's contact patch ``sum_i c_i x_i + offset``
    (``patch``, :class:`CouplingWork` ``tip_patch``; :func:`_anchor_point`). The exit anchor (ROW_EXIT) is the
    same row with the normal turned inward: the tip held ``eps`` inside.

    The tip is a point of a rigid body whose generalised inverse mass is a full 3 x 3 matrix
    (``K = I/m - [r]x I^-1 [r]x``, :func:`~suture_gym.sim.needle.point_inv_mass_matrix`, plus the anchor's
    ``sum_k b_k^2 w_k``): an impulse across the normal also moves the tip along it and sideways, so the
    normal and friction rows are solved together as one point constraint: the impulse ``P = K^-1 (t - q)``
    that puts the tip on its target ``t = p + (eps + floor) n``. With the patch's series compliance ``alpha``
    (m/N, isotropic: the tangential compliance of a punch is taken equal to its normal one) the row is an XPBD
    spring in series: ``P = (K + alpha/dt^2 I)^-1 (t - q - alpha/dt^2 Lambda)`` with ``Lambda`` the impulse
    accumulated this substep (kg m), and ``floor`` is not applied (the spring lets the tip sink by
    ``alpha F``, which is not an old penetration). If the accumulated tangential impulse (``friction_out[:3]``,
    kg m) would leave the cone ``|P_t| <= friction * P_n``, it is scaled back onto it and the normal part
    re-solved with it fixed, so the tip slides; ``friction_out[3]`` gets the tangential offset left, m (0 while
    the tip sticks). The needle takes ``P`` at the tip, tissue vertex ``k`` moves by ``-w_k c_k P``. Updates the
    needle pose, ``tissue_q`` and ``friction_out`` (4,).
    """
    p, k_tissue = _anchor_point(tri, bary, tri_vertices, tissue_q, tissue, patch)
    alpha = patch[4][0] / (dt * dt)
    if alpha > 0.0:
        floor = 0.0
    q = body_point(needle_pos, needle_quat, node_body)
    d = p + (eps + floor) * normal - q
    friction_out[3] = 0.0
    if d @ normal <= 0.0 and lam == 0.0:  # clear of the surface: no load, the tip slides freely
        offset = d - (d @ normal) * normal
        friction_out[3] = math.sqrt(offset @ offset)
        return lam
    inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
    r = q - needle_pos
    k = point_inv_mass_matrix(needle_inv_mass, inv_inertia, r)
    if is_diagonal(tissue):
        for a in range(3):
            k[a, a] += k_tissue[a, a]
    else:
        k += k_tissue
    if alpha > 0.0:
        d = d - alpha * (lam * normal + friction_out[:3])
        for a in range(3):
            k[a, a] += alpha
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
            friction_out[3] = max(math.sqrt(offset @ offset), TINY_LENGTH)
    friction_out[:3] += impulse - (impulse @ normal) * normal
    rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, impulse, cross3(r, impulse), 1.0)
    vertex, weight, count = patch[0], patch[1], patch[2][0]
    tissue_inv_mass = tissue[0]
    if not is_diagonal(tissue):
        if count == 0:
            apply_impulse(tissue, tri_vertices[tri], bary, bary.shape[0], impulse, tissue_q)
        else:
            apply_impulse(tissue, vertex, weight, count, impulse, tissue_q)
    elif count == 0:
        for a in range(3):
            vi = tri_vertices[tri, a]
            tissue_q[vi] -= tissue_inv_mass[vi] * bary[a] * impulse
    else:
        for a in range(count):
            vi = vertex[a]
            tissue_q[vi] -= tissue_inv_mass[vi] * weight[a] * impulse
    return lam + (impulse @ normal)


@njit(cache=True)
def project_needle_rows(needle, tissue, coefficients, rows, tip_friction_out, needle_pos, needle_quat, tissue_q):
    """One Gauss-Seidel pass over the rows of the needle nodes (strand nodes ``0 .. Nn-1``).

    Contact rows (ROW_TRIANGLE, ROW_WALL, ROW_ANCHOR, ROW_EXIT: :func:`node_surface_constraint` in the row's frame,
    ``C >= row_floor``, multiplier kept ``>= 0``) and node-path rows (eq. 1) are rigid (zero compliance) and
    two-way (:func:`_project_contact`, :func:`_project_path_row`): ``dlambda = -C / (w_needle + sum_k b_k^2 w_k)``
    with ``w_needle`` the needle's generalised inverse mass at the node along the gradient; the needle takes the
    impulse ``dlambda n`` at the node, tissue vertex ``k`` moves by ``-w_k b_k dlambda n``. The tip's anchor row
    adds Coulomb friction with coefficient ``tip_friction`` (:func:`_project_anchor`; its tangential impulse
    and slip in ``tip_friction_out`` (4,)). A node-path row's impulse is kept within ``tear_force dt^2`` in
    size (the tissue gives way beyond it). After each path row, kinetic axial friction
    (:func:`_project_axial_friction`). Last the tip's cutting row, if any (:func:`project_cutting`). Updates the
    needle pose, ``tissue_q`` and the multipliers.

    Args:
        needle: ``(Nn, inv_mass 1/kg, inv_inertia_body (3, 3), node_body (Nn, 3) m, pos_prev (3,) m,
            quat_prev (4,))``: the needle's nodes, inertia and pose at the start of the substep.
        tissue: ``(inv_mass (N,) 1/kg, q_prev (N, 3) m, tri_vertices (F, 3))``.
        coefficients: ``(strand_friction (M,) N, eps m, dt s, tip_friction, tear_force N)``.
        rows: ``CouplingWork.needle_rows``: ``(row_kind, row_tri, row_bary, row_contact_normal, row_floor,
            row_tissue, row_weight, row_tangent, row_lambda, row_friction_lambda, tip_patch, cut_rows,
            row_impulse)`` (:class:`CouplingWork`).
        tip_friction_out: ``(4,)``. needle_pos: ``(3,)`` m, needle_quat: ``(4,)``, tissue_q: ``(N, 3)`` m.
    """
    needle_node_count, needle_inv_mass, needle_inv_inertia_body, needle_node_body = needle[:4]
    compliance, _, tri_vertices = tissue
    _, eps, dt, tip_friction, _ = coefficients
    row_kind, row_tri, row_bary, row_contact_normal, row_floor = rows[:5]
    row_lambda = rows[8]
    for i in range(needle_node_count):
        kind = row_kind[i]
        if kind == ROW_NONE:
            continue
        if kind == ROW_ANCHOR or kind == ROW_EXIT:
            row_lambda[i] = _project_anchor(
                needle_inv_mass, needle_inv_inertia_body, needle_node_body[i], row_tri[i], row_bary[i],
                row_contact_normal[i], tri_vertices, compliance, eps, row_floor[i], tip_friction,
                row_lambda[i], tip_friction_out, rows[10], dt, needle_pos, needle_quat, tissue_q,
            )  # fmt: skip
        elif kind != ROW_PATH:
            row_lambda[i] = _project_contact(
                needle_inv_mass, needle_inv_inertia_body, needle_node_body[i], row_tri[i], row_bary[i],
                row_contact_normal[i], tri_vertices, compliance, eps, row_floor[i], row_lambda[i],
                needle_pos, needle_quat, tissue_q,
            )  # fmt: skip
        else:
            _project_path_row(i, needle, compliance, coefficients, rows, needle_pos, needle_quat, tissue_q)
            _project_axial_friction(i, needle, tissue, coefficients, rows, needle_pos, needle_quat, tissue_q)
    if rows[11][3][0] > 0.0:
        project_cutting(needle, tissue, dt, rows[11], needle_pos, needle_quat, tissue_q)


@njit(cache=True, inline="always")
def project_cutting(needle, tissue, dt, cut, needle_pos, needle_quat, tissue_q):
    """The tip's cutting row (Okamura et al. 2004: a constant cutting force while the tip advances): the tip's
    advance along its direction ``t`` relative to the tissue point ``p`` since the start of the substep,
    ``s = ((q - q0) - (p - p0)) . t``, is removed by a multiplier kept in ``[-cap dt^2, 0]``: the tip advances
    only under more than ``cap`` N along ``t`` and is then resisted by exactly ``cap``; a tip that stands or
    retreats feels nothing. Two-way: the tissue point takes the reaction. Like the axial friction it is solved
    against the needle's generalised inverse mass along ``t`` at the tip plus the tissue point's.

    Args:
        needle: as :func:`project_needle_rows`. tissue: ``(compliance, q_prev (N, 3) m, tri_vertices)``.
        dt: s. cut: ``CouplingWork.cut_rows`` ``(tissue (4,), weight (4,), direction (3,), cap (1,) N,
            lambda (1,) kg m)``; ``lambda`` accumulates over the sweeps of the substep.
        needle_pos, needle_quat, tissue_q: updated in place.
    """
    _, needle_inv_mass, needle_inv_inertia_body, needle_node_body, needle_pos_prev, needle_quat_prev = needle
    compliance, tissue_q_prev, _ = tissue
    idx, wt, t, cap_force, lam = cut
    cap = cap_force[0] * dt * dt
    inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
    q = body_point(needle_pos, needle_quat, needle_node_body[0])
    r = q - needle_pos
    q0 = body_point(needle_pos_prev, needle_quat_prev, needle_node_body[0])
    p = tissue_point(tissue_q, idx, wt)
    p0 = tissue_point(tissue_q_prev, idx, wt)
    advance = _relative_advance(q, q0, p, p0, t)
    w_tissue = weighted_inv_mass(compliance, idx, wt, t)
    w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, t, cross3(r, t)) + w_tissue
    dlam = xpbd_delta_lambda(advance, w, 0.0, 0.0)
    total = min(max(lam[0] + dlam, -cap), 0.0)
    dlam = total - lam[0]
    lam[0] = total
    rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, t, cross3(r, t), dlam)
    move_point(compliance, idx, wt, dlam, t, tissue_q)


@njit(cache=True, inline="always")
def _project_path_row(i, needle, compliance, coefficients, rows, needle_pos, needle_quat, tissue_q):
    """Needle node ``i``'s node-path row (eq. 1, :func:`node_path_constraint`), rigid and two-way.

    The row's direction ``n`` turns with the node's offset from the path between projections, so its impulse on
    the needle this substep, ``row_impulse[i]`` (kg m), is summed as a vector and kept within ``tear_force dt^2``
    in size (a step that would take it beyond is cut to reach the bound: the tissue gives way); ``row_lambda[i]``
    is minus its size, the force the readings take. (Summed as a scalar, a row pulled one way and then back read,
    and was bounded at, the sum of the two steps' sizes, not the impulse it gave.) Arguments as
    :func:`project_needle_rows`."""
    _, needle_inv_mass, needle_inv_inertia_body, needle_node_body = needle[:4]
    _, _, dt, _, tear_force = coefficients
    idx, wt, t, row_lambda, total = rows[5][i], rows[6][i], rows[7][i], rows[8], rows[12]
    inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
    q = body_point(needle_pos, needle_quat, needle_node_body[i])
    r = q - needle_pos
    p = tissue_point(tissue_q, idx, wt)
    ok, c, n = node_path_constraint(q, p, t)
    if ok:
        w_tissue = weighted_inv_mass(compliance, idx, wt, n)
        w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, n, cross3(r, n)) + w_tissue
        dlam = xpbd_delta_lambda(c, w, 0.0, 0.0)
        # the step dlam n, cut back onto the bound if it would take the summed impulse past it; n is reused for it
        a0, a1, a2 = total[i, 0] + dlam * n[0], total[i, 1] + dlam * n[1], total[i, 2] + dlam * n[2]
        size = math.sqrt(a0 * a0 + a1 * a1 + a2 * a2)
        scale = min(1.0, tear_force * dt * dt / size) if size > 0.0 else 1.0
        n[0], n[1], n[2] = a0 * scale - total[i, 0], a1 * scale - total[i, 1], a2 * scale - total[i, 2]
        total[i, 0], total[i, 1], total[i, 2] = a0 * scale, a1 * scale, a2 * scale
        rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, n, cross3(r, n), 1.0)
        move_point(compliance, idx, wt, 1.0, n, tissue_q)
    row_lambda[i] = -math.sqrt(total[i, 0] ** 2 + total[i, 1] ** 2 + total[i, 2] ** 2)


@njit(cache=True, inline="always")
def _relative_advance(q, q0, p, p0, t):
    """``((q - q0) - (p - p0)) . t`` (m) of (3,) arrays, in scalars (no temporaries, no BLAS call)."""
    total = 0.0
    for i in range(3):
        total += ((q[i] - q0[i]) - (p[i] - p0[i])) * t[i]
    return total


@njit(cache=True, inline="always")
def _project_axial_friction(i, needle, tissue, coefficients, rows, needle_pos, needle_quat, tissue_q):
    """Kinetic axial friction of needle node ``i`` on its path: the relative displacement of node and path point
    along the tangent since the start of the substep is removed up to a multiplier of ``strand_friction[i] dt^2``
    in magnitude (static below the cap, sliding at the cap). Arguments as :func:`project_needle_rows`."""
    _, needle_inv_mass, needle_inv_inertia_body, needle_node_body, needle_pos_prev, needle_quat_prev = needle
    compliance, tissue_q_prev, _ = tissue
    strand_friction, _, dt, _, _ = coefficients
    idx, wt, t, row_friction_lambda = rows[5][i], rows[6][i], rows[7][i], rows[9]
    cap = strand_friction[i] * dt * dt
    if cap <= 0.0:
        return
    inv_inertia = world_inv_inertia(needle_quat, needle_inv_inertia_body)
    q = body_point(needle_pos, needle_quat, needle_node_body[i])
    r = q - needle_pos
    q0 = body_point(needle_pos_prev, needle_quat_prev, needle_node_body[i])
    p = tissue_point(tissue_q, idx, wt)
    p0 = tissue_point(tissue_q_prev, idx, wt)
    slip = _relative_advance(q, q0, p, p0, t)
    w = rigid_generalized_inv_mass(needle_inv_mass, inv_inertia, t, cross3(r, t)) + weighted_inv_mass(
        compliance, idx, wt, t
    )
    dlam = xpbd_delta_lambda(slip, w, 0.0, 0.0)
    total = min(max(row_friction_lambda[i] + dlam, -cap), cap)
    dlam = total - row_friction_lambda[i]
    row_friction_lambda[i] = total
    rigid_apply(needle_pos, needle_quat, needle_inv_mass, inv_inertia, t, cross3(r, t), dlam)
    move_point(compliance, idx, wt, dlam, t, tissue_q)
