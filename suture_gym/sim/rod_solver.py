"""The direct block-tridiagonal XPBD solve of the suture rod (:mod:`suture_gym.sim.rod`): the constraint maths,
their linearisation into the block system, its solve and the application of the multiplier steps.

The rod's module docstring describes the model and the solver; :func:`rod_iteration_kernel` is one iteration.
Kernels take their arrays in groups (tuples built once by :class:`~suture_gym.sim.rod.RodWork`), named as there:

* ``rod``: ``(node_inv_mass (N,) 1/kg, seg_rest_length (N-1,) m, seg_inv_inertia (N-1, 3) 1/(kg m^2),
  seg_stretch_compliance (N-1, 3), bend_compliance (N-2, 3), contact_w (N,) 1/kg, axis_inv_mass (N,) 1/kg,
  axis (N, 3))``: node ``i``'s inverse mass is the matrix ``W_i = w_i I + a_i t_i t_i^T`` (``w_i``
  ``node_inv_mass``, ``a_i`` ``axis_inv_mass``, unit ``t_i`` ``axis``; ``a_i = 0`` for an isotropic node,
  see :func:`inv_mass_times`);
* ``needle``: ``(has_needle, needle_inv_mass 1/kg, needle_inv_inertia_body (3, 3), swage_body (3,) m)``;
* ``start``: ``RodWork.start``, ``(seg_quat_start (N-1, 4), seg_tension_prev (N-1,) kg m^2)``;
* ``frames``: ``RodWork.frames``, ``(seg_rot, seg_s, seg_winv (N-1, 3, 3), bend_b (N-2, 3, 3), seg_h (N-1, 3),
  att_r (3,), att_winv (3, 3))``;
* ``contacts``: ``RodWork.contacts``, ``(contact_gap (N,) m, contact_normal (N, 3), contact_active (N,),
  contact_push (N, 3) m, contact_cap (N,) kg m, contact_eligible (N,) bool)``: row 6 of node ``i`` is a
  one-sided contact where ``contact_cap[i] == 0`` and a two-sided friction row whose accumulated multiplier stays
  within ``+-contact_cap[i]`` where it is positive; a penetrating node that does not yet push opens its contact
  row only where ``contact_eligible[i]`` (:func:`_contact_rows`);
* ``system``: ``RodWork.system``, ``(diag, lower, fac (N, 7, 7), rhs, y, z (N, 7))``.

The 3 x 3 and quaternion helpers the rows are built with and the block solve are in
:mod:`~suture_gym.sim.rod_linalg`, compiled into these kernels.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.quat import (
    cross3,
    quat_premultiply_row,
    quat_to_matrix,
    quat_to_matrix_into,
    quat_to_matrix_row,
    quat_turn_into,
    quat_turn_row,
)
from suture_gym.sim.rod_linalg import (
    ab_into,
    abt_acc,
    darboux,
    mtv_acc,
    mv_acc,
    relative_rotation_vector,
    rot_diag_into,
    skew_into,
    skew_times_into,
    solve_block_tridiagonal,
    times_skew_t_acc,
)

#: Weight of the frames' Newton residual |h| (rad) in the convergence measure. Measured on a 200-node thread
#: dragged over the ground: once |h| <= 1e-3 rad the nodes are within ~3e-8 m (3e-5 of a segment) of the fully
#: converged solve, so a tolerance of 1e-6 on the weighted value stops there.
_FRAME_RESIDUAL_WEIGHT = 1.0e-3
#: Most re-solves per iteration for releasing contacts that would pull (a thread peeling off the ground or the
#: tissue releases about one node per pass; the rest follow in the next iterations).
_MAX_RELEASE_PASSES = 4


# ---------------------------------------------------------------------------------------------------------
# Constraint maths
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def inv_mass_times(rod, i, v, iv, out, io):
    """``out[io] = W_i v[iv]`` (3,): node ``i``'s inverse mass matrix ``w_i I + a_i t_i t_i^T`` (``rod`` group, module
    docstring) times a vector. With ``a_i = 0`` this is ``w_i v`` to the bit."""
    axis = rod[7]
    w, a = rod[0][i], rod[6][i]
    at = a * (axis[i, 0] * v[iv, 0] + axis[i, 1] * v[iv, 1] + axis[i, 2] * v[iv, 2])
    for k in range(3):
        out[io, k] = w * v[iv, k] + at * axis[i, k]


@njit(cache=True, inline="always")
def _add_axis_inv_mass(rod, i, scale, out, io, r0, c0):
    """``out[io, r0:r0+3, c0:c0+3] += scale * a_i t_i t_i^T``: the anisotropic part of node ``i``'s inverse mass."""
    a, axis = rod[6][i], rod[7]
    if a == 0.0:
        return
    for k in range(3):
        for m in range(3):
            out[io, r0 + k, c0 + m] += scale * a * axis[i, k] * axis[i, m]


