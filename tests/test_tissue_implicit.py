"""Implicit tissue integrators: stress/tangent vs finite differences, rest state, energy decrease, determinism,
clear errors for settings outside what they support."""

import warnings
from dataclasses import replace

import numpy as np
import pytest
import scipy.sparse
import scipy.sparse.linalg

from suture_gym.sim.mesh import rest_shape, signed_volumes
from suture_gym.sim.model import Control, State, TissueMaterial, TissueState
from suture_gym.sim.rest_system import SparseCholesky
from suture_gym.sim.scenes import PAPER_SOLVER, compression_block, suturing_pad
from suture_gym.sim.solver import Solver
from suture_gym.sim.tissue_energy import (
    incremental_potential,
    stable_neo_hookean_stress,
    stable_neo_hookean_tangent,
    stiffness_matrix,
    tet_stiffness,
)
from suture_gym.sim.tissue_implicit import ImplicitTissue, QuasiNewton, VertexBlockDescent, implicit_tissue

REST = np.array([[0.0, 0.0, 0.0], [0.011, 0.001, -0.002], [0.002, 0.009, 0.001], [-0.001, 0.002, 0.010]])
MU, LAM = 1.0e3, 9.0e3


def _deformation(kind: str) -> np.ndarray:
    rng = np.random.default_rng(3)
    if kind == "mild":
        return np.eye(3) + 0.1 * rng.standard_normal((3, 3))
    if kind == "large":
        return np.diag([1.6, 0.6, 1.2]) + 0.3 * rng.standard_normal((3, 3))
    return np.diag([1.0, 1.0, -0.6]) + 0.1 * rng.standard_normal((3, 3))  # inverted


def _psi(f: np.ndarray) -> float:
    return stable_neo_hookean_stress(f, MU, LAM, np.empty((3, 3)))


@pytest.mark.parametrize("kind", ["mild", "large", "inverted"])
def test_stress_and_tangent_match_central_differences(kind):
    f = _deformation(kind)
    stress = np.empty((3, 3))
    stable_neo_hookean_stress(f, MU, LAM, stress)
    tangent = np.empty((3, 3, 3, 3))
    stable_neo_hookean_tangent(f, MU, LAM, tangent)
    step = 1e-6
    numeric_p = np.zeros((3, 3))
    numeric_c = np.zeros((3, 3, 3, 3))
    for k in range(3):
        for m in range(3):
            fp, fm = f.copy(), f.copy()
            fp[k, m] += step
            fm[k, m] -= step
            numeric_p[k, m] = (_psi(fp) - _psi(fm)) / (2 * step)
            pp, pm = np.empty((3, 3)), np.empty((3, 3))
            stable_neo_hookean_stress(fp, MU, LAM, pp)
            stable_neo_hookean_stress(fm, MU, LAM, pm)
            numeric_c[:, :, k, m] = (pp - pm) / (2 * step)
    assert np.allclose(stress, numeric_p, rtol=1e-6, atol=1e-6 * np.abs(stress).max())
    assert np.allclose(tangent, numeric_c, rtol=1e-6, atol=1e-6 * np.abs(tangent).max())


@pytest.mark.parametrize("kind", ["mild", "large", "inverted"])
def test_element_hessian_matches_central_differences_of_node_forces(kind):
    dm_inv, volume = rest_shape(REST, np.array([[0, 1, 2, 3]]))
    x = REST @ _deformation(kind).T
    hessian = np.empty((12, 12))
    tet_stiffness(x, dm_inv[0], volume[0], MU, LAM, hessian)

    def forces(xx):
        g = np.vstack([-dm_inv[0].sum(axis=0), dm_inv[0]])  # (4, 3) shape gradients
        stress = np.empty((3, 3))
        stable_neo_hookean_stress(xx.T @ g, MU, LAM, stress)
        return (volume[0] * stress @ g.T).T.ravel()

    step = 1e-8
    numeric = np.zeros((12, 12))
    for c in range(12):
        xp, xm = x.copy(), x.copy()
        xp.reshape(-1)[c] += step
        xm.reshape(-1)[c] -= step
        numeric[:, c] = (forces(xp) - forces(xm)) / (2 * step)
    assert np.allclose(hessian, numeric, rtol=1e-5, atol=1e-6 * np.abs(hessian).max())
    assert np.allclose(hessian, hessian.T, atol=1e-9 * np.abs(hessian).max())


