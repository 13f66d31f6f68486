"""Quaternion helpers: algebra against rotation matrices and closed forms, normalisation kept."""

import numpy as np
import pytest

from suture_gym.sim.quat import (
    cross3,
    quat_conj,
    quat_from_axis_angle,
    quat_from_rotation_vector,
    quat_from_two_vectors,
    quat_integrate,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_rotate_inv,
    quat_rotation_vector,
    quat_to_matrix,
    quat_to_matrix_into,
    quat_turn_into,
)

RNG = np.random.default_rng(7)


def random_unit(n=20):
    q = RNG.normal(size=(n, 4))
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def test_matrix_is_a_rotation_and_composes_like_the_product():
    for a, b in zip(random_unit(), random_unit(), strict=True):
        ra = quat_to_matrix(a)
        np.testing.assert_allclose(ra @ ra.T, np.eye(3), atol=1e-14)
        assert np.linalg.det(ra) == pytest.approx(1.0, abs=1e-14)
        np.testing.assert_allclose(quat_to_matrix(quat_mul(a, b)), ra @ quat_to_matrix(b), atol=1e-14)
        out = np.empty((3, 3))
        quat_to_matrix_into(a, out)
        np.testing.assert_array_equal(out, ra)


def test_rotate_matches_matrix_and_inverse_undoes_it():
    for q in random_unit():
        v = RNG.normal(size=3)
        np.testing.assert_allclose(quat_rotate(q, v), quat_to_matrix(q) @ v, atol=1e-14)
        np.testing.assert_allclose(quat_rotate_inv(q, quat_rotate(q, v)), v, atol=1e-14)
        np.testing.assert_allclose(quat_mul(q, quat_conj(q)), [1.0, 0.0, 0.0, 0.0], atol=1e-15)


def test_axis_angle_closed_form():
    q = quat_from_axis_angle(np.array([0.0, 0.0, 2.0]), np.pi / 2)  # axis need not be unit
    np.testing.assert_allclose(quat_rotate(q, np.array([1.0, 0.0, 0.0])), [0.0, 1.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(q, [np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)], atol=1e-15)
    np.testing.assert_array_equal(quat_from_axis_angle(np.zeros(3), 1.0), [1.0, 0.0, 0.0, 0.0])


def test_rotation_vector_round_trip_and_short_way():
    for _ in range(20):
        theta = RNG.normal(size=3)
        theta *= RNG.uniform(0.0, 3.0) / np.linalg.norm(theta)
        q = quat_from_rotation_vector(theta)
        np.testing.assert_allclose(quat_rotation_vector(q), theta, atol=1e-12)
        np.testing.assert_allclose(quat_rotation_vector(-q), theta, atol=1e-12)  # same rotation, w < 0


def test_normalize_and_degenerate_zero():
    q = np.array([2.0, 0.0, -2.0, 1.0])
    np.testing.assert_allclose(quat_normalize(q), q / 3.0, atol=1e-16)
    np.testing.assert_array_equal(quat_normalize(np.zeros(4)), [1.0, 0.0, 0.0, 0.0])


def test_integrate_is_the_exact_exponential_and_keeps_unit_norm():
    omega = np.array([0.3, -1.2, 2.0])
    dt, steps = 1e-3, 5000
    q = quat_from_axis_angle(np.array([1.0, 1.0, 0.0]), 0.4)
    q0 = q.copy()
    for _ in range(steps):
        q = quat_integrate(q, omega, dt)
    expected = quat_mul(quat_from_rotation_vector(omega * dt * steps), q0)
    assert min(np.abs(q - expected).max(), np.abs(q + expected).max()) < 1e-11
    assert np.linalg.norm(q) == pytest.approx(1.0, abs=1e-14)


def test_from_two_vectors_minimal_rotation():
    for _ in range(20):
        a, b = RNG.normal(size=3), RNG.normal(size=3)
        q = quat_from_two_vectors(a, b)
        np.testing.assert_allclose(quat_rotate(q, a / np.linalg.norm(a)), b / np.linalg.norm(b), atol=1e-13)
        # minimal: the rotation axis is perpendicular to both
        axis = quat_rotation_vector(q)
        assert abs(axis @ a) < 1e-10 * np.linalg.norm(a) and abs(axis @ b) < 1e-10 * np.linalg.norm(b)
    a = np.array([0.0, 0.0, 1.0])
    q = quat_from_two_vectors(a, -a)
    np.testing.assert_allclose(quat_rotate(q, a), -a, atol=1e-15)
    np.testing.assert_array_equal(quat_from_two_vectors(np.zeros(3), a), [1.0, 0.0, 0.0, 0.0])


def test_turn_into_matches_product_and_may_alias():
    for q in random_unit():
        theta = RNG.normal(size=3)
        expected = quat_normalize(quat_mul(quat_from_rotation_vector(theta), q))
        out = np.empty(4)
        quat_turn_into(q, theta, out)
        np.testing.assert_allclose(out, expected, atol=1e-15)
        q_alias = q.copy()
        quat_turn_into(q_alias, theta, q_alias)
        np.testing.assert_array_equal(q_alias, out)


def test_cross3_matches_numpy_bit_for_bit():
    rng = np.random.default_rng(7)
    for a, b in rng.standard_normal((50, 2, 3)):
        assert np.array_equal(cross3(a, b), np.cross(a, b))
