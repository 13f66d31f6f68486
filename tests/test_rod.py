"""Cosserat suture rod: constraint maths (finite differences), the direct block solve against dense algebra,
inextensibility, two-way needle attachment, contacts, determinism and bad input."""

import math

import numpy as np
import pytest

from suture_gym.sim.model import Control, Model, State
from suture_gym.sim.needle import NeedleModel, NeedleState, needle_point_world
from suture_gym.sim.quat import quat_from_axis_angle, quat_from_rotation_vector, quat_mul, quat_to_matrix
from suture_gym.sim.rod import (
    RodModel,
    RodState,
    RodWork,
    StaticObstacles,
    SutureMaterial,
    SutureParams,
    rod_detect_contacts,
    rod_predict,
    rod_solve_iteration,
    segment_strain,
)
from suture_gym.sim.rod_linalg import BLOCK, COUPLING_PATTERN, solve_block_tridiagonal
from suture_gym.sim.rod_solver import (
    align_frames,
    assemble_rod_system,
    bend_twist_constraint,
    bend_twist_jacobian,
    stretch_shear_constraint,
    stretch_shear_jacobian,
)
from suture_gym.sim.solver import Solver

RNG = np.random.default_rng(3)
G = (0.0, 0.0, -9.81)
SOLVER = Solver(iterations=1, max_speed=50.0, tissue_integrator="xpbd")  # rod_iterations 8, rod_tolerance 1e-6


def step_solver(model, rod_state, steps, needle_state=None, suture_force=None, dt=1e-3):
    """``steps`` substeps of ``model`` through Solver.step; ``rod_state`` (and ``needle_state``) advance in place."""
    state = State.initial(model, needle=needle_state, suture=rod_state)
    control = Control(suture_force=suture_force)
    for _ in range(steps):
        SOLVER.step(model, state, control, dt)
    return state


def turned(q, theta):
    return quat_mul(quat_from_rotation_vector(theta), q)


def random_quat():
    q = RNG.normal(size=4)
    return q / np.linalg.norm(q)


# ---------------------------------------------------------------------------------------------------------
# Constraint maths
# ---------------------------------------------------------------------------------------------------------


def test_stretch_shear_value_and_gradient():
    for _ in range(10):
        q = random_quat()
        x0, x1, l = RNG.normal(size=3), RNG.normal(size=3), 0.7
        c = stretch_shear_constraint(x0, x1, q, l)
        np.testing.assert_allclose(c, (x1 - x0) / l - quat_to_matrix(q)[:, 2], atol=1e-15)
        jac = stretch_shear_jacobian(q)
        h = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            fd = stretch_shear_constraint(x0, x1, turned(q, e), l) - stretch_shear_constraint(x0, x1, turned(q, -e), l)
            np.testing.assert_allclose(fd / (2 * h), jac[:, k], atol=1e-9)
            fdx = (stretch_shear_constraint(x0, x1 + e, q, l) - stretch_shear_constraint(x0, x1 - e, q, l)) / (2 * h)
            np.testing.assert_allclose(fdx, np.eye(3)[k] / l, atol=1e-9)


def test_bend_twist_value_and_gradient():
    for _ in range(10):
        q0 = random_quat()
        q1 = turned(q0, RNG.normal(size=3) * 0.5)
        c = bend_twist_constraint(q0, q1)
        # small relative turn theta in q0's frame: C ~ theta / 2
        theta_body = np.array([0.01, -0.02, 0.005])
        c_small = bend_twist_constraint(q0, quat_mul(q0, quat_from_rotation_vector(theta_body)))
        np.testing.assert_allclose(c_small, theta_body / 2, atol=1e-6)
        jac = bend_twist_jacobian(q0, q1)
        h = 1e-6
        for k in range(3):
            e = np.zeros(3)
            e[k] = h
            fd1 = (bend_twist_constraint(q0, turned(q1, e)) - bend_twist_constraint(q0, turned(q1, -e))) / (2 * h)
            fd0 = (bend_twist_constraint(turned(q0, e), q1) - bend_twist_constraint(turned(q0, -e), q1)) / (2 * h)
            np.testing.assert_allclose(fd1, jac[:, k], atol=1e-9)
            np.testing.assert_allclose(fd0, -jac[:, k], atol=1e-9)
        # the sign convention makes q1 and -q1 (the same rotation) give the same constraint
        np.testing.assert_allclose(bend_twist_constraint(q0, -q1), c, atol=1e-15)