def test_rest_state_has_zero_stress_and_the_linear_elastic_tangent():
    material = TissueMaterial(youngs_modulus=2.0e4, poisson_ratio=0.45)
    mu, lam = material.lame_mu, material.hydrostatic_modulus
    stress = np.empty((3, 3))
    assert stable_neo_hookean_stress(np.eye(3), mu, lam, stress) == pytest.approx(0.0, abs=1e-9)
    assert np.abs(stress).max() < 1e-9 * mu
    tangent = np.empty((3, 3, 3, 3))
    stable_neo_hookean_tangent(np.eye(3), mu, lam, tangent)
    d = np.eye(3)
    lame = material.lame_lambda
    linear = lame * np.einsum("ij,kl->ijkl", d, d) + mu * (
        np.einsum("ik,jl->ijkl", d, d) + np.einsum("il,jk->ijkl", d, d)
    )
    # Equal on symmetric strains (the stable neo-Hookean tangent differs only on the rotation part).
    rng = np.random.default_rng(0)
    for _ in range(5):
        e = rng.standard_normal((3, 3))
        e = 0.5 * (e + e.T)
        assert np.einsum("ijkl,kl->ij", tangent, e) == pytest.approx(np.einsum("ijkl,kl->ij", linear, e), rel=1e-12)


@pytest.mark.parametrize("with_gradient", [True, False])
def test_incremental_potential_is_its_definition_tet_by_tet(with_gradient):
    """The vectorised energy passes against ``Phi`` summed tet by tet with the stress helper: a deformed pad of two
    materials with an inverted tet, held dofs and external forces, over a subset of tets whose count is no multiple
    of a vector width (the loops' scalar tails)."""
    scene = suturing_pad(cells=(3, 3, 2), material=TissueMaterial(youngs_modulus=5.0e4, poisson_ratio=0.45))
    tissue = scene.model.tissue
    stiffer = np.where(np.arange(tissue.tet_count) % 2 == 0, 3.0, 1.0)
    tissue = replace(tissue, tet_mu=tissue.tet_mu * stiffer, tet_lambda=tissue.tet_lambda * stiffer)
    integrator = implicit_tissue(tissue, "quasi_newton", 1e-3)
    rng = np.random.default_rng(5)
    q = tissue.particle_rest_q + 1e-3 * rng.standard_normal(tissue.particle_rest_q.shape)
    first = tissue.tet_indices[0]
    q[first[3]] = q[first[0]] + 0.5 * (q[first[0]] - q[first[3]])  # node 3 through the opposite face: inverted
    assert signed_volumes(q, tissue.tet_indices[:1])[0] < 0.0
    y = q + 1e-4 * rng.standard_normal(q.shape)
    external = rng.standard_normal(q.shape)
    tets = integrator.active_tets[: integrator.active_tets.size - 3]
    assert tets.size % 8 != 0
    free = integrator.free_mask

    total = 0.0
    grad = np.zeros_like(q)
    for p in range(q.shape[0]):
        d = (q[p] - y[p]) * free[p]
        total += np.sum(0.5 * tissue.particle_mass[p] * integrator.inv_h2 * d * d - external[p] * q[p])
        grad[p] = (tissue.particle_mass[p] * integrator.inv_h2 * d - external[p]) * free[p]
    stress = np.empty((3, 3))
    for t in tets:
        nodes = tissue.tet_indices[t]
        shape = np.vstack([-tissue.tet_dm_inv[t].sum(axis=0), tissue.tet_dm_inv[t]])  # (4, 3) shape gradients
        f = q[nodes].T @ shape
        volume = tissue.tet_rest_volume[t]
        total += volume * stable_neo_hookean_stress(f, tissue.tet_mu[t], tissue.tet_lambda[t], stress)
        grad[nodes] += volume * (stress @ shape.T).T
    grad *= free

    out = np.full_like(q, 7.0)
    phi = incremental_potential(
        q, y, tissue.particle_mass, free, integrator.inv_h2, tissue.tet_indices, tissue.tet_dm_inv,
        tissue.tet_rest_volume, tissue.tet_mu, tissue.tet_lambda, tets, external, out, with_gradient,
    )  # fmt: skip
    assert phi == pytest.approx(total, rel=1e-11, abs=1e-11 * np.abs(total))
    if with_gradient:
        assert np.allclose(out, grad, rtol=1e-9, atol=1e-9 * np.abs(grad).max())
    else:
        assert np.all(out == 7.0)


def test_global_stiffness_annihilates_rigid_translation_and_gradient_vanishes_at_rest():
    scene = suturing_pad(size=(0.006, 0.006, 0.004), cells=(3, 3, 2))
    tissue = scene.model.tissue
    k = stiffness_matrix(tissue)
    for axis in range(3):
        u = np.zeros((tissue.particle_count, 3))
        u[:, axis] = 1.0
        assert np.abs(k @ u.ravel()).max() < 1e-9 * abs(k).max()
    integrator = implicit_tissue(tissue, "quasi_newton", 1e-3)
    integrator.y[...] = tissue.particle_rest_q
    integrator.external[...] = 0.0
    assert integrator.potential(tissue.particle_rest_q.copy()) == pytest.approx(0.0, abs=1e-15)
    assert np.abs(integrator.grad).max() < 1e-12


