"""The stable neo-Hookean elastic energy of a tet mesh and the kernels over the implicit-Euler incremental
potential built on it: what :mod:`~suture_gym.sim.tissue_implicit`'s integrators evaluate.

The density (Macklin & Muller 2021's form of Smith et al. 2018), per tet with deformation gradient ``F`` (3, 3)::

    Psi(F) = mu/2 (||F||^2 - 3) + lambda/2 ((det F - gamma)^2 - (1 - gamma)^2),   gamma = 1 + mu / lambda,

``mu`` the deviatoric modulus and ``lambda`` the hydrostatic modulus (Lame lambda + mu, see
:class:`~suture_gym.sim.model.TissueMaterial`), both Pa: at ``F = I`` it linearises to linear elasticity with the
material's ``E`` and ``nu``. Its first Piola stress is ``P = mu F + lambda (J - gamma) cof F`` and its second
derivative ``d2Psi/dF_ij dF_kl = mu d_ik d_jl + lambda cof_ij cof_kl + lambda (J - gamma) eps_ikm eps_jln F_mn``.
A tet's energy is ``V0 Psi(F)`` (J) with ``F = sum_k x_k g_k^T`` from its node positions ``x_k`` (m) and the
shape gradients ``g_k`` (1/m, rows of ``Dm^-1``, :func:`shape_gradients`).

Here: the density, stress and tangent of one ``F``; a tet's stiffness (12, 12) and the mesh's (3N, 3N); the
incremental potential ``Phi`` of one substep and its gradient over the tets in columns (:func:`tet_columns`,
:func:`potential_kernel`); one Vertex Block Descent sweep over it (:func:`vbd_sweep`). The kernels are compiled
(numba) and allocate nothing per call unless said.
"""

from __future__ import annotations

import numpy as np
import scipy.sparse as sp
from numba import njit


@njit(cache=True)
def _cofactor(f: np.ndarray, cof: np.ndarray) -> float:
    """Write ``cof F`` (columns ``f2 x f3, f3 x f1, f1 x f2``) into ``cof`` (3, 3); return ``det F``."""
    for j in range(3):
        a = (j + 1) % 3
        b = (j + 2) % 3
        cof[0, j] = f[1, a] * f[2, b] - f[2, a] * f[1, b]
        cof[1, j] = f[2, a] * f[0, b] - f[0, a] * f[2, b]
        cof[2, j] = f[0, a] * f[1, b] - f[1, a] * f[0, b]
    return f[0, 0] * cof[0, 0] + f[1, 0] * cof[1, 0] + f[2, 0] * cof[2, 0]


@njit(cache=True)
def shape_gradients(dm_inv: np.ndarray, g: np.ndarray) -> None:
    """``g[k]`` (4, 3): ``dF/dx_k = I (x) g_k``; rows of ``Dm^-1`` for k = 1..3, minus their sum for k = 0."""
    for j in range(3):
        g[1, j] = dm_inv[0, j]
        g[2, j] = dm_inv[1, j]
        g[3, j] = dm_inv[2, j]
        g[0, j] = -(dm_inv[0, j] + dm_inv[1, j] + dm_inv[2, j])


@njit(cache=True)
def _tet_f(q: np.ndarray, nodes: np.ndarray, g: np.ndarray, f: np.ndarray) -> None:
    """``F = sum_k x_k g_k^T`` of one tet (3, 3)."""
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(4):
                s += q[nodes[k], i] * g[k, j]
            f[i, j] = s


@njit(cache=True)
def _stress(f: np.ndarray, mu: float, lam: float, cof: np.ndarray, p_out: np.ndarray) -> float:
    """:func:`stable_neo_hookean_stress` with a caller-owned ``(3, 3)`` scratch ``cof`` (no allocation)."""
    gamma = 1.0 + mu / lam
    det = _cofactor(f, cof)
    s = lam * (det - gamma)
    norm2 = 0.0
    for i in range(3):
        for j in range(3):
            norm2 += f[i, j] * f[i, j]
            p_out[i, j] = mu * f[i, j] + s * cof[i, j]
    return 0.5 * mu * (norm2 - 3.0) + 0.5 * lam * ((det - gamma) ** 2 - (1.0 - gamma) ** 2)


