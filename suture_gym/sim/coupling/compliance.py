"""How the tissue answers a coupling row's impulse: the tissue side of every two-way row.

A row acts on a tissue point ``p = sum_a b_a x_a`` (a surface point of a triangle, a path point of two tets, a
contact patch). Given an impulse ``P`` (kg m, 3-vector) on the strand, the tissue takes ``-P`` at ``p``, i.e.
``-b_a P`` at vertex ``a``, and moves by ``Delta x = -C J^T P`` with ``C`` its compliance (inverse mass, 1/kg).
The row needs the point's generalised inverse mass along its direction ``n``: ``n^T (sum_ab b_a b_b C_ab) n``.

Two compliances, one interface (the tuple ``tissue`` every projection kernel takes; :func:`diagonal` builds the
first kind, :meth:`~suture_gym.sim.tissue_implicit.ImplicitTissue.begin_rows` the second):

* diagonal (the XPBD tissue): ``C_ab = delta_ab w_a I``, each vertex moves by its own inverse mass (the
  tet constraints then spread the move). The kernels keep their original arithmetic for it, bit for bit.
* the implicit integrator's substep compliance ``C = A0^-1 / h^2`` among the set ``S`` of tissue vertices any
  row touches this substep (a dense ``(3|S|, 3|S|)`` block, gathered from cached columns of ``A0^-1``): a
  row's generalised inverse mass uses the off-diagonal blocks between its vertices (a point inside a triangle
  moves with all three, so the diagonal alone under-estimates its compliance by up to 3x), and its impulse
  moves every vertex of ``S`` by ``-C_{S,a} b_a P``: Gauss-Seidel over the rows on their exact linearised
  coupling (the Schur complement of the implicit step). The impulses are summed in the tuple's ``impulse``
  array, from which :meth:`~suture_gym.sim.tissue_implicit.ImplicitTissue.propagate_rows` spreads the response
  to the whole tissue; at ``S`` that response is exactly the moves made here.

``tissue = (inv_mass (N,) 1/kg, slot (N,) int32, vertices (m,) int32, matrix (3m, 3m) 1/kg, impulse (N, 3) kg m)``:
``slot[v]`` is vertex ``v``'s index in ``vertices`` (``-1``: not in ``S``, no response: pinned or untouched);
``slot`` empty means diagonal. ``impulse`` gains ``-b_a P`` at each vertex (the tissue's impulses).
"""

from __future__ import annotations

import numpy as np
from numba import njit

from suture_gym.sim.coupling.params import ROW_NONE, ROW_PATH


def diagonal(inv_mass: np.ndarray) -> tuple:
    """The diagonal compliance tuple of per-vertex inverse masses ``inv_mass`` (N,) 1/kg (the XPBD tissue)."""
    return (
        inv_mass, np.zeros(0, np.int32), np.zeros(0, np.int32), np.zeros((0, 0)), np.zeros((inv_mass.shape[0], 3)),
    )  # fmt: skip


@njit(cache=True)
def is_diagonal(tissue) -> bool:
    """Whether ``tissue`` is the diagonal (XPBD) compliance."""
    return tissue[1].shape[0] == 0


@njit(cache=True)
def answers_for(tissue, idx, count) -> bool:
    """Whether ``tissue`` answers for every free vertex of ``idx[:count]``: always with the diagonal compliance;
    with a block, whether each of them (inverse mass above 0) is in ``S``. A point with a free vertex outside
    ``S`` has no true generalised inverse mass here: summed over the vertices of ``S`` alone it can be the
    compliance of one vertex times a weight of 1e-3 squared, and the impulse that closes a gap with it throws
    that vertex by the gap over the weight."""
    if is_diagonal(tissue):
        return True
    w, slot = tissue[0], tissue[1]
    for a in range(count):
        if w[idx[a]] > 0.0 and slot[idx[a]] < 0:
            return False
    return True


@njit(cache=True)
def point_compliance(tissue, idx, weight, count, out):
    """``out`` (3, 3) = ``sum_ab b_a b_b C_ab`` (1/kg) of the point of vertices ``idx[:count]`` and weights
    ``weight[:count]`` (diagonal: ``sum_a b_a^2 w_a I``)."""
    w, slot, _, c, _ = tissue
    out[:, :] = 0.0
    if slot.shape[0] == 0:
        s = 0.0
        for a in range(count):
            s += weight[a] * weight[a] * w[idx[a]]
        for i in range(3):
            out[i, i] = s
        return
    for a in range(count):
        sa = slot[idx[a]]
        if sa < 0 or weight[a] == 0.0:
            continue
        for b in range(count):
            sb = slot[idx[b]]
            if sb < 0 or weight[b] == 0.0:
                continue
            f = weight[a] * weight[b]
            for i in range(3):
                for j in range(3):
                    out[i, j] += f * c[3 * sa + i, 3 * sb + j]


