"""Tet constraint maths: gradients vs finite differences, the coupled solve, rest state, degenerate tets."""

import math

import numpy as np
import pytest

from suture_gym.sim.mesh import box_tet_grid, rest_shape, signed_volumes
from suture_gym.sim.model import TissueMaterial, TissueModel
from suture_gym.sim.tissue import (
    TET_BLOCK,
    coupled_multiplier_update,
    deformation_gradient,
    neo_hookean_constraints,
    node_gradients,
    project_rollers,
    project_supports,
    project_tets,
    tet_blocks,
    tet_elastic_energy,
    tet_residual,
)

REST = np.array([[0.0, 0.0, 0.0], [0.011, 0.001, -0.002], [0.002, 0.009, 0.001], [-0.001, 0.002, 0.010]])


def _dm_inv(rest=REST):
    dm_inv, _ = rest_shape(rest, np.array([[0, 1, 2, 3]]))
    return dm_inv[0]


def _constraints(x, dm_inv, gamma):
    f = np.empty((3, 3))
    dcdf = np.empty((2, 3, 3))
    deformation_gradient(x, dm_inv, f)
    c = neo_hookean_constraints(f, gamma, dcdf)
    grad = np.empty((2, 4, 3))
    node_gradients(dcdf, dm_inv, grad)
    return np.array(c), grad, f, dcdf


def _deformed(kind):
    rng = np.random.default_rng(7)
    if kind == "mild":
        a = np.eye(3) + 0.2 * rng.standard_normal((3, 3))
    elif kind == "large":
        a = np.diag([1.8, 0.5, 1.2]) + 0.4 * rng.standard_normal((3, 3))
    else:  # inverted: reflect through a plane
        a = np.diag([1.0, 1.0, -0.7]) + 0.1 * rng.standard_normal((3, 3))
    x = REST @ a.T + rng.standard_normal(3) * 0.01
    return x


@pytest.mark.parametrize("kind", ["mild", "large", "inverted"])
def test_node_gradients_match_central_differences(kind):
    x = _deformed(kind)
    dm_inv = _dm_inv()
    gamma = 1.0 + 0.3 / 16.0
    _, grad, _, _ = _constraints(x, dm_inv, gamma)
    if kind == "inverted":
        assert signed_volumes(x, np.array([[0, 1, 2, 3]]))[0] < 0
    step = 1e-7
    numeric = np.zeros((2, 4, 3))
    for k in range(4):
        for i in range(3):
            xp, xm = x.copy(), x.copy()
            xp[k, i] += step
            xm[k, i] -= step
            numeric[:, k, i] = (_constraints(xp, dm_inv, gamma)[0] - _constraints(xm, dm_inv, gamma)[0]) / (2 * step)
    scale = np.abs(grad).max()
    assert np.allclose(grad, numeric, rtol=1e-6, atol=1e-7 * scale)
    assert np.allclose(grad.sum(axis=1), 0.0, atol=1e-12 * scale)  # translation invariance


def test_deformation_gradient_of_affine_map_and_cofactor():
    a = np.array([[1.2, 0.1, -0.3], [0.05, 0.9, 0.2], [0.0, -0.1, 1.1]])
    x = REST @ a.T + np.array([0.3, -0.2, 0.1])
    c, _, f, dcdf = _constraints(x, _dm_inv(), 1.0)
    assert np.allclose(f, a, atol=1e-13)
    assert np.allclose(dcdf[1], np.linalg.det(a) * np.linalg.inv(a).T, atol=1e-13)
    assert c[0] == pytest.approx(np.linalg.norm(a))
    assert c[1] == pytest.approx(np.linalg.det(a) - 1.0)


