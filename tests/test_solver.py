"""Solver step, Model/State/Control, materials and scenes: validation, determinism, snapshots, divergence."""

import dataclasses
import math

import numpy as np
import pytest

from suture_gym.sim.mesh import box_tet_grid
from suture_gym.sim.model import Control, Model, State, TissueMaterial, TissueModel, TissueState
from suture_gym.sim.needle import NeedleModel, NeedleState
from suture_gym.sim.scenes import (
    PAPER_SOLVER,
    PAPER_TISSUE,
    cantilever,
    compression_block,
    hanging_bar,
    paper_cube,
    two_bar_wound,
)
from suture_gym.sim.solver import Solver

DT = 1e-3


def _small_scene(gravity=(0.0, 0.0, -9.81), damping=10.0, pin=True, nu=0.49):
    mesh = box_tet_grid((0.04, 0.02, 0.02), (4, 2, 2))
    pinned = mesh.vertices[:, 0] == 0.0 if pin else np.zeros(mesh.vertex_count, dtype=bool)
    tissue = TissueModel.from_mesh(mesh, TissueMaterial(damping=damping, poisson_ratio=nu, youngs_modulus=1.0e3),
                                   pinned=pinned)
    return Model(tissue=tissue, gravity=gravity), State(tissue=TissueState.at_rest(tissue))


def _run(model, state, steps, solver=None, dt=DT):
    solver = solver or PAPER_SOLVER
    control = Control()
    for _ in range(steps):
        solver.step(model, state, control, dt)


# --- validation -----------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("youngs_modulus", 0.0),
        ("youngs_modulus", -5.0),
        ("youngs_modulus", math.nan),
        ("poisson_ratio", -0.1),
        ("poisson_ratio", 0.51),
        ("poisson_ratio", math.inf),
        ("density", 0.0),
        ("density", math.nan),
        ("damping", -1.0),
        ("damping", math.inf),
        ("damping", "strong"),
    ],
)
def test_bad_material_field_is_named(field, value):
    with pytest.raises(ValueError, match=f"TissueMaterial.{field}"):
        TissueMaterial(**{field: value})


def test_material_moduli():
    m = TissueMaterial(youngs_modulus=1000.0, poisson_ratio=0.25)
    assert m.lame_mu == pytest.approx(400.0)
    assert m.lame_lambda == pytest.approx(400.0)
    assert m.hydrostatic_modulus == pytest.approx(800.0)
    incompressible = TissueMaterial(poisson_ratio=0.5, youngs_modulus=1.0e3)
    assert math.isinf(incompressible.lame_lambda) and math.isinf(incompressible.hydrostatic_modulus)


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"iterations": 0}, "iterations must be >= 1"),
        ({"iterations": 1.5}, "iterations must be an integer"),
        ({"iterations": True}, "iterations must be an integer"),
        ({"max_speed": 0.0}, "max_speed"),
        ({"max_speed": math.nan}, "max_speed"),
        ({"max_speed": math.inf}, "max_speed"),
    ],
)
def test_bad_solver_parameters_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Solver(**kwargs)


@pytest.mark.parametrize("dt", [0.0, -1e-3, math.nan, math.inf, "1ms", None])
def test_bad_dt_is_rejected(dt):
    model, state = _small_scene()
    with pytest.raises(ValueError, match="dt must be"):
        PAPER_SOLVER.step(model, state, Control(), dt)


def test_mismatched_state_and_bad_residual_buffer_are_rejected():
    model, _ = _small_scene()
    other_model, other_state = _small_scene()
    mesh = box_tet_grid((0.01, 0.01, 0.01), (1, 1, 1))
    small = TissueModel.from_mesh(mesh, PAPER_TISSUE)
    with pytest.raises(ValueError, match="does not match"):
        PAPER_SOLVER.step(model, State(tissue=TissueState.at_rest(small)), Control(), DT)
    with pytest.raises(ValueError, match="residuals"):
        Solver(iterations=3, max_speed=50.0, tissue_integrator="xpbd").step(other_model, other_state, Control(), DT,
                                                                            residuals=np.zeros(2))