def test_rest_system_is_the_rest_stiffness_plus_the_mass_term_for_each_modulus():
    """The integrator's A0, assembled through the cached per-mesh pattern and the closed-form rest stiffness, is
    M / h^2 plus stiffness_matrix's K0 (the general tangent at F = I), also for a second modulus on the same mesh
    (the pattern reused), a layered material and a roller-held axis."""
    for material, roller in ((TissueMaterial(1.0e5, 0.45), False), (TissueMaterial(3.0e3, 0.3), True)):
        scene = suturing_pad(size=(0.006, 0.006, 0.004), cells=(3, 3, 2), material=material)
        tissue = scene.model.tissue
        if roller:
            held = int(np.flatnonzero(tissue.particle_inv_mass > 0)[0])
            tissue = replace(tissue, tet_mu=tissue.tet_mu * np.linspace(1.0, 4.0, tissue.tet_count),
                             tet_lambda=tissue.tet_lambda * np.linspace(1.0, 4.0, tissue.tet_count),
                             roller_particle=np.array([held], np.int32), roller_normal=np.array([[0.0, 0.0, 1.0]]),
                             roller_offset=np.array([tissue.particle_rest_q[held, 2]]))  # fmt: skip
        integrator = QuasiNewton(tissue, 1e-3)
        free = integrator.free_index
        a0 = (stiffness_matrix(tissue)[free][:, free]
              + scipy.sparse.diags(np.repeat(tissue.particle_mass, 3)[free] * 1e6)).toarray()  # fmt: skip
        rhs = np.random.default_rng(0).standard_normal((free.size, 3))
        np.testing.assert_allclose(integrator.factor.solve(rhs), np.linalg.solve(a0, rhs), rtol=1e-9, atol=1e-15)


def _loaded_state(kind: str, youngs: float, amplitude: float = 3e-4):
    """A small pad's free particles displaced at random by ``amplitude`` (m) and its substep begun: the
    integrator, the positions and the scene (which keeps the tissue, held weakly by the integrator, alive)."""
    scene = suturing_pad(size=(0.006, 0.006, 0.004), cells=(3, 3, 2), material=TissueMaterial(youngs, 0.45))
    tissue = scene.model.tissue
    integrator = implicit_tissue(tissue, kind, 1e-3)
    rng = np.random.default_rng(1)
    q = scene.state.tissue.particle_q
    free = tissue.particle_inv_mass > 0
    q[free] += amplitude * rng.standard_normal((int(free.sum()), 3))
    integrator.begin(q, scene.model.gravity)
    return integrator, q, scene


@pytest.mark.parametrize("kind", ["quasi_newton", "vbd"])
@pytest.mark.parametrize("youngs", [1.0e3, 1.0e6])
def test_each_solve_does_not_raise_the_incremental_potential(kind, youngs):
    integrator, q, _scene = _loaded_state(kind, youngs)
    before = integrator.potential(q)
    for iterations in (1, 2, 4):
        trial = q.copy()
        integrator.solve(trial, iterations)
        after = integrator.potential(trial)
        assert after <= before
    assert after < before  # and does lower it from a perturbed start


def _first_solve(youngs: float, amplitude: float):
    """A pad's particles displaced at random by ``amplitude`` (m), one quasi-Newton step of a first sweep; returns
    the integrator, the step's largest move and the largest move of the step that would follow it (m)."""
    integrator, q, scene = _loaded_state("quasi_newton", youngs, amplitude)
    before = q.copy()
    integrator.solve(q, 1, converge=False)
    integrator.potential(q)
    following = integrator.factor.solve(integrator.grad.reshape(-1)[integrator.free_index])
    return integrator, float(np.abs(q - before).max()), float(np.abs(following).max()), scene


@pytest.mark.parametrize("youngs", [3.0e3, 3.0e5])
def test_a_small_first_step_far_from_its_solution_leaves_the_solve_unconverged(youngs):
    """The first sweep's step is below ``large_step`` in both cases; the energy's estimate of the next step flags
    the one whose next step would move a particle by more than the convergence test's 0.1 mm (0.1 m/s over 1 ms),
    not the one whose next step is under half of it."""
    converged = 0.1 * 1e-3
    integrator, size, following, _scene = _first_solve(youngs, 1.8e-4)
    assert size < 0.9 * integrator.large_step and following > 1.5 * converged  # the case is what it claims
    assert integrator.unconverged
    integrator, size, following, _scene = _first_solve(youngs, 1.0e-4)
    assert size < integrator.large_step and following < 0.7 * converged
    assert not integrator.unconverged


def test_the_next_step_estimate_reads_a_linear_step_as_converged():
    """Near rest the energy along a step is the rest system's quadratic to round-off: the estimate is zero or far
    below the step that follows (itself under a hundredth of the step)."""
    integrator, size, following, _scene = _first_solve(3.0e5, 1e-7)
    assert following < 1e-2 * size
    assert not integrator.unconverged