@pytest.mark.parametrize("nu", [0.0, 0.3, 0.49, 0.5])
def test_small_strain_moduli_reproduce_youngs_modulus_and_poisson_ratio(nu):
    """The stress mu F + lambda (J - gamma) cof F of a uniaxial small strain is E eps along the axis and zero
    across it: the constraint moduli (mu, lambda = Lame lambda + mu) linearise to the requested E and nu."""
    material = TissueMaterial(youngs_modulus=2.0e3, poisson_ratio=nu)
    mu, lam = material.lame_mu, material.hydrostatic_modulus
    eps = 1e-6
    f = np.diag([1.0 + eps, 1.0 - nu * eps, 1.0 - nu * eps])
    dcdf = np.empty((2, 3, 3))
    c_dev, c_hyd = neo_hookean_constraints(f, 1.0 + mu / lam, dcdf)
    if math.isinf(lam):  # incompressible: the pressure is whatever keeps J = 1; lateral stress zero defines it
        pressure = -mu * dcdf[0, 1, 1] * c_dev / dcdf[1, 1, 1]
        stress = mu * c_dev * dcdf[0] + pressure * dcdf[1]
    else:
        stress = mu * c_dev * dcdf[0] + lam * c_hyd * dcdf[1]
    assert stress[0, 0] == pytest.approx(material.youngs_modulus * eps, rel=1e-4)
    assert abs(stress[1, 1]) < 1e-4 * material.youngs_modulus * eps
    assert abs(stress[2, 2]) < 1e-4 * material.youngs_modulus * eps


def test_energy_gradient_matches_constraint_forces():
    """The XPBD elastic force sum_i grad C_i C_i / alpha_i is minus the gradient of the stored energy."""
    mesh_tets = np.array([[0, 1, 2, 3]], dtype=np.int32)
    dm_inv, volume = rest_shape(REST, mesh_tets)
    mu, lam = np.array([300.0]), np.array([5000.0])
    x = _deformed("mild")
    c, grad, _, _ = _constraints(x, dm_inv[0], 1.0 + mu[0] / lam[0])
    force = -(grad[0] * c[0] * mu[0] * volume[0] + grad[1] * c[1] * lam[0] * volume[0])
    step = 1e-8
    numeric = np.zeros((4, 3))
    for k in range(4):
        for i in range(3):
            xp, xm = x.copy(), x.copy()
            xp[k, i] += step
            xm[k, i] -= step
            numeric[k, i] = -(
                tet_elastic_energy(mesh_tets, dm_inv, volume, mu, lam, xp)
                - tet_elastic_energy(mesh_tets, dm_inv, volume, mu, lam, xm)
            ) / (2 * step)
    assert np.allclose(force, numeric, rtol=1e-5, atol=1e-6 * np.abs(force).max())
    assert tet_elastic_energy(mesh_tets, dm_inv, volume, mu, lam, REST.copy()) == pytest.approx(0.0, abs=1e-18)


def test_coupled_update_solves_the_2x2_system():
    x = _deformed("large")
    dm_inv = _dm_inv()
    c, grad, _, _ = _constraints(x, dm_inv, 1.05)
    w = np.array([2.0, 0.5, 1.0, 0.0])
    alpha = np.array([3.0, 0.7])
    lam = np.array([0.1, -0.2])
    d = np.array(coupled_multiplier_update(c[0], c[1], grad, w, alpha[0], alpha[1], lam[0], lam[1]))
    a = np.einsum("k,ikj,lkj->il", w, grad, grad) + np.diag(alpha)
    expected = np.linalg.solve(a, -c - alpha * lam)
    assert np.allclose(d, expected, rtol=1e-10)


def test_coupled_update_incompressible_collapsed_tet_falls_back_to_deviatoric():
    """A tet collapsed onto a line has cof F = 0; with alpha_H = 0 the hydrostatic row is empty."""
    x = np.array([[0.0, 0, 0], [0.01, 0, 0], [0.02, 0, 0], [0.005, 0, 0]])
    c, grad, _, _ = _constraints(x, _dm_inv(), 1.0)
    assert np.all(grad[1] == 0.0)
    w = np.ones(4)
    d = coupled_multiplier_update(c[0], c[1], grad, w, 2.0, 0.0, 0.0, 0.0)
    a_dd = np.sum(w[:, None] * grad[0] ** 2)
    assert d == pytest.approx((-c[0] / (a_dd + 2.0), 0.0))


def _single_tet_arrays(mu=300.0, lam=5000.0, masses=(1e-3, 2e-3, 1.5e-3, 1e-3)):
    tets = np.array([[0, 1, 2, 3]], dtype=np.int32)
    dm_inv, volume = rest_shape(REST, tets)
    return {
        "inv_mass": 1.0 / np.array(masses),
        "tets": tets,
        "dm_inv": dm_inv,
        "volume": volume,
        "mu": np.array([mu]),
        "lam": np.array([lam]),
        "order": np.array([0], dtype=np.int32),
    }