def test_rest_state_has_zero_constraints_and_does_not_move():
    model = RodModel.from_params(SutureParams(node_count=12, length=0.02), pinned_nodes=[0])
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 2.0, -0.5])
    for j in range(model.node_count - 1):
        np.testing.assert_allclose(
            stretch_shear_constraint(state.node_pos[j], state.node_pos[j + 1], state.seg_quat[j], 0.02 / 11),
            0.0,
            atol=1e-14,
        )
    for j in range(model.node_count - 2):
        np.testing.assert_allclose(bend_twist_constraint(state.seg_quat[j], state.seg_quat[j + 1]), 0.0, atol=0.0)
    before = state.copy()
    work = RodWork(model)
    work.begin(state)
    residual = rod_solve_iteration(model, state, work, 1e-3)
    assert residual < 1e-14
    np.testing.assert_allclose(state.node_pos, before.node_pos, atol=1e-16)
    np.testing.assert_allclose(np.abs(state.seg_quat), np.abs(before.seg_quat), atol=1e-15)


def test_align_frames_puts_d3_on_the_edges_and_keeps_twist():
    model = RodModel.from_params(SutureParams(node_count=6, length=0.01))
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    state.node_pos += RNG.normal(size=state.node_pos.shape) * 5e-4
    d1_before = np.array([quat_to_matrix(q)[:, 0] for q in state.seg_quat])
    align_frames(state.node_pos, model.seg_inv_inertia, state.seg_quat)
    for j in range(5):
        edge = state.node_pos[j + 1] - state.node_pos[j]
        r = quat_to_matrix(state.seg_quat[j])
        np.testing.assert_allclose(r[:, 2], edge / np.linalg.norm(edge), atol=1e-14)
        # minimal rotation: d1 only leaves the plane it must (no spin about d3)
        assert r[:, 0] @ d1_before[j] > 0.5


# ---------------------------------------------------------------------------------------------------------
# Direct solve
# ---------------------------------------------------------------------------------------------------------


def block_tridiagonal_system(nb, null_row=None):
    """A random symmetric positive definite block-tridiagonal system whose coupling blocks fill the rod's pattern,
    as ``(dense, diag, lower)``; with ``null_row`` (a dense row index) that row and column are zeroed."""
    k = BLOCK
    dense = np.zeros((nb * k, nb * k))
    for b in range(nb):
        m = RNG.normal(size=(k, k))
        dense[b * k : (b + 1) * k, b * k : (b + 1) * k] = m @ m.T + 3.0 * k * np.eye(k)
        if b:
            low = RNG.normal(size=(k, k)) * COUPLING_PATTERN
            dense[b * k : (b + 1) * k, (b - 1) * k : b * k] = low
            dense[(b - 1) * k : b * k, b * k : (b + 1) * k] = low.T
    assert np.all(np.linalg.eigvalsh(dense) > 0.0)
    if null_row is not None:
        dense[null_row, :] = 0.0
        dense[:, null_row] = 0.0
    diag = np.array([dense[b * k : (b + 1) * k, b * k : (b + 1) * k] for b in range(nb)])
    lower = np.zeros_like(diag)
    for b in range(1, nb):
        lower[b] = dense[b * k : (b + 1) * k, (b - 1) * k : b * k]
    return dense, diag, lower


def test_block_tridiagonal_solve_matches_dense():
    dense, diag, lower = block_tridiagonal_system(9)
    rhs = RNG.normal(size=(9, BLOCK))
    z = np.zeros_like(rhs)
    solve_block_tridiagonal(diag, lower, rhs, np.zeros_like(diag), np.zeros_like(rhs), z)
    np.testing.assert_allclose(z.ravel(), np.linalg.solve(dense, rhs.ravel()), rtol=1e-11, atol=1e-14)