@njit(cache=True)
def stretch_shear_constraint(x0, x1, q, rest_length):
    """Stretch-shear ``C = (x1 - x0) / l - d3(q)`` (3,) of one segment (Kugelstadt & Schomer 2016).

    ``x0, x1`` (3,) m, ``q`` (4,) unit, ``rest_length`` m. Gradients: ``dC/dx1 = I/l``, ``dC/dx0 = -I/l`` and,
    for a world rotation-vector perturbation ``q <- exp(dtheta/2) q``, ``dC/dtheta = [d3]x``
    (:func:`stretch_shear_jacobian`).
    """
    r = quat_to_matrix(q)
    out = np.empty(3)
    for i in range(3):
        out[i] = (x1[i] - x0[i]) / rest_length - r[i, 2]
    return out


@njit(cache=True)
def stretch_shear_jacobian(q):
    """``dC_ss / dtheta = [d3(q)]x`` (3, 3) for a world rotation vector ``dtheta`` applied to ``q``."""
    r = quat_to_matrix(q)
    s = np.zeros((1, 3, 3))
    skew_into(r[0, 2], r[1, 2], r[2, 2], s, 0)
    return s[0]



@njit(cache=True)
def bend_twist_constraint(q0, q1):
    """Bend-twist ``C = Im(conj(q0) q1)`` (3,) in q0's frame, rest shape straight (Kugelstadt & Schomer 2016).

    ``C ~ (l/2) Omega`` with Omega the discrete Darboux vector (curvatures about d1, d2 and twist about d3);
    the sign of ``conj(q0) q1`` is chosen with a non-negative real part.
    """
    quats = np.empty((2, 4))
    quats[0] = q0
    quats[1] = q1
    _, x, y, z = darboux(quats, 0, 1)
    out = np.empty(3)
    out[0] = x
    out[1] = y
    out[2] = z
    return out


@njit(cache=True, inline="always")
def _bend_twist_jacobian_into(quats, j, rot, out, io):
    """Write ``B = 1/2 (r_w I - [r_v]x) R0^T`` of ``q0 = quats[j]``, ``q1 = quats[j + 1]`` into ``out[io]`` (3, 3);
    ``rot[j]`` (3, 3) is ``R(q0)``."""
    w, x, y, z = darboux(quats, j, j + 1)
    # the rows of r_w I - [r_v]x, without an allocation (this runs once per segment and iteration)
    for k in range(3):
        out[io, 0, k] = 0.5 * (w * rot[j, k, 0] + z * rot[j, k, 1] + -y * rot[j, k, 2])
        out[io, 1, k] = 0.5 * (-z * rot[j, k, 0] + w * rot[j, k, 1] + x * rot[j, k, 2])
        out[io, 2, k] = 0.5 * (y * rot[j, k, 0] + -x * rot[j, k, 1] + w * rot[j, k, 2])


@njit(cache=True)
def bend_twist_jacobian(q0, q1):
    """``B = dC_bt / dtheta1 = 1/2 (r_w I - [r_v]x) R(q0)^T`` (3, 3); ``dC_bt / dtheta0 = -B``.

    ``r = conj(q0) q1`` (sign as in :func:`bend_twist_constraint`), ``dtheta`` world rotation vectors.
    """
    quats = np.empty((2, 4))
    quats[0] = q0
    quats[1] = q1
    rot = np.empty((1, 3, 3))
    quat_to_matrix_into(q0, rot[0])
    out = np.empty((1, 3, 3))
    _bend_twist_jacobian_into(quats, 0, rot, out, 0)
    return out[0]



# ---------------------------------------------------------------------------------------------------------
# Iteration: linearise, solve, apply
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def align_frames(node_pos, seg_inv_inertia, seg_quat):
    """Parallel-transport each free segment frame so that d3 points along its edge (minimal rotation).

    Clamped segments (zero inverse inertia) and zero-length edges are left alone. Updates ``seg_quat``.
    """
    for j in range(seg_quat.shape[0]):
        if seg_inv_inertia[j, 0] == 0.0 and seg_inv_inertia[j, 1] == 0.0 and seg_inv_inertia[j, 2] == 0.0:
            continue
        ex = node_pos[j + 1, 0] - node_pos[j, 0]
        ey = node_pos[j + 1, 1] - node_pos[j, 1]
        ez = node_pos[j + 1, 2] - node_pos[j, 2]
        en = np.sqrt(ex * ex + ey * ey + ez * ez)
        if en == 0.0:
            continue
        w, x, y, z = seg_quat[j, 0], seg_quat[j, 1], seg_quat[j, 2], seg_quat[j, 3]
        dx, dy, dz = 2.0 * (x * z + w * y), 2.0 * (y * z - w * x), 1.0 - 2.0 * (x * x + y * y)  # d3(q)
        ex, ey, ez = ex / en, ey / en, ez / en
        cx, cy, cz = dy * ez - dz * ey, dz * ex - dx * ez, dx * ey - dy * ex  # d3 x edge
        s = np.sqrt(cx * cx + cy * cy + cz * cz)
        c = dx * ex + dy * ey + dz * ez
        if s < 1.0e-15 and c > 0.0:
            continue
        if s < 1.0e-15:  # antiparallel: half turn about an axis perpendicular to d3
            ax, ay, az = (dz, 0.0, -dx) if abs(dy) > 0.5 else (-dy, dx, 0.0)
            quat_premultiply_row(seg_quat, j, 0.0, ax, ay, az)
        else:
            # the turn by the angle between them about d3 x edge, as the unnormalised quaternion (1 + cos, sin
            # axis) = 2 cos(angle / 2) (cos(angle / 2), sin(angle / 2) axis): no trigonometric call
            quat_premultiply_row(seg_quat, j, 1.0 + c, cx, cy, cz)


