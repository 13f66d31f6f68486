"""The constant rest-shape system ``A0 = M / h^2 + K0`` of an implicit tissue over its free degrees of freedom:
its sparsity pattern (kept per mesh and set of free dofs), its assembly and its sparse Cholesky factor.

``K0`` (N/m) is the stiffness of the stable neo-Hookean energy at the rest shape (:mod:`~suture_gym.sim.tissue_energy`),
``M / h^2`` (N/m) the lumped masses over the substep squared on the diagonal; the matrix is ``(n, n)`` over the ``n``
free dofs (dof ``3 p + a`` = particle ``p``, axis ``a``, in ascending order), CSC with both triangles stored.
:class:`~suture_gym.sim.tissue_implicit.ImplicitTissue` builds and factorises it once per model and substep.
"""

from __future__ import annotations

import cholespy
import numpy as np
import scipy.sparse as sp
from numba import njit

from suture_gym.sim.tissue_energy import shape_gradients


@njit(cache=True)
def assemble_rest_system(tet_indices, tet_dm_inv, tet_rest_volume, tet_mu, tet_lambda, entry, diagonal,
                          diagonal_values, data) -> None:  # fmt: skip
    """``A0 = K0 + diag`` into ``data`` (the CSC values of :class:`RestPattern`, N/m): each tet's rest stiffness
    summed into its entries (``entry`` (T, 144), -1 for a held dof), in tet order, then ``diagonal_values`` (n,)
    N/m at the diagonal (``diagonal`` (n,)).

    At the rest shape (``F = I``) the tangent of :func:`~suture_gym.sim.tissue_energy.tet_stiffness` is linear
    elasticity's, ``C_ajbm = mu d_ab d_jm + (lambda - mu) d_aj d_bm + mu d_am d_jb`` (``lambda`` the hydrostatic
    modulus), so node ``k``'s block with node ``n`` is ``V0 (mu (g_k . g_n) I + (lambda - mu) g_k g_n^T + mu g_n
    g_k^T)``: the same matrix up to round-off, without the general tangent's 12 x 12 x 9 sums (4 ms of a rebuild on
    WoundClosure's 3,600 tets)."""
    g = np.empty((4, 3))
    for t in range(tet_indices.shape[0]):
        shape_gradients(tet_dm_inv[t], g)
        volume = tet_rest_volume[t]
        vm = volume * tet_mu[t]
        vl = volume * (tet_lambda[t] - tet_mu[t])
        for k in range(4):
            for n in range(4):
                dot = vm * (g[k, 0] * g[n, 0] + g[k, 1] * g[n, 1] + g[k, 2] * g[n, 2])
                for a in range(3):
                    for b in range(3):
                        e = entry[t, 12 * (3 * k + a) + 3 * n + b]
                        if e >= 0:
                            value = vl * g[k, a] * g[n, b] + vm * g[k, b] * g[n, a]
                            data[e] += value + dot if a == b else value
    for i in range(diagonal.shape[0]):
        data[diagonal[i]] += diagonal_values[i]


class RestPattern:
    """The sparsity pattern of ``A0`` over the free dofs (CSC, both triangles) of one mesh and set of free dofs,
    and where each tet's stiffness entries and each diagonal entry go in its values: what a rebuild for a new
    modulus reuses (:func:`rest_pattern`).

    Attributes:
        indptr, indices: ``(n + 1,)``, ``(nnz,) int32`` CSC structure, rows sorted within each column.
        entry: ``(T, 144) int32`` value index of tet ``t``'s stiffness entry ``(r, c)`` at ``12 r + c`` (the
            layout of :func:`~suture_gym.sim.tissue_energy.tet_stiffness`), -1 where either dof is held.
        diagonal: ``(n,) int32`` value index of each diagonal entry.
    """

    def __init__(self, tet_indices: np.ndarray, particle_count: int, free_index: np.ndarray):
        n = free_index.size
        position = np.full(3 * particle_count, -1, np.int64)
        position[free_index] = np.arange(n)
        free_dof = position[(3 * tet_indices[:, :, None] + np.arange(3)).reshape(-1, 12)]
        rows = np.repeat(free_dof, 12, axis=1)
        cols = np.tile(free_dof, (1, 12))
        valid = (rows >= 0) & (cols >= 0)
        keys = cols * n + rows  # column-major: sorted keys are the CSC order
        diagonal_keys = np.arange(n) * (n + 1)
        structure = np.unique(np.concatenate([keys[valid], diagonal_keys]))
        self.indptr = np.searchsorted(structure, np.arange(n + 1) * n).astype(np.int32)
        self.indices = (structure % n).astype(np.int32)
        self.entry = np.where(valid, np.searchsorted(structure, keys), -1).astype(np.int32)
        self.diagonal = np.searchsorted(structure, diagonal_keys).astype(np.int32)