def _sweep(a, q, multiplier, dt):
    project_tets(a["inv_mass"], a["tets"], a["dm_inv"], a["volume"], a["mu"], a["lam"], a["order"], dt, q, multiplier)


@pytest.mark.parametrize("lam", [3000.0 + 300.0, 1.5e4 + 300.0, math.inf])
@pytest.mark.parametrize("dt", [1e-5, 1e-3, 1e-1])
def test_zero_correction_at_rest_single_tet(lam, dt):
    a = _single_tet_arrays(lam=lam)
    q = REST.copy()
    multiplier = np.zeros((1, 2))
    _sweep(a, q, multiplier, dt)
    assert np.abs(q - REST).max() <= 1e-13 * 0.01
    assert np.all(np.isfinite(multiplier))
    if math.isfinite(lam):  # rest: the two multipliers balance each other, both non-zero
        assert multiplier[0, 0] != 0.0 and multiplier[0, 1] != 0.0


@pytest.mark.parametrize("nu", [0.3, 0.49, 0.5])
@pytest.mark.parametrize("scheme", ["five", "six"])
def test_zero_correction_at_rest_mesh(nu, scheme):
    mesh = box_tet_grid((0.03, 0.02, 0.02), (3, 2, 2), scheme=scheme)
    pinned = mesh.vertices[:, 0] == 0.0
    model = TissueModel.from_mesh(mesh, TissueMaterial(poisson_ratio=nu, youngs_modulus=1.0e3), pinned=pinned)
    q = np.array(model.particle_rest_q)
    multiplier = np.zeros((model.tet_count, 2))
    for _ in range(5):
        multiplier[...] = 0.0
        project_tets(
            model.particle_inv_mass,
            model.tet_indices,
            model.tet_dm_inv,
            model.tet_rest_volume,
            model.tet_mu,
            model.tet_lambda,
            model.tet_color_order,
            1e-3,
            q,
            multiplier,
        )
    assert np.abs(q - model.particle_rest_q).max() <= 1e-13 * 0.01


def _helper_sweep(inv_mass, tets, dm_inv, volume, mu, lam, order, dt, q, multiplier):
    """project_tets composed from the documented helpers, tet by tet (the reference of the written-out kernel)."""
    f, dcdf, grad = np.empty((3, 3)), np.empty((2, 3, 3)), np.empty((2, 4, 3))
    for t in order:
        nodes = tets[t]
        w = inv_mass[nodes]
        if w.sum() == 0.0:
            continue
        deformation_gradient(q[nodes], dm_inv[t], f)
        c_dev, c_hyd = neo_hookean_constraints(f, 1.0 + mu[t] / lam[t], dcdf)
        node_gradients(dcdf, dm_inv[t], grad)
        inv_dt2 = 1.0 / (dt * dt)
        d_dev, d_hyd = coupled_multiplier_update(c_dev, c_hyd, grad, w, inv_dt2 / (mu[t] * volume[t]),
                                                 inv_dt2 / (lam[t] * volume[t]), multiplier[t, 0], multiplier[t, 1])
        multiplier[t] += (d_dev, d_hyd)
        for k in range(4):
            if w[k] > 0.0:
                q[nodes[k]] += w[k] * (grad[0, k] * d_dev + grad[1, k] * d_hyd)


def _orders(model, kind):
    """The colour order, or every tet (pinned ones too) in index order or reversed: consecutive tets that share
    particles, which the sweep's blocks must then split."""
    if kind == "colour":
        return model.tet_color_order
    natural = np.arange(model.tet_count, dtype=np.int32)
    return natural if kind == "index" else natural[::-1].copy()