@njit(cache=True, inline="always")
def assemble_rod_system(node_pos, seg_quat, rod, needle, start, frames, contacts, system, lam, needle_pos, needle_quat,
                        dt, tolerance, check_first):  # fmt: skip
    """Linearise all rod constraints at the current configuration into the block-tridiagonal XPBD system.

    With ``check_first`` the residual (below) is computed first and, if it is within ``tolerance``, ``diag``,
    ``lower`` and ``rhs`` are left as they are: the iteration that only confirms convergence, one in every
    substep's solve, skips its matrices (27 against 48 us on the paper cube's 200-node suture; the residual pass
    costs the iterations that do build about 4 us). Without it the system is built straight away (a substep's
    first iteration, which never finds the rod converged after the prediction).

    Rows (see :class:`~suture_gym.sim.rod.RodWork`): attachment ``C = x_0 - (p_needle + R s_swage)`` (rigid),
    stretch-shear and bend-twist per segment, and a one-sided contact ``C = gap_i`` along ``contact_normal[i]``
    for node i, active while the node already pushes (``lam[i, 6] > 0``) or penetrates (``contact_gap[i] < 0``)
    and is ``contact_eligible``. Unused rows carry an identity diagonal and a zero right-hand side.

    Outputs (argument groups in the module docstring): Jacobian pieces ``seg_rot``, ``seg_s`` (= [d3]x),
    ``seg_winv``, ``bend_b``, frame residuals ``seg_h``, ``att_r``, ``att_winv``, ``contact_active``, and
    ``diag``, ``lower`` (N, 7, 7), ``rhs`` (N, 7) = ``-C - alpha~ lambda + J_theta h``, ``alpha~ = alpha/dt^2``;
    ``lam`` (N, 7) holds the multipliers so far, ``needle_pos`` (3,) m and ``needle_quat`` (4,) the needle's pose.

    Frame "mass": the frames are nearly massless, so their block uses inertia plus the geometric stiffness of
    the stretch-shear rows, ``|lambda_ss| (I - d3 d3^T)`` (a bound on the lambda-weighted Hessian of
    ``-d3(theta)``; the previous substep's value stands in while this substep's multipliers build up), and
    about ``d3`` that of the bend-twist rows on either side, ``(|lambda_bt,j| + |lambda_bt,j+1|) / 4``, and
    keeps their Newton residual ``h = W (I dtheta - J_theta^T lambda)`` in the right-hand side, so the
    stiffness shapes the steps but not the solution. Without it Newton steps on the frames diverge under load;
    without the twist term a thread held in the tissue's paths creeps along its twist (its frames' inertia about
    ``d3`` is ~1e-15 kg m^2), its ``|h|`` shrinking 3% an iteration, and the solve never reaches its tolerance.

    Returns the largest residual before the solve, dimensionless: ``|C + alpha~ lambda|`` (strain for
    stretch-shear, half-angle for bend-twist, gap / segment length for attachment and contacts) and
    ``1e-3 |h|`` (h in rad, see :data:`_FRAME_RESIDUAL_WEIGHT`).
    """
    frame_residual = _frame_blocks(seg_quat, rod[2], start, frames, lam, 0.0)
    if check_first:
        residual = _constraint_rows(node_pos, seg_quat, rod, needle, frames, contacts, system, lam, needle_pos,
                                    needle_quat, dt, frame_residual, False)  # fmt: skip
        if residual <= tolerance:
            return residual
    diag, lower, _, rhs = system[:4]
    diag[:] = 0.0
    lower[:] = 0.0
    rhs[:] = 0.0
    return _constraint_rows(node_pos, seg_quat, rod, needle, frames, contacts, system, lam, needle_pos, needle_quat,
                            dt, frame_residual, True)  # fmt: skip