def test_block_tridiagonal_solve_drops_a_null_row():
    """A row with a zero diagonal and no coupling (a redundant or fully pinned constraint, or an unused row) gets
    no multiplier, whatever its right-hand side, and the other rows solve the system without it."""
    nb, null = 4, (2, 4)
    row = null[0] * BLOCK + null[1]
    dense, diag, lower = block_tridiagonal_system(nb, row)
    rhs = RNG.normal(size=(nb, BLOCK))
    z = np.zeros_like(rhs)
    solve_block_tridiagonal(diag, lower, rhs, np.zeros_like(diag), np.zeros_like(rhs), z)
    keep = [i for i in range(nb * BLOCK) if i != row]
    expected = np.linalg.solve(dense[np.ix_(keep, keep)], rhs.ravel()[keep])
    assert z[null] == 0.0
    np.testing.assert_allclose(z.ravel()[keep], expected, rtol=1e-10, atol=1e-14)


@pytest.mark.parametrize("anisotropic", [False, True])
def test_assembled_system_matches_dense_finite_difference_jacobians(anisotropic):
    """``diag/lower`` = ``J W J^T + alpha~`` and ``rhs = -C - alpha~ lambda + J h``, with J from finite
    differences of the constraint functions (attachment, stretch-shear, bend-twist, contacts); with
    ``anisotropic`` the nodes' inverse masses are ``w I + a t t^T`` matrices (nodes held across a path)."""
    n, dt = 6, 1e-3
    model = RodModel.from_params(SutureParams(node_count=n, length=0.01, inextensible=False))
    needle = NeedleModel.from_shape()
    ns = NeedleState.at_rest([0.0, 0.0, 0.01], quat_from_axis_angle(np.array([1.0, 2.0, 3.0]), 0.6))
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    state.node_pos += RNG.normal(size=state.node_pos.shape) * 1e-5
    for j in range(n - 1):
        state.seg_quat[j] = turned(state.seg_quat[j], RNG.normal(size=3) * 0.05)
    work = RodWork(model)
    work.begin(state)
    work.lam[:, :] = RNG.normal(size=work.lam.shape) * 1e-16
    work.lam[:, 6] = 0.0
    work.lam[1, 6] = 1e-16  # node 1 already pushes: active although separated
    work.contact_gap[:] = np.array([-1.0, 2.0, -0.5, 1.0, -2.0, 3.0])[:n] * 1e-5
    normals = RNG.normal(size=(n, 3))
    work.contact_normal[:] = normals / np.linalg.norm(normals, axis=1, keepdims=True)
    align_frames(state.node_pos, model.seg_inv_inertia, state.seg_quat)
    node_w = model.node_inv_mass.copy()
    axis_w = np.zeros(n)
    axis = np.zeros((n, 3))
    if anisotropic:  # heavy across a random axis, light along it, as embedded_inv_mass makes them
        node_w[1:] *= 1e-3
        axis_w[1:] = model.node_inv_mass[1:] - node_w[1:]
        axis[1:] = RNG.normal(size=(n - 1, 3))
        axis[1:] /= np.linalg.norm(axis[1:], axis=1, keepdims=True)
    rod = (
        node_w, model.seg_rest_length, model.seg_inv_inertia, model.seg_stretch_compliance,
        model.bend_compliance, work.contact_obstacle_w, axis_w, axis,
    )  # fmt: skip
    needle_group = (True, needle.body_inv_mass, needle.body_inv_inertia, needle.swage_pos_body)

    def assemble(tolerance, check_first):
        return assemble_rod_system(
            state.node_pos, state.seg_quat, rod, needle_group, work.start, work.frames, work.contacts, work.system,
            work.lam, ns.body_pos, ns.body_quat, dt, tolerance, check_first,
        )  # fmt: skip

    # checked first, the residual is the built system's; within the tolerance the system is not touched
    residual = assemble(0.0, False)
    built = [a.copy() for a in (work.diag, work.lower, work.rhs)]
    assert residual > 0.0
    for a in (work.diag, work.lower, work.rhs):
        a[:] = np.nan
    assert assemble(residual, True) == residual
    assert np.isnan(work.diag).all() and np.isnan(work.lower).all() and np.isnan(work.rhs).all()
    assert assemble(np.nextafter(residual, 0.0), True) == residual
    for a, b in zip((work.diag, work.lower, work.rhs), built, strict=True):
        np.testing.assert_array_equal(a, b)
    k = BLOCK
    ndof = 3 * n + 3 * (n - 1) + 6

    def constraints(d):
        x = state.node_pos + d[: 3 * n].reshape(n, 3)
        th = d[3 * n : 3 * n + 3 * (n - 1)].reshape(n - 1, 3)
        q = [turned(state.seg_quat[j], th[j]) for j in range(n - 1)]
        pn, qn = ns.body_pos + d[-6:-3], turned(ns.body_quat, d[-3:])
        out = np.zeros((n, k))
        out[0, :3] = x[0] - pn - quat_to_matrix(qn) @ needle.swage_pos_body
        for j in range(n - 1):
            out[j + 1, :3] = stretch_shear_constraint(x[j], x[j + 1], q[j], model.seg_rest_length[j])
            if j < n - 2:
                out[j + 1, 3:6] = bend_twist_constraint(q[j], q[j + 1])
        for i in range(n):
            out[i, 6] = work.contact_gap[i] + work.contact_normal[i] @ (x[i] - state.node_pos[i])
        return out.ravel()

    jac = np.zeros((n * k, ndof))
    h = 1e-7
    for c in range(ndof):
        e = np.zeros(ndof)
        e[c] = h
        jac[:, c] = (constraints(e) - constraints(-e)) / (2 * h)
    winv = np.zeros((ndof, ndof))
    for i in range(n):
        winv[3 * i : 3 * i + 3, 3 * i : 3 * i + 3] = np.eye(3) * node_w[i] + axis_w[i] * np.outer(axis[i], axis[i])
    for j in range(n - 1):
        o = 3 * n + 3 * j
        winv[o : o + 3, o : o + 3] = work.seg_winv[j]
    winv[-6:-3, -6:-3] = np.eye(3) * needle.body_inv_mass
    winv[-3:, -3:] = work.att_winv
    a_ref = jac @ winv @ jac.T
    alpha_lam = np.zeros((n, k))
    for j in range(n - 1):
        b = j + 1
        r = quat_to_matrix(state.seg_quat[j])
        alpha_ss = r @ np.diag(model.seg_stretch_compliance[j]) @ r.T / dt**2
        a_ref[b * k : b * k + 3, b * k : b * k + 3] += alpha_ss
        alpha_lam[b, :3] = alpha_ss @ work.lam[b, :3]
        if j < n - 2:
            a_ref[b * k + 3 : b * k + 6, b * k + 3 : b * k + 6] += np.diag(model.bend_compliance[j]) / dt**2
            alpha_lam[b, 3:6] = model.bend_compliance[j] / dt**2 * work.lam[b, 3:6]
    hvec = np.zeros(ndof)
    hvec[3 * n : 3 * n + 3 * (n - 1)] = work.seg_h.ravel()
    rhs_ref = (-constraints(np.zeros(ndof)).reshape(n, k) - alpha_lam).ravel() + jac @ hvec

    assembled = np.zeros((n * k, n * k))
    for b in range(n):
        assembled[b * k : (b + 1) * k, b * k : (b + 1) * k] = work.diag[b]
        if b:
            assembled[b * k : (b + 1) * k, (b - 1) * k : b * k] = work.lower[b]
            assembled[(b - 1) * k : b * k, b * k : (b + 1) * k] = work.lower[b].T
    used = np.ones(n * k, dtype=bool)
    used[3:6] = False  # unused rows of block 0
    used[(n - 1) * k + 3 : (n - 1) * k + 6] = False  # no bend-twist after the last segment
    used[6::k] = work.contact_active
    np.testing.assert_array_equal(work.contact_active, [True, True, True, False, True, False])
    scale = np.sqrt(np.abs(np.diag(a_ref)))[used]
    err = np.abs(assembled[np.ix_(used, used)] - a_ref[np.ix_(used, used)]) / np.outer(scale, scale)
    assert err.max() < 1e-6
    np.testing.assert_allclose(work.rhs.ravel()[used], rhs_ref[used], atol=1e-9 * np.abs(rhs_ref).max())
    unused = ~used
    np.testing.assert_array_equal(work.rhs.ravel()[unused], 0.0)
    # the block solve skips the coupling entries outside the pattern: the assembly must leave them zero
    np.testing.assert_array_equal(work.lower[1:, ~COUPLING_PATTERN], 0.0)
    assert work.lower[1:, COUPLING_PATTERN].any(axis=0).sum() > 20  # the pattern is used, not just allowed