@pytest.mark.parametrize("kind", ["quasi_newton", "vbd"])
def test_solves_are_deterministic(kind):
    a_int, a, _a_scene = _loaded_state(kind, 3.0e4)
    a_int.solve(a, 3)
    b_int, b, _b_scene = _loaded_state(kind, 3.0e4)
    b_int.solve(b, 3)
    assert np.array_equal(a, b)


@pytest.mark.parametrize("kind", ["quasi_newton", "vbd"])
def test_stiff_pad_stays_at_rest_at_the_env_substep(kind):
    scene = suturing_pad(size=(0.008, 0.008, 0.008), cells=(4, 4, 4), material=TissueMaterial(1.0e6, 0.45))
    solver, control = Solver(tissue_integrator=kind, iterations=1, max_speed=50.0), Control()
    for _ in range(200):
        solver.step(scene.model, scene.state, control, 1e-3)
    q = scene.state.tissue.particle_q
    assert not scene.state.diverged
    assert np.abs(scene.state.tissue.particle_qd).max() < 1e-3
    assert (signed_volumes(q, scene.model.tissue.tet_indices) > 0).all()


def test_sparse_cholesky_solves_one_and_several_right_hand_sides():
    scene = suturing_pad(size=(0.006, 0.006, 0.004), cells=(3, 3, 2), material=TissueMaterial(1.0e5, 0.45))
    integrator = QuasiNewton(scene.model.tissue, 1e-3)
    free = integrator.free_index
    mass = np.repeat(scene.model.tissue.particle_mass, 3)[free]
    matrix = stiffness_matrix(scene.model.tissue)[free][:, free] + scipy.sparse.diags(mass * 1e6)
    rng = np.random.default_rng(0)
    one, several = rng.standard_normal(free.size), rng.standard_normal((free.size, 3))
    factor = SparseCholesky(matrix)
    assert np.allclose(matrix @ factor.solve(one), one, rtol=0, atol=1e-9 * np.abs(one).max())
    assert np.allclose(matrix @ factor.solve(several), several, rtol=0, atol=1e-9 * np.abs(several).max())


def test_later_sweeps_skip_the_solve_when_no_rows_moved_the_tissue():
    """Without coupling rows a second sweep would only refine the same solve: it is skipped, so two sweeps and
    one give the same trajectory bit for bit; the quasi-Newton iteration count is what refines it."""
    runs = {}
    for sweeps in (1, 2):
        scene = suturing_pad(size=(0.008, 0.008, 0.004), cells=(4, 4, 2), material=TissueMaterial(1.0e5, 0.45))
        scene.state.tissue.particle_qd[:, 0] = 0.05  # a shear wave, so the solves have work to do
        solver, control = Solver(tissue_integrator="quasi_newton", iterations=sweeps, max_speed=50.0), Control()
        for _ in range(20):
            solver.step(scene.model, scene.state, control, 1e-3)
        runs[sweeps] = scene.state.tissue.particle_q.copy()
    assert np.array_equal(runs[1], runs[2])
    assert not np.allclose(runs[1], suturing_pad(size=(0.008, 0.008, 0.004), cells=(4, 4, 2)).state.tissue.particle_q)


def test_row_compliance_is_the_substep_compliance_among_the_touched_vertices():
    """begin_rows gathers C = A0^-1 / h^2 among the free touched vertices (pinned ones get no slot), and the
    rows' impulses spread by propagate_rows reproduce, at those vertices, exactly the moves the rows made."""
    from suture_gym.sim.coupling.compliance import apply_impulse

    scene = suturing_pad(size=(0.006, 0.006, 0.004), cells=(3, 3, 2), material=TissueMaterial(1.0e5, 0.45))
    tissue = scene.model.tissue
    integrator = QuasiNewton(tissue, 1e-3)
    touched = np.zeros(tissue.particle_count, dtype=bool)
    top = np.flatnonzero(tissue.particle_rest_q[:, 2] > 0.0039)[:3]
    pinned = np.flatnonzero(tissue.particle_inv_mass == 0)[0]
    touched[[*top, pinned]] = True
    compliance = integrator.begin_rows(touched)
    _, slot, vertices, matrix, _ = compliance
    assert set(vertices) == set(top) and slot[pinned] == -1
    dense = np.linalg.inv(
        (stiffness_matrix(tissue)[integrator.free_index][:, integrator.free_index]
         + scipy.sparse.diags(np.repeat(tissue.particle_mass, 3)[integrator.free_index] * 1e6)).toarray()
    ) * 1e6  # fmt: skip
    position = {d: k for k, d in enumerate(integrator.free_index)}
    dofs = [3 * v + i for v in vertices for i in range(3)]
    expected = np.array([[dense[position[a], position[b]] for b in dofs] for a in dofs])
    np.testing.assert_allclose(matrix, expected, rtol=1e-9, atol=1e-12 * np.abs(expected).max())
    q = scene.state.tissue.particle_q
    before = q.copy()
    apply_impulse(compliance, top, np.array([0.2, 0.3, 0.5]), 3, np.array([0.0, 0.0, 1e-7]), q)
    moved = q[vertices].copy()
    integrator.propagate_rows(before, q)
    np.testing.assert_allclose(q[vertices], moved, rtol=0, atol=1e-15)
    assert np.abs(q - before).max() > 0.0
    assert integrator.rows_move == pytest.approx(np.abs(q - before).max(), rel=1e-12)  # what a later sweep tests
    np.testing.assert_allclose(integrator.external.sum(axis=0), [0.0, 0.0, -1e-7 * 1e6], rtol=1e-12)