@njit(cache=True, inline="always")
def _constraint_rows(node_pos, seg_quat, rod, needle, frames, contacts, system, lam, needle_pos, needle_quat, dt,
                     residual, build):  # fmt: skip
    """The attachment, segment and contact rows: their residuals (``residual`` raised to them is returned) and,
    with ``build``, their blocks of ``diag``, ``lower`` and ``rhs`` (zeroed by the caller). Without ``build``
    only ``att_r`` and ``contact_active`` are written, as with it."""
    residual = _attachment_block(node_pos, rod, needle, frames, system, needle_pos, needle_quat, residual, build)
    residual = _segment_blocks(node_pos, seg_quat, rod, needle[0], frames, system, lam, dt, residual, build)
    return _contact_rows(rod, needle[0], contacts, system, lam, residual, build)


@njit(cache=True, inline="always")
def _frame_blocks(seg_quat, seg_inv_inertia, start, frames, lam, residual):
    """Frame Jacobians (``seg_rot``, ``seg_s``, ``bend_b``), inverse "mass" ``W_j`` and Newton residual
    ``h_j = W_j (I_j dtheta_j - (J_theta^T lambda)_j)`` of every segment frame; returns ``residual`` raised to
    the frames' weighted ``|h|``."""
    seg_quat_start, seg_tension_prev = start
    seg_rot, seg_s, seg_winv, bend_b, seg_h = frames[:5]
    nseg = seg_quat.shape[0]
    inertia = np.empty((1, 3))
    winv_mod = np.empty((1, 3))
    body = np.empty((1, 3))
    g = np.empty((1, 3))
    dth = np.empty((1, 3))
    for j in range(nseg):
        quat_to_matrix_row(seg_quat, j, seg_rot, j)
        skew_into(seg_rot[j, 0, 2], seg_rot[j, 1, 2], seg_rot[j, 2, 2], seg_s, j)
    for j in range(nseg - 1):
        _bend_twist_jacobian_into(seg_quat, j, seg_rot, bend_b, j)
    _frame_torque(lam, seg_s, bend_b, seg_h)
    for j in range(nseg):
        if not (seg_inv_inertia[j, 0] > 0.0 and seg_inv_inertia[j, 1] > 0.0 and seg_inv_inertia[j, 2] > 0.0):
            for i in range(3):
                seg_h[j, i] = 0.0
                for k in range(3):
                    seg_winv[j, i, k] = 0.0
            continue
        stiff = max(np.sqrt(lam[j + 1, 0] ** 2 + lam[j + 1, 1] ** 2 + lam[j + 1, 2] ** 2), seg_tension_prev[j])
        for i in range(3):
            inertia[0, i] = 1.0 / seg_inv_inertia[j, i]
        winv_mod[0, 0] = 1.0 / (inertia[0, 0] + stiff)
        winv_mod[0, 1] = 1.0 / (inertia[0, 1] + stiff)
        # twist: the bend-twist rows on either side, |lambda_bt| / 4 each (a row-sum bound on their lambda-weighted
        # Hessian: d^2 Im(conj(q0) q1) / dtheta^2 is -C/4 on a frame and at most 1/4 across the two frames)
        twist_stiff = 0.0
        if j >= 1:
            twist_stiff += 0.25 * np.sqrt(lam[j, 3] ** 2 + lam[j, 4] ** 2 + lam[j, 5] ** 2)
        if j < nseg - 1:
            twist_stiff += 0.25 * np.sqrt(lam[j + 1, 3] ** 2 + lam[j + 1, 4] ** 2 + lam[j + 1, 5] ** 2)
        winv_mod[0, 2] = 1.0 / (inertia[0, 2] + twist_stiff)
        rot_diag_into(seg_rot, j, winv_mod, 0, 1.0, seg_winv, j)
        relative_rotation_vector(seg_quat, j, seg_quat_start, dth, 0)
        # g = R diag(inertia) R^T dtheta - (J_theta^T lambda)_j, through the body frame
        for k in range(3):
            body[0, k] = inertia[0, k] * (
                seg_rot[j, 0, k] * dth[0, 0] + seg_rot[j, 1, k] * dth[0, 1] + seg_rot[j, 2, k] * dth[0, 2]
            )
        for i in range(3):
            g[0, i] = -seg_h[j, i]
        mv_acc(seg_rot, j, body, 0, 1.0, g, 0)
        for i in range(3):
            seg_h[j, i] = 0.0
        mv_acc(seg_winv, j, g, 0, 1.0, seg_h, j)
        residual = max(residual, _FRAME_RESIDUAL_WEIGHT * max(abs(seg_h[j, 0]), abs(seg_h[j, 1]), abs(seg_h[j, 2])))
    return residual