# ---------------------------------------------------------------------------------------------------------
# Behaviour
# ---------------------------------------------------------------------------------------------------------


def small_rod(**kwargs):
    params = SutureParams(node_count=30, length=0.03, **kwargs)
    return RodModel.from_params(params, pinned_nodes=[0])


def test_mass_and_compliance_from_the_material():
    params = SutureParams(node_count=11, length=0.1, radius=2e-4, material=SutureMaterial(3e9, 0.25, 1000.0))
    model = RodModel.from_params(params)
    area = math.pi * 2e-4**2
    assert model.node_mass.sum() == pytest.approx(1000.0 * area * 0.1, rel=1e-14)
    ei = 3e9 * math.pi * 2e-4**4 / 4
    gj = 3e9 / 2.5 * math.pi * 2e-4**4 / 2
    np.testing.assert_allclose(model.bend_compliance[0], [0.01 / (4 * ei), 0.01 / (4 * ei), 0.01 / (4 * gj)])
    np.testing.assert_array_equal(model.seg_stretch_compliance, 0.0)
    soft = RodModel.from_params(replace_params(params, inextensible=False))
    np.testing.assert_allclose(soft.seg_stretch_compliance[0, 2], 1.0 / (3e9 * area * 0.01))


def replace_params(params, **kwargs):
    from dataclasses import replace

    return replace(params, **kwargs)


