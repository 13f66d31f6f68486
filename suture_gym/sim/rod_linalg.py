"""Small dense linear algebra of the suture rod's direct solve (:mod:`~suture_gym.sim.rod_solver`): 3 x 3
products, skew matrices and quaternion differences on stacks of arrays, and the symmetric block-tridiagonal
``L D L^T`` factor and solve of its :data:`BLOCK` x :data:`BLOCK` blocks.

The helpers take their arrays whole with an index (``a, ia`` is the (3, 3) matrix ``a[ia]``, a local one a stack
of one; ``quats, j`` the unit quaternion ``quats[j]``, (w, x, y, z)) and write at row and column offsets, rather
than taking views such as ``seg_rot[j]`` or ``diag[b, :3, :3]``: numba counts the reference of every view it makes
in and out with atomic operations, a large share of the rod's solve when the helpers took views
(docs/notes/performance.md). They are compiled into their callers (``inline="always"``; numba's cache does not see
an edit to one from a caller in another module: clear the cache after editing). :func:`factor_block` is compiled
into :func:`solve_block_tridiagonal` at its one call site; the block solve stays a separate function (compiled into
the iteration's two call sites it doubles the compilation time for a few percent).
"""

from __future__ import annotations

import numpy as np
from numba import njit

#: A pivot of the block solve below this fraction of its row's diagonal marks the row as redundant.
_PIVOT_TOL = 1.0e-12
#: Rows per block of the direct solve: 3 stretch-shear (or attachment), 3 bend-twist, 1 contact.
BLOCK = 7
#: Entries of a coupling block ``A[b, b-1]`` of the rod's system that may be non-zero, (7, 7) bool: rows 0-2 of
#: block b (stretch-shear, or attachment) in every column, rows 3-5 (bend-twist) in columns 3-5, row 6 (contact)
#: in none. :func:`~suture_gym.sim.rod_solver.assemble_rod_system` writes no other entry and
#: :func:`solve_block_tridiagonal` skips them.
COUPLING_PATTERN = np.zeros((BLOCK, BLOCK), dtype=np.bool_)
COUPLING_PATTERN[:3, :] = True
COUPLING_PATTERN[3:6, 3:6] = True


# ---------------------------------------------------------------------------------------------------------
# 3 x 3 products
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def dot3(a, b):
    """Dot product of two 3-vectors."""
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


@njit(cache=True, inline="always")
def ab_into(a, ia, b, ib, out, io):
    """``out[io] = a[ia] @ b[ib]`` for stacks of (3, 3) matrices, by loops (no BLAS call, no allocation; the fixed
    bounds let them compile unrolled)."""
    for i in range(3):
        for j in range(3):
            t = 0.0
            for k in range(3):
                t += a[ia, i, k] * b[ib, k, j]
            out[io, i, j] = t


@njit(cache=True, inline="always")
def abt_acc(a, ia, b, ib, scale, out, io, r0, c0):
    """``out[io, r0:r0+3, c0:c0+3] += scale * a[ia] @ b[ib].T`` for stacks of (3, 3) matrices, by loops."""
    for i in range(3):
        for j in range(3):
            t = 0.0
            for k in range(3):
                t += a[ia, i, k] * b[ib, j, k]
            out[io, r0 + i, c0 + j] += scale * t


@njit(cache=True, inline="always")
def mv_acc(a, ia, v, iv, scale, out, io):
    """``out[io] += scale * a[ia] @ v[iv]`` for a stack of (3, 3) matrices and stacks of 3-vectors."""
    for i in range(3):
        t = 0.0
        for k in range(3):
            t += a[ia, i, k] * v[iv, k]
        out[io, i] += scale * t


@njit(cache=True, inline="always")
def mtv_acc(a, ia, v, iv, c0, scale, out, io):
    """``out[io] += scale * a[ia].T @ v[iv, c0:c0+3]`` for a stack of (3, 3) matrices."""
    for k in range(3):
        vk = scale * v[iv, c0 + k]
        for i in range(3):
            out[io, i] += a[ia, k, i] * vk


