"""The tissue side of the coupling rows (sim/coupling/compliance.py): diagonal and dense-block compliances."""

import numpy as np

from suture_gym.sim.coupling.compliance import (
    apply_impulse,
    diagonal,
    point_compliance,
    point_inv_mass,
    row_vertices,
)
from suture_gym.sim.coupling.params import ROW_PATH, ROW_TRIANGLE


def _dense(n_particles: int, vertices: np.ndarray, seed: int = 1) -> tuple:
    """A compliance tuple with a random SPD block among ``vertices``."""
    rng = np.random.default_rng(seed)
    a = rng.standard_normal((3 * vertices.size, 3 * vertices.size))
    matrix = a @ a.T + 3 * vertices.size * np.eye(3 * vertices.size)
    slot = np.full(n_particles, -1, np.int32)
    slot[vertices] = np.arange(vertices.size, dtype=np.int32)
    return (np.ones(n_particles), slot, vertices.astype(np.int32), matrix, np.zeros((n_particles, 3)))


def test_diagonal_compliance_is_the_weighted_inverse_masses():
    w = np.array([2.0, 3.0, 5.0, 7.0])
    tissue = diagonal(w)
    idx, b = np.array([0, 2, 3], np.int32), np.array([0.2, 0.3, 0.5])
    k = np.empty((3, 3))
    point_compliance(tissue, idx, b, 3, k)
    np.testing.assert_allclose(k, np.eye(3) * (0.04 * 2 + 0.09 * 5 + 0.25 * 7))
    q = np.zeros((4, 3))
    apply_impulse(tissue, idx, b, 3, np.array([0.0, 0.0, 1.0]), q)
    np.testing.assert_allclose(q[:, 2], [-0.4, 0.0, -1.5, -3.5])
    np.testing.assert_allclose(tissue[4][:, 2], [-0.2, 0.0, -0.3, -0.5])


def test_dense_compliance_couples_the_vertices_and_moves_every_touched_one():
    vertices = np.array([1, 3, 4])
    tissue = _dense(6, vertices)
    c = tissue[3]
    idx, b = np.array([3, 4, 5], np.int32), np.array([0.6, 0.4, 0.0])  # vertex 5 untouched: no response
    n = np.array([0.0, 0.6, 0.8])
    block = lambda i, j: c[3 * i : 3 * i + 3, 3 * j : 3 * j + 3]  # noqa: E731
    k_ref = 0.36 * block(1, 1) + 0.24 * (block(1, 2) + block(2, 1)) + 0.16 * block(2, 2)
    assert np.isclose(point_inv_mass(tissue, idx, b, 3, n), n @ k_ref @ n, rtol=1e-13, atol=0.0)
    q = np.zeros((6, 3))
    impulse = np.array([1e-3, -2e-3, 5e-4])
    apply_impulse(tissue, idx, b, 3, impulse, q)
    expected = np.zeros((6, 3))
    for s, v in enumerate(vertices):
        expected[v] = -(block(s, 1) @ (0.6 * impulse) + block(s, 2) @ (0.4 * impulse))
    np.testing.assert_allclose(q, expected, rtol=1e-12, atol=1e-18)
    np.testing.assert_allclose(tissue[4][3], -0.6 * impulse)
    np.testing.assert_allclose(tissue[4][5], 0.0)
    # the point's own move is its compliance times the impulse
    moved = 0.6 * q[3] + 0.4 * q[4]
    np.testing.assert_allclose(moved, -k_ref @ impulse, rtol=1e-12)


def test_row_vertices_marks_every_vertex_a_row_touches():
    kind = np.array([ROW_TRIANGLE, ROW_PATH, 0], np.int8)
    tri = np.array([1, -1, -1], np.int32)
    tissue_idx = np.zeros((3, 8), np.int32)
    tissue_idx[1] = [7, 8, 9, 10, 11, 12, 13, 14]
    weight = np.zeros((3, 8))
    weight[1, :4] = 0.25  # only the first tet of the path row carries weight
    tri_vertices = np.array([[0, 1, 2], [3, 4, 5], [15, 16, 17]], np.int32)
    access_tri = np.array([2, 0], np.int32)
    patch = (np.array([20, 21], np.int32), np.array([0.5, 0.5]), np.array([1]), np.zeros(3), np.zeros(1))
    cut = (np.array([22, 23, 24, 25], np.int32), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros(3), np.array([0.2]),
           np.zeros(1))  # fmt: skip
    mark = np.zeros(30, bool)
    row_vertices(kind, tri, tissue_idx, weight, tri_vertices, access_tri, 1, patch, cut, mark)
    assert set(np.flatnonzero(mark)) == {3, 4, 5, 7, 8, 9, 10, 15, 16, 17, 20, 22}