@pytest.mark.parametrize("order", ["colour", "index", "reversed"])
@pytest.mark.parametrize("nu", [0.3, 0.45, 0.5])
def test_project_tets_is_its_helpers_bit_for_bit(nu, order):
    """The blocked, vectorised sweep equals the helpers' arithmetic tet by tet exactly: a deformed, partly pinned,
    partly inverted mesh with a collapsed tet and mixed moduli (layers), several sweeps with multipliers carried
    over, in the colour order and in orders whose consecutive tets share particles."""
    mesh = box_tet_grid((0.03, 0.02, 0.02), (3, 2, 2))
    pinned = mesh.vertices[:, 0] == 0.0
    pinned[mesh.tets[0]] = True  # a tet with four pinned nodes: skipped
    model = TissueModel.from_mesh(mesh, [TissueMaterial(poisson_ratio=nu), TissueMaterial(youngs_modulus=3e5)],
                                  pinned=pinned, tet_material=np.arange(len(mesh.tets)) % 2)  # fmt: skip
    rng = np.random.default_rng(3)
    q = np.array(model.particle_rest_q) + 4e-3 * rng.standard_normal((model.particle_count, 3))
    q[model.tet_indices[-1]] = q[model.tet_indices[-1, 0]]  # a tet collapsed to a point
    args = (model.particle_inv_mass, model.tet_indices, model.tet_dm_inv, model.tet_rest_volume, model.tet_mu,
            model.tet_lambda, _orders(model, order), 1e-3)  # fmt: skip
    assert (signed_volumes(q, model.tet_indices) < 0).any()
    q_ref, m_ref = q.copy(), np.zeros((model.tet_count, 2))
    m = m_ref.copy()
    for _ in range(3):
        project_tets(*args, q, m)
        _helper_sweep(*args, q_ref, m_ref)
    assert np.array_equal(q, q_ref) and np.array_equal(m, m_ref)
    assert not np.array_equal(q, model.particle_rest_q)


@pytest.mark.parametrize("order", ["colour", "index", "reversed"])
def test_tet_blocks_partition_the_order_into_independent_blocks(order):
    """Every tet with a free node is in exactly one lane, in the order's sequence; a block's tets share no particle
    and number at most TET_BLOCK; the colour order fills the blocks (only a colour's last block is partial)."""
    mesh = box_tet_grid((0.04, 0.03, 0.02), (4, 3, 2))
    pinned = mesh.vertices[:, 2] == 0.0
    model = TissueModel.from_mesh(mesh, TissueMaterial(), pinned=pinned)
    sequence = _orders(model, order)
    blocks = tet_blocks(model.particle_inv_mass, model.tet_indices, model.tet_dm_inv, model.tet_rest_volume,
                        model.tet_mu, model.tet_lambda, sequence)  # fmt: skip
    active = sequence[model.particle_inv_mass[model.tet_indices[sequence]].sum(axis=1) > 0]
    lanes = blocks.lanes
    assert np.all((lanes >= 1) & (lanes <= TET_BLOCK))
    taken = np.concatenate([blocks.tets[k, : lanes[k]] for k in range(lanes.size)])
    assert np.array_equal(taken, active)
    assert np.all(blocks.tets[np.arange(TET_BLOCK)[None, :] >= lanes[:, None]] == -1)
    for k in range(lanes.size):
        tets = blocks.tets[k, : lanes[k]]
        nodes = model.tet_indices[tets]
        assert np.array_equal(blocks.nodes[k, :, : lanes[k]], nodes.T)
        assert np.unique(nodes).size == nodes.size
    if order == "colour":
        colour_sizes = np.diff(model.tet_color_offsets)
        assert lanes.size <= np.sum(-(-colour_sizes // TET_BLOCK))
    else:  # neighbours in index order share nodes: blocks end early, but each holds at least one tet
        assert lanes.size > -(-active.size // TET_BLOCK)


def test_repeated_sweeps_solve_the_xpbd_equations_and_conserve_momentum():
    a = _single_tet_arrays()
    mass = 1.0 / a["inv_mass"]
    q = _deformed("large")
    q0 = q.copy()
    multiplier = np.zeros((1, 2))
    dt = 1e-3
    first = None
    for _ in range(40):
        _sweep(a, q, multiplier, dt)
        r = tet_residual(a["tets"], a["dm_inv"], a["volume"], a["mu"], a["lam"], a["order"], q, multiplier, dt)
        first = r if first is None else first
    assert r < 1e-10 * max(first, 1.0)
    dx = q - q0
    assert np.allclose((mass[:, None] * dx).sum(axis=0), 0.0, atol=1e-15)
    assert np.allclose((mass[:, None] * np.cross(q0, dx)).sum(axis=0), 0.0, atol=1e-15)


def test_inverted_tet_recovers_without_nan():
    a = _single_tet_arrays(lam=2e4)
    q = _deformed("inverted")
    assert signed_volumes(q, a["tets"])[0] < 0
    multiplier = np.zeros((1, 2))
    for _ in range(200):
        multiplier[...] = 0.0
        _sweep(a, q, multiplier, 1e-2)
    assert np.all(np.isfinite(q))
    assert signed_volumes(q, a["tets"])[0] > 0


def test_tet_collapsed_to_a_point_gets_no_correction():
    a = _single_tet_arrays()
    q = np.full((4, 3), 0.004)
    multiplier = np.zeros((1, 2))
    _sweep(a, q, multiplier, 1e-3)
    assert np.all(q == 0.004)
    assert np.all(np.isfinite(multiplier))


def test_fully_pinned_tet_is_untouched():
    a = _single_tet_arrays()
    a["inv_mass"][:] = 0.0
    q = _deformed("mild")
    q0 = q.copy()
    _sweep(a, q, np.zeros((1, 2)), 1e-3)
    assert np.array_equal(q, q0)


def test_rollers_project_onto_planes_and_keep_tangential_motion():
    q = np.array([[0.1, 0.2, 0.3], [0.5, -0.2, 0.05], [1.0, 1.0, 1.0]])
    inv_mass = np.array([1.0, 2.0, 0.0])
    normal = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])
    offset = np.array([0.25, 0.4, 0.0])
    project_rollers(inv_mass, np.array([0, 1, 2], dtype=np.int32), normal, offset, q)
    assert np.allclose(q, [[0.1, 0.2, 0.25], [0.4, -0.2, 0.05], [1.0, 1.0, 1.0]])


def test_residual_is_zero_for_a_converged_rest_state():
    a = _single_tet_arrays()
    q = REST.copy()
    multiplier = np.zeros((1, 2))
    _sweep(a, q, multiplier, 1e-3)
    r = tet_residual(a["tets"], a["dm_inv"], a["volume"], a["mu"], a["lam"], a["order"], q, multiplier, 1e-3)
    assert r < 1e-12


def test_supports_hold_free_particles_on_the_allowed_side_and_leave_pinned_ones():
    normal, offset = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]]), np.array([0.0, -0.01])
    q = np.array([[0.1, 0.2, -0.003], [-0.02, 0.0, 0.5], [0.0, 0.0, -1.0], [0.3, 0.3, 0.3]])
    inv_mass = np.array([1.0, 1.0, 0.0, 1.0])
    expected = q.copy()
    expected[0, 2] = 0.0  # below the base: moved straight up onto it, keeping x and y
    expected[1, 0] = -0.01  # behind the second plane: moved onto it
    project_supports(inv_mass, normal, offset, q)
    assert np.array_equal(q, expected)  # the pinned particle 2 is left below the base