@njit(cache=True, inline="always")
def rot_diag_into(r, ir, d, idd, scale, out, io):
    """``out[io] = scale * R diag(d) R^T`` (3, 3) for the rotation ``R = r[ir]`` and the diagonal ``d[idd]``
    (symmetric: the upper triangle is computed and mirrored)."""
    for i in range(3):
        for j in range(i, 3):
            t = scale * (
                r[ir, i, 0] * d[idd, 0] * r[ir, j, 0]
                + r[ir, i, 1] * d[idd, 1] * r[ir, j, 1]
                + r[ir, i, 2] * d[idd, 2] * r[ir, j, 2]
            )
            out[io, i, j] = t
            out[io, j, i] = t


@njit(cache=True, inline="always")
def skew_times_into(x, y, z, a, ia, out, io):
    """``out[io] = [(x, y, z)]x a[ia]`` (3, 3): each column the cross product of ``(x, y, z)`` with ``a``'s."""
    for k in range(3):
        out[io, 0, k] = y * a[ia, 2, k] - z * a[ia, 1, k]
        out[io, 1, k] = z * a[ia, 0, k] - x * a[ia, 2, k]
        out[io, 2, k] = x * a[ia, 1, k] - y * a[ia, 0, k]


@njit(cache=True, inline="always")
def times_skew_t_acc(a, ia, x, y, z, out, io, r0, c0):
    """``out[io, r0:r0+3, c0:c0+3] += a[ia] [(x, y, z)]x^T``: row ``r`` gains ``(x, y, z)`` crossed with ``a``'s row
    ``r``."""
    for r in range(3):
        out[io, r0 + r, c0 + 0] += y * a[ia, r, 2] - z * a[ia, r, 1]
        out[io, r0 + r, c0 + 1] += z * a[ia, r, 0] - x * a[ia, r, 2]
        out[io, r0 + r, c0 + 2] += x * a[ia, r, 1] - y * a[ia, r, 0]


@njit(cache=True, inline="always")
def skew_into(x, y, z, out, io):
    """Write ``[(x, y, z)]x`` into ``out[io]`` (3, 3)."""
    out[io, 0, 0] = 0.0
    out[io, 0, 1] = -z
    out[io, 0, 2] = y
    out[io, 1, 0] = z
    out[io, 1, 1] = 0.0
    out[io, 1, 2] = -x
    out[io, 2, 0] = -y
    out[io, 2, 1] = x
    out[io, 2, 2] = 0.0


# ---------------------------------------------------------------------------------------------------------
# Quaternions
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def darboux(quats, j0, j1):
    """``r = conj(q0) q1`` of ``q0 = quats[j0]``, ``q1 = quats[j1]`` as a tuple (w, x, y, z), sign chosen so that
    ``w >= 0`` (same rotation)."""
    a0, a1, a2, a3 = quats[j0, 0], quats[j0, 1], quats[j0, 2], quats[j0, 3]
    b0, b1, b2, b3 = quats[j1, 0], quats[j1, 1], quats[j1, 2], quats[j1, 3]
    w = a0 * b0 + a1 * b1 + a2 * b2 + a3 * b3
    x = a0 * b1 - a1 * b0 - a2 * b3 + a3 * b2
    y = a0 * b2 + a1 * b3 - a2 * b0 - a3 * b1
    z = a0 * b3 - a1 * b2 + a2 * b1 - a3 * b0
    if w < 0.0:
        return -w, -x, -y, -z
    return w, x, y, z

