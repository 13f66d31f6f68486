"""Rigid-body maths of extended position based dynamics (Muller et al. 2020, "Detailed rigid body simulation
with extended position based dynamics"), shared by the needle and the coupling rows.

A body has a pose (``pos`` (3,) m, ``quat`` (4,) unit quaternion w, x, y, z), a scalar inverse mass (1/kg) and a
body-frame inverse inertia (3, 3) (1/(kg m^2)); positional constraints act on it through its generalised inverse
mass and move it by impulses (kg m).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from suture_gym.sim.quat import (
    cross3,
    quat_conj,
    quat_from_rotation_vector,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_rotate_inv,
    quat_rotation_vector,
    quat_to_matrix,
)

# The 3 x 3 products below are written in scalars: numba's ``@`` on such small arrays calls BLAS, whose per-call
# cost would otherwise dominate the needle's path rows' projection.


@njit(cache=True, inline="always")
def _product3(a, b):
    """``a b`` (3, 3) of two (3, 3) matrices (either may be a transposed view)."""
    out = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            out[i, j] = a[i, 0] * b[0, j] + a[i, 1] * b[1, j] + a[i, 2] * b[2, j]
    return out


@njit(cache=True, inline="always")
def _quadratic_form(m, v):
    """``v^T m v`` of a (3, 3) matrix and a (3,) vector."""
    total = 0.0
    for i in range(3):
        total += v[i] * (m[i, 0] * v[0] + m[i, 1] * v[1] + m[i, 2] * v[2])
    return total


@njit(cache=True)
def world_inv_inertia(quat, inv_inertia_body):
    """World-frame inverse inertia ``R I_body^-1 R^T`` (3, 3) of a body with orientation ``quat`` (4,)."""
    r = quat_to_matrix(quat)
    return _product3(_product3(r, inv_inertia_body), r.T)


@njit(cache=True)
def point_inv_mass(inv_mass, inv_inertia_world, r, n):
    """Generalised inverse mass (1/kg) of a body point for a correction along unit direction ``n`` (3,).

    ``w = 1/m + (r x n)^T I^-1 (r x n)`` with ``r`` (3,) the point relative to the centre of mass (world, m)
    and ``I^-1`` the world inverse inertia (3, 3) (Muller et al. 2020).
    """
    return inv_mass + _quadratic_form(inv_inertia_world, cross3(r, n))


@njit(cache=True)
def point_inv_mass_matrix(inv_mass, inv_inertia_world, r):
    """Generalised inverse mass matrix (3, 3) (1/kg) of a body point: ``K = I/m - [r]x I^-1 [r]x``.

    ``n^T K n`` equals :func:`point_inv_mass` for any unit ``n``; a point impulse ``p`` moves the point by
    ``K p`` to first order.
    """
    s = np.zeros((3, 3))
    s[0, 1] = -r[2]
    s[0, 2] = r[1]
    s[1, 0] = r[2]
    s[1, 2] = -r[0]
    s[2, 0] = -r[1]
    s[2, 1] = r[0]
    k = _product3(_product3(s, inv_inertia_world), s)
    for i in range(3):
        for j in range(3):
            k[i, j] = -k[i, j]
        k[i, i] += inv_mass
    return k


@njit(cache=True)
def apply_point_impulse(pos, quat, inv_mass, inv_inertia_world, r, p):
    """Rigid XPBD pose update for a positional impulse ``p`` (3,) (kg m) at body point ``r`` (3,) (world, m).

    ``x += p / m`` and the orientation turns by ``I^-1 (r x p)`` (rad): :func:`rigid_apply` with the gradients
    ``(p, r x p)`` and a unit multiplier step. Returns new ``(pos (3,), quat (4,))``; the inputs are not changed.
    """
    new_pos = pos.copy()
    new_quat = quat.copy()
    rigid_apply(new_pos, new_quat, inv_mass, inv_inertia_world, p, cross3(r, p), 1.0)
    return new_pos, new_quat


@njit(cache=True)
def rigid_predict(
    pos, quat, vel, omega, inv_mass, inertia_body, inv_inertia_body, force, torque, accel, lin_damp, ang_damp, dt
):
    """Semi-implicit Newton-Euler step of a rigid body (prediction step of Muller et al. 2020).

    Inputs: pose ``pos`` (3,) m, ``quat`` (4,); velocities ``vel`` (3,) m/s, ``omega`` (3,) rad/s (world);
    ``inv_mass`` 1/kg; body-frame ``inertia_body`` and ``inv_inertia_body`` (3, 3); world ``force`` (3,) N
    and ``torque`` (3,) N m about the centre of mass; uniform field ``accel`` (3,) m/s^2 (gravity);
    damping rates ``lin_damp``, ``ang_damp`` 1/s; ``dt`` s.

    ``v <- v / (1 + dt c) + dt (F/m + g)``, ``x <- x + dt v``; in the body frame
    ``w <- w / (1 + dt c_w) + dt I^-1 (tau - w x I w)`` (gyroscopic term explicit), ``q <- exp(dt w / 2) q``.
    Damping acts on the old velocities only, so it never scales the applied loads.
    Returns ``(pos, quat, vel, omega)``.
    """
    new_vel = vel / (1.0 + dt * lin_damp) + dt * (inv_mass * force + accel)
    new_pos = pos + dt * new_vel
    w_b = quat_rotate_inv(quat, omega)
    tau_b = quat_rotate_inv(quat, torque)
    gyro = cross3(w_b, inertia_body @ w_b)
    w_b = w_b / (1.0 + dt * ang_damp) + dt * (inv_inertia_body @ (tau_b - gyro))
    new_omega = quat_rotate(quat, w_b)
    new_quat = quat_normalize(quat_mul(quat_from_rotation_vector(dt * new_omega), quat))
    return new_pos, new_quat, new_vel, new_omega


@njit(cache=True)
def rigid_velocities(pos, quat, pos_prev, quat_prev, dt):
    """Velocities from the substep's pose change: ``v = dx/dt``, ``omega = log(q conj(q_prev)) / dt``.

    Returns ``(vel (3,) m/s, omega (3,) rad/s world)``.
    """
    vel = (pos - pos_prev) / dt
    omega = quat_rotation_vector(quat_mul(quat, quat_conj(quat_prev))) / dt
    return vel, omega


@njit(cache=True)
def body_points_world(pos, quat, points_body, out):
    """World positions of body-frame points ``points_body`` (K, 3) for pose (``pos`` (3,), ``quat`` (4,)).

    Writes ``out`` (K, 3) m.
    """
    r = quat_to_matrix(quat)
    for k in range(points_body.shape[0]):
        for i in range(3):
            out[k, i] = pos[i] + r[i, 0] * points_body[k, 0] + r[i, 1] * points_body[k, 1] + r[i, 2] * points_body[k, 2]


@njit(cache=True)
def rigid_generalized_inv_mass(inv_mass, inv_inertia_world, lin, ang):
    """``w = |lin|^2 / m + ang^T I^-1 ang`` (1/kg) of a rigid body for a constraint whose gradients at body
    points ``r_i`` are ``g_i``: ``lin = sum g_i``, ``ang = sum r_i x g_i`` (world frame)."""
    return inv_mass * (lin[0] * lin[0] + lin[1] * lin[1] + lin[2] * lin[2]) + _quadratic_form(inv_inertia_world, ang)


@njit(cache=True)
def rigid_apply(pos, quat, inv_mass, inv_inertia_world, lin, ang, dlam):
    """Rigid XPBD pose update for multiplier step ``dlam`` of a constraint with gradients (``lin``, ``ang``):
    ``x += dlam lin / m``; the orientation turns by ``dlam I^-1 ang`` (exact exponential map). Updates ``pos``
    (3,) and ``quat`` (4,) in place."""
    for i in range(3):
        pos[i] += inv_mass * dlam * lin[i]
    dtheta = np.empty(3)
    for i in range(3):
        dtheta[i] = dlam * (
            inv_inertia_world[i, 0] * ang[0] + inv_inertia_world[i, 1] * ang[1] + inv_inertia_world[i, 2] * ang[2]
        )
    quat[:] = quat_normalize(quat_mul(quat_from_rotation_vector(dtheta), quat))


@njit(cache=True)
def body_point(pos, quat, point_body):
    """World position (3,) of body-frame point ``point_body`` for pose (``pos``, ``quat``)."""
    r = quat_to_matrix(quat)
    out = np.empty(3)
    for i in range(3):
        out[i] = pos[i] + r[i, 0] * point_body[0] + r[i, 1] * point_body[1] + r[i, 2] * point_body[2]
    return out