@njit(cache=True, inline="always")
def _attachment_block(node_pos, rod, needle, frames, system, needle_pos, needle_quat, residual, build):
    """Block 0: the attachment of node 0 to the needle swage (rows 0-2; identity rows without a needle) and the
    unused rows 3-5. Writes ``att_r`` (and with ``build`` ``att_winv`` and the block); returns ``residual`` raised
    to the attachment's."""
    node_inv_mass, seg_rest_length = rod[0], rod[1]
    has_needle, needle_inv_mass, needle_inv_inertia_body, swage_body = needle
    att_r, att_winv = frames[5], frames[6]
    diag, rhs = system[0], system[3]
    if has_needle:  # once per iteration: the helpers' stacks are made of the single arrays by reshaping
        rn = np.empty((1, 3, 3))
        quat_to_matrix_row(needle_quat.reshape(1, 4), 0, rn, 0)
        r = att_r.reshape(1, 3)
        att_r[:] = 0.0
        mv_acc(rn, 0, swage_body.reshape(1, 3), 0, 1.0, r, 0)
        for i in range(3):
            val = -(node_pos[0, i] - needle_pos[i] - att_r[i])
            residual = max(residual, abs(val) / seg_rest_length[0])
            if build:
                rhs[0, i] = val
        if build:
            tmp = np.empty((1, 3, 3))
            tmp2 = np.empty((1, 3, 3))
            winv = att_winv.reshape(1, 3, 3)
            ab_into(rn, 0, needle_inv_inertia_body.reshape(1, 3, 3), 0, tmp, 0)
            att_winv[:] = 0.0
            abt_acc(tmp, 0, rn, 0, 1.0, winv, 0, 0, 0)
            skew_into(att_r[0], att_r[1], att_r[2], tmp2, 0)
            ab_into(tmp2, 0, winv, 0, tmp, 0)
            abt_acc(tmp, 0, tmp2, 0, 1.0, diag, 0, 0, 0)
            for i in range(3):
                diag[0, i, i] += node_inv_mass[0] + needle_inv_mass
            _add_axis_inv_mass(rod, 0, 1.0, diag, 0, 0, 0)
    elif build:
        for i in range(3):
            diag[0, i, i] = 1.0
    if build:
        for i in range(3, 6):
            diag[0, i, i] = 1.0
    return residual


@njit(cache=True, inline="always")
def _stretch_value(node_pos, seg_rot, j, i, compliant, alpha, lam, l):
    """Row ``i`` of ``-C - alpha~ lambda`` of segment j's stretch-shear rows (``alpha`` (1, 3, 3) holds ``alpha~``
    in the world frame where ``compliant``; ``l`` the rest length)."""
    val = -((node_pos[j + 1, i] - node_pos[j, i]) / l - seg_rot[j, i, 2])
    if compliant:
        for k in range(3):
            val -= alpha[0, i, k] * lam[j + 1, k]
    return val


@njit(cache=True, inline="always")
def _bend_values(seg_quat, j, bend_compliance, lam, inv_dt2):
    """``-C - alpha~ lambda`` (a 3-tuple) of the bend-twist rows of segments j, j+1."""
    _, c_x, c_y, c_z = darboux(seg_quat, j, j + 1)  # bend_twist_constraint, as scalars
    b = j + 1
    return (
        -c_x - bend_compliance[j, 0] * inv_dt2 * lam[b, 3],
        -c_y - bend_compliance[j, 1] * inv_dt2 * lam[b, 4],
        -c_z - bend_compliance[j, 2] * inv_dt2 * lam[b, 5],
    )