@njit(cache=True, inline="always")
def relative_rotation_vector(quats, j, quats0, out, io):
    """Write the rotation vector (rad, world) of ``q conj(q0)``, ``q = quats[j]``, ``q0 = quats0[j]``, into
    ``out[io]`` (3,), the short way."""
    q_0, q_1, q_2, q_3 = quats[j, 0], quats[j, 1], quats[j, 2], quats[j, 3]
    p_0, p_1, p_2, p_3 = quats0[j, 0], quats0[j, 1], quats0[j, 2], quats0[j, 3]
    w = q_0 * p_0 + q_1 * p_1 + q_2 * p_2 + q_3 * p_3
    x = -q_0 * p_1 + q_1 * p_0 - q_2 * p_3 + q_3 * p_2
    y = -q_0 * p_2 + q_1 * p_3 + q_2 * p_0 - q_3 * p_1
    z = -q_0 * p_3 - q_1 * p_2 + q_2 * p_1 + q_3 * p_0
    if w < 0.0:
        w, x, y, z = -w, -x, -y, -z
    s = np.sqrt(x * x + y * y + z * z)
    if s < 1.0e-300:
        out[io, 0], out[io, 1], out[io, 2] = 0.0, 0.0, 0.0
        return
    f = 2.0 * np.arctan2(s, w) / s
    out[io, 0], out[io, 1], out[io, 2] = x * f, y * f, z * f


# ---------------------------------------------------------------------------------------------------------
# Direct block-tridiagonal solve
# ---------------------------------------------------------------------------------------------------------


@njit(cache=True, inline="always")
def factor_block(s, fac, b, pivots, ld):
    """Factor the symmetric positive semi-definite :data:`BLOCK` x :data:`BLOCK` matrix ``s`` (its lower triangle is
    read) as ``L D L^T`` into ``fac[b]``: ``L``'s unit lower triangle strictly below the diagonal, ``D^+`` (the
    pivots' reciprocals) on it. A row whose pivot falls below :data:`_PIVOT_TOL` of its diagonal (a redundant or
    fully pinned constraint) is dropped: its ``D^+`` entry and its column of ``L`` are zero, so
    ``L^-T D^+ L^-1`` has zero rows and columns there and the row receives no multiplier. ``pivots``, ``ld``
    (7,) are scratch. (Fixed size, so that the loops compile unrolled.)"""
    n = BLOCK
    for j in range(n):
        s_jj = s[j, j]
        t = s_jj
        for k in range(j):
            ld[k] = fac[b, j, k] * pivots[k]
            t -= fac[b, j, k] * ld[k]
        if s_jj <= 0.0 or t <= _PIVOT_TOL * s_jj:
            pivots[j] = 0.0
            fac[b, j, j] = 0.0
            for i in range(j + 1, n):
                fac[b, i, j] = 0.0
            continue
        pivots[j] = t
        r = 1.0 / t
        fac[b, j, j] = r
        for i in range(j + 1, n):
            t = s[i, j]
            for k in range(j):
                t -= fac[b, i, k] * ld[k]
            fac[b, i, j] = t * r