@njit(cache=True)
def stable_neo_hookean_stress(f: np.ndarray, mu: float, lam: float, p_out: np.ndarray) -> float:
    """Energy density and first Piola-Kirchhoff stress of the stable neo-Hookean material.

    Args:
        f: ``(3, 3)`` deformation gradient.
        mu: deviatoric modulus, Pa.
        lam: hydrostatic modulus (Lame lambda + mu), Pa, finite.
        p_out: ``(3, 3)`` written with ``P = dPsi/dF``, Pa.

    Returns:
        ``Psi(F)``, J/m^3, zero at ``F = I`` (see the module docstring).
    """
    return _stress(f, mu, lam, np.empty((3, 3)), p_out)


@njit(cache=True, inline="always")
def stable_neo_hookean_tangent(f: np.ndarray, mu: float, lam: float, c_out: np.ndarray) -> None:
    """Second derivative ``c_out[i, j, k, l] = d2Psi / dF_ij dF_kl`` (3, 3, 3, 3), Pa (not projected)."""
    gamma = 1.0 + mu / lam
    cof = np.empty((3, 3))
    det = _cofactor(f, cof)
    s = lam * (det - gamma)
    for i in range(3):
        for j in range(3):
            for k in range(3):
                for m in range(3):
                    value = lam * cof[i, j] * cof[k, m]
                    if i == k and j == m:
                        value += mu
                    if i != k and j != m:
                        # eps_ikp eps_jmq F_pq: the only p, q left are the third indices.
                        p = 3 - i - k
                        q = 3 - j - m
                        sign = (1.0 if (k - i) % 3 == 1 else -1.0) * (1.0 if (m - j) % 3 == 1 else -1.0)
                        value += s * sign * f[p, q]
                    c_out[i, j, k, m] = value


@njit(cache=True, inline="always")
def tet_stiffness(x: np.ndarray, dm_inv: np.ndarray, volume: float, mu: float, lam: float, k_out: np.ndarray) -> None:
    """Element Hessian ``d2 (V0 Psi) / dx dx`` of one tet, ``k_out`` (12, 12) in N/m, row ``3 k + a`` = node
    ``k``, axis ``a``; ``x`` (4, 3) node positions, m; ``dm_inv`` (3, 3) 1/m; ``volume`` m^3; moduli Pa."""
    g = np.empty((4, 3))
    shape_gradients(dm_inv, g)
    f = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            s = 0.0
            for k in range(4):
                s += x[k, i] * g[k, j]
            f[i, j] = s
    c = np.empty((3, 3, 3, 3))
    stable_neo_hookean_tangent(f, mu, lam, c)
    for k in range(4):
        for a in range(3):
            for n in range(4):
                for b in range(3):
                    s = 0.0
                    for j in range(3):
                        for m in range(3):
                            s += g[k, j] * g[n, m] * c[a, j, b, m]
                    k_out[3 * k + a, 3 * n + b] = volume * s


@njit(cache=True)
def _stiffness_blocks(q, tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, blocks) -> None:
    """:func:`tet_stiffness` of every tet into ``blocks`` (T, 12, 12), N/m (one compiled loop: per tet from
    Python it cost 6-19 ms on the environments' 960-tet pad, paid again at every reset that draws a new modulus)."""
    x = np.empty((4, 3))
    for t in range(tet_indices.shape[0]):
        for k in range(4):
            for a in range(3):
                x[k, a] = q[tet_indices[t, k], a]
        tet_stiffness(x, tet_dm_inv[t], tet_rest_volume[t], tet_mu[t], tet_lambda[t], blocks[t])


