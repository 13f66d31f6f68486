"""Rigid needle: mass properties (vs a swept-tube mesh), wrench integration, rigid XPBD corrections,
virtual coupling, determinism and bad input."""

import math

import numpy as np
import pytest
import trimesh

from suture_gym.sim.needle import (
    ARC_PRESETS,
    NeedleModel,
    NeedleShape,
    NeedleState,
    VirtualCoupling,
    arc_wire_mass_properties,
    needle_apply_impulse,
    needle_constraint_wrench,
    needle_move_point,
    needle_node_positions,
    needle_point_inv_mass,
    needle_point_world,
    needle_predict,
    needle_update_velocities,
    wrench_at_com,
)
from suture_gym.sim.quat import quat_from_axis_angle, quat_to_matrix
from suture_gym.sim.rigid import apply_point_impulse, point_inv_mass, point_inv_mass_matrix, world_inv_inertia

ZERO_G = np.zeros(3)


def swept_tube(radius, wire, angle0, angle1, n_arc=720, n_ring=96):
    """Closed triangle mesh of a round wire along a circular arc (end caps included)."""
    phis = np.linspace(angle0, angle1, n_arc + 1)
    psis = np.linspace(0.0, 2.0 * np.pi, n_ring, endpoint=False)
    verts = []
    for phi in phis:
        radial = np.array([np.cos(phi), np.sin(phi), 0.0])
        for psi in psis:
            verts.append((radius + wire * np.cos(psi)) * radial + np.array([0.0, 0.0, wire * np.sin(psi)]))
    verts.append([radius * np.cos(angle0), radius * np.sin(angle0), 0.0])
    verts.append([radius * np.cos(angle1), radius * np.sin(angle1), 0.0])
    verts = np.array(verts)
    faces = []
    for i in range(n_arc):
        for j in range(n_ring):
            a, b = i * n_ring + j, i * n_ring + (j + 1) % n_ring
            c, d = a + n_ring, b + n_ring
            faces += [[a, b, d], [a, d, c]]
    c0, c1 = len(verts) - 2, len(verts) - 1
    for j in range(n_ring):
        faces.append([c0, (j + 1) % n_ring, j])
        faces.append([c1, n_arc * n_ring + j, n_arc * n_ring + (j + 1) % n_ring])
    mesh = trimesh.Trimesh(verts, np.array(faces), process=True)
    mesh.fix_normals()
    return mesh


@pytest.mark.parametrize("arc", ["3/8", "1/2", "5/8"])
def test_wire_mass_properties_match_a_swept_tube_mesh(arc):
    shape = NeedleShape(arc=arc, wire_radius=1.0e-3)  # thick wire so the cross-section terms matter
    mass, com, inertia = arc_wire_mass_properties(
        shape.curvature_radius, shape.wire_radius, shape.tip_angle, shape.swage_angle, shape.density
    )
    mesh = swept_tube(shape.curvature_radius, shape.wire_radius, shape.tip_angle, shape.swage_angle)
    assert mesh.is_watertight
    mesh.density = shape.density
    # the polygonal tube under-fills the round wire by (1 - sin(2 pi/n)/(2 pi/n)); compare to that tolerance
    assert mass == pytest.approx(mesh.mass, rel=2e-3)
    np.testing.assert_allclose(com, mesh.center_mass, atol=2e-3 * shape.curvature_radius)
    np.testing.assert_allclose(inertia, mesh.moment_inertia, atol=3e-3 * np.abs(inertia).max())


def test_full_torus_closed_form():
    R, a, rho = 0.01, 0.002, 7850.0
    mass, com, inertia = arc_wire_mass_properties(R, a, 0.0, 2.0 * np.pi, rho)
    m = rho * 2.0 * np.pi**2 * a * a * R
    assert mass == pytest.approx(m, rel=1e-14)
    np.testing.assert_allclose(com, 0.0, atol=1e-18)
    expected = np.diag([m * (R * R / 2 + 5 * a * a / 8), m * (R * R / 2 + 5 * a * a / 8), m * (R * R + 3 * a * a / 4)])
    np.testing.assert_allclose(inertia, expected, rtol=1e-13, atol=1e-20)