def test_out_of_range_settings_raise_or_warn_naming_the_parameter():
    with pytest.raises(ValueError, match="tissue_integrator"):
        Solver(tissue_integrator="explicit", iterations=1, max_speed=50.0)
    with pytest.raises(ValueError, match="tissue_iterations"):
        Solver(tissue_integrator="quasi_newton", tissue_iterations=0, iterations=1, max_speed=50.0)
    incompressible = suturing_pad(cells=(2, 2, 1), material=TissueMaterial(3.0e4, 0.5))
    with pytest.raises(ValueError, match="poisson_ratio"):
        QuasiNewton(incompressible.model.tissue, 1e-3)
    too_stiff = suturing_pad(cells=(2, 2, 1), material=TissueMaterial(1.0e7, 0.45))
    with pytest.warns(UserWarning, match="youngs_modulus"):
        VertexBlockDescent(too_stiff.model.tissue, 1e-3)
    too_low_nu = suturing_pad(cells=(2, 2, 1), material=TissueMaterial(1.0e4, 0.1))
    with pytest.warns(UserWarning, match="poisson_ratio"):
        QuasiNewton(too_low_nu.model.tissue, 1e-3)
    in_range = suturing_pad(cells=(2, 2, 1), material=TissueMaterial(1.0e4, 0.45))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ImplicitTissue(in_range.model.tissue, 1e-3)


def test_axis_aligned_rollers_are_held_and_others_rejected():
    scene = compression_block(cells=2, material=TissueMaterial(1.0e4, 0.45))
    solver, control = Solver(tissue_integrator="quasi_newton", iterations=1, max_speed=50.0), Control()
    for _ in range(20):
        solver.step(scene.model, scene.state, control, 1e-3)
    tissue = scene.model.tissue
    q = scene.state.tissue.particle_q
    assert np.allclose(np.einsum("ij,ij->i", q[tissue.roller_particle], tissue.roller_normal), tissue.roller_offset)

    tilted = replace(tissue, roller_normal=np.tile([0.6, 0.8, 0.0], (len(tissue.roller_particle), 1)))
    with pytest.raises(ValueError, match="axis-aligned"):
        QuasiNewton(tilted, 1e-3)


def _press(youngs: float, force: float, solver: Solver, seconds: float = 0.4):
    """Needle tip pushed straight down into a 12 x 12 x 6 mm pad of 2 mm cells (bottom pinned) with ``force`` N
    ramped over 0.2 s, lateral pose held by a virtual coupling. Returns (scene, tip depth m)."""
    from suture_gym.sim.coupling import CouplingParams
    from suture_gym.sim.needle import NeedleModel, VirtualCoupling, needle_point_velocity
    from suture_gym.sim.quat import quat_to_matrix
    from suture_gym.sim.rod import SutureParams
    from suture_gym.sim.scenes import WOUND_ARC_AXIS, WOUND_ARC_U, add_strands, needle_circle_pose, wound_tip_angle

    base = suturing_pad(size=(0.012, 0.012, 0.006), cells=(6, 6, 3), material=TissueMaterial(youngs, 0.45))
    needle = NeedleModel.from_shape()
    params = CouplingParams(puncture_force=100.0, exit_puncture_force=0.0, cutting_force=0.0, tip_contact_radius=0.0,
                            tear_force=4.0, needle_axial_friction=10.0)
    center = np.array([0.0063, 0.0063 + needle.shape.curvature_radius, 0.006 + params.resistance_eps])
    scene = add_strands(
        base,
        needle_circle_pose(needle, center, WOUND_ARC_AXIS, WOUND_ARC_U, wound_tip_angle(needle)),
        suture_params=SutureParams(length=0.02, node_count=21),
        suture_direction=(0.0, 0.0, 1.0),
        coupling_params=params,
    )
    model, state = scene.model, scene.state
    hold = VirtualCoupling()
    quat = state.needle.body_quat.copy()
    grip = state.needle.body_pos + quat_to_matrix(quat) @ needle.grip_pos_body
    tip_z0 = float((state.needle.body_pos + quat_to_matrix(quat) @ needle.tip_pos_body)[2])
    control, dt = Control(), 1e-3
    for k in range(int(round(seconds / dt))):
        push = -force * min(1.0, k * dt / 0.2) - needle_point_velocity(needle, state.needle, needle.tip_pos_body)[2]
        w = hold.wrench(needle, state.needle, grip, quat)
        arm = quat_to_matrix(state.needle.body_quat) @ (needle.tip_pos_body - needle.grip_pos_body)
        control.needle_wrench = np.concatenate([[w[0], w[1], push], w[3:] + np.cross(arm, [0.0, 0.0, push])])
        solver.step(model, state, control, dt)
    tip = state.needle.body_pos + quat_to_matrix(state.needle.body_quat) @ needle.tip_pos_body
    return scene, tip_z0 - float(tip[2])