@njit(cache=True)
def solve_block_tridiagonal(diag, lower, rhs, fac, y, z):
    """Solve ``A z = rhs`` for symmetric block-tridiagonal ``A`` by a block ``L D L^T`` sweep, O(number of blocks).

    ``diag`` (B, 7, 7) are the diagonal blocks ``A[b, b]`` (their lower triangles are read), ``lower`` (B, 7, 7)
    the blocks ``A[b, b-1]`` (``lower[0]`` unused), ``rhs`` (B, 7). Scratch: ``fac`` (B, 7, 7) receives each Schur
    complement's factors (:func:`factor_block`), ``y`` (B, 7). Output ``z`` (B, 7).

    With ``S_b = L_b D_b L_b^T`` the Schur complements, ``S_b = A[b, b] - G_b D_(b-1)^+ G_b^T`` where
    ``G_b = A[b, b-1] L_(b-1)^-T``; the forward sweep keeps ``w_b = D_b^+ L_b^-1 y_b`` in ``y`` and the backward
    sweep gives ``z_b = L_b^-T (w_b - D_b^+ L_b^-1 A[b+1, b]^T z_(b+1))``. No block is inverted: about half the
    multiplications of inverting each ``S_b`` (230 blocks: 54.5-56 against 76-78 us), and more accurate.

    ``lower`` must be zero outside :data:`COUPLING_PATTERN`, as the rod's system is: block ``b``'s stretch-shear
    rows 0-2 couple to any row of block ``b-1`` (through ``x_j``, ``q_j`` and node ``j``'s contact row), its
    bend-twist rows 3-5 only to bend-twist rows 3-5 (through ``q_j``), its contact row 6 to none. The products
    skip the entries outside the pattern (so rows 3-5 of ``G_b`` are zero in columns 0-2, and row 6 is zero).
    """
    k7 = BLOCK
    nb = rhs.shape[0]
    schur = np.empty((k7, k7))
    g = np.empty((6, k7))
    hg = np.empty((6, k7))
    pivots = np.empty(k7)
    ld = np.empty(k7)
    tv = np.empty(k7)
    for b in range(nb):
        if b == 0:
            for i in range(k7):
                for j in range(i + 1):
                    schur[i, j] = diag[0, i, j]
                y[0, i] = rhs[0, i]
        else:
            # G = lower[b] L^-T (forward substitution along each row: G L^T = lower[b]); hg = G D^+
            for i in range(3):
                for j in range(k7):
                    t = lower[b, i, j]
                    for k in range(j):
                        t -= g[i, k] * fac[b - 1, j, k]
                    g[i, j] = t
                    hg[i, j] = t * fac[b - 1, j, j]
            for i in range(3, 6):
                for j in range(3):
                    g[i, j] = 0.0
                    hg[i, j] = 0.0
                for j in range(3, k7):
                    t = lower[b, i, j] if j < 6 else 0.0
                    for k in range(3, j):
                        t -= g[i, k] * fac[b - 1, j, k]
                    g[i, j] = t
                    hg[i, j] = t * fac[b - 1, j, j]
            # the Schur complement's lower triangle; rows 3-5 of G vanish in columns 0-2, its row 6 everywhere
            for i in range(3):
                for j in range(i + 1):
                    t = diag[b, i, j]
                    for k in range(k7):
                        t -= hg[i, k] * g[j, k]
                    schur[i, j] = t
            for i in range(3, 6):
                for j in range(i + 1):
                    t = diag[b, i, j]
                    for k in range(3, k7):
                        t -= hg[i, k] * g[j, k]
                    schur[i, j] = t
            for j in range(k7):
                schur[6, j] = diag[b, 6, j]
            # y_b = rhs_b - G w_(b-1)
            for i in range(3):
                t = rhs[b, i]
                for k in range(k7):
                    t -= g[i, k] * y[b - 1, k]
                y[b, i] = t
            for i in range(3, 6):
                t = rhs[b, i]
                for k in range(3, k7):
                    t -= g[i, k] * y[b - 1, k]
                y[b, i] = t
            y[b, 6] = rhs[b, 6]
        factor_block(schur, fac, b, pivots, ld)
        # w_b = D^+ L^-1 y_b, in place
        for j in range(k7):
            t = y[b, j]
            for k in range(j):
                t -= fac[b, j, k] * tv[k]
            tv[j] = t
        for j in range(k7):
            y[b, j] = tv[j] * fac[b, j, j]
    for b in range(nb - 1, -1, -1):
        if b == nb - 1:
            for i in range(k7):
                tv[i] = y[b, i]
        else:
            # lower[b+1]^T z_(b+1): columns 0-2 and 6 of lower[b+1] are non-zero in rows 0-2 only
            for i in range(k7):
                t = 0.0
                kmax = 6 if 3 <= i < 6 else 3
                for k in range(kmax):
                    t += lower[b + 1, k, i] * z[b + 1, k]
                tv[i] = t
            # tv <- w_b - D^+ L^-1 tv
            for j in range(k7):
                t = tv[j]
                for k in range(j):
                    t -= fac[b, j, k] * tv[k]
                tv[j] = t
            for j in range(k7):
                tv[j] = y[b, j] - fac[b, j, j] * tv[j]
        # z_b = L^-T tv
        for j in range(k7 - 1, -1, -1):
            t = tv[j]
            for k in range(j + 1, k7):
                t -= fac[b, k, j] * z[b, k]
            z[b, j] = t