def test_control_and_model_validation():
    with pytest.raises(ValueError, match="needle_wrench must have shape"):
        Control(needle_wrench=np.zeros(5))
    with pytest.raises(ValueError, match="needle_wrench must be finite"):
        Control(needle_wrench=[0, 0, np.nan, 0, 0, 0])
    with pytest.raises(ValueError, match="gravity"):
        Model(gravity=(0.0, np.inf, 0.0))
    with pytest.raises(ValueError, match="Model.tissue"):
        Model(tissue="tissue")


def test_from_mesh_validation_and_mixed_materials():
    mesh = box_tet_grid((0.02, 0.01, 0.01), (2, 1, 1))
    soft = TissueMaterial(youngs_modulus=1e3, poisson_ratio=0.49)
    stiff = TissueMaterial(youngs_modulus=4e3, damping=1.0, poisson_ratio=0.49)
    ids = (np.arange(mesh.tet_count) >= 5).astype(np.int64)
    model = TissueModel.from_mesh(mesh, [soft, stiff], tet_material=ids)
    assert np.allclose(model.tet_mu[:5], soft.lame_mu) and np.allclose(model.tet_mu[5:], stiff.lame_mu)
    assert np.all((model.particle_damping >= 1.0) & (model.particle_damping <= 10.0))
    assert np.any(model.particle_damping < 9.9) and np.any(np.isclose(model.particle_damping, 10.0))
    with pytest.raises(ValueError, match="tet_material"):
        TissueModel.from_mesh(mesh, [soft, stiff])
    with pytest.raises(ValueError, match=r"tet_material\[5\] = 2"):
        TissueModel.from_mesh(mesh, [soft, stiff], tet_material=ids * 2)
    with pytest.raises(ValueError, match="pinned"):
        TissueModel.from_mesh(mesh, soft, pinned=np.zeros(3, dtype=bool))
    with pytest.raises(ValueError, match="roller"):
        TissueModel.from_mesh(mesh, soft, rollers=([0], [[0.0, 0.0, 0.0]], [0.0]))
    with pytest.raises(ValueError):
        model.particle_inv_mass[0] = 1.0
    bad_index = np.array(model.tet_indices)
    bad_index[3, 2] = model.particle_count
    with pytest.raises(ValueError, match="TissueModel.tet_indices holds indices outside"):
        dataclasses.replace(model, tet_indices=bad_index)
    with pytest.raises(ValueError, match="TissueModel.tet_mu must have shape"):
        dataclasses.replace(model, tet_mu=np.ones(3))


# --- physics of the step ---------------------------------------------------------------------------------


@pytest.mark.parametrize("nu", [0.3, 0.49, 0.5])
def test_rest_state_stays_at_rest(nu):
    model, state = _small_scene(gravity=(0.0, 0.0, 0.0), nu=nu)
    _run(model, state, 20)
    assert np.abs(state.tissue.particle_q - model.tissue.particle_rest_q).max() <= 1e-15
    assert not state.diverged
    assert state.time == pytest.approx(20 * DT)


def test_free_body_falls_with_gravity_and_conserves_momentum():
    """Constraint corrections are mass weighted and sum to zero: the centre of mass falls like a point mass."""
    model, state = _small_scene(damping=0.0, pin=False)
    mass = model.tissue.particle_mass
    state.tissue.particle_q[:, 0] *= 1.1  # stretched: internal forces act during the fall
    com0 = (mass[:, None] * state.tissue.particle_q).sum(axis=0) / mass.sum()
    steps = 30
    _run(model, state, steps)
    com = (mass[:, None] * state.tissue.particle_q).sum(axis=0) / mass.sum()
    # Semi-implicit Euler from rest: z_n = z_0 - g dt^2 n (n + 1) / 2.
    expected = com0 + np.array([0.0, 0.0, -9.81 * DT**2 * steps * (steps + 1) / 2])
    assert np.allclose(com, expected, rtol=0, atol=1e-14)