def stiffness_matrix(tissue, q: np.ndarray | None = None) -> sp.csr_matrix:
    """Global Hessian of the elastic energy ``d2E/dx dx`` at positions ``q`` (default: the rest shape).

    Args:
        tissue: a :class:`~suture_gym.sim.model.TissueModel` (finite hydrostatic moduli).
        q: ``(N, 3)`` positions, m, or None for ``particle_rest_q``.

    Returns:
        ``(3N, 3N)`` CSR matrix in N/m, dof ``3 p + a`` = particle ``p``, axis ``a``. At the rest shape it is
        the small-strain linear-elastic stiffness with the material's ``E`` and ``nu`` (SPD up to rigid
        motions).
    """
    q = tissue.particle_rest_q if q is None else np.asarray(q, dtype=np.float64)
    t_count = tissue.tet_count
    blocks = np.empty((t_count, 12, 12))
    _stiffness_blocks(q, tissue.tet_indices, tissue.tet_dm_inv, tissue.tet_rest_volume, tissue.tet_mu,
                      tissue.tet_lambda, blocks)  # fmt: skip
    dof = (3 * tissue.tet_indices[:, :, None] + np.arange(3)[None, None, :]).reshape(t_count, 12)
    rows = np.repeat(dof, 12, axis=1).ravel()
    cols = np.tile(dof, (1, 12)).ravel()
    n = 3 * tissue.particle_count
    return sp.csr_matrix((blocks.ravel(), (rows, cols)), shape=(n, n))


@njit(cache=True)
def tet_columns(tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, tets) -> tuple:
    """The per-tet data :func:`potential_kernel` reads, one contiguous row per quantity over ``tets`` (A,):
    ``(nodes (4, A) int64, data (12, A))``, ``data`` rows 0-8 ``Dm^-1[r, c]`` at ``3 r + c``, 9 the rest volume
    (m^3), 10 ``mu`` and 11 ``lambda`` (Pa). Laid out so that the stress pass runs over consecutive tets in vector
    registers."""
    count = tets.shape[0]
    nodes = np.empty((4, count), np.int64)
    data = np.empty((12, count))
    for n in range(count):
        t = tets[n]
        for k in range(4):
            nodes[k, n] = tet_indices[t, k]
        for r in range(3):
            for c in range(3):
                data[3 * r + c, n] = tet_dm_inv[t, r, c]
        data[9, n] = tet_rest_volume[t]
        data[10, n] = tet_mu[t]
        data[11, n] = tet_lambda[t]
    return nodes, data


@njit(cache=True)
def _edges(q, nodes, x):
    """``x`` (9, A): each tet's edge vectors ``x_k - x_0`` (k = 1, 2, 3), rows ``a1 a2 a3 b1 b2 b3 c1 c2 c3`` for the
    x, y and z components (``nodes`` (4, A) of :func:`tet_columns`)."""
    for n in range(nodes.shape[1]):
        n0, n1, n2, n3 = nodes[0, n], nodes[1, n], nodes[2, n], nodes[3, n]
        for i in range(3):
            base = q[n0, i]
            x[3 * i, n] = q[n1, i] - base
            x[3 * i + 1, n] = q[n2, i] - base
            x[3 * i + 2, n] = q[n3, i] - base


# error_model="numpy" below: a float division by zero gives inf instead of raising, so the loops carry no exception
# branch and compile to vector instructions (mu / lambda is finite and non-zero).
@njit(cache=True, inline="always", error_model="numpy")
def _tet_state(x, data, n) -> tuple:
    """Tet ``n``'s ``F`` (row by row), ``cof F``, ``V0 Psi(F)`` (J) and the stress scales ``V0 mu``, ``V0 lambda
    (J - gamma)`` from its edges ``x`` (9, A) and ``data`` (12, A) of :func:`tet_columns`:
    ``(f (9-tuple), k (9-tuple), energy, vm, vs)``."""
    a1, a2, a3 = x[0, n], x[1, n], x[2, n]
    b1, b2, b3 = x[3, n], x[4, n], x[5, n]
    c1, c2, c3 = x[6, n], x[7, n], x[8, n]
    d00, d01, d02 = data[0, n], data[1, n], data[2, n]
    d10, d11, d12 = data[3, n], data[4, n], data[5, n]
    d20, d21, d22 = data[6, n], data[7, n], data[8, n]
    f00 = a1 * d00 + a2 * d10 + a3 * d20
    f01 = a1 * d01 + a2 * d11 + a3 * d21
    f02 = a1 * d02 + a2 * d12 + a3 * d22
    f10 = b1 * d00 + b2 * d10 + b3 * d20
    f11 = b1 * d01 + b2 * d11 + b3 * d21
    f12 = b1 * d02 + b2 * d12 + b3 * d22
    f20 = c1 * d00 + c2 * d10 + c3 * d20
    f21 = c1 * d01 + c2 * d11 + c3 * d21
    f22 = c1 * d02 + c2 * d12 + c3 * d22
    # cof F: its columns are the cross products of F's columns (as _cofactor)
    k00, k10, k20 = f11 * f22 - f21 * f12, f21 * f02 - f01 * f22, f01 * f12 - f11 * f02
    k01, k11, k21 = f12 * f20 - f22 * f10, f22 * f00 - f02 * f20, f02 * f10 - f12 * f00
    k02, k12, k22 = f10 * f21 - f20 * f11, f20 * f01 - f00 * f21, f00 * f11 - f10 * f01
    det = f00 * k00 + f10 * k10 + f20 * k20
    mu = data[10, n]
    lam = data[11, n]
    gamma = 1.0 + mu / lam
    norm2 = f00 * f00 + f01 * f01 + f02 * f02 + f10 * f10 + f11 * f11 + f12 * f12 + f20 * f20 + f21 * f21
    norm2 += f22 * f22
    volume = data[9, n]
    e = det - gamma
    g = 1.0 - gamma
    energy = volume * (0.5 * mu * (norm2 - 3.0) + 0.5 * lam * (e * e - g * g))
    f = (f00, f01, f02, f10, f11, f12, f20, f21, f22)
    k = (k00, k01, k02, k10, k11, k12, k20, k21, k22)
    return f, k, energy, volume * mu, volume * lam * e


