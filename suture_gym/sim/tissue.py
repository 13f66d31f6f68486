"""Tetrahedral tissue constraints: the stable neo-Hookean XPBD split, solved per tet as a coupled 2x2 system.

Model (Macklin & Muller 2021, "A Constraint-based Formulation of Stable Neo-Hookean Materials", which
builds on Smith et al. 2018, "Stable Neo-Hookean Flesh Simulation", and XPBD, Macklin et al. 2016). Per tet
with deformation gradient ``F = Ds Dm^-1``, rest volume ``V0`` and stable-neo-Hookean moduli ``mu`` and
``lambda`` (see :mod:`suture_gym.sim.model` for how they follow from Young's modulus and Poisson's ratio):

* deviatoric constraint ``C_D(x) = ||F||_F`` with compliance ``alpha_D = 1 / (mu V0)``;
* hydrostatic constraint ``C_H(x) = det F - gamma``, ``gamma = 1 + mu / lambda``, compliance
  ``alpha_H = 1 / (lambda V0)``; an incompressible material has ``lambda = inf``: ``alpha_H = 0``,
  ``gamma = 1``.

Together they store the energy ``V0 (mu/2 ||F||^2 + lambda/2 (det F - gamma)^2)`` whose stress vanishes at
``F = I``. With ``alpha~ = alpha / dt^2`` and multipliers ``lambda_i`` reset each substep, XPBD asks each
projection for ``d_lambda`` solving the linearised equations ``C_i + grad C_i . dx + alpha~_i (lambda_i +
d_lambda_i) = 0`` with ``dx_k = w_k sum_j grad_k C_j d_lambda_j``.

Why the two constraints of one tet are solved together: at rest ``C_D = sqrt(3)`` and
``C_H = -mu / lambda`` are both non-zero while their gradients are parallel (``dC_D/dF = F / ||F||`` and
``dC_H/dF = cof F`` are both multiples of the identity). Projected one after the other, each constraint
moves the nodes to reduce its own value and the other undoes it, so a tet at rest jitters. The coupled
2x2 solve ``A d_lambda = -C - alpha~ lambda`` with ``A_ij = sum_k w_k grad_k C_i . grad_k C_j +
alpha~_i delta_ij`` finds the multipliers whose combined correction is exactly zero at rest (the forces of
the two constraints cancel there), and ``A`` stays invertible for incompressible material
(``alpha~_H = 0``) because ``alpha~_D > 0``.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numba import njit

from suture_gym.sim.coupling.compliance import answers_for, apply_impulse, weighted_inv_mass

#: ``||F||_F`` below which a tet is treated as collapsed to a point and left uncorrected (dimensionless).
MIN_FROBENIUS = 1e-12


@njit(cache=True)
def deformation_gradient(x: np.ndarray, dm_inv: np.ndarray, f_out: np.ndarray) -> None:
    """Deformation gradient ``F = Ds Dm^-1`` of one tet.

    Args:
        x: ``(4, 3)`` current node positions, m.
        dm_inv: ``(3, 3)`` inverse rest shape matrix, 1/m.
        f_out: ``(3, 3)`` written with ``F`` (dimensionless).
    """
    for i in range(3):
        d1 = x[1, i] - x[0, i]
        d2 = x[2, i] - x[0, i]
        d3 = x[3, i] - x[0, i]
        for j in range(3):
            f_out[i, j] = d1 * dm_inv[0, j] + d2 * dm_inv[1, j] + d3 * dm_inv[2, j]


@njit(cache=True)
def neo_hookean_constraints(f: np.ndarray, gamma: float, dcdf_out: np.ndarray) -> tuple[float, float]:
    """Stable neo-Hookean constraint values and their derivatives with respect to ``F``.

    ``C_D = ||F||_F``, ``dC_D/dF = F / ||F||_F``; ``C_H = det F - gamma``, ``dC_H/dF = cof F`` whose columns
    are ``f2 x f3, f3 x f1, f1 x f2`` for the columns ``f1, f2, f3`` of ``F`` (Macklin & Muller 2021).

    Args:
        f: ``(3, 3)`` deformation gradient.
        gamma: rest value of ``det F``, ``1 + mu / lambda``.
        dcdf_out: ``(2, 3, 3)`` written with ``dC_D/dF`` and ``dC_H/dF``; both zero for a tet collapsed to a
            point (``||F|| < MIN_FROBENIUS``), which then gets no correction.

    Returns:
        ``(C_D, C_H)``.
    """
    norm = 0.0
    for i in range(3):
        for j in range(3):
            norm += f[i, j] * f[i, j]
    norm = math.sqrt(norm)
    if norm < MIN_FROBENIUS:
        for c in range(2):
            for i in range(3):
                for j in range(3):
                    dcdf_out[c, i, j] = 0.0
        return norm, -gamma
    for i in range(3):
        for j in range(3):
            dcdf_out[0, i, j] = f[i, j] / norm
    # Columns of the cofactor matrix: cross products of the other two columns of F.
    for j in range(3):
        a = (j + 1) % 3
        b = (j + 2) % 3
        dcdf_out[1, 0, j] = f[1, a] * f[2, b] - f[2, a] * f[1, b]
        dcdf_out[1, 1, j] = f[2, a] * f[0, b] - f[0, a] * f[2, b]
        dcdf_out[1, 2, j] = f[0, a] * f[1, b] - f[1, a] * f[0, b]
    det = f[0, 0] * dcdf_out[1, 0, 0] + f[1, 0] * dcdf_out[1, 1, 0] + f[2, 0] * dcdf_out[1, 2, 0]
    return norm, det - gamma


@njit(cache=True)
def node_gradients(dcdf: np.ndarray, dm_inv: np.ndarray, grad_out: np.ndarray) -> None:
    """Node gradients ``dC/dx_k`` from ``dC/dF``.

    ``dC/dx_k = (dC/dF Dm^-T)[:, k - 1]`` for ``k = 1, 2, 3`` and ``dC/dx_0 = -sum_k dC/dx_k``.

    Args:
        dcdf: ``(m, 3, 3)`` derivatives of ``m`` constraints with respect to ``F``.
        dm_inv: ``(3, 3)`` inverse rest shape matrix, 1/m.
        grad_out: ``(m, 4, 3)`` written with the node gradients, 1/m.
    """
    for c in range(dcdf.shape[0]):
        for i in range(3):
            total = 0.0
            for k in range(3):
                g = dcdf[c, i, 0] * dm_inv[k, 0] + dcdf[c, i, 1] * dm_inv[k, 1] + dcdf[c, i, 2] * dm_inv[k, 2]
                grad_out[c, k + 1, i] = g
                total += g
            grad_out[c, 0, i] = -total


@njit(cache=True)
def coupled_multiplier_update(
    c_dev: float,
    c_hyd: float,
    grad: np.ndarray,
    w: np.ndarray,
    alpha_tilde_dev: float,
    alpha_tilde_hyd: float,
    lambda_dev: float,
    lambda_hyd: float,
) -> tuple[float, float]:
    """Multiplier increments of the coupled deviatoric/hydrostatic XPBD solve of one tet.

    Solves ``A d_lambda = b`` with ``A_ij = sum_k w_k grad_k C_i . grad_k C_j + alpha~_i delta_ij`` and
    ``b_i = -C_i - alpha~_i lambda_i``. The determinant is assembled as
    ``G + alpha~_D A'_HH + alpha~_H A'_DD + alpha~_D alpha~_H`` with the Gram determinant
    ``G = A'_DD A'_HH - A'_DH^2 >= 0`` clamped at zero against round-off (``A'`` is ``A`` without
    compliance), so it is positive whenever ``alpha~_D > 0`` and the hydrostatic row is not empty. When it
    is not (a flattened tet of incompressible material: ``cof F = 0``, ``alpha~_H = 0``), the deviatoric
    constraint is solved alone.

    Args:
        c_dev, c_hyd: constraint values ``C_D``, ``C_H``.
        grad: ``(2, 4, 3)`` node gradients of ``C_D`` and ``C_H``, 1/m.
        w: ``(4,)`` inverse masses of the tet's nodes, 1/kg (0 for pinned nodes).
        alpha_tilde_dev, alpha_tilde_hyd: ``alpha / dt^2`` of each constraint, 1/(J s^2).
        lambda_dev, lambda_hyd: multipliers accumulated so far in this substep, J s^2.

    Returns:
        ``(d_lambda_D, d_lambda_H)`` in J s^2.
    """
    a_dd = a_dh = a_hh = 0.0
    for k in range(4):
        dd, dh, hh = _gram(w[k], grad[0, k, 0], grad[0, k, 1], grad[0, k, 2], grad[1, k, 0], grad[1, k, 1],
                           grad[1, k, 2])  # fmt: skip
        a_dd += dd
        a_dh += dh
        a_hh += hh
    return _coupled_solve(a_dd, a_dh, a_hh, c_dev, c_hyd, alpha_tilde_dev, alpha_tilde_hyd, lambda_dev, lambda_hyd)


@njit(cache=True, inline="always")
def _gram(w, ax, ay, az, bx, by, bz):
    """One node's terms ``w (a.a, a.b, b.b)`` of :func:`coupled_multiplier_update`'s matrix."""
    return w * (ax * ax + ay * ay + az * az), w * (ax * bx + ay * by + az * bz), w * (bx * bx + by * by + bz * bz)


@njit(cache=True, inline="always")
def _coupled_solve(a_dd, a_dh, a_hh, c_dev, c_hyd, alpha_dev, alpha_hyd, lambda_dev, lambda_hyd):
    """The 2x2 solve of :func:`coupled_multiplier_update` from its summed matrix terms ``a_dd, a_dh, a_hh``."""
    b_dev = -c_dev - alpha_dev * lambda_dev
    b_hyd = -c_hyd - alpha_hyd * lambda_hyd
    gram = max(a_dd * a_hh - a_dh * a_dh, 0.0)
    det = gram + alpha_dev * a_hh + alpha_hyd * a_dd + alpha_dev * alpha_hyd
    m_dd = a_dd + alpha_dev
    m_hh = a_hh + alpha_hyd
    if det > 1e-14 * m_dd * m_hh:
        return (m_hh * b_dev - a_dh * b_hyd) / det, (m_dd * b_hyd - a_dh * b_dev) / det
    if m_dd > 0.0:
        return b_dev / m_dd, 0.0
    return 0.0, 0.0


#: Tets projected together by :func:`project_tets`: the block's arithmetic runs as one loop over the block's
#: lanes, which the compiler vectorises (it must know the lanes' count and the rows' offsets at compile time to
#: see that no row overlaps another, so a block always computes all its lanes and ignores the unused ones).
#: 16 swept the paper's cube and the environments' pad as fast as 8 or 32 and faster than 64 (the pad's colours
#: hold about 26 tets, so larger blocks compute mostly unused lanes).
TET_BLOCK = 16
# Rows of the block buffer (each TET_BLOCK lanes): the gathered inputs, then the results.
_EDGE = 0  # 9 rows: axis i's edge differences x_k - x_0 of nodes k = 1, 2, 3 at 3 i + k - 1
_DM = 9  # 9 rows: Dm^-1 entry (a, b) at 3 a + b
_W = 18  # 4 rows: the nodes' inverse masses
_MU, _LAMBDA, _VOLUME, _MULT_DEV, _MULT_HYD = 22, 23, 24, 25, 26
_CORRECTION = 27  # 12 rows: node k's move along axis i at 3 k + i
_D_DEV, _D_HYD = 39, 40
_BLOCK_ROWS = 41


@njit(cache=True, inline="always")
def _grad_row(r0, r1, r2, m00, m01, m02, m10, m11, m12, m20, m21, m22):
    """Axis ``i`` of the node gradients ``(dC/dx_0, .., dC/dx_3)[i]`` from row ``i`` ``(r0, r1, r2)`` of ``dC/dF``
    and ``Dm^-1`` entries ``m_ab`` (:func:`node_gradients`' arithmetic, in its order), a tuple."""
    g1 = r0 * m00 + r1 * m01 + r2 * m02
    g2 = r0 * m10 + r1 * m11 + r2 * m12
    g3 = r0 * m20 + r1 * m21 + r2 * m22
    return -(0.0 + g1 + g2 + g3), g1, g2, g3


@njit(cache=True, inline="always", error_model="numpy")
def _block_corrections(b, inv_dt2):
    """The XPBD projection of every lane of a block buffer ``b`` (rows :data:`_EDGE` ...) in one loop: from each
    tet's edges, ``Dm^-1``, inverse masses, moduli, volume and multipliers, its multiplier increments and its
    nodes' moves (the arithmetic of :func:`deformation_gradient`, :func:`neo_hookean_constraints`,
    :func:`node_gradients` and :func:`coupled_multiplier_update`, operation for operation; the compiler turns their
    branches into selections)."""
    n = TET_BLOCK
    for j in range(TET_BLOCK):
        m00, m01, m02 = b[(_DM + 0) * n + j], b[(_DM + 1) * n + j], b[(_DM + 2) * n + j]
        m10, m11, m12 = b[(_DM + 3) * n + j], b[(_DM + 4) * n + j], b[(_DM + 5) * n + j]
        m20, m21, m22 = b[(_DM + 6) * n + j], b[(_DM + 7) * n + j], b[(_DM + 8) * n + j]
        d1, d2, d3 = b[(_EDGE + 0) * n + j], b[(_EDGE + 1) * n + j], b[(_EDGE + 2) * n + j]
        f00, f01, f02 = d1 * m00 + d2 * m10 + d3 * m20, d1 * m01 + d2 * m11 + d3 * m21, d1 * m02 + d2 * m12 + d3 * m22
        d1, d2, d3 = b[(_EDGE + 3) * n + j], b[(_EDGE + 4) * n + j], b[(_EDGE + 5) * n + j]
        f10, f11, f12 = d1 * m00 + d2 * m10 + d3 * m20, d1 * m01 + d2 * m11 + d3 * m21, d1 * m02 + d2 * m12 + d3 * m22
        d1, d2, d3 = b[(_EDGE + 6) * n + j], b[(_EDGE + 7) * n + j], b[(_EDGE + 8) * n + j]
        f20, f21, f22 = d1 * m00 + d2 * m10 + d3 * m20, d1 * m01 + d2 * m11 + d3 * m21, d1 * m02 + d2 * m12 + d3 * m22
        mu = b[_MU * n + j]
        lam = b[_LAMBDA * n + j]
        gamma = 1.0 + mu / lam
        norm = 0.0 + f00 * f00
        norm = norm + f01 * f01
        norm = norm + f02 * f02
        norm = norm + f10 * f10
        norm = norm + f11 * f11
        norm = norm + f12 * f12
        norm = norm + f20 * f20
        norm = norm + f21 * f21
        norm = norm + f22 * f22
        norm = math.sqrt(norm)
        c_dev = norm
        live = not norm < MIN_FROBENIUS  # collapsed to a point: zero gradients, no correction
        e00, e01, e02 = f00 / norm if live else 0.0, f01 / norm if live else 0.0, f02 / norm if live else 0.0
        e10, e11, e12 = f10 / norm if live else 0.0, f11 / norm if live else 0.0, f12 / norm if live else 0.0
        e20, e21, e22 = f20 / norm if live else 0.0, f21 / norm if live else 0.0, f22 / norm if live else 0.0
        k00 = f11 * f22 - f21 * f12 if live else 0.0
        k10 = f21 * f02 - f01 * f22 if live else 0.0
        k20 = f01 * f12 - f11 * f02 if live else 0.0
        k01 = f12 * f20 - f22 * f10 if live else 0.0
        k11 = f22 * f00 - f02 * f20 if live else 0.0
        k21 = f02 * f10 - f12 * f00 if live else 0.0
        k02 = f10 * f21 - f20 * f11 if live else 0.0
        k12 = f20 * f01 - f00 * f21 if live else 0.0
        k22 = f00 * f11 - f10 * f01 if live else 0.0
        c_hyd = (f00 * k00 + f10 * k10 + f20 * k20) - gamma if live else -gamma
        a0x, a1x, a2x, a3x = _grad_row(e00, e01, e02, m00, m01, m02, m10, m11, m12, m20, m21, m22)
        a0y, a1y, a2y, a3y = _grad_row(e10, e11, e12, m00, m01, m02, m10, m11, m12, m20, m21, m22)
        a0z, a1z, a2z, a3z = _grad_row(e20, e21, e22, m00, m01, m02, m10, m11, m12, m20, m21, m22)
        b0x, b1x, b2x, b3x = _grad_row(k00, k01, k02, m00, m01, m02, m10, m11, m12, m20, m21, m22)
        b0y, b1y, b2y, b3y = _grad_row(k10, k11, k12, m00, m01, m02, m10, m11, m12, m20, m21, m22)
        b0z, b1z, b2z, b3z = _grad_row(k20, k21, k22, m00, m01, m02, m10, m11, m12, m20, m21, m22)
        w0, w1, w2, w3 = b[(_W + 0) * n + j], b[(_W + 1) * n + j], b[(_W + 2) * n + j], b[(_W + 3) * n + j]
        dd0, dh0, hh0 = _gram(w0, a0x, a0y, a0z, b0x, b0y, b0z)
        dd1, dh1, hh1 = _gram(w1, a1x, a1y, a1z, b1x, b1y, b1z)
        dd2, dh2, hh2 = _gram(w2, a2x, a2y, a2z, b2x, b2y, b2z)
        dd3, dh3, hh3 = _gram(w3, a3x, a3y, a3z, b3x, b3y, b3z)
        a_dd = 0.0 + dd0 + dd1 + dd2 + dd3
        a_dh = 0.0 + dh0 + dh1 + dh2 + dh3
        a_hh = 0.0 + hh0 + hh1 + hh2 + hh3
        volume = b[_VOLUME * n + j]
        d_dev, d_hyd = _coupled_solve(a_dd, a_dh, a_hh, c_dev, c_hyd, inv_dt2 / (mu * volume), inv_dt2 / (lam * volume),
                                      b[_MULT_DEV * n + j], b[_MULT_HYD * n + j])  # fmt: skip
        b[_D_DEV * n + j] = d_dev
        b[_D_HYD * n + j] = d_hyd
        b[(_CORRECTION + 0) * n + j] = w0 * (a0x * d_dev + b0x * d_hyd)
        b[(_CORRECTION + 1) * n + j] = w0 * (a0y * d_dev + b0y * d_hyd)
        b[(_CORRECTION + 2) * n + j] = w0 * (a0z * d_dev + b0z * d_hyd)
        b[(_CORRECTION + 3) * n + j] = w1 * (a1x * d_dev + b1x * d_hyd)
        b[(_CORRECTION + 4) * n + j] = w1 * (a1y * d_dev + b1y * d_hyd)
        b[(_CORRECTION + 5) * n + j] = w1 * (a1z * d_dev + b1z * d_hyd)
        b[(_CORRECTION + 6) * n + j] = w2 * (a2x * d_dev + b2x * d_hyd)
        b[(_CORRECTION + 7) * n + j] = w2 * (a2y * d_dev + b2y * d_hyd)
        b[(_CORRECTION + 8) * n + j] = w2 * (a2z * d_dev + b2z * d_hyd)
        b[(_CORRECTION + 9) * n + j] = w3 * (a3x * d_dev + b3x * d_hyd)
        b[(_CORRECTION + 10) * n + j] = w3 * (a3y * d_dev + b3y * d_hyd)
        b[(_CORRECTION + 11) * n + j] = w3 * (a3z * d_dev + b3z * d_hyd)


class TetBlocks(NamedTuple):
    """The tets of a Gauss-Seidel order in blocks for :func:`project_tet_blocks`, built by :func:`tet_blocks`.

    Each block holds up to :data:`TET_BLOCK` tets, consecutive in the order, that share no particle (a colour
    order fills the blocks), and skips tets with four pinned nodes. Lanes past a block's count hold tet -1, node 0
    and zeros.

    Attributes:
        tets: ``(K, TET_BLOCK) int32`` each lane's tet.
        nodes: ``(K, 4, TET_BLOCK) int32`` each lane's node indices.
        data: ``(K, 16 TET_BLOCK) float64`` each lane's constant data in the block buffer's rows 9-24 (``Dm^-1``
            (1/m), the nodes' inverse masses (1/kg), ``mu`` and ``lambda`` (Pa), rest volume (m^3)), row-major.
        lanes: ``(K,) int32`` tets in each block.
    """

    tets: np.ndarray
    nodes: np.ndarray
    data: np.ndarray
    lanes: np.ndarray


@njit(cache=True)
def _block_members(inv_mass, tet_indices, order):
    """Each position of ``order``'s block (-1: a tet with four pinned nodes, skipped) and the number of blocks."""
    block_of = np.full(inv_mass.shape[0], -1, np.int64)  # the last block that took each particle
    member = np.full(order.shape[0], -1, np.int64)
    block, lanes = 0, 0
    for n in range(order.shape[0]):
        t = order[n]
        p0, p1, p2, p3 = tet_indices[t, 0], tet_indices[t, 1], tet_indices[t, 2], tet_indices[t, 3]
        if inv_mass[p0] + inv_mass[p1] + inv_mass[p2] + inv_mass[p3] == 0.0:
            continue
        if lanes == TET_BLOCK or (
            block_of[p0] == block or block_of[p1] == block or block_of[p2] == block or block_of[p3] == block
        ):
            block += 1
            lanes = 0
        block_of[p0] = block_of[p1] = block_of[p2] = block_of[p3] = block
        member[n] = block
        lanes += 1
    return member, (block + 1 if lanes else 0)


@njit(cache=True)
def _fill_blocks(inv_mass, tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, order, member, tets, nodes,
                 data, lanes):  # fmt: skip
    """Write :class:`TetBlocks`' arrays from :func:`_block_members`' assignment."""
    n = TET_BLOCK
    for i in range(order.shape[0]):
        k = member[i]
        if k < 0:
            continue
        j = lanes[k]
        lanes[k] += 1
        t = order[i]
        tets[k, j] = t
        for c in range(4):
            nodes[k, c, j] = tet_indices[t, c]
            data[k, (_W - _DM + c) * n + j] = inv_mass[tet_indices[t, c]]
        for a in range(3):
            for c in range(3):
                data[k, (3 * a + c) * n + j] = tet_dm_inv[t, a, c]
        data[k, (_MU - _DM) * n + j] = tet_mu[t]
        data[k, (_LAMBDA - _DM) * n + j] = tet_lambda[t]
        data[k, (_VOLUME - _DM) * n + j] = tet_rest_volume[t]


def tet_blocks(
    inv_mass: np.ndarray,
    tet_indices: np.ndarray,
    tet_dm_inv: np.ndarray,
    tet_rest_volume: np.ndarray,
    tet_mu: np.ndarray,
    tet_lambda: np.ndarray,
    order: np.ndarray,
) -> TetBlocks:
    """The :class:`TetBlocks` of the tets in ``order`` (arguments as in :func:`project_tets`)."""
    member, count = _block_members(inv_mass, tet_indices, order)
    tets = np.full((count, TET_BLOCK), -1, np.int32)
    nodes = np.zeros((count, 4, TET_BLOCK), np.int32)
    data = np.zeros((count, (_VOLUME + 1 - _DM) * TET_BLOCK))
    lanes = np.zeros(count, np.int32)
    _fill_blocks(inv_mass, tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, order, member, tets, nodes,
                 data, lanes)  # fmt: skip
    return TetBlocks(tets, nodes, data, lanes)


@njit(cache=True, error_model="numpy")
def project_tet_blocks(
    tets: np.ndarray, nodes: np.ndarray, data: np.ndarray, lanes: np.ndarray, dt: float, q: np.ndarray,
    multiplier: np.ndarray,
) -> None:  # fmt: skip
    """:func:`project_tets` over the blocks of :func:`tet_blocks` (``tets, nodes, data, lanes``: the
    :class:`TetBlocks` fields): per block, its constant rows and its tets' edges and multipliers are gathered into
    one buffer, every lane is projected in one vectorised loop (:func:`_block_corrections`), and the nodes and
    multipliers take the results. The block's tets share no particle, so this is exactly the sequential sweep.

    Args:
        tets, nodes, data, lanes: a :class:`TetBlocks`.
        dt: substep, s.
        q: ``(N, 3)`` particle positions, m; corrected in place.
        multiplier: ``(T, 2)`` XPBD multipliers ``[lambda_D, lambda_H]`` of this substep, J s^2; updated.
    """
    inv_dt2 = 1.0 / (dt * dt)
    n = TET_BLOCK
    b = np.zeros(_BLOCK_ROWS * n)
    for k in range(tets.shape[0]):
        for i in range(data.shape[1]):
            b[_DM * n + i] = data[k, i]
        for j in range(lanes[k]):
            t = tets[k, j]
            p0, p1, p2, p3 = nodes[k, 0, j], nodes[k, 1, j], nodes[k, 2, j], nodes[k, 3, j]
            for i in range(3):
                x0 = q[p0, i]
                b[(_EDGE + 3 * i) * n + j] = q[p1, i] - x0
                b[(_EDGE + 3 * i + 1) * n + j] = q[p2, i] - x0
                b[(_EDGE + 3 * i + 2) * n + j] = q[p3, i] - x0
            b[_MULT_DEV * n + j] = multiplier[t, 0]
            b[_MULT_HYD * n + j] = multiplier[t, 1]
        _block_corrections(b, inv_dt2)
        for j in range(lanes[k]):
            t = tets[k, j]
            multiplier[t, 0] += b[_D_DEV * n + j]
            multiplier[t, 1] += b[_D_HYD * n + j]
            for c in range(4):
                if b[(_W + c) * n + j] > 0.0:
                    p = nodes[k, c, j]
                    for i in range(3):
                        q[p, i] += b[(_CORRECTION + 3 * c + i) * n + j]


def project_tets(
    inv_mass: np.ndarray,
    tet_indices: np.ndarray,
    tet_dm_inv: np.ndarray,
    tet_rest_volume: np.ndarray,
    tet_mu: np.ndarray,
    tet_lambda: np.ndarray,
    order: np.ndarray,
    dt: float,
    q: np.ndarray,
    multiplier: np.ndarray,
) -> None:
    """One Gauss-Seidel sweep of the coupled stable neo-Hookean XPBD projection over the tets in ``order``.

    Per tet: ``C_D = ||F||_F`` (compliance ``1/(mu V0)``) and ``C_H = det F - (1 + mu/lambda)``
    (compliance ``1/(lambda V0)``), Macklin & Muller 2021; increments from
    :func:`coupled_multiplier_update`, then ``x_k += w_k (grad_k C_D d_lambda_D + grad_k C_H d_lambda_H)``.

    The tets go in blocks of up to :data:`TET_BLOCK` consecutive tets that share no particle (:func:`tet_blocks`,
    which the solver builds once per model) through the vectorised :func:`project_tet_blocks`; such tets are
    independent, so this is exactly the sequential sweep. The arithmetic is that of :func:`deformation_gradient`,
    :func:`neo_hookean_constraints`, :func:`node_gradients` and :func:`coupled_multiplier_update`, operation for
    operation (the same result bit for bit, ``tests/test_tissue.py``); tets with four pinned nodes are skipped.
    Sweeping the paper's cube (6,840 tets) this way took 0.4x the time of the tet-by-tet scalar loop.

    Args:
        inv_mass: ``(N,)`` inverse particle masses, 1/kg (0 = pinned).
        tet_indices: ``(T, 4) int32`` node indices.
        tet_dm_inv: ``(T, 3, 3)`` inverse rest shape matrices, 1/m.
        tet_rest_volume: ``(T,)`` rest volumes, m^3.
        tet_mu: ``(T,)`` deviatoric modulus, Pa.
        tet_lambda: ``(T,)`` hydrostatic modulus, Pa (``inf`` = incompressible).
        order: ``(A,) int32`` tets in Gauss-Seidel order (the colour order).
        dt: substep, s.
        q: ``(N, 3)`` particle positions, m; corrected in place.
        multiplier: ``(T, 2)`` XPBD multipliers ``[lambda_D, lambda_H]`` of this substep, J s^2; updated.
    """
    blocks = tet_blocks(inv_mass, tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, order)
    project_tet_blocks(*blocks, dt, q, multiplier)


@njit(cache=True)
def tet_residual(
    tet_indices: np.ndarray,
    tet_dm_inv: np.ndarray,
    tet_rest_volume: np.ndarray,
    tet_mu: np.ndarray,
    tet_lambda: np.ndarray,
    order: np.ndarray,
    q: np.ndarray,
    multiplier: np.ndarray,
    dt: float,
) -> float:
    """XPBD residual ``sqrt(sum_t sum_i (C_i(x) + alpha~_i lambda_i)^2)`` over both constraints of the tets in
    ``order`` (the ones the solver projects).

    It vanishes when the multipliers and positions solve the substep's implicit equations; Gauss-Seidel
    sweeps of :func:`project_tets` drive it down (dimensionless).

    Args:
        tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, order: as in :func:`project_tets`.
        q: ``(N, 3)`` particle positions, m.
        multiplier: ``(T, 2)`` multipliers of the current substep, J s^2.
        dt: substep, s.
    """
    x = np.empty((4, 3))
    f = np.empty((3, 3))
    dcdf = np.empty((2, 3, 3))
    inv_dt2 = 1.0 / (dt * dt)
    total = 0.0
    for n in range(order.shape[0]):
        t = order[n]
        for k in range(4):
            for i in range(3):
                x[k, i] = q[tet_indices[t, k], i]
        deformation_gradient(x, tet_dm_inv[t], f)
        mu = tet_mu[t]
        lam = tet_lambda[t]
        c_dev, c_hyd = neo_hookean_constraints(f, 1.0 + mu / lam, dcdf)
        volume = tet_rest_volume[t]
        r_dev = c_dev + inv_dt2 / (mu * volume) * multiplier[t, 0]
        r_hyd = c_hyd + inv_dt2 / (lam * volume) * multiplier[t, 1]
        total += r_dev * r_dev + r_hyd * r_hyd
    return math.sqrt(total)


@njit(cache=True)
def tet_elastic_energy(
    tet_indices: np.ndarray,
    tet_dm_inv: np.ndarray,
    tet_rest_volume: np.ndarray,
    tet_mu: np.ndarray,
    tet_lambda: np.ndarray,
    q: np.ndarray,
) -> float:
    """Stored elastic energy ``sum_t V0 (mu/2 (||F||^2 - 3) + lambda/2 ((det F - gamma)^2 - (1 - gamma)^2))``, J.

    Shifted so that the rest state has zero energy. For incompressible tets (``lambda = inf``) the
    hydrostatic term is a hard constraint and contributes nothing.
    """
    x = np.empty((4, 3))
    f = np.empty((3, 3))
    dcdf = np.empty((2, 3, 3))
    total = 0.0
    for t in range(tet_indices.shape[0]):
        for k in range(4):
            for i in range(3):
                x[k, i] = q[tet_indices[t, k], i]
        deformation_gradient(x, tet_dm_inv[t], f)
        mu = tet_mu[t]
        lam = tet_lambda[t]
        gamma = 1.0 + mu / lam
        c_dev, c_hyd = neo_hookean_constraints(f, gamma, dcdf)
        energy = 0.5 * mu * (c_dev * c_dev - 3.0)
        if math.isfinite(lam):
            energy += 0.5 * lam * (c_hyd * c_hyd - (1.0 - gamma) * (1.0 - gamma))
        total += tet_rest_volume[t] * energy
    return total


@njit(cache=True)
def project_rollers(
    inv_mass: np.ndarray,
    roller_particle: np.ndarray,
    roller_normal: np.ndarray,
    roller_offset: np.ndarray,
    q: np.ndarray,
) -> None:
    """Hard frictionless plane supports: ``C(x_p) = n . x_p - d = 0``, projected as ``x_p -= C n``.

    A single-particle constraint with zero compliance, so the projection is exact and the particle keeps
    its tangential motion (a roller support / symmetry plane; position-based constraint of Muller et al.
    2007, "Position Based Dynamics"). Pinned particles (inverse mass 0) are left alone.

    Args:
        inv_mass: ``(N,)`` inverse masses, 1/kg.
        roller_particle: ``(R,) int32`` particle of each support.
        roller_normal: ``(R, 3)`` unit plane normals.
        roller_offset: ``(R,)`` plane offsets ``d``, m.
        q: ``(N, 3)`` positions, m; projected in place.
    """
    for r in range(roller_particle.shape[0]):
        p = roller_particle[r]
        if inv_mass[p] == 0.0:
            continue
        n0, n1, n2 = roller_normal[r, 0], roller_normal[r, 1], roller_normal[r, 2]
        c = n0 * q[p, 0] + n1 * q[p, 1] + n2 * q[p, 2] - roller_offset[r]
        q[p, 0] -= c * n0
        q[p, 1] -= c * n1
        q[p, 2] -= c * n2


#: Largest ``dt sqrt(E / rho) / h`` at which the XPBD tissue projection is known to stay at rest: measured
#: stable at 0.89 and oscillating at 1.10 (:mod:`suture_gym.sim.solver`, Stability); above it the solver warns.
XPBD_STABILITY_LIMIT = 1.0


def xpbd_stability_number(tissue, dt: float) -> float:
    """Largest ``dt sqrt(E / rho) / h`` over the free tets of ``tissue`` (a
    :class:`~suture_gym.sim.model.TissueModel`) at substep ``dt`` (s): ``E`` each tet's Young's modulus (Pa,
    recovered from ``mu`` and ``lambda``; ``3 mu`` when incompressible), ``rho`` the mesh's mean density (kg/m^3,
    total mass over rest volume) and ``h`` the tet's shortest rest edge (m). Dimensionless; the XPBD tissue
    projection is stable at rest only below about :data:`XPBD_STABILITY_LIMIT`."""
    tets = tissue.tet_color_order
    if tets.size == 0:
        return 0.0
    mu, lam = tissue.tet_mu[tets], tissue.tet_lambda[tets]
    with np.errstate(invalid="ignore"):
        youngs = np.where(np.isfinite(lam), mu * (3.0 * lam - mu) / lam, 3.0 * mu)
    density = tissue.particle_mass.sum() / tissue.tet_rest_volume.sum()
    corners = tissue.particle_rest_q[tissue.tet_indices[tets]]
    edges = [np.linalg.norm(corners[:, a] - corners[:, b], axis=1) for a in range(4) for b in range(a + 1, 4)]
    shortest = np.min(edges, axis=0)
    return float(np.max(dt * np.sqrt(youngs / density) / shortest))


@njit(cache=True)
def supports_violated(inv_mass: np.ndarray, normal: np.ndarray, offset: np.ndarray, q: np.ndarray) -> bool:
    """Whether :func:`project_supports` would move any particle (a free one with ``n . x < d``); same arguments."""
    for s in range(normal.shape[0]):
        for p in range(q.shape[0]):
            if inv_mass[p] == 0.0:
                continue
            if normal[s, 0] * q[p, 0] + normal[s, 1] * q[p, 1] + normal[s, 2] * q[p, 2] - offset[s] < 0.0:
                return True
    return False


#: How far outside a triangle (in barycentric units) a particle's projection may fall and still touch it: an
#: incision's faces mirror each other vertex for vertex, so a particle pushed straight across meets the mirror
#: vertex, where its projection lies exactly on the corners of the triangles around it (round-off puts it just
#: outside each of them, and it passed between them).
FACE_CONTACT_EDGE = 0.05


@njit(cache=True, inline="always")
def face_contact(tri_indices: np.ndarray, v: int, f: int, reach: float, q: np.ndarray) -> tuple:
    """Whether particle ``v`` touches boundary triangle ``f`` (its corners ``tri_indices[f]``, counter-clockwise
    seen from outside) at positions ``q`` (N, 3) m, and where: ``(touching, gap, nx, ny, nz, b0, b1, b2)``.

    ``n`` is the triangle's unit outward normal (into the wound), ``gap = (x_v - x_a) . n`` (m) and ``b`` the
    barycentrics of ``v``'s projection onto the triangle's plane. They touch where ``-reach < gap < 0`` (behind
    the face, but not by more than ``reach``, m: beyond it the faces wrapped around each other) and the
    projection falls inside the triangle or within :data:`FACE_CONTACT_EDGE` of it; ``b`` are then clamped into
    the triangle (the nearest point of it at an edge or corner) and normalised."""
    a, b, c = tri_indices[f, 0], tri_indices[f, 1], tri_indices[f, 2]
    e1x, e1y, e1z = q[b, 0] - q[a, 0], q[b, 1] - q[a, 1], q[b, 2] - q[a, 2]
    e2x, e2y, e2z = q[c, 0] - q[a, 0], q[c, 1] - q[a, 1], q[c, 2] - q[a, 2]
    nx, ny, nz = e1y * e2z - e1z * e2y, e1z * e2x - e1x * e2z, e1x * e2y - e1y * e2x
    area2 = math.sqrt(nx * nx + ny * ny + nz * nz)
    if area2 <= 0.0:
        return False, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0
    nx, ny, nz = nx / area2, ny / area2, nz / area2
    dx, dy, dz = q[v, 0] - q[a, 0], q[v, 1] - q[a, 1], q[v, 2] - q[a, 2]
    gap = dx * nx + dy * ny + dz * nz
    if not (-reach < gap < 0.0):
        return False, gap, nx, ny, nz, 0.0, 0.0, 0.0
    # barycentrics of the projection: areas of the sub-triangles over the whole (along n)
    px, py, pz = dx - gap * nx, dy - gap * ny, dz - gap * nz
    b1 = ((py * e2z - pz * e2y) * nx + (pz * e2x - px * e2z) * ny + (px * e2y - py * e2x) * nz) / area2
    b2 = ((e1y * pz - e1z * py) * nx + (e1z * px - e1x * pz) * ny + (e1x * py - e1y * px) * nz) / area2
    b0 = 1.0 - b1 - b2
    if b0 < -FACE_CONTACT_EDGE or b1 < -FACE_CONTACT_EDGE or b2 < -FACE_CONTACT_EDGE:
        return False, gap, nx, ny, nz, b0, b1, b2
    b0, b1, b2 = max(b0, 0.0), max(b1, 0.0), max(b2, 0.0)
    total = b0 + b1 + b2
    return True, gap, nx, ny, nz, b0 / total, b1 / total, b2 / total


@njit(cache=True)
def project_face_contacts(
    tri_indices: np.ndarray,
    contact_vertex: np.ndarray,
    contact_face: np.ndarray,
    reach: float,
    q: np.ndarray,
    tissue: tuple,
) -> int:
    """One Gauss-Seidel pass of the tissue's contact with itself across a wound (``TissueModel.contact_vertex``,
    ``contact_face``): particle ``v`` of a pair may not lie behind the boundary triangle ``f`` facing it
    (:func:`face_contact`). Where it does, with ``C = (x_v - p) . n`` and ``p = sum_k b_k x_k``, the two are pushed
    apart along ``n`` with zero compliance (frictionless) by the impulse ``dlambda = -C / W`` (kg m) between the
    particle (weight 1) and the triangle's point (weights ``-b_k``), ``W = n^T (sum_ab w_a w_b C_ab) n`` with the
    tissue's compliance ``C`` (1/kg, the tuple of :mod:`~suture_gym.sim.coupling.compliance`). With the diagonal
    compliance (the XPBD tissue's) that is ``W = w_v + sum_k b_k^2 w_k``, ``x_v += w_v dlambda n``,
    ``x_k -= w_k b_k dlambda n``, which keeps the mass-weighted mean position; with an implicit integrator's
    (:meth:`~suture_gym.sim.tissue_implicit.ImplicitTissue.project_face_contacts`) every vertex of the tuple moves
    by its response and the impulses are summed in the tuple. A block holds the vertices of the pairs touching when
    the pass began; a pair that begins to touch during the pass with a free vertex outside it is left to the next
    pass (:func:`~suture_gym.sim.coupling.compliance.answers_for`: its impulse, weighed on part of its vertices,
    once threw a vertex 37 m).

    Args:
        tri_indices: ``(F, 3)`` boundary triangles, counter-clockwise seen from outside. contact_vertex,
            contact_face: ``(P,)`` the pairs. reach: m.
        q: ``(N, 3)`` positions, m; projected in place.
        tissue: the compliance tuple.

    Returns:
        The number of pairs corrected.
    """
    idx = np.empty(4, np.int64)
    weight = np.empty(4)
    normal = np.empty(3)
    impulse = np.empty(3)
    corrected = 0
    for k in range(contact_vertex.shape[0]):
        v, f = contact_vertex[k], contact_face[k]
        touching, gap, nx, ny, nz, b0, b1, b2 = face_contact(tri_indices, v, f, reach, q)
        if not touching:
            continue
        idx[0], idx[1], idx[2], idx[3] = v, tri_indices[f, 0], tri_indices[f, 1], tri_indices[f, 2]
        if not answers_for(tissue, idx, 4):
            continue  # began to touch during this pass, with a free vertex outside its block; next pass
        weight[0], weight[1], weight[2], weight[3] = 1.0, -b0, -b1, -b2
        normal[0], normal[1], normal[2] = nx, ny, nz
        w = weighted_inv_mass(tissue, idx, weight, normal)
        if not w > 0.0:
            continue
        dlam = -gap / w
        for i in range(3):
            impulse[i] = -dlam * normal[i]  # the tissue takes -weight_a * impulse at vertex a: v along +n
        apply_impulse(tissue, idx, weight, 4, impulse, q)
        corrected += 1
    return corrected


@njit(cache=True)
def project_supports(inv_mass: np.ndarray, normal: np.ndarray, offset: np.ndarray, q: np.ndarray) -> None:
    """Rigid, frictionless, one-sided supports: every free particle with ``n . x < d`` is moved onto the plane
    (``x -= (n . x - d) n``); the support has infinite mass, so the whole correction goes to the particle.

    Args:
        inv_mass: ``(N,)`` inverse masses, 1/kg (pinned particles are left alone).
        normal: ``(S, 3)`` unit normals pointing into the allowed side.
        offset: ``(S,)`` plane offsets ``d``, m.
        q: ``(N, 3)`` positions, m; projected in place.
    """
    for s in range(normal.shape[0]):
        n0, n1, n2 = normal[s, 0], normal[s, 1], normal[s, 2]
        for p in range(q.shape[0]):
            if inv_mass[p] == 0.0:
                continue
            c = n0 * q[p, 0] + n1 * q[p, 1] + n2 * q[p, 2] - offset[s]
            if c < 0.0:
                q[p, 0] -= c * n0
                q[p, 1] -= c * n1
                q[p, 2] -= c * n2