def test_damping_decays_free_velocity_exponentially():
    model, state = _small_scene(gravity=(0.0, 0.0, 0.0), damping=20.0, pin=False)
    state.tissue.particle_qd[:] = [0.01, -0.02, 0.005]
    _run(model, state, 10)
    expected = np.array([0.01, -0.02, 0.005]) * math.exp(-20.0 * 10 * DT)
    assert np.allclose(state.tissue.particle_qd, expected, rtol=1e-10, atol=0)


def test_pinned_particles_do_not_move():
    model, state = _small_scene()
    pinned = model.tissue.particle_inv_mass == 0.0
    _run(model, state, 30)
    assert np.array_equal(state.tissue.particle_q[pinned], model.tissue.particle_rest_q[pinned])
    assert np.all(state.tissue.particle_qd[pinned] == 0.0)
    assert np.all(state.tissue.particle_q[~pinned, 2] < model.tissue.particle_rest_q[~pinned, 2])


def test_residual_decreases_over_sweeps():
    model, state = _small_scene()
    _run(model, state, 10)
    residuals = np.zeros(8)
    Solver(iterations=8, max_speed=50.0, tissue_integrator="xpbd").step(model, state, Control(), DT,
                                                                        residuals=residuals)
    assert np.all(np.isfinite(residuals))
    assert residuals[-1] < 1e-2 * residuals[0]


def test_steps_are_deterministic():
    results = []
    for _ in range(2):
        model, state = _small_scene()
        state.tissue.particle_qd[:, 1] = np.linspace(-0.1, 0.1, model.tissue.particle_count)
        _run(model, state, 25)
        results.append(state)
    a, b = results
    for name in ("particle_q", "particle_qd", "particle_q_prev", "tet_multiplier"):
        assert np.array_equal(getattr(a.tissue, name), getattr(b.tissue, name)), name
    assert a.time == b.time


def test_snapshot_restore_is_bit_identical():
    small, _ = _small_scene()
    needle = NeedleModel.from_shape()
    model = Model(tissue=small.tissue, needle=needle, gravity=small.gravity)
    state = State.initial(model, needle=NeedleState.at_rest([0.1, 0.0, 0.1], [1.0, 0.0, 0.0, 0.0]))
    _run(model, state, 5)
    snap = state.snapshot()
    q_array = state.tissue.particle_q
    _run(model, state, 15)
    first = state.snapshot()
    state.needle.body_pos[:] = -1.0
    state.restore(snap)
    assert state.tissue.particle_q is q_array  # restored in place
    assert np.array_equal(state.needle.body_pos, snap.needle.body_pos) and state.needle is not snap.needle
    _run(model, state, 15)
    for name in ("particle_q", "particle_qd", "particle_q_prev", "tet_multiplier"):
        assert np.array_equal(getattr(state.tissue, name), getattr(first.tissue, name)), name
    assert state.time == first.time
    assert np.array_equal(state.needle.body_pos, first.needle.body_pos)
    assert np.array_equal(state.needle.body_quat, first.needle.body_quat)
    # The snapshot is independent of later steps and can be restored twice.
    state.restore(snap)
    assert state.time == snap.time and np.array_equal(state.tissue.particle_q, snap.tissue.particle_q)


def test_divergence_sets_flag_without_raising():
    model, state = _small_scene()
    state.tissue.particle_q[7, 1] = np.nan
    solver = PAPER_SOLVER
    solver.step(model, state, Control(), DT)
    assert state.diverged
    frozen = state.snapshot()
    solver.step(model, state, Control(), DT)  # a diverged state is left alone
    assert state.time == frozen.time

    model, state = _small_scene()
    state.tissue.particle_qd[3] = [0.0, 0.0, 1e3]
    Solver(max_speed=50.0, iterations=1, tissue_integrator="xpbd").step(model, state, Control(), DT)
    assert state.diverged