def test_model_composes_wire_and_holder_about_the_common_centre_of_mass():
    shape = NeedleShape(holder_mass=0.01, holder_inertia=2e-7)
    model = NeedleModel.from_shape(shape)
    wm, wc, wi = arc_wire_mass_properties(
        shape.curvature_radius, shape.wire_radius, shape.tip_angle, shape.swage_angle, shape.density
    )
    grip_shape = model.grip_pos_body - model.arc_center_body  # shape-frame position of the grip
    com = (wm * wc + shape.holder_mass * grip_shape) / (wm + shape.holder_mass)
    np.testing.assert_allclose(-model.arc_center_body, com, atol=1e-15)
    expected = wi + shape.holder_inertia * np.eye(3)
    for m, c in ((wm, wc), (shape.holder_mass, grip_shape)):
        d = c - com
        expected = expected + m * (d @ d * np.eye(3) - np.outer(d, d))
    np.testing.assert_allclose(model.body_inertia, expected, rtol=1e-12)
    np.testing.assert_allclose(model.body_inertia @ model.body_inv_inertia, np.eye(3), atol=1e-9)
    assert model.body_mass == pytest.approx(wm + shape.holder_mass)
    assert abs(model.body_inertia[0, 1]) > 1e-3 * model.body_inertia[0, 0]  # holder off the symmetry axis


def test_bare_needle_equals_the_wire():
    shape = NeedleShape(holder_mass=0.0, holder_inertia=0.0)
    model = NeedleModel.from_shape(shape)
    wm, _, wi = arc_wire_mass_properties(
        shape.curvature_radius, shape.wire_radius, shape.tip_angle, shape.swage_angle, shape.density
    )
    assert model.body_mass == pytest.approx(wm, rel=1e-15)
    np.testing.assert_allclose(model.body_inertia, wi, rtol=1e-13, atol=1e-25)


@pytest.mark.parametrize("arc", list(ARC_PRESETS) + [2.0])
def test_nodes_tip_swage_and_grip_lie_on_the_arc(arc):
    model = NeedleModel.from_shape(NeedleShape(arc=arc, node_count=12))
    shape = model.shape
    rel = model.node_pos_body - model.arc_center_body
    np.testing.assert_allclose(np.linalg.norm(rel, axis=1), shape.curvature_radius, rtol=1e-14)
    np.testing.assert_allclose(rel[:, 2], 0.0, atol=1e-18)
    tip, swage = rel[0], rel[-1]
    assert math.atan2(tip[1], tip[0]) == pytest.approx(shape.tip_angle)
    assert math.atan2(swage[1], swage[0]) % (2 * np.pi) == pytest.approx(shape.swage_angle % (2 * np.pi))
    chord = np.linalg.norm(rel[1:] - rel[:-1], axis=1)
    np.testing.assert_allclose(chord, chord[0], rtol=1e-12)  # evenly spaced
    grip = model.grip_pos_body - model.arc_center_body
    assert np.linalg.norm(grip) == pytest.approx(shape.curvature_radius, rel=1e-14)
    # the tip travels along the tangent pointing away from the swage
    assert model.tip_dir_body @ (rel[0] - rel[1]) > 0.0
    assert model.tip_dir_body @ tip == pytest.approx(0.0, abs=1e-18)


def test_half_circle_layout():
    model = NeedleModel.from_shape(NeedleShape(arc="1/2"))
    r = model.shape.curvature_radius
    np.testing.assert_allclose(model.tip_pos_body - model.arc_center_body, [r, 0.0, 0.0], atol=1e-17)
    np.testing.assert_allclose(model.swage_pos_body - model.arc_center_body, [-r, 0.0, 0.0], atol=1e-17)
    np.testing.assert_allclose(model.tip_dir_body, [0.0, -1.0, 0.0], atol=1e-16)


def tilted_state(model):
    return NeedleState.at_rest([0.01, -0.02, 0.05], quat_from_axis_angle(np.array([0.3, 1.0, -0.2]), 0.9))


def test_grip_wrench_is_moved_to_the_centre_of_mass():
    model = NeedleModel.from_shape()
    state = tilted_state(model)
    force = np.array([0.3, -0.1, 0.2])
    f, tau = wrench_at_com(model, state, np.concatenate([force, np.zeros(3)]))
    grip = needle_point_world(model, state, model.grip_pos_body)
    np.testing.assert_array_equal(f, force)
    np.testing.assert_allclose(tau, np.cross(grip - state.body_pos, force), rtol=1e-12)


def test_one_substep_from_rest_gives_newton_euler_accelerations():
    model = NeedleModel.from_shape()
    state = tilted_state(model)
    wrench = np.array([0.02, -0.01, 0.03, 1e-4, -2e-4, 5e-5])
    force, tau = wrench_at_com(model, state, wrench)
    r = quat_to_matrix(state.body_quat)
    alpha = np.linalg.solve(r @ model.body_inertia @ r.T, tau)
    dt = 1e-3
    needle_predict(model, state, wrench, dt, ZERO_G)
    np.testing.assert_allclose(state.body_vel, dt * force / model.body_mass, rtol=1e-14)
    np.testing.assert_allclose(state.body_omega, dt * alpha, rtol=1e-12)
    needle_update_velocities(state, dt)  # no constraints: velocities unchanged
    np.testing.assert_allclose(state.body_vel, dt * force / model.body_mass, rtol=1e-9)
    np.testing.assert_allclose(state.body_omega, dt * alpha, rtol=1e-9)