@njit(cache=True, error_model="numpy")
def _tet_energies(x, data, energy):
    """``energy[n]`` (J): ``V0 Psi(F)`` of tet ``n`` from its edges ``x`` (9, A) and ``data`` of :func:`tet_columns`."""
    for n in range(x.shape[1]):
        energy[n] = _tet_state(x, data, n)[2]


@njit(cache=True, inline="always", error_model="numpy")
def _force_row(f, k, vm, vs, data, n, i, force):
    """Rows ``3 i .. 3 i + 2`` of :func:`_tet_forces`' ``force`` at tet ``n``: component ``i`` of the force on
    nodes 1..3, from :func:`_tet_state`'s ``f``, ``k``, ``vm``, ``vs``."""
    p0 = vm * f[3 * i] + vs * k[3 * i]
    p1 = vm * f[3 * i + 1] + vs * k[3 * i + 1]
    p2 = vm * f[3 * i + 2] + vs * k[3 * i + 2]
    force[3 * i, n] = p0 * data[0, n] + p1 * data[1, n] + p2 * data[2, n]
    force[3 * i + 1, n] = p0 * data[3, n] + p1 * data[4, n] + p2 * data[5, n]
    force[3 * i + 2, n] = p0 * data[6, n] + p1 * data[7, n] + p2 * data[8, n]


@njit(cache=True, error_model="numpy")
def _tet_forces(x, data, energy, force):
    """:func:`_tet_energies` and each tet's elastic force ``V0 P Dm^-T`` (N) on its nodes 1..3 into ``force`` (9, A),
    rows ``x1 x2 x3 y1 y2 y3 z1 z2 z3`` (node 0 takes minus their sum). Three passes, the energies with the x rows,
    then the y rows, then the z rows: loops storing seven or ten rows compiled to scalar code (inspected in the
    assembly; the compiler's overlap checks between so many output streams, presumably), and recomputing ``F``
    costs less than that."""
    for n in range(x.shape[1]):
        f, k, e, vm, vs = _tet_state(x, data, n)
        energy[n] = e
        _force_row(f, k, vm, vs, data, n, 0, force)
    for n in range(x.shape[1]):
        f, k, _, vm, vs = _tet_state(x, data, n)
        _force_row(f, k, vm, vs, data, n, 1, force)
    for n in range(x.shape[1]):
        f, k, _, vm, vs = _tet_state(x, data, n)
        _force_row(f, k, vm, vs, data, n, 2, force)