def test_large_substeps_stay_finite():
    model, state = _small_scene()
    with pytest.warns(UserWarning, match="unstable for this tissue"):
        _run(model, state, 20, dt=2e-2)
    assert np.all(np.isfinite(state.tissue.particle_q)) and not state.diverged


# --- scenes ----------------------------------------------------------------------------------------------


def test_paper_cube_matches_table_1_scale():
    scene = paper_cube()
    assert scene.model.tissue.tet_count == 6840
    assert scene.model.tissue.particle_count == 1960
    left, right = scene.regions["left_wound_face"], scene.regions["right_wound_face"]
    q = scene.state.tissue.particle_q
    assert len(left) == len(right) == 20 * 7
    assert np.allclose(q[right, 1] - q[left, 1].mean(), scene.settings["gap_m"])
    pinned = scene.model.tissue.particle_inv_mass == 0.0
    assert np.array_equal(np.flatnonzero(pinned), scene.regions["pinned"])


def test_two_bar_wound_without_base_pins_only_the_ends():
    scene = two_bar_wound(bar_size=(0.04, 0.01, 0.01), cells=(4, 1, 1), gap=0.002, base=False)
    q = scene.model.tissue.particle_rest_q
    pinned = scene.model.tissue.particle_inv_mass == 0.0
    assert np.all((q[pinned, 0] == 0.0) | np.isclose(q[pinned, 0], 0.04))
    assert pinned.sum() == 2 * 2 * 4


def test_test_bar_scenes_pin_the_documented_faces():
    bar = hanging_bar(length=0.05, width=0.01, cells=(1, 1, 5))
    assert np.all(bar.model.tissue.particle_inv_mass[bar.regions["top"]] == 0.0)
    assert np.allclose(bar.model.tissue.particle_rest_q[bar.regions["bottom"], 2], -0.05)
    beam = cantilever(length=0.05, thickness=0.01, width=0.01, cells=(5, 1, 1))
    assert np.all(beam.model.tissue.particle_inv_mass[beam.regions["clamped"]] == 0.0)
    assert np.allclose(beam.model.tissue.particle_rest_q[beam.regions["tip"], 0], 0.05)
    block = compression_block(size=0.01, cells=2, stretch=0.8)
    assert np.allclose(block.state.tissue.particle_q[block.regions["top"], 2], 0.008)
    assert len(block.model.tissue.roller_particle) == 4 * 9
    with pytest.raises(ValueError, match="length"):
        hanging_bar(length=-1.0)


# --- stability range of the XPBD tissue -----------------------------------------------------------------


def _pad(youngs):
    mesh = box_tet_grid((0.01, 0.01, 0.004), (5, 5, 2))
    material = TissueMaterial(youngs_modulus=youngs, poisson_ratio=0.45)
    tissue = TissueModel.from_mesh(mesh, material, pinned=mesh.vertices[:, 2] == 0.0)
    return Model(tissue=tissue), State(tissue=TissueState.at_rest(tissue))


def test_xpbd_stability_number_of_a_grid_is_dt_wave_speed_over_cell():
    from suture_gym.sim.tissue import xpbd_stability_number

    model, _ = _pad(3.0e4)
    density = PAPER_TISSUE.density
    assert xpbd_stability_number(model.tissue, DT) == pytest.approx(DT * math.sqrt(3.0e4 / density) / 0.002)


def test_solver_warns_naming_the_parameters_when_xpbd_tissue_is_outside_its_stability_range():
    model, state = _pad(3.0e4)
    with pytest.warns(UserWarning, match=r"tissue_integrator 'xpbd'.*youngs_modulus.*dt"):
        _run(model, state, 2)


@pytest.mark.parametrize("youngs, solver", [(3.0e3, PAPER_SOLVER), (3.0e4, Solver(tissue_integrator="quasi_newton",
                                                                                  iterations=1, max_speed=50.0))])
def test_no_stability_warning_inside_the_range_or_with_the_implicit_integrator(youngs, solver):
    import warnings

    model, state = _pad(youngs)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        _run(model, state, 2, solver=solver)