def test_pulled_rod_stays_inextensible_and_still():
    model = small_rod()
    state = RodState.straight(model, [0.0, 0.0, 0.1], [0.0, 0.0, -1.0])
    force = np.zeros((model.node_count, 3))
    force[-1] = [0.0, 0.0, -1.0]
    full = step_solver(Model(suture=model, gravity=G), state, 200, suture_force=force)
    assert np.abs(segment_strain(model, state)).max() < 1e-9
    assert np.abs(state.node_vel).max() < 1e-8
    assert 1 <= full.work.rod_solves <= 2  # at rest one or two direct solves converge


@pytest.mark.parametrize("free_axis", [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0)])
def test_anisotropic_node_takes_the_correction_along_its_free_axis(free_axis):
    """A 2-node inextensible rod along x stretched by 1e-4 m: node 1 is 1e4 times heavier than node 0 except
    along ``free_axis``, where it has node 0's mass. Along x it shares the correction equally with node 0;
    across (free axis y) node 0 takes it all. The momentum the step exchanges is zero either way."""
    model = RodModel.from_params(SutureParams(node_count=2, length=0.01))
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    state.node_pos[1, 0] += 1e-4
    work = RodWork(model)
    work.begin(state)
    w = model.node_inv_mass[0]
    node_w = np.array([w, w * 1e-4])
    axis_inv_mass = np.array([0.0, w - w * 1e-4])
    axis = np.array([[0.0, 0.0, 0.0], free_axis])
    start = state.node_pos.copy()
    for _ in range(3):
        rod_solve_iteration(model, state, work, 1e-3, node_inv_mass=node_w, axis_inv_mass=axis_inv_mass, axis=axis)
    moved = state.node_pos - start
    assert np.linalg.norm(state.node_pos[1] - state.node_pos[0]) == pytest.approx(0.01, abs=1e-12)
    share = 0.5 if free_axis[0] else 1.0 / (1.0 + 1e-4)
    assert moved[0, 0] == pytest.approx(1e-4 * share, rel=1e-6)
    assert moved[1, 0] == pytest.approx(-1e-4 * (1.0 - share), rel=1e-4, abs=1e-15)
    w1 = np.eye(3) * node_w[1] + axis_inv_mass[1] * np.outer(axis[1], axis[1])
    impulse = moved[0] / w + np.linalg.solve(w1, moved[1])
    np.testing.assert_allclose(impulse, 0.0, atol=1e-9 * np.abs(moved[0] / w).max())