#: :class:`RestPattern` by mesh and free dofs, the most recent :data:`_PATTERN_CACHE_SIZE`: the environments build
#: a new integrator for the same mesh at every reset that draws a new modulus (on WoundClosure's pad the assembly
#: through scipy's COO-to-CSR conversion was 9 ms of a 28 ms rebuild; through the pattern it is under 1 ms and the
#: rebuild 13 ms, mostly CHOLMOD's analysis and factorisation).
_PATTERNS: dict = {}
_PATTERN_CACHE_SIZE = 8


def rest_pattern(tissue, free_index: np.ndarray) -> RestPattern:
    """The cached :class:`RestPattern` of ``tissue``'s mesh with free dofs ``free_index``, made on first use."""
    key = (tissue.particle_count, tissue.tet_indices.tobytes(), free_index.tobytes())
    pattern = _PATTERNS.pop(key, None)
    if pattern is None:
        pattern = RestPattern(tissue.tet_indices, tissue.particle_count, free_index)
        if len(_PATTERNS) >= _PATTERN_CACHE_SIZE:
            del _PATTERNS[next(iter(_PATTERNS))]
    _PATTERNS[key] = pattern
    return pattern


class SparseCholesky:
    """``A = L L^T`` of a sparse SPD matrix, factorised once (CHOLMOD through ``cholespy``, its own fill-reducing
    ordering); solves with one or several right-hand sides. Measured against scipy's SuperLU on the same
    matrices (symmetric mode, MMD ordering): 1.8x faster solves on the paper's cube (4,536 dofs), 1.4x on the
    environments' pad (780 dofs) (docs/tissue_integrator.md).

    Args:
        matrix: ``(n, n)`` sparse SPD matrix (both triangles stored).
    """

    def __init__(self, matrix: sp.spmatrix):
        csc = sp.csc_matrix(matrix, dtype=np.float64)
        csc.sum_duplicates()
        csc.sort_indices()
        self.size = csc.shape[0]
        self._solver = cholespy.CholeskySolverD(
            self.size, csc.indptr.astype(np.int32), csc.indices.astype(np.int32), csc.data, cholespy.MatrixType.CSC
        )
        self._solved = False

    def solve(self, rhs: np.ndarray) -> np.ndarray:
        """``A^-1 rhs`` for ``rhs`` of shape ``(n,)`` or ``(n, k)`` with ``k >= 1``; a new array of the same shape."""
        rhs = np.ascontiguousarray(rhs, dtype=np.float64)
        if rhs.ndim == 2 and rhs.shape[1] == 0:
            raise ValueError(f"rhs must have at least one column, got shape {rhs.shape}")
        out = np.empty_like(rhs)
        self._solver.solve(rhs, out)
        self._solved = True
        return out

    def release_buffer(self) -> None:
        """Free the right-hand-side buffer cholespy keeps from the last solve (its destructor does not: 8 n k bytes
        lost per factorisation otherwise). A solve with no column swaps it for an empty one; before any solve there
        is none (and cholespy's zero-column solve would crash), so nothing is done."""
        if self._solved:
            empty = np.empty((self.size, 0))
            self._solver.solve(empty, empty.copy())
            self._solved = False