def test_gravity_compensation_and_damping():
    g = np.array([0.0, 0.0, -9.81])
    free = NeedleModel.from_shape()
    held = NeedleModel.from_shape(gravity_compensation=True)
    s_free, s_held = tilted_state(free), tilted_state(held)
    needle_predict(free, s_free, np.zeros(6), 1e-3, g)
    needle_predict(held, s_held, np.zeros(6), 1e-3, g)
    np.testing.assert_allclose(s_free.body_vel, 1e-3 * g)
    np.testing.assert_array_equal(s_held.body_vel, 0.0)
    damped = NeedleModel.from_shape(linear_damping=10.0, angular_damping=20.0)
    s = tilted_state(damped)
    s.body_vel[:] = [1.0, 0.0, 0.0]
    s.body_omega[:] = [0.0, 2.0, 0.0]
    needle_predict(damped, s, np.zeros(6), 1e-2, ZERO_G)
    np.testing.assert_allclose(s.body_vel, [1.0 / 1.1, 0.0, 0.0], rtol=1e-14)
    assert np.linalg.norm(s.body_omega) == pytest.approx(2.0 / 1.2, rel=1e-3)  # gyroscopic term rotates it slightly


def test_torque_free_spin_conserves_angular_momentum():
    model = NeedleModel.from_shape(NeedleShape(holder_inertia=0.0))
    state = tilted_state(model)
    state.body_omega[:] = [3.0, -1.0, 2.0]  # not a principal axis: the body precesses
    r = quat_to_matrix(state.body_quat)
    momentum0 = r @ model.body_inertia @ r.T @ state.body_omega
    for _ in range(2000):
        needle_predict(model, state, np.zeros(6), 1e-4, ZERO_G)
        needle_update_velocities(state, 1e-4)
    r = quat_to_matrix(state.body_quat)
    momentum = r @ model.body_inertia @ r.T @ state.body_omega
    assert np.linalg.norm(momentum - momentum0) < 1e-2 * np.linalg.norm(momentum0)
    assert np.linalg.norm(state.body_omega - [3.0, -1.0, 2.0]) > 0.1  # and it did precess


def test_generalised_inverse_mass_matches_the_finite_response():
    model = NeedleModel.from_shape()
    state = tilted_state(model)
    point = needle_point_world(model, state, model.tip_pos_body)
    iw = world_inv_inertia(state.body_quat, model.body_inv_inertia)
    r = point - state.body_pos
    k = point_inv_mass_matrix(model.body_inv_mass, iw, r)
    for n in np.eye(3):
        eps = 1e-9  # kg m
        pos, quat = apply_point_impulse(state.body_pos, state.body_quat, model.body_inv_mass, iw, r, eps * n)
        moved = pos + quat_to_matrix(quat) @ model.tip_pos_body - point
        w = needle_point_inv_mass(model, state, point, n)
        assert w == pytest.approx(point_inv_mass(model.body_inv_mass, iw, r, n))
        assert moved @ n / eps == pytest.approx(w, rel=1e-5)
        np.testing.assert_allclose(moved / eps, k @ n, rtol=1e-5, atol=1e-5 * w)


def test_move_point_moves_the_point_to_first_order_and_keeps_the_quaternion_unit():
    model = NeedleModel.from_shape()
    errors = []
    for scale in (1.0, 0.1):
        state = tilted_state(model)
        point = needle_point_world(model, state, model.tip_pos_body)
        dx = scale * np.array([2e-6, -1e-6, 3e-6])
        needle_move_point(model, state, point, dx)
        moved = needle_point_world(model, state, model.tip_pos_body) - point
        errors.append(np.linalg.norm(moved - dx))
        assert np.linalg.norm(moved - dx) < 1e-3 * np.linalg.norm(dx)
        assert np.linalg.norm(state.body_quat) == pytest.approx(1.0, abs=1e-15)
    assert errors[0] / errors[1] == pytest.approx(100.0, rel=0.05)  # the error is second order