@pytest.mark.parametrize("cap_factor", [1.5, 0.5])
def test_friction_row_sticks_below_its_cap_and_slides_at_it(cap_factor):
    """A 3-node inextensible rod along x, node 2 displaced by 1e-4 m along x (a pull), node 1 with a friction
    row along x (``contact_cap > 0``: ``C = slip = 0`` while the multiplier stays within the cap). With a cap
    above the multiplier that holding node 1 takes, node 1 sticks and nodes 0 and 2 alone restore the lengths;
    with a smaller cap the row's multiplier ends at the cap exactly and node 1 slides."""
    model = RodModel.from_params(SutureParams(node_count=3, length=0.002))
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    state.node_pos[2, 0] += 1e-4
    start = state.node_pos.copy()
    work = RodWork(model)
    work.begin(state)
    w = model.node_inv_mass
    # holding node 1 still takes the impulse that moves node 2 back by the whole stretch: 1e-4 / w[2] (kg m)
    hold = 1e-4 / w[2]
    work.contact_normal[1] = [1.0, 0.0, 0.0]
    work.contact_cap[1] = cap_factor * hold
    for _ in range(8):
        work.contact_gap[1] = state.node_pos[1, 0] - start[1, 0]  # slip since the start
        rod_solve_iteration(model, state, work, 1e-3)
    lengths = np.linalg.norm(np.diff(state.node_pos, axis=0), axis=1)
    np.testing.assert_allclose(lengths, 0.001, atol=1e-12)
    if cap_factor > 1.0:
        assert abs(state.node_pos[1, 0] - start[1, 0]) < 1e-12
        assert abs(work.lam[1, 6]) < work.contact_cap[1]
    else:
        assert state.node_pos[1, 0] - start[1, 0] > 1e-6
        assert abs(work.lam[1, 6]) == pytest.approx(work.contact_cap[1], rel=1e-9)
    np.testing.assert_array_equal(work.contact_push[1], 0.0)  # a friction row is not a contact's push


def test_compliant_stretch_matches_hooke():
    """With ``inextensible=False`` a hanging 1 N load stretches each segment by T / (E A)."""
    model = small_rod(inextensible=False, damping=50.0)
    state = RodState.straight(model, [0.0, 0.0, 0.1], [0.0, 0.0, -1.0])
    force = np.zeros((model.node_count, 3))
    force[-1] = [0.0, 0.0, -1.0]
    step_solver(Model(suture=model, gravity=(0.0, 0.0, 0.0)), state, 400, suture_force=force)
    ea = model.params.material.youngs_modulus * math.pi * model.radius**2
    np.testing.assert_allclose(segment_strain(model, state), 1.0 / ea, rtol=1e-4)


@pytest.mark.parametrize("sweeps", [1, 2, 4])
def test_compliant_stretch_does_not_depend_on_the_sweeps(sweeps):
    """An extensible thread pulled with 2 N keeps the strain T / (E A) whatever the solver's sweeps per substep:
    its multipliers accumulate over all the sweeps of a substep."""
    model = small_rod(inextensible=False, damping=20.0)
    system = Model(suture=model, gravity=(0.0, 0.0, 0.0))
    state = State.initial(system, suture=RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0]))
    force = np.zeros((model.node_count, 3))
    force[-1] = [2.0, 0.0, 0.0]
    control = Control(suture_force=force)
    solver = Solver(iterations=sweeps, max_speed=1.0e3, tissue_integrator="xpbd")
    for _ in range(100):
        solver.step(system, state, control, 1e-3)
    assert not state.diverged
    ea = model.params.material.youngs_modulus * math.pi * model.radius**2
    np.testing.assert_allclose(segment_strain(model, state.suture), 2.0 / ea, rtol=0.02)