BDF2_TOLERANCE = {"tissue_scheme": "bdf2", "tissue_tolerance": 1e-6, "tissue_iterations": 20}


@pytest.mark.parametrize("options", [{}, {"tissue_scheme": "bdf2"}, BDF2_TOLERANCE])
def test_needle_load_reaches_the_implicit_tissue_and_its_base(options):
    """1 N tip on a 100 kPa pad at 1 ms, quasi-Newton with two sweeps (implicit Euler, or BDF2 with or without a
    tolerance): no divergence, the tissue comes to rest, the tip dents it by under a cell, and the pinned base
    carries the tissue's weight plus the push."""
    from suture_gym.measure.tissue_stiff import _elastic_gradient

    scene, dent = _press(1.0e5, 1.0, Solver(tissue_integrator="quasi_newton", iterations=2, max_speed=50.0, **options))
    state, tissue = scene.state, scene.model.tissue
    assert not state.diverged
    assert np.abs(state.tissue.particle_qd).max() < 1e-2
    assert 1e-4 < dent < 2e-3
    base = tissue.particle_inv_mass == 0
    support = _elastic_gradient(tissue, state.tissue.particle_q)[base, 2].sum()  # N, downward on the base
    weight = tissue.particle_mass[~base].sum() * 9.81
    # the rows' impulses reach the tissue whole (the rows solve against its compliance among their vertices)
    assert support == pytest.approx(weight + state.coupling.tip_force, rel=0.01)
    assert state.coupling.tip_force == pytest.approx(1.0, rel=0.02)
    scheme = options.get("tissue_scheme", "euler")
    assert state.work.tissue_integrator("quasi_newton", 1e-3, scheme).substep_scheme == "euler"  # rows touch: Euler


def test_a_state_can_change_integrator_between_steps_and_its_rows_follow():
    """The coupling rows' tissue side is chosen every substep: after implicit steps, an XPBD step of the same
    state uses the particles' inverse masses again (not the implicit compliance block of the last substep)."""
    scene, _ = _press(1.0e5, 1.0, Solver(tissue_integrator="quasi_newton", iterations=2, max_speed=50.0), seconds=0.05)
    work = scene.state.work
    assert work.compliance is not work.diagonal_compliance
    PAPER_SOLVER.step(scene.model, scene.state, Control(), 1e-3)
    assert work.compliance is work.diagonal_compliance


def test_a_sweep_whose_rows_moved_nothing_ends_the_substep():
    """With the needle clear of the pad the first sweep's rows move nothing: it does the suture's solve itself and
    the second sweep is skipped; pressed into the pad, the rows act in every substep and both sweeps run."""
    solver = Solver(tissue_integrator="quasi_newton", iterations=2, max_speed=50.0)
    clear, _ = _press(1.0e5, 0.0, solver, seconds=0.01)
    assert clear.state.work.tissue_integrator("quasi_newton", 1e-3).sweeps_done
    pressed, _ = _press(1.0e5, 1.0, solver, seconds=0.1)
    assert not pressed.state.work.tissue_integrator("quasi_newton", 1e-3).sweeps_done


@pytest.mark.parametrize("force", [0.2, 1.0])
def test_a_later_sweep_trusts_row_moves_within_the_large_step_to_the_rest_system(monkeypatch, force):
    """A later sweep solves again only if the rows moved the tissue by more than ``large_step`` since the last
    solve. A tip pressed into a 100 kPa pad comes to the same dent as when every move of the rows is solved again,
    with fewer solves."""
    from suture_gym.sim import tissue_implicit

    solves = [0]
    plain_solve, plain_propagate = QuasiNewton.solve, QuasiNewton.propagate_rows

    def counted(self, *args, **kwargs):
        solves[0] += 1
        plain_solve(self, *args, **kwargs)

    monkeypatch.setattr(QuasiNewton, "solve", counted)
    runs = {}
    for rule in ("default", "every move"):
        if rule == "every move":
            def propagate(self, q_before, q):
                plain_propagate(self, q_before, q)
                if self.rows_move > 0.0:
                    self.rows_move = np.inf

            monkeypatch.setattr(tissue_implicit.ImplicitTissue, "propagate_rows", propagate)
            monkeypatch.setattr(QuasiNewton, "rows_linear", lambda self, q: False)
        solves[0] = 0
        _, depth = _press(1.0e5, force, Solver(tissue_integrator="quasi_newton", iterations=2, max_speed=50.0),
                          seconds=0.3)
        runs[rule] = depth, solves[0]
    (depth, count), (every_depth, every_count) = runs["default"], runs["every move"]
    assert depth > 1e-4  # a real dent (0.1 mm and more)
    assert depth == pytest.approx(every_depth, abs=1e-8)
    assert count < every_count  # 0.2 N: 454 solves against 597 in 300 substeps; 1 N: 568 against 598