@njit(cache=True, inline="always")
def _segment_blocks(node_pos, seg_quat, rod, has_needle, frames, system, lam, dt, residual, build):
    """Blocks 1..N-1: the stretch-shear rows of segment j and the bend-twist rows of segments j, j+1 in block
    j+1, and their coupling with block j through ``x_j`` (and ``q_j``); returns ``residual`` raised to theirs.
    Without ``build`` only the residual."""
    node_inv_mass, seg_rest_length, _, seg_stretch_compliance, bend_compliance = rod[:5]
    seg_rot, seg_s, seg_winv, bend_b, seg_h = frames[:5]
    diag, lower, _, rhs = system[:4]
    nseg = seg_quat.shape[0]
    inv_dt2 = 1.0 / (dt * dt)
    tmp = np.empty((1, 3, 3))
    tmp2 = np.empty((1, 3, 3))
    tmp3 = np.empty((1, 3, 3))
    for j in range(nseg):
        b = j + 1
        l = seg_rest_length[j]
        # stretch-shear rows, into diag[b, :3, :3]; a rigid segment (the inextensible thread's) has no compliance
        # term: adding its zeros cost about 6% of the assembly
        compliant = (
            seg_stretch_compliance[j, 0] != 0.0 or seg_stretch_compliance[j, 1] != 0.0
            or seg_stretch_compliance[j, 2] != 0.0
        )  # fmt: skip
        if compliant:
            rot_diag_into(seg_rot, j, seg_stretch_compliance, j, inv_dt2, tmp3, 0)  # alpha~_ss, world frame
        if not build:
            for i in range(3):
                residual = max(residual, abs(_stretch_value(node_pos, seg_rot, j, i, compliant, tmp3, lam, l)))
            if j < nseg - 1:
                v0, v1, v2 = _bend_values(seg_quat, j, bend_compliance, lam, inv_dt2)
                residual = max(residual, abs(v0), abs(v1), abs(v2))
            continue
        d3x, d3y, d3z = seg_rot[j, 0, 2], seg_rot[j, 1, 2], seg_rot[j, 2, 2]
        skew_times_into(d3x, d3y, d3z, seg_winv, j, tmp, 0)  # tmp = [d3]x W_j
        times_skew_t_acc(tmp, 0, d3x, d3y, d3z, diag, b, 0, 0)
        w_sum = (node_inv_mass[j] + node_inv_mass[j + 1]) / (l * l)
        for i in range(3):
            val = _stretch_value(node_pos, seg_rot, j, i, compliant, tmp3, lam, l)
            hterm = 0.0
            diag[b, i, i] += w_sum
            if compliant:
                for k in range(3):
                    diag[b, i, k] += tmp3[0, i, k]
            for k in range(3):
                hterm += seg_s[j, i, k] * seg_h[j, k]
            rhs[b, i] = val + hterm
            residual = max(residual, abs(val))
        _add_axis_inv_mass(rod, j, 1.0 / (l * l), diag, b, 0, 0)
        _add_axis_inv_mass(rod, j + 1, 1.0 / (l * l), diag, b, 0, 0)
        if j < nseg - 1:
            residual = _bend_rows(j, seg_quat, bend_compliance, frames, diag, rhs, lam, inv_dt2, tmp, tmp2, tmp3,
                                  residual)  # fmt: skip
        else:
            for i in range(3, 6):
                diag[b, i, i] = 1.0
        # coupling with the previous block through x_j (and q_j)
        if j == 0:
            if has_needle:
                for i in range(3):
                    lower[1, i, i] = -node_inv_mass[0] / l
                _add_axis_inv_mass(rod, 0, -1.0 / l, lower, 1, 0, 0)
        else:
            lp = seg_rest_length[j - 1]
            for i in range(3):
                lower[b, i, i] = -node_inv_mass[j] / (l * lp)
            _add_axis_inv_mass(rod, j, -1.0 / (l * lp), lower, b, 0, 0)
            abt_acc(tmp, 0, bend_b, j - 1, 1.0, lower, b, 0, 3)
            if j < nseg - 1:
                ab_into(bend_b, j, seg_winv, j, tmp2, 0)
                abt_acc(tmp2, 0, bend_b, j - 1, -1.0, lower, b, 3, 3)
    return residual


@njit(cache=True, inline="always")
def _bend_rows(j, seg_quat, bend_compliance, frames, diag, rhs, lam, inv_dt2, tmp, tmp2, tmp3, residual):
    """The bend-twist rows of segments j, j+1 in block j+1 (``tmp`` (1, 3, 3) holds ``[d3_j]x W_j``; ``tmp2``,
    ``tmp3`` (1, 3, 3) are scratch); returns ``residual`` raised to theirs."""
    seg_winv, bend_b, seg_h = frames[2], frames[3], frames[4]
    b = j + 1
    for i in range(3):
        for k in range(3):
            tmp2[0, i, k] = seg_winv[j, i, k] + seg_winv[j + 1, i, k]
    ab_into(bend_b, j, tmp2, 0, tmp3, 0)
    abt_acc(tmp3, 0, bend_b, j, 1.0, diag, b, 3, 3)
    abt_acc(tmp, 0, bend_b, j, -1.0, diag, b, 0, 3)
    values = _bend_values(seg_quat, j, bend_compliance, lam, inv_dt2)
    for i in range(3):
        diag[b, 3 + i, 3 + i] += bend_compliance[j, i] * inv_dt2
        val = values[i]
        hterm = 0.0
        for k in range(3):
            hterm += bend_b[j, i, k] * (seg_h[j + 1, k] - seg_h[j, k])
            diag[b, 3 + i, k] = diag[b, k, 3 + i]
        rhs[b, 3 + i] = val + hterm
        residual = max(residual, abs(val))
    return residual