def test_supports_are_validated_and_normalised():
    mesh = box_tet_grid((0.01, 0.01, 0.01), (1, 1, 1))
    model = TissueModel.from_mesh(mesh, TissueMaterial(), supports=([[0.0, 0.0, 2.0]], [0.0]))
    assert np.array_equal(model.support_normal, [[0.0, 0.0, 1.0]])
    with pytest.raises(ValueError, match="support normals"):
        TissueModel.from_mesh(mesh, TissueMaterial(), supports=([[0.0, 0.0, 0.0]], [0.0]))
    with pytest.raises(ValueError, match="support normals"):
        TissueModel.from_mesh(mesh, TissueMaterial(), supports=([0.0, 0.0, 1.0], [0.0]))


@pytest.mark.parametrize("integrator", ["xpbd", "quasi_newton"])
def test_pad_base_is_a_contact_for_both_integrators(integrator):
    from suture_gym.sim.model import Control
    from suture_gym.sim.scenes import suturing_pad, two_bar_wound
    from suture_gym.sim.solver import Solver

    assert two_bar_wound(cells=(4, 2, 2)).model.tissue.support_offset.size == 1
    assert two_bar_wound(cells=(4, 2, 2), base=False).model.tissue.support_offset.size == 0
    scene = suturing_pad(size=(0.008, 0.008, 0.004), cells=(4, 4, 2), material=TissueMaterial(3.0e3, 0.45))
    tissue, q = scene.model.tissue, scene.state.tissue.particle_q
    free = np.flatnonzero(tissue.particle_inv_mass > 0)
    scene.state.tissue.particle_qd[free, 2] = -20.0  # m/s: one substep would carry them 2 cm below the base
    Solver(tissue_integrator=integrator).step(scene.model, scene.state, Control(), 1e-3)
    assert q[free, 2].min() >= 0.0