@njit(cache=True)
def potential_kernel(q, y, mass, free, inv_h2, columns, scratch, external, grad_out, with_gradient) -> float:
    """:func:`incremental_potential` on the tets' data in columns (:func:`tet_columns`) with caller-owned
    ``scratch = (x (9, A), energy (A,), force (9, A))``: three passes, the gather of the tets' edges, their stresses
    (consecutive tets, no indirection: the pass the compiler vectorises) and the sums (the tets' energies in order,
    their forces scattered onto the nodes), the same arithmetic in the same order as one pass tet by tet."""
    nodes, data = columns
    x, energy, force = scratch
    _edges(q, nodes, x)
    if with_gradient:
        _tet_forces(x, data, energy, force)
    else:
        _tet_energies(x, data, energy)
    total = 0.0
    for p in range(q.shape[0]):
        half_m = 0.5 * mass[p] * inv_h2
        for i in range(3):
            d = (q[p, i] - y[p, i]) * free[p, i]
            total += half_m * d * d - external[p, i] * q[p, i]
            if with_gradient:
                grad_out[p, i] = (2.0 * half_m * d - external[p, i]) * free[p, i]
    for n in range(energy.shape[0]):
        total += energy[n]
    if not with_gradient:
        return total
    for n in range(energy.shape[0]):
        n0, n1, n2, n3 = nodes[0, n], nodes[1, n], nodes[2, n], nodes[3, n]
        x1, x2, x3 = force[0, n], force[1, n], force[2, n]
        y1, y2, y3 = force[3, n], force[4, n], force[5, n]
        z1, z2, z3 = force[6, n], force[7, n], force[8, n]
        grad_out[n1, 0] += x1
        grad_out[n1, 1] += y1
        grad_out[n1, 2] += z1
        grad_out[n2, 0] += x2
        grad_out[n2, 1] += y2
        grad_out[n2, 2] += z2
        grad_out[n3, 0] += x3
        grad_out[n3, 1] += y3
        grad_out[n3, 2] += z3
        grad_out[n0, 0] -= x1 + x2 + x3
        grad_out[n0, 1] -= y1 + y2 + y3
        grad_out[n0, 2] -= z1 + z2 + z3
    for p in range(q.shape[0]):  # held dofs took forces above: masked once here
        for i in range(3):
            grad_out[p, i] *= free[p, i]
    return total


def potential_scratch(tet_count: int) -> tuple:
    """Scratch of :func:`potential_kernel` for ``tet_count`` tets."""
    return np.empty((9, tet_count)), np.empty(tet_count), np.empty((9, tet_count))


def incremental_potential(
    q: np.ndarray,
    y: np.ndarray,
    mass: np.ndarray,
    free: np.ndarray,
    inv_h2: float,
    tet_indices: np.ndarray,
    tet_dm_inv: np.ndarray,
    tet_rest_volume: np.ndarray,
    tet_mu: np.ndarray,
    tet_lambda: np.ndarray,
    tets: np.ndarray,
    external: np.ndarray,
    grad_out: np.ndarray,
    with_gradient: bool = True,
) -> float:
    """``Phi(x) - f_ext . x`` of the implicit-Euler substep and its gradient.

    :class:`~suture_gym.sim.tissue_implicit.ImplicitTissue` keeps the tets' columns and the scratch and calls
    :func:`potential_kernel` itself; this builds them for one call.

    Args:
        q: ``(N, 3)`` positions ``x``, m.
        y: ``(N, 3)`` inertial target ``x_prev + h v + h^2 g``, m.
        mass: ``(N,)`` lumped masses, kg.
        free: ``(N, 3) float64`` 1.0 on free degrees of freedom, 0.0 on held ones (the inertia term and the
            gradient count only free ones).
        inv_h2: ``1 / h^2``, 1/s^2.
        tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda: the
            :class:`~suture_gym.sim.model.TissueModel` arrays.
        tets: ``(A,) int32`` tets to include (those with a free node; ascending order reads memory in order).
        external: ``(N, 3)`` external forces ``f_ext`` on the particles, N (the coupling rows'; zeros for none).
        grad_out: ``(N, 3)`` written with the gradient, N (zero on held degrees of freedom).
        with_gradient: False: only ``Phi`` (``grad_out`` is left untouched), cheaper.

    Returns:
        ``Phi - f_ext . x`` in J (elastic energy shifted to zero at rest, the inertia term, the external work).
    """
    columns = tet_columns(tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, tets)
    return potential_kernel(q, y, mass, free, inv_h2, columns, potential_scratch(tets.shape[0]), external, grad_out,
                            with_gradient)  # fmt: skip


