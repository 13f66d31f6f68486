"""Quaternion helpers for rigid bodies and rod frames, as numba kernels.

Convention: a quaternion is a float64 array ``(4,)`` ordered ``(w, x, y, z)`` (scalar first), Hamilton
product, and a unit quaternion ``q`` rotates a vector ``v`` from the body frame to the world frame by
``q v conj(q)``, so ``quat_to_matrix(q) @ v == quat_rotate(q, v)``. Angular velocities and rotation vectors
are world-frame, in rad/s and rad. Every function returns a new array and never modifies its inputs.
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: Below this norm a quaternion or rotation vector is treated as zero (degenerate input).
_TINY = 1.0e-300


@njit(cache=True)
def quat_mul(a, b):
    """Hamilton product ``a b`` of two quaternions ``(4,)``; rotating by ``a b`` means ``b`` first, then ``a``."""
    out = np.empty(4)
    out[0] = a[0] * b[0] - a[1] * b[1] - a[2] * b[2] - a[3] * b[3]
    out[1] = a[0] * b[1] + a[1] * b[0] + a[2] * b[3] - a[3] * b[2]
    out[2] = a[0] * b[2] - a[1] * b[3] + a[2] * b[0] + a[3] * b[1]
    out[3] = a[0] * b[3] + a[1] * b[2] - a[2] * b[1] + a[3] * b[0]
    return out


@njit(cache=True)
def quat_conj(q):
    """Conjugate ``(w, -x, -y, -z)`` of ``q`` ``(4,)``: the inverse rotation for a unit quaternion."""
    out = np.empty(4)
    out[0] = q[0]
    out[1] = -q[1]
    out[2] = -q[2]
    out[3] = -q[3]
    return out


@njit(cache=True)
def quat_rotate(q, v):
    """Rotate vector ``v`` ``(3,)`` by unit quaternion ``q`` ``(4,)``: body frame to world frame."""
    w = q[0]
    ux, uy, uz = q[1], q[2], q[3]
    # t = 2 u x v ; v' = v + w t + u x t
    tx = 2.0 * (uy * v[2] - uz * v[1])
    ty = 2.0 * (uz * v[0] - ux * v[2])
    tz = 2.0 * (ux * v[1] - uy * v[0])
    out = np.empty(3)
    out[0] = v[0] + w * tx + (uy * tz - uz * ty)
    out[1] = v[1] + w * ty + (uz * tx - ux * tz)
    out[2] = v[2] + w * tz + (ux * ty - uy * tx)
    return out


@njit(cache=True)
def cross3(a, b):
    """Cross product ``a x b`` of two ``(3,)`` vectors, a new ``(3,)`` array (``np.cross`` costs ~10 us a call
    in the per-substep Python layer; this ~0.3 us)."""
    out = np.empty(3)
    out[0] = a[1] * b[2] - a[2] * b[1]
    out[1] = a[2] * b[0] - a[0] * b[2]
    out[2] = a[0] * b[1] - a[1] * b[0]
    return out


@njit(cache=True)
def quat_rotate_inv(q, v):
    """Rotate vector ``v`` ``(3,)`` by the inverse of unit quaternion ``q``: world frame to body frame."""
    return quat_rotate(quat_conj(q), v)


@njit(cache=True)
def quat_normalize(q):
    """Unit quaternion along ``q`` ``(4,)``; a zero (degenerate) input returns the identity ``(1, 0, 0, 0)``."""
    n = np.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    out = np.zeros(4)
    if n < _TINY:
        out[0] = 1.0
        return out
    for i in range(4):
        out[i] = q[i] / n
    return out


@njit(cache=True)
def quat_from_axis_angle(axis, angle):
    """Unit quaternion rotating by ``angle`` (rad) about ``axis`` ``(3,)`` (any length; zero gives identity)."""
    n = np.sqrt(axis[0] * axis[0] + axis[1] * axis[1] + axis[2] * axis[2])
    out = np.zeros(4)
    if n < _TINY:
        out[0] = 1.0
        return out
    s = np.sin(0.5 * angle) / n
    out[0] = np.cos(0.5 * angle)
    out[1] = axis[0] * s
    out[2] = axis[1] * s
    out[3] = axis[2] * s
    return out


@njit(cache=True)
def quat_from_rotation_vector(theta):
    """Unit quaternion ``exp(theta / 2)`` of a rotation vector ``theta`` ``(3,)`` (rad): angle |theta| about theta."""
    angle = np.sqrt(theta[0] * theta[0] + theta[1] * theta[1] + theta[2] * theta[2])
    return quat_from_axis_angle(theta, angle)


@njit(cache=True, inline="always")
def _rotation_entries(w, x, y, z):
    """The rotation matrix of the unit quaternion ``(w, x, y, z)``, row by row, as a tuple of nine."""
    return (
        1.0 - 2.0 * (y * y + z * z), 2.0 * (x * y - w * z), 2.0 * (x * z + w * y),
        2.0 * (x * y + w * z), 1.0 - 2.0 * (x * x + z * z), 2.0 * (y * z - w * x),
        2.0 * (x * z - w * y), 2.0 * (y * z + w * x), 1.0 - 2.0 * (x * x + y * y),
    )  # fmt: skip


@njit(cache=True)
def quat_to_matrix_into(q, out):
    """Write the rotation matrix of unit quaternion ``q`` into ``out`` (3, 3) (no allocation)."""
    e = _rotation_entries(q[0], q[1], q[2], q[3])
    out[0, 0], out[0, 1], out[0, 2] = e[0], e[1], e[2]
    out[1, 0], out[1, 1], out[1, 2] = e[3], e[4], e[5]
    out[2, 0], out[2, 1], out[2, 2] = e[6], e[7], e[8]


@njit(cache=True, inline="always")
def quat_to_matrix_row(quats, j, out, io):
    """Write the rotation matrix of the unit quaternion ``quats[j]`` ((M, 4)) into ``out[io]`` ((K, 3, 3)), as
    :func:`quat_to_matrix_into` does; indexed rather than given views, as :func:`quat_turn_row`."""
    e = _rotation_entries(quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3])
    out[io, 0, 0], out[io, 0, 1], out[io, 0, 2] = e[0], e[1], e[2]
    out[io, 1, 0], out[io, 1, 1], out[io, 1, 2] = e[3], e[4], e[5]
    out[io, 2, 0], out[io, 2, 1], out[io, 2, 2] = e[6], e[7], e[8]


@njit(cache=True)
def quat_to_matrix(q):
    """Rotation matrix ``(3, 3)`` of unit quaternion ``q``: ``R @ v == quat_rotate(q, v)``."""
    r = np.empty((3, 3))
    quat_to_matrix_into(q, r)
    return r


@njit(cache=True, inline="always")
def _turned(bw, bx, by, bz, tx, ty, tz):
    """``normalize(exp(theta / 2) b)`` as a tuple (w, x, y, z), for ``b`` turned by the world rotation vector
    ``theta = (tx, ty, tz)`` (rad); ``(1, 0, 0, 0)`` if the product vanishes."""
    angle = np.sqrt(tx * tx + ty * ty + tz * tz)
    if angle < _TINY:
        aw, ax, ay, az = 1.0, 0.0, 0.0, 0.0
    else:
        s = np.sin(0.5 * angle) / angle
        aw, ax, ay, az = np.cos(0.5 * angle), tx * s, ty * s, tz * s
    return _premultiplied(aw, ax, ay, az, bw, bx, by, bz)


@njit(cache=True, inline="always")
def _premultiplied(aw, ax, ay, az, bw, bx, by, bz):
    """``normalize(a b)`` as a tuple (w, x, y, z) for quaternions ``a`` (any non-zero length: a rotation scaled)
    and ``b``; ``(1, 0, 0, 0)`` if the product vanishes."""
    w = aw * bw - ax * bx - ay * by - az * bz
    x = aw * bx + ax * bw + ay * bz - az * by
    y = aw * by - ax * bz + ay * bw + az * bx
    z = aw * bz + ax * by - ay * bx + az * bw
    n = np.sqrt(w * w + x * x + y * y + z * z)
    if n < _TINY:
        return 1.0, 0.0, 0.0, 0.0
    return w / n, x / n, y / n, z / n


@njit(cache=True, inline="always")
def quat_premultiply_row(quats, j, aw, ax, ay, az):
    """Row ``j`` of ``quats`` (M, 4) <- ``normalize(a quats[j])`` in place, for the quaternion ``a = (aw, ax, ay,
    az)`` of any non-zero length (a world rotation, unnormalised); indexed as :func:`quat_turn_row`."""
    quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3] = _premultiplied(
        aw, ax, ay, az, quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3]
    )


@njit(cache=True)
def quat_turn_into(q, theta, out):
    """Write ``normalize(exp(theta / 2) q)`` into ``out`` (4,): ``q`` (4,) turned by the world rotation vector
    ``theta`` (3,) (rad), without allocating; ``out`` may be ``q`` itself."""
    out[0], out[1], out[2], out[3] = _turned(q[0], q[1], q[2], q[3], theta[0], theta[1], theta[2])


@njit(cache=True, inline="always")
def quat_turn_row(quats, j, tx, ty, tz):
    """Turn row ``j`` of ``quats`` (M, 4) in place by the world rotation vector ``(tx, ty, tz)`` (rad), as
    :func:`quat_turn_into` does. Indexed rather than given a row view: per segment and iteration, a view passed
    to a separately compiled function costs atomic reference counting in and out."""
    quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3] = _turned(
        quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3], tx, ty, tz
    )


@njit(cache=True)
def quat_integrate(q, omega, dt):
    """Orientation after turning at constant world angular velocity ``omega`` ``(3,)`` (rad/s) for ``dt`` (s).

    Exact exponential map ``exp(omega dt / 2) q``, renormalised, so repeated steps keep ``|q| = 1``.
    """
    theta = np.empty(3)
    for i in range(3):
        theta[i] = omega[i] * dt
    return quat_normalize(quat_mul(quat_from_rotation_vector(theta), q))


@njit(cache=True)
def quat_rotation_vector(q):
    """Rotation vector ``(3,)`` (rad) of unit quaternion ``q``, taking the short way (angle in [0, pi])."""
    w = q[0]
    sign = 1.0
    if w < 0.0:
        sign = -1.0
        w = -w
    s = np.sqrt(q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
    out = np.zeros(3)
    if s < _TINY:
        return out
    angle = 2.0 * np.arctan2(s, w)
    f = sign * angle / s
    out[0] = q[1] * f
    out[1] = q[2] * f
    out[2] = q[3] * f
    return out


@njit(cache=True)
def quat_from_two_vectors(a, b):
    """Minimal-angle unit quaternion rotating direction ``a`` ``(3,)`` onto direction ``b`` ``(3,)``.

    Neither vector needs unit length. A zero vector (degenerate) gives the identity; antiparallel vectors
    give a half turn about an axis perpendicular to ``a``.
    """
    na = np.sqrt(a[0] * a[0] + a[1] * a[1] + a[2] * a[2])
    nb = np.sqrt(b[0] * b[0] + b[1] * b[1] + b[2] * b[2])
    out = np.zeros(4)
    if na < _TINY or nb < _TINY:
        out[0] = 1.0
        return out
    ua = a / na
    ub = b / nb
    d = ua[0] * ub[0] + ua[1] * ub[1] + ua[2] * ub[2]
    if d < -1.0 + 1.0e-12:
        # Half turn about any axis perpendicular to a: cross a with the coordinate axis it is least along.
        k = 0
        if abs(ua[1]) < abs(ua[k]):
            k = 1
        if abs(ua[2]) < abs(ua[k]):
            k = 2
        e = np.zeros(3)
        e[k] = 1.0
        axis = cross3(ua, e)
        return quat_from_axis_angle(axis, np.pi)
    c = cross3(ua, ub)
    out[0] = 1.0 + d
    out[1] = c[0]
    out[2] = c[1]
    out[3] = c[2]
    return quat_normalize(out)