@njit(cache=True, inline="always")
def _contact_rows(rod, has_needle, contacts, system, lam, residual, build):
    """Row 6 of block i, ``C = gap_i + n_i . (x - x_i)``, coupled to the stretch-shear (or attachment) rows
    through ``x_i``: node i's one-sided contact (``C >= 0``), active while it already pushes or penetrates and is
    ``contact_eligible``; or, where ``contact_cap[i] > 0``, a friction row (``C = 0``, always active, its
    multiplier bounded by the cap in :func:`rod_iteration_kernel`). Writes ``contact_active`` (and with ``build``
    the rows); returns ``residual`` raised to the gaps' (an ineligible node's penetration counts too: the solve
    does not stop while it lasts)."""
    node_inv_mass, seg_rest_length = rod[0], rod[1]
    contact_gap, contact_normal, contact_active = contacts[:3]
    contact_cap, contact_eligible = contacts[4], contacts[5]
    diag, lower, _, rhs = system[:4]
    n = node_inv_mass.shape[0]
    nseg = n - 1
    wn = np.empty((1, 3))
    axis = rod[7]
    for i in range(n):
        w = node_inv_mass[i]
        gap = contact_gap[i]
        scale = seg_rest_length[i - 1] if i >= 1 else seg_rest_length[0]
        active = w > 0.0 and np.isfinite(gap) and (
            contact_cap[i] > 0.0 or lam[i, 6] > 0.0 or (gap < 0.0 and contact_eligible[i])
        )
        contact_active[i] = active
        if not active:
            if w > 0.0 and gap < 0.0:  # a penetration held back by the contact-set warm start
                residual = max(residual, -gap / scale)
            if build:
                diag[i, 6, 6] = 1.0
            continue
        residual = max(residual, abs(gap) / scale)
        if not build:
            continue
        inv_mass_times(rod, i, contact_normal, i, wn, 0)  # W_i n
        tn = axis[i, 0] * contact_normal[i, 0] + axis[i, 1] * contact_normal[i, 1] + axis[i, 2] * contact_normal[i, 2]
        diag[i, 6, 6] = w + rod[6][i] * tn * tn  # n^T W_i n
        rhs[i, 6] = -gap
        if i >= 1:  # stretch-shear of segment i-1 (same block): dC_ss/dx_i = I / l_{i-1}
            for k in range(3):
                diag[i, 6, k] = wn[0, k] / seg_rest_length[i - 1]
                diag[i, k, 6] = diag[i, 6, k]
        elif has_needle:  # attachment: dC_att/dx_0 = I
            for k in range(3):
                diag[0, 6, k] = wn[0, k]
                diag[0, k, 6] = diag[0, 6, k]
        if i < nseg:  # stretch-shear of segment i (next block): dC_ss/dx_i = -I / l_i
            for k in range(3):
                lower[i + 1, k, 6] = -wn[0, k] / seg_rest_length[i]
    return residual


@njit(cache=True, inline="always")
def _frame_torque(mult, seg_s, bend_b, out):
    """``out[j] = (J_theta^T mult)_j`` (N-1, 3): generalised torque impulse of multipliers ``mult`` (N, 7) on
    each segment frame, from its stretch-shear rows and the bend-twist rows on either side."""
    nseg = out.shape[0]
    out[:] = 0.0
    for j in range(nseg):
        mtv_acc(seg_s, j, mult, j + 1, 0, 1.0, out, j)
        if j < nseg - 1:
            mtv_acc(bend_b, j, mult, j + 1, 3, -1.0, out, j)
        if j >= 1:
            mtv_acc(bend_b, j - 1, mult, j, 3, 1.0, out, j)


@njit(cache=True, inline="always")
def fix_contact_step(i, step, contact_active, diag, lower, rhs):
    """Take node i's row 6 out of the system with its multiplier step fixed at ``step`` (kg m): ``-lambda``
    releases a contact that would pull (its whole push undone), ``+-cap - lambda`` holds a friction row at its
    bound (the node slides).

    The fixed step's effect on the coupled stretch-shear/attachment rows moves to their right-hand side, then
    the row becomes an identity row with right-hand side ``step``. Updates ``contact_active``, ``diag``,
    ``lower``, ``rhs``.
    """
    contact_active[i] = False
    for k in range(6):
        rhs[i, k] -= diag[i, k, 6] * step
        diag[i, k, 6] = 0.0
        diag[i, 6, k] = 0.0
    if i + 1 < diag.shape[0]:
        for k in range(7):
            rhs[i + 1, k] -= lower[i + 1, k, 6] * step
            lower[i + 1, k, 6] = 0.0
    diag[i, 6, 6] = 1.0
    rhs[i, 6] = step