@njit(cache=True)
def vbd_sweep(
    q: np.ndarray,
    y: np.ndarray,
    mass: np.ndarray,
    free: np.ndarray,
    inv_h2: float,
    tet_indices: np.ndarray,
    tet_dm_inv: np.ndarray,
    tet_rest_volume: np.ndarray,
    tet_mu: np.ndarray,
    tet_lambda: np.ndarray,
    vertex_order: np.ndarray,
    adjacency_offsets: np.ndarray,
    adjacency_tet: np.ndarray,
    adjacency_corner: np.ndarray,
) -> None:
    """One Gauss-Seidel sweep of Vertex Block Descent (Chen et al. 2024) over ``vertex_order``, in place.

    Per vertex ``i``: ``f = -m/h^2 (x_i - y_i) - sum_t V0 P_t g_k``, ``H = m/h^2 I + sum_t V0 (mu |g_k|^2 I +
    lambda c c^T)`` with ``c = cof(F_t) g_k`` (SPD), then ``x_i += H^-1 f`` on its free axes.

    Args:
        q: ``(N, 3)`` positions, m; updated in place.
        y, mass, free, inv_h2, tet_*: as in :func:`incremental_potential`.
        vertex_order: ``(V,) int32`` vertices with a free axis.
        adjacency_offsets: ``(N + 1,) int32`` CSR offsets of each vertex's tets.
        adjacency_tet: ``(4 T,) int32`` tet of each incidence; ``adjacency_corner``: its local node 0..3.
    """
    g = np.empty((4, 3))
    f = np.empty((3, 3))
    cof = np.empty((3, 3))
    hess = np.empty((3, 3))
    force = np.empty(3)
    for n in range(vertex_order.shape[0]):
        v = vertex_order[n]
        m_h2 = mass[v] * inv_h2
        for i in range(3):
            force[i] = -m_h2 * (q[v, i] - y[v, i])
            for j in range(3):
                hess[i, j] = m_h2 if i == j else 0.0
        for e in range(adjacency_offsets[v], adjacency_offsets[v + 1]):
            t = adjacency_tet[e]
            k = adjacency_corner[e]
            shape_gradients(tet_dm_inv[t], g)
            _tet_f(q, tet_indices[t], g, f)
            mu = tet_mu[t]
            lam = tet_lambda[t]
            det = _cofactor(f, cof)
            s = lam * (det - (1.0 + mu / lam))
            volume = tet_rest_volume[t]
            gk0, gk1, gk2 = g[k, 0], g[k, 1], g[k, 2]
            gg = gk0 * gk0 + gk1 * gk1 + gk2 * gk2
            c0 = cof[0, 0] * gk0 + cof[0, 1] * gk1 + cof[0, 2] * gk2
            c1 = cof[1, 0] * gk0 + cof[1, 1] * gk1 + cof[1, 2] * gk2
            c2 = cof[2, 0] * gk0 + cof[2, 1] * gk1 + cof[2, 2] * gk2
            c = (c0, c1, c2)
            for i in range(3):
                fg = f[i, 0] * gk0 + f[i, 1] * gk1 + f[i, 2] * gk2
                force[i] -= volume * (mu * fg + s * c[i])
                for j in range(3):
                    hess[i, j] += volume * lam * c[i] * c[j]
                hess[i, i] += volume * mu * gg
        for i in range(3):
            if not free[v, i]:
                force[i] = 0.0
                for j in range(3):
                    hess[i, j] = 0.0
                    hess[j, i] = 0.0
                hess[i, i] = 1.0
        # 3x3 SPD solve by the adjugate.
        a00, a01, a02 = hess[0, 0], hess[0, 1], hess[0, 2]
        a11, a12, a22 = hess[1, 1], hess[1, 2], hess[2, 2]
        i00 = a11 * a22 - a12 * a12
        i01 = a02 * a12 - a01 * a22
        i02 = a01 * a12 - a02 * a11
        det3 = a00 * i00 + a01 * i01 + a02 * i02
        if not det3 > 0.0:
            continue
        i11 = a00 * a22 - a02 * a02
        i12 = a01 * a02 - a00 * a12
        i22 = a00 * a11 - a01 * a01
        q[v, 0] += (i00 * force[0] + i01 * force[1] + i02 * force[2]) / det3
        q[v, 1] += (i01 * force[0] + i11 * force[1] + i12 * force[2]) / det3
        q[v, 2] += (i02 * force[0] + i12 * force[1] + i22 * force[2]) / det3