@njit(cache=True)
def point_inv_mass(tissue, idx, weight, count, n) -> float:
    """``n^T (sum_ab b_a b_b C_ab) n`` (1/kg times ``|n|^2``): the point's generalised inverse mass along ``n``
    (3,)."""
    k = np.empty((3, 3))
    point_compliance(tissue, idx, weight, count, k)
    total = 0.0
    for i in range(3):
        for j in range(3):
            total += n[i] * k[i, j] * n[j]
    return total


@njit(cache=True)
def apply_impulse(tissue, idx, weight, count, impulse, tissue_q) -> None:
    """The tissue takes ``-b_a impulse`` (kg m, (3,)) at vertex ``idx[a]``: every vertex ``v`` of ``S`` moves by
    ``-sum_a C_{v,a} b_a impulse`` (diagonal: vertex ``a`` by ``-w_a b_a impulse``), and the tuple's impulse
    sum gains ``-b_a impulse`` at each. Updates ``tissue_q`` (N, 3) m."""
    w, slot, vertices, c, total = tissue
    if slot.shape[0] == 0:
        for a in range(count):  # in scalars: no row views or temporaries (reference counting) per vertex
            v = idx[a]
            f = w[v] * weight[a]
            for i in range(3):
                tissue_q[v, i] -= f * impulse[i]
                total[v, i] -= weight[a] * impulse[i]
        return
    for a in range(count):
        sa = slot[idx[a]]
        if sa < 0 or weight[a] == 0.0:
            continue
        f0, f1, f2 = weight[a] * impulse[0], weight[a] * impulse[1], weight[a] * impulse[2]
        total[idx[a], 0] -= f0
        total[idx[a], 1] -= f1
        total[idx[a], 2] -= f2
        col = 3 * sa
        for s in range(vertices.shape[0]):
            v = vertices[s]
            row = 3 * s
            for i in range(3):
                tissue_q[v, i] -= c[row + i, col] * f0 + c[row + i, col + 1] * f1 + c[row + i, col + 2] * f2


@njit(cache=True)
def weighted_inv_mass(tissue, idx, weight, n) -> float:
    """The generalised inverse mass (1/kg) along unit ``n`` (3,) of the point of all of ``idx`` (k,) with
    ``weight`` (k,): ``sum_a b_a^2 w_a`` with the diagonal compliance (its original arithmetic),
    :func:`point_inv_mass` otherwise."""
    if is_diagonal(tissue):
        w = tissue[0]
        total = 0.0
        for a in range(idx.shape[0]):
            total += weight[a] * weight[a] * w[idx[a]]
        return total
    return point_inv_mass(tissue, idx, weight, idx.shape[0], n)


@njit(cache=True)
def move_point(tissue, idx, weight, dlam, n, tissue_q) -> None:
    """The tissue takes ``-dlam n`` (kg m) at the point of all of ``idx`` with ``weight``: vertex ``a`` moves by
    ``-w_a b_a dlam n`` with the diagonal compliance (its original arithmetic), :func:`apply_impulse`
    otherwise. Updates ``tissue_q``."""
    if is_diagonal(tissue):
        w = tissue[0]
        for a in range(idx.shape[0]):  # in scalars, as apply_impulse
            v = idx[a]
            f = w[v] * weight[a] * dlam
            for i in range(3):
                tissue_q[v, i] -= f * n[i]
        return
    apply_impulse(tissue, idx, weight, idx.shape[0], dlam * n, tissue_q)


@njit(cache=True)
def _mark(mark, v):
    mark[v] = True


@njit(cache=True)
def row_vertices(row_kind, row_tri, row_tissue, row_weight, tri_vertices, access_tri, access_count, patch, cut,
                 mark) -> None:  # fmt: skip
    """Mark (``mark`` (N,) bool, in place) every tissue vertex a coupling row of this substep touches: the
    triangles of contact, wall, anchor and exit rows, the weighted vertices of path rows, the access points'
    triangles, the tip's contact patch and the cutting row's point."""
    for i in range(row_kind.shape[0]):
        kind = row_kind[i]
        if kind == ROW_NONE:
            continue
        if kind == ROW_PATH:
            for a in range(row_tissue.shape[1]):
                if row_weight[i, a] != 0.0:
                    _mark(mark, row_tissue[i, a])
        elif row_tri[i] >= 0:
            for k in range(3):
                _mark(mark, tri_vertices[row_tri[i], k])
    for a in range(access_count):
        for k in range(3):
            _mark(mark, tri_vertices[access_tri[a], k])
    vertex, _, count = patch[0], patch[1], patch[2][0]
    for a in range(count):
        _mark(mark, vertex[a])
    if cut[3][0] > 0.0:
        for a in range(cut[0].shape[0]):
            if cut[1][a] != 0.0:
                _mark(mark, cut[0][a])