def test_needle_attachment_is_two_way_and_conserves_momentum():
    model = RodModel.from_params(SutureParams(node_count=25, length=0.025, damping=0.0))
    needle = NeedleModel.from_shape()
    ns = NeedleState.at_rest([0.0, 0.0, 0.0], quat_from_axis_angle(np.array([0.0, 0.0, 1.0]), 0.3))
    swage = needle_point_world(needle, ns, needle.swage_pos_body)
    state = RodState.straight(model, swage, [1.0, 0.5, 0.0])
    state.node_vel[:] = RNG.normal(size=state.node_vel.shape) * 0.05
    ns.body_vel[:] = [0.0, 0.02, -0.01]

    def momentum():
        return needle.body_mass * ns.body_vel + model.node_mass @ state.node_vel

    p0 = momentum()
    step_solver(Model(needle=needle, suture=model, gravity=(0.0, 0.0, 0.0)), state, 100, needle_state=ns)
    np.testing.assert_allclose(momentum(), p0, atol=1e-12 * needle.body_mass)
    gap = state.node_pos[0] - needle_point_world(needle, ns, needle.swage_pos_body)
    assert np.linalg.norm(gap) < 1e-12
    # the thread's weight pulls a free needle down: the attachment acts on the needle
    ns2 = NeedleState.at_rest([0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    held = NeedleModel.from_shape(gravity_compensation=True)
    state2 = RodState.straight(model, needle_point_world(held, ns2, held.swage_pos_body), [0.0, 0.0, -1.0])
    step_solver(Model(needle=held, suture=model, gravity=G), state2, 1, needle_state=ns2)
    assert ns2.body_vel[2] < 0.0


def test_ground_contact_holds_the_thread_without_pulling():
    model = RodModel.from_params(SutureParams(node_count=30, length=0.03, damping=0.0))
    ground = StaticObstacles.ground(0.0)
    state = RodState.straight(model, [0.0, 0.0, 0.004], [1.0, 0.0, 0.2])  # tilted: one end lands first
    grounded = Model(suture=model, gravity=G, obstacles=ground)
    full = State.initial(grounded, suture=state)
    for _ in range(300):
        SOLVER.step(grounded, full, Control(), 1e-3)
        work = full.work.rod_work
        assert state.node_pos[:, 2].min() > model.radius - 1e-12
        assert work.lam[:, 6].min() >= 0.0
        assert np.abs(segment_strain(model, state)).max() < 1e-6
    assert work.contact_active.all()  # it lies flat on the floor
    np.testing.assert_allclose(state.node_pos[:, 2], model.radius, atol=1e-12)


def test_friction_decelerates_a_sliding_thread_at_mu_g():
    model = RodModel.from_params(SutureParams(node_count=30, length=0.03, damping=0.0))
    ground = StaticObstacles.ground(0.0, friction=0.5)
    state = RodState.straight(model, [0.0, 0.0, model.radius], [1.0, 0.0, 0.0])
    state.node_vel[:] = [0.2, 0.0, 0.0]
    steps = 20
    step_solver(Model(suture=model, gravity=G, obstacles=ground), state, steps)
    np.testing.assert_allclose(state.node_vel[:, 0], 0.2 - 0.5 * 9.81 * steps * 1e-3, rtol=1e-6)
    assert np.abs(state.node_pos[:, 2] - model.radius).max() < 1e-12


def test_sphere_obstacle_keeps_nodes_outside():
    model = small_rod()
    state = RodState.straight(model, [0.0, 0.0, 0.1], [1.0, 0.0, 0.0])
    ball = StaticObstacles(sphere_center=[[0.015, 0.0, 0.09]], sphere_radius=[0.006])
    step_solver(Model(suture=model, gravity=G, obstacles=ball), state, 300)
    dist = np.linalg.norm(state.node_pos - [0.015, 0.0, 0.09], axis=1)
    assert dist.min() > 0.006 + model.radius - 1e-10
    assert np.abs(segment_strain(model, state)).max() < 1e-9
    work = RodWork(model)
    rod_detect_contacts(model, state, work, ball)
    assert (work.contact_gap < 1e-9).any()  # it drapes over the ball


def test_clamped_segment_keeps_its_frame():
    model = RodModel.from_params(SutureParams(node_count=10, length=0.01), pinned_nodes=[0], clamped_segments=[0])
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    q0 = state.seg_quat[0].copy()
    step_solver(Model(suture=model, gravity=G), state, 50)
    np.testing.assert_array_equal(state.seg_quat[0], q0)
    assert state.node_pos[-1, 2] < 0.0  # it sags beyond the clamp


def test_deterministic():
    def run():
        model = small_rod()
        needle = NeedleModel.from_shape()
        ns = NeedleState.at_rest([0.0, 0.0, 0.05], [1.0, 0.0, 0.0, 0.0])
        state = RodState.straight(model, needle_point_world(needle, ns, needle.swage_pos_body), [0.3, 0.0, -1.0])
        full_model = Model(needle=needle, suture=model, gravity=G, obstacles=StaticObstacles.ground(0.04))
        full = State.initial(full_model, needle=ns, suture=state)
        for k in range(150):
            wrench = np.array([0.01 * np.sin(0.1 * k), 0.0, 0.0, 0.0, 0.0, 0.0])
            SOLVER.step(full_model, full, Control(needle_wrench=wrench), 1e-3)
        return state, ns

    (a, na), (b, nb) = run(), run()
    np.testing.assert_array_equal(a.node_pos, b.node_pos)
    np.testing.assert_array_equal(a.seg_quat, b.seg_quat)
    np.testing.assert_array_equal(na.body_pos, nb.body_pos)


def test_quaternions_stay_unit():
    model = small_rod()
    state = RodState.straight(model, [0.0, 0.0, 0.1], [1.0, 0.0, 0.0])
    step_solver(Model(suture=model, gravity=G), state, 200)
    np.testing.assert_allclose(np.linalg.norm(state.seg_quat, axis=1), 1.0, atol=1e-14)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"radius": 0.0}, "radius"),
        ({"radius": -1e-4}, "radius"),
        ({"radius": float("nan")}, "radius"),
        ({"length": 0.0}, "length"),
        ({"length": float("inf")}, "length"),
        ({"node_count": 1}, "node_count"),
        ({"node_count": 10.0}, "node_count"),
        ({"damping": -1.0}, "damping"),
    ],
)
def test_bad_params_raise_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        SutureParams(**kwargs)


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"youngs_modulus": 0.0}, "youngs_modulus"),
        ({"youngs_modulus": -2e9}, "youngs_modulus"),
        ({"youngs_modulus": float("nan")}, "youngs_modulus"),
        ({"poisson_ratio": 0.6}, "poisson_ratio"),
        ({"density": 0.0}, "density"),
    ],
)
def test_bad_material_raises_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        SutureMaterial(**kwargs)


def test_bad_solver_input_raises():
    model = small_rod()
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="suture_force"):
        Control(suture_force=np.full((model.node_count, 3), np.nan))
    with pytest.raises(ValueError, match="suture_force"):
        step_solver(Model(suture=model), state, 1, suture_force=np.zeros((model.node_count + 1, 3)))
    with pytest.raises(ValueError, match="dt"):
        rod_predict(model, state, 0.0, G)
    with pytest.raises(ValueError, match="need Model.suture"):
        Model(obstacles=StaticObstacles.ground(0.0))
    with pytest.raises(ValueError, match="pinned_nodes"):
        model.with_pins(pinned_nodes=[model.node_count])
    with pytest.raises(ValueError, match="direction"):
        RodState.straight(model, [0.0, 0.0, 0.0], [0.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="sphere_radius"):
        StaticObstacles(sphere_center=[[0.0, 0.0, 0.0]], sphere_radius=[-1.0])