@njit(cache=True, inline="always")
def apply_rod_solution(rod, needle, frames, contacts, z, lam, node_pos, seg_quat, needle_pos, needle_quat):
    """Apply multiplier steps ``z`` (N, 7): ``dx = M^-1 J^T z`` to nodes, ``dtheta = W J^T z - h`` to frames
    (exact exponential map), and the attachment impulse ``-z[0, :3]`` to the needle (rigid XPBD).

    ``z`` is added to ``lam``. Updates ``node_pos`` (N, 3), ``seg_quat`` (N-1, 4), ``needle_pos`` (3,),
    ``needle_quat`` (4,), and adds the pushes (m) of contacts with static obstacles (``contact_w == 0``; a
    deformable one, the tissue, takes its share of the push instead) to ``contact_push`` (argument groups in
    the module docstring).
    """
    node_inv_mass, seg_rest_length = rod[0], rod[1]
    has_needle, needle_inv_mass = needle[0], needle[1]
    _, seg_s, seg_winv, bend_b, seg_h, att_r, att_winv = frames
    contact_normal, contact_push, contact_cap = contacts[1], contacts[3], contacts[4]
    n = node_pos.shape[0]
    nseg = n - 1
    lam += z
    contact_w = rod[5]
    impulse = np.empty((1, 3))
    step = np.empty((1, 3))
    for i in range(n):
        if node_inv_mass[i] == 0.0:
            continue
        for k in range(3):
            impulse[0, k] = z[i, 6] * contact_normal[i, k]
        inv_mass_times(rod, i, impulse, 0, step, 0)
        for k in range(3):
            if contact_cap[i] == 0.0 and contact_w[i] == 0.0:  # pushes of static contacts: their Coulomb friction
                contact_push[i, k] += step[0, k]
            if i == 0 and has_needle:
                impulse[0, k] += z[0, k]
            if i >= 1:
                impulse[0, k] += z[i, k] / seg_rest_length[i - 1]
            if i < nseg:
                impulse[0, k] -= z[i + 1, k] / seg_rest_length[i]
        inv_mass_times(rod, i, impulse, 0, step, 0)
        for k in range(3):
            node_pos[i, k] += step[0, k]
    t = np.empty((nseg, 3))
    _frame_torque(z, seg_s, bend_b, t)
    dtheta = np.empty((1, 3))
    for j in range(nseg):
        for k in range(3):
            dtheta[0, k] = -seg_h[j, k]
        mv_acc(seg_winv, j, t, j, 1.0, dtheta, 0)
        if dtheta[0, 0] != 0.0 or dtheta[0, 1] != 0.0 or dtheta[0, 2] != 0.0:  # clamped frames stay bit-exact
            quat_turn_row(seg_quat, j, dtheta[0, 0], dtheta[0, 1], dtheta[0, 2])
    if has_needle:  # once per iteration
        p = -z[0, :3]
        needle_pos += needle_inv_mass * p
        dtheta[:] = 0.0
        mv_acc(att_winv.reshape(1, 3, 3), 0, cross3(att_r, p).reshape(1, 3), 0, 1.0, dtheta, 0)
        quat_turn_into(needle_quat, dtheta[0], needle_quat)


@njit(cache=True)
def rod_iteration_kernel(rod, needle, start, frames, contacts, system, lam, node_pos, seg_quat, needle_pos,
                         needle_quat, dt, tolerance, check_first):  # fmt: skip
    """One direct XPBD iteration: align frames, assemble; if the residual exceeds ``tolerance``, solve and
    apply. Returns the residual before the solve (see :func:`assemble_rod_system`, also for ``check_first``;
    argument groups in the module docstring).

    ``contact_w`` (``rod[5]``, (N,)) is the obstacle's share of each contact row's generalised inverse mass,
    ``J M^-1 J^T``: 0 for static obstacles; for a deformable one (a tissue triangle, see
    :func:`~suture_gym.sim.coupling.suture_contact_rows`) it makes the contact multiplier the two-way XPBD one,
    and the caller moves the obstacle by its share afterwards.
    """
    align_frames(node_pos, rod[2], seg_quat)
    residual = assemble_rod_system(
        node_pos, seg_quat, rod, needle, start, frames, contacts, system, lam, needle_pos, needle_quat, dt, tolerance,
        check_first,
    )
    if residual <= tolerance:
        return residual
    contact_w = rod[5]
    contact_active = contacts[2]
    diag, lower, fac, rhs, y, z = system
    for i in range(node_pos.shape[0]):
        if contact_active[i]:
            diag[i, 6, 6] += contact_w[i]
    # active-set refinement: contacts whose multiplier would turn negative (pull) are released, friction rows
    # whose multiplier would pass their cap are held at it, and the system re-solved; rows still outside their
    # bounds after the last pass stay in for this iteration (the solution remains consistent) and are dealt
    # with by the next iteration's.
    contact_cap = contacts[4]
    solve_block_tridiagonal(diag, lower, rhs, fac, y, z)
    for _ in range(_MAX_RELEASE_PASSES):
        released = False
        for i in range(node_pos.shape[0]):
            if not contact_active[i]:
                continue
            total = lam[i, 6] + z[i, 6]
            cap = contact_cap[i]
            if cap > 0.0 and abs(total) > cap:
                fix_contact_step(i, math.copysign(cap, total) - lam[i, 6], contact_active, diag, lower, rhs)
                released = True
            elif cap == 0.0 and total < 0.0:
                fix_contact_step(i, -lam[i, 6], contact_active, diag, lower, rhs)
                released = True
        if not released:
            break
        solve_block_tridiagonal(diag, lower, rhs, fac, y, z)
    apply_rod_solution(rod, needle, frames, contacts, z, lam, node_pos, seg_quat, needle_pos, needle_quat)
    return residual


@njit(cache=True)
def tension_from_multipliers(lam, out):
    """``out[j] = |lam[j+1, :3]|`` (N-1,): size of the stretch-shear multipliers (kg m^2) of segment j."""
    for j in range(out.shape[0]):
        out[j] = np.sqrt(lam[j + 1, 0] ** 2 + lam[j + 1, 1] ** 2 + lam[j + 1, 2] ** 2)