@pytest.mark.parametrize("youngs", [3.0e3, 3.0e5])
def test_rows_linear_reads_the_rest_systems_response_to_the_rows_forces_as_linear(youngs):
    """After a solve, forces ``f`` at a few vertices (the rows') that move the tissue by ``A0^-1 f``: linear for a
    move of 10 um, not for the same move scaled to 1.5 mm (most of a 2 mm cell), nor for a 10 um move that is not
    the response to ``f``."""
    integrator, q, scene = _loaded_state("quasi_newton", youngs, 0.0)
    tissue = scene.model.tissue
    integrator.solve(q, 1)
    solved = q.copy()
    top = np.flatnonzero(solved[:, 2] > solved[:, 2].max() - 1e-9)[:3]
    force = np.zeros_like(q)
    force[top] = [0.0, 0.0, -1.0]
    response = np.zeros(q.size)
    response[integrator.free_index] = integrator.factor.solve(force.reshape(-1)[integrator.free_index])
    response = response.reshape(q.shape)

    def moved(size: float, extra: np.ndarray | None = None) -> bool:
        scale = size / np.abs(response).max()
        integrator.external[...] = integrator._solved_external + scale * force
        q[...] = solved + scale * response + (0.0 if extra is None else extra)
        return integrator.rows_linear(q)

    assert moved(1e-5)
    assert not moved(1.5e-3)
    noise = np.zeros_like(q)
    free = tissue.particle_inv_mass > 0
    noise[free] = 1e-5 * np.random.default_rng(2).standard_normal((int(free.sum()), 3))
    assert not moved(1e-5, noise)


def test_the_stiff_env_benchmark_changes_only_the_stiffness_for_its_soft_physics():
    from suture_gym.measure.tissue_stiff import V0_YOUNGS, _stiff_env

    env_id = "SutureGym/NeedleInsert-v3"
    configs = {physics: _stiff_env(env_id, physics)[0].unwrapped.config for physics in ("stiff", "soft", "v0")}
    stiff, soft, v0 = configs["stiff"], configs["soft"], configs["v0"]
    scale = V0_YOUNGS / stiff.tissue.youngs_modulus
    assert soft.tissue.youngs_modulus == v0.tissue.youngs_modulus == V0_YOUNGS
    assert soft.solver == stiff.solver  # same integrator and sweeps
    assert (v0.solver.tissue_integrator, v0.solver.iterations) == ("xpbd", 1)
    for name in ("puncture_force", "tear_force", "exit_puncture_force", "cutting_force"):
        assert getattr(soft.coupling, name) == pytest.approx(getattr(stiff.coupling, name) * scale)
    assert soft.coupling.tip_contact_radius == stiff.coupling.tip_contact_radius
    assert (v0.coupling.exit_puncture_force, v0.coupling.cutting_force, v0.coupling.tip_contact_radius) == (0, 0, 0)
    assert soft.action.max_force == pytest.approx(stiff.action.max_force * scale)
    with pytest.raises(ValueError, match="physics must be one of"):
        _stiff_env(env_id, "medium")


def test_a_solve_with_a_tolerance_iterates_until_the_gradient_is_below_it():
    integrator, q, _scene = _loaded_state("quasi_newton", 3.0e4)
    integrator.tolerance = 1e-9
    integrator.solve(q, 50)
    integrator.potential(q)
    free = integrator.free_index
    assert np.abs(integrator.grad.reshape(-1)[free]).max() <= 1e-9
    taken = integrator.substep_iterations
    assert 1 < taken < 50
    assert integrator.iteration_summary() == {"substeps": 1, "mean": taken, "max": taken}
    capped, q_capped, _ = _loaded_state("quasi_newton", 3.0e4)
    capped.tolerance = 1e-9
    capped.solve(q_capped, 1, converge=False)  # a first sweep's solve stopped by the cap is left unconverged
    assert capped.substep_iterations == 1 and capped.unconverged
    loose, q_loose, _ = _loaded_state("quasi_newton", 3.0e4)
    loose.tolerance = 1e3  # above every force: the first step is still taken, and only it
    loose.solve(q_loose, 50)
    assert loose.substep_iterations == 1