def test_constraint_wrench_reports_the_projection_as_a_force():
    model = NeedleModel.from_shape()
    state = tilted_state(model)
    dt = 1e-3
    needle_predict(model, state, np.zeros(6), dt, ZERO_G)
    impulse = np.array([1e-8, 0.0, -2e-8])  # at the centre of mass: pure force
    needle_apply_impulse(model, state, state.body_pos.copy(), impulse)
    w = needle_constraint_wrench(model, state, dt)
    np.testing.assert_allclose(w[:3], impulse / dt**2, rtol=1e-9)
    grip = needle_point_world(model, state, model.grip_pos_body) - state.body_pos
    np.testing.assert_allclose(w[3:], -np.cross(grip, w[:3]), rtol=1e-6, atol=1e-12)


def test_node_positions_follow_the_pose():
    model = NeedleModel.from_shape()
    state = tilted_state(model)
    nodes = needle_node_positions(model, state)
    expected = state.body_pos + model.node_pos_body @ quat_to_matrix(state.body_quat).T
    np.testing.assert_allclose(nodes, expected, atol=1e-16)


@pytest.mark.parametrize("dt", [1e-3, 2e-3])
def test_virtual_coupling_brings_the_grip_to_the_target(dt):
    model = NeedleModel.from_shape()
    coupling = VirtualCoupling()
    state = NeedleState.from_grip_pose(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0])
    target = np.array([0.01, -0.005, 0.02])
    target_q = quat_from_axis_angle(np.array([0.0, 1.0, 1.0]), 0.5)
    np.testing.assert_allclose(coupling.wrench(model, state, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]), 0.0, atol=1e-18)
    for _ in range(int(0.3 / dt)):
        needle_predict(model, state, coupling.wrench(model, state, target, target_q), dt, ZERO_G)
        needle_update_velocities(state, dt)
    grip = needle_point_world(model, state, model.grip_pos_body)
    assert np.linalg.norm(grip - target) < 1e-3 * np.linalg.norm(target)
    assert min(np.abs(state.body_quat - target_q).max(), np.abs(state.body_quat + target_q).max()) < 1e-3


def test_deterministic():
    def run():
        model = NeedleModel.from_shape()
        state = tilted_state(model)
        coupling = VirtualCoupling()
        for k in range(200):
            target = np.array([0.01 * np.sin(0.05 * k), 0.0, 0.0])
            needle_predict(model, state, coupling.wrench(model, state, target, [1.0, 0, 0, 0]), 1e-3, [0, 0, -9.81])
            needle_update_velocities(state, 1e-3)
        return state

    a, b = run(), run()
    for f in ("body_pos", "body_quat", "body_vel", "body_omega"):
        np.testing.assert_array_equal(getattr(a, f), getattr(b, f))


@pytest.mark.parametrize(
    "kwargs, field",
    [
        ({"curvature_radius": 0.0}, "curvature_radius"),
        ({"curvature_radius": -1e-3}, "curvature_radius"),
        ({"curvature_radius": float("nan")}, "curvature_radius"),
        ({"wire_radius": 0.0}, "wire_radius"),
        ({"wire_radius": float("inf")}, "wire_radius"),
        ({"wire_radius": 0.01, "curvature_radius": 0.005}, "wire_radius"),
        ({"density": 0.0}, "density"),
        ({"density": -7850.0}, "density"),
        ({"holder_mass": -0.01}, "holder_mass"),
        ({"holder_mass": float("nan")}, "holder_mass"),
        ({"holder_inertia": -1e-6}, "holder_inertia"),
        ({"node_count": 1}, "node_count"),
        ({"node_count": 2.5}, "node_count"),
        ({"arc": "2/3"}, "arc"),
        ({"arc": 0.0}, "arc"),
        ({"arc": 7.0}, "arc"),
        ({"grip_fraction": 1.5}, "grip_fraction"),
    ],
)
def test_bad_shape_raises_naming_the_field(kwargs, field):
    with pytest.raises(ValueError, match=field):
        NeedleShape(**kwargs)


def test_bad_wrench_raises():
    model = NeedleModel.from_shape()
    state = tilted_state(model)
    with pytest.raises(ValueError, match="needle_wrench"):
        needle_predict(model, state, [0.0, np.nan, 0.0, 0.0, 0.0, 0.0], 1e-3, ZERO_G)
    with pytest.raises(ValueError, match="needle_wrench"):
        needle_predict(model, state, [0.0, 1.0, 0.0], 1e-3, ZERO_G)
    with pytest.raises(ValueError, match="dt"):
        needle_predict(model, state, np.zeros(6), 0.0, ZERO_G)
    with pytest.raises(ValueError, match="linear_damping"):
        NeedleModel.from_shape(linear_damping=-1.0)