def test_solver_options_are_validated_naming_the_field():
    with pytest.raises(ValueError, match="tissue_tolerance"):
        Solver(tissue_tolerance=-1e-6)
    with pytest.raises(ValueError, match="tissue_tolerance"):
        Solver(tissue_tolerance=True)
    with pytest.raises(ValueError, match="tissue_scheme"):
        Solver(tissue_scheme="midpoint")
    with pytest.raises(ValueError, match="tissue_scheme"):
        QuasiNewton(suturing_pad(cells=(2, 2, 1), material=TissueMaterial(1.0e4, 0.45)).model.tissue, 1e-3, "rk4")


@pytest.mark.parametrize("tolerance", [0.0, 1e-7])
def test_bdf2_keeps_a_stiff_pad_at_rest(tolerance):  # no coupling rows: every substep is BDF2
    scene = suturing_pad(size=(0.008, 0.008, 0.008), cells=(4, 4, 4), material=TissueMaterial(1.0e6, 0.45))
    solver = Solver(iterations=1, max_speed=50.0, tissue_scheme="bdf2", tissue_tolerance=tolerance)
    for _ in range(100):
        solver.step(scene.model, scene.state, Control(), 1e-3)
    assert not scene.state.diverged
    assert np.abs(scene.state.tissue.particle_qd).max() < 1e-6


def _released_beam_energy(scheme: str, steps: int) -> tuple[float, float]:
    """(energy at release, energy after ``steps`` 1 ms substeps) of an undamped 300 kPa cantilever released from its
    static deflection scaled to a 0.2 mm tip deflection."""
    from suture_gym.sim.scenes import cantilever

    material = TissueMaterial(3.0e5, 0.45, damping=0.0)
    scene = cantilever(0.02, 0.004, 0.004, (10, 2, 2), material, gravity=0.0)
    tissue = scene.model.tissue
    free = np.flatnonzero(np.repeat(tissue.particle_inv_mass > 0, 3))
    shape = np.zeros(3 * tissue.particle_count)  # the static deflection under a tip-down body load (linear FE)
    load = np.repeat(tissue.particle_mass, 3) * np.tile([0.0, 0.0, -1.0], tissue.particle_count)
    shape[free] = scipy.sparse.linalg.spsolve(stiffness_matrix(tissue).tocsc()[free][:, free], load[free])
    shape = shape.reshape(-1, 3)
    scene.state.tissue.particle_q += shape * (2e-4 / np.abs(shape).max())
    scene.state.tissue.particle_q_prev[...] = scene.state.tissue.particle_q
    solver = Solver(iterations=1, max_speed=50.0, tissue_scheme=scheme)

    def energy() -> float:
        q, v = scene.state.tissue.particle_q, scene.state.tissue.particle_qd
        grad = np.zeros_like(q)
        elastic = incremental_potential(
            q, q, np.zeros(tissue.particle_count), np.ones(q.shape), 0.0, tissue.tet_indices, tissue.tet_dm_inv,
            tissue.tet_rest_volume, tissue.tet_mu, tissue.tet_lambda, np.arange(tissue.tet_count, dtype=np.int32),
            np.zeros_like(q), grad,
        )  # fmt: skip
        return elastic + 0.5 * float(np.sum(tissue.particle_mass[:, None] * v * v))

    start = energy()
    for _ in range(steps):
        solver.step(scene.model, scene.state, Control(), 1e-3)
    return start, energy()


def test_bdf2_loses_far_less_energy_than_implicit_euler_on_a_free_beam():
    start, euler = _released_beam_energy("euler", 300)
    same, bdf2 = _released_beam_energy("bdf2", 300)
    assert same == start
    assert euler < 1e-3 * start  # implicit Euler's numerical damping (omega h about 0.18)
    assert 0.6 * start < bdf2 < 1.001 * start  # measured: 0.69


def test_bdf2_material_damping_decays_a_free_body_at_its_rate():
    pad = suturing_pad(size=(0.004, 0.004, 0.004), cells=(1, 1, 1), material=TissueMaterial(1.0e4, 0.45, damping=20.0))
    tissue = replace(pad.model.tissue, particle_inv_mass=1.0 / pad.model.tissue.particle_mass)  # nothing pinned
    model = replace(pad.model, tissue=tissue, gravity=np.zeros(3))
    state = State(tissue=TissueState.at_rest(tissue))
    state.tissue.particle_qd[:, 0] = 0.1
    solver, speeds = Solver(iterations=1, max_speed=50.0, tissue_scheme="bdf2"), []
    for _ in range(2):
        for _ in range(50):
            solver.step(model, state, Control(), 1e-3)
        speeds.append(state.tissue.particle_qd[:, 0].copy())
    # the first substep starts from a constant-velocity history (its decay is short by c h / 3); after it, BDF2's
    assert speeds[1] / speeds[0] == pytest.approx(np.exp(-20.0 * 0.05), rel=1e-3)
    np.testing.assert_allclose(state.tissue.particle_qd[:, 1:], 0.0, atol=1e-12)
