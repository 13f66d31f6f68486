"""The insertion force model (issue 14): exit threshold, cutting force, tip contact patch, backing out and
re-puncture, and the validation of their parameters."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from suture_gym.measure.interaction import StitchController
from suture_gym.sim.coupling import ROW_PATH, CouplingParams, project_cutting, tip_patch, tip_series_compliance
from suture_gym.sim.coupling.compliance import diagonal
from suture_gym.sim.model import Control, TissueMaterial
from suture_gym.sim.needle import NeedleModel, VirtualCoupling, needle_point_velocity
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.scenes import (
    PAPER_COUPLING,
    PAPER_SOLVER,
    WOUND_ARC_AXIS,
    WOUND_ARC_U,
    add_strands,
    needle_circle_pose,
    suturing_pad,
    two_bar_suturing,
    wound_tip_angle,
)
from suture_gym.sim.solver import Solver


@pytest.mark.parametrize("name", ["exit_puncture_force", "cutting_force", "tip_contact_radius"])
@pytest.mark.parametrize("bad", [-1.0, math.nan, math.inf, "1"])
def test_new_parameters_reject_bad_values_by_name(name, bad):
    with pytest.raises(ValueError, match=rf"CouplingParams\.{name} must be a finite number >= 0, got {bad!r}"):
        CouplingParams(**{name: bad})


def _point_tip(radius: float) -> CouplingParams:
    """1 N to puncture, 4 N to tear, 10 N/m of friction, no cutting or exit force, a tip patch of ``radius`` m."""
    return CouplingParams(tip_contact_radius=radius, puncture_force=1.0, exit_puncture_force=0.0, cutting_force=0.0,
                          tear_force=4.0, needle_axial_friction=10.0)


def test_tip_length_must_cover_the_local_dent_of_the_tip_contact_model():
    pad = suturing_pad(size=(0.01, 0.01, 0.004), cells=(2, 2, 1), material=TissueMaterial(youngs_modulus=3.0e4,
                                                                                          poisson_ratio=0.49))
    needle = NeedleModel.from_shape()
    pose = needle_circle_pose(needle, (0.005, 0.005 + needle.shape.curvature_radius, 0.0045), WOUND_ARC_AXIS,
                              WOUND_ARC_U, wound_tip_angle(needle))  # fmt: skip
    with pytest.raises(ValueError, match=r"CouplingParams\.tip_length \(0\.002 m\) must cover"):
        add_strands(pad, pose, coupling_params=_point_tip(1.0e-4))
    add_strands(pad, pose, coupling_params=_point_tip(5.0e-3))  # a blunt tip is fine


def test_tip_series_compliance_is_the_punch_minus_the_patch():
    e, nu, a, b = 1.0e5, 0.45, 1.0e-3, 3.0e-3
    factor = (1.0 - nu**2) / e
    expected = factor / (2.0 * a) - factor * 16.0 / (3.0 * math.pi**2 * b)
    assert tip_series_compliance(a, b, e, nu) == pytest.approx(expected, rel=1e-12)
    # a punch wider than the patch's equivalent needs no series compliance
    assert tip_series_compliance(2.0 * b, b, e, nu) == 0.0
    # per-triangle arrays
    np.testing.assert_allclose(tip_series_compliance(a, b, np.array([e, 2 * e]), nu), [expected, expected / 2])


def _cut(advance, cap, tissue_inv_mass=0.0):
    """:func:`project_cutting` on the default needle whose tip moved ``advance`` m along its direction this
    substep, against a tissue point of one vertex with inverse mass ``tissue_inv_mass`` that did not move."""
    needle = NeedleModel.from_shape()
    dt = 1.0e-3
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    t = needle.tip_dir_body / np.linalg.norm(needle.tip_dir_body)
    pos_prev = np.zeros(3)
    pos = pos_prev + advance * t
    tissue_q = np.zeros((1, 3))
    cut = (np.zeros(4, np.int32), np.array([1.0, 0.0, 0.0, 0.0]), t.copy(), np.array([cap]), np.zeros(1))
    project_cutting(
        (needle.node_count, needle.body_inv_mass, needle.body_inv_inertia, needle.node_pos_body, pos_prev,
         quat.copy()),
        (diagonal(np.array([tissue_inv_mass])), tissue_q.copy(), np.zeros((1, 3), np.int32)), dt, cut, pos, quat,
        tissue_q,
    )  # fmt: skip
    rotation = quat_to_matrix(quat)
    tip_moved = (pos + rotation @ needle.node_pos_body[0]) - (pos_prev + needle.node_pos_body[0])
    return tip_moved @ t, -cut[4][0] / dt**2


def test_cutting_row_resists_only_an_advancing_tip():
    # a small advance is held entirely (the push is below the cutting force): the tip stays
    moved, force = _cut(1.0e-7, cap=0.2)
    assert moved == pytest.approx(0.0, abs=1e-12) and 0.0 < force < 0.2
    # a large advance is resisted by exactly the cutting force: the tip moves on
    moved, force = _cut(1.0e-3, cap=0.2)
    assert force == pytest.approx(0.2, rel=1e-12) and 0.0 < moved < 1.0e-3
    # a retreating tip feels nothing
    moved, force = _cut(-1.0e-4, cap=0.2)
    assert force == 0.0 and moved == pytest.approx(-1.0e-4, rel=1e-12)


def test_tip_patch_spreads_the_anchor_over_the_vertices_within_its_radius():
    pad = suturing_pad(size=(0.02, 0.02, 0.004), cells=(10, 10, 2), material=TissueMaterial(youngs_modulus=1.5e5,
                                                                                            poisson_ratio=0.49))
    needle = NeedleModel.from_shape()
    pose = needle_circle_pose(needle, (0.01, 0.01 + needle.shape.curvature_radius, 0.0045), WOUND_ARC_AXIS,
                              WOUND_ARC_U, wound_tip_angle(needle))  # fmt: skip
    scene = add_strands(pad, pose, coupling_params=_point_tip(1.0e-3))
    model, state = scene.model.coupling, scene.state.coupling
    tissue_q = scene.state.tissue.particle_q + 1.0e-4  # a shifted tissue: the offset keeps the anchor in place
    corners = model.tissue_rest_q[model.surface.tri_vertices]  # (F, 3, 3)
    on_top = np.all(corners[:, :, 2] > 0.0039, axis=1)
    off_centre = np.linalg.norm(corners.mean(axis=1)[:, :2] - 0.01, axis=1)
    tri = int(np.argmin(np.where(on_top, off_centre, np.inf)))
    state.tip_anchor_tri = tri
    state.tip_anchor_bary[:] = (0.2, 0.3, 0.5)
    tip_patch(model, state, tissue_q, np.zeros(3))  # no load yet: the tip's position does not matter
    count = state.tip_patch_count
    vertices, weights = state.tip_patch_vertex[:count], state.tip_patch_weight[:count]
    anchor_rest = state.tip_anchor_bary @ model.tissue_rest_q[model.surface.tri_vertices[tri]]
    assert count > 3 and weights.sum() == pytest.approx(1.0) and np.all(weights > 0.0)
    assert np.all(np.linalg.norm(model.tissue_rest_q[vertices] - anchor_rest, axis=1) <= model.tip_patch_radius)
    anchor_now = state.tip_anchor_bary @ tissue_q[model.surface.tri_vertices[tri]]
    np.testing.assert_allclose(weights @ tissue_q[vertices] + state.tip_patch_offset, anchor_now, atol=1e-15)
    assert state.tip_patch_compliance == model.tri_tip_compliance[tri] > 0.0


def _stitch(coupling: CouplingParams, duration: float) -> dict:
    """The scripted stitch of :func:`~suture_gym.sim.scenes.two_bar_suturing` (1 kPa, XPBD) with ``coupling``:
    the largest tip force while the tip pressed on an exit anchor, and the time of the first exit."""
    scene = two_bar_suturing(coupling_params=coupling)
    controller = StitchController.for_scene(scene)
    solver, control, dt = PAPER_SOLVER, Control(), 1.0e-3
    held, first_exit = 0.0, math.nan
    for k in range(int(round(duration / dt))):
        control.needle_wrench = controller.wrench(k * dt, scene.state)
        solver.step(scene.model, scene.state, control, dt)
        c = scene.state.coupling
        if c.tip_anchor_inside:
            held = max(held, c.tip_force)
        if math.isnan(first_exit) and np.any(~c.path_open[: c.path_count]):
            first_exit = (k + 1) * dt
        assert not scene.state.diverged
    return {"held": held, "exit_time": first_exit}


def test_exit_threshold_holds_the_tip_until_it_is_passed():
    free = _stitch(PAPER_COUPLING, 2.0)
    threshold = 0.5 * PAPER_COUPLING.puncture_force
    held = _stitch(replace(PAPER_COUPLING, exit_puncture_force=threshold), 2.0)
    assert free["held"] == 0.0 and math.isfinite(free["exit_time"])  # no threshold: no exit anchor
    # with it, the tip pressed on the wound face from the inside up to the threshold, and left later
    assert held["held"] == pytest.approx(threshold, rel=0.25)
    assert held["exit_time"] > free["exit_time"]


def _pad_push_scene(coupling: CouplingParams):
    """The tip upright over the middle of a 1 kPa 2 x 2 x 1 cm pad of 5 mm cells, ``eps`` above it."""
    pad = suturing_pad(size=(0.02, 0.02, 0.01), cells=(4, 4, 2), material=TissueMaterial(youngs_modulus=1.0e3,
                                                                                         poisson_ratio=0.49))
    needle = NeedleModel.from_shape()
    center = np.array([0.01, 0.01 + needle.shape.curvature_radius, 0.01 + coupling.resistance_eps])
    return add_strands(
        pad,
        needle_circle_pose(needle, center, WOUND_ARC_AXIS, WOUND_ARC_U, wound_tip_angle(needle)),
        suture_params=SutureParams(length=0.02, node_count=11),
        suture_direction=(0.0, 0.0, 1.0),
        coupling_params=coupling,
    )


def _push(scene, force: float, duration: float, solver: Solver, dt: float = 1.0e-3) -> None:
    """Push the tip straight down (up for ``force < 0``) with ``force`` N at the tip, the needle's lateral
    position and orientation held by a virtual coupling, vertical damping 1 N s/m."""
    model, state = scene.model, scene.state
    needle = model.needle
    hold = VirtualCoupling()
    grip = state.needle.body_pos + quat_to_matrix(state.needle.body_quat) @ needle.grip_pos_body
    quat = state.needle.body_quat.copy()
    control = Control()
    for _ in range(int(round(duration / dt))):
        w = hold.wrench(needle, state.needle, grip, quat)
        push = np.array([0.0, 0.0, -force - needle_point_velocity(needle, state.needle, needle.tip_pos_body)[2]])
        tip_from_grip = quat_to_matrix(state.needle.body_quat) @ (needle.tip_pos_body - needle.grip_pos_body)
        control.needle_wrench = np.concatenate([[w[0], w[1], push[2]], w[3:] + np.cross(tip_from_grip, push)])
        solver.step(model, state, control, dt)
        assert not state.diverged


def test_backing_out_releases_the_path_and_a_later_push_punctures_again():
    coupling = CouplingParams(puncture_force=0.05, exit_puncture_force=0.025, cutting_force=0.01,
                              tip_contact_radius=0.0, tear_force=4.0, needle_axial_friction=10.0)
    scene = _pad_push_scene(coupling)
    solver = PAPER_SOLVER
    c = scene.state.coupling
    _push(scene, 0.1, 0.4, solver)  # twice the threshold: through the surface
    assert c.punctures == 1 and c.punctured and c.path_entered[0]
    _push(scene, -0.1, 0.4, solver)  # back out through the entry
    assert c.path_count == 0 and not c.punctured and c.pathnode_count == 0
    assert not np.any(scene.state.work.coupling_work.row_kind[: scene.model.coupling.needle_node_count] == ROW_PATH)
    _push(scene, 0.03, 0.3, solver)  # below the threshold: no new puncture
    assert c.punctures == 1 and c.path_count == 0
    _push(scene, 0.1, 0.4, solver)  # above it: a new puncture
    assert c.punctures == 2 and c.punctured


@pytest.mark.parametrize("slid", [False, True])
def test_a_new_anchor_keeps_a_spring_deflection_only_after_the_tip_slid(slid):
    """A tip anchored anew while the last tip force was read by the taper's rigid contact rows (no anchor, so no
    spring was deflected) gets its anchor at the surface; after a slide off an anchor it keeps that spring's
    deflection: the anchor is set ``alpha F`` out along the normal, so the tip stays that far below it."""
    pad = suturing_pad(size=(0.02, 0.02, 0.004), cells=(10, 10, 2), material=TissueMaterial(youngs_modulus=1.5e5,
                                                                                            poisson_ratio=0.49))
    needle = NeedleModel.from_shape()
    pose = needle_circle_pose(needle, (0.01, 0.01 + needle.shape.curvature_radius, 0.0045), WOUND_ARC_AXIS,
                              WOUND_ARC_U, wound_tip_angle(needle))  # fmt: skip
    scene = add_strands(pad, pose, coupling_params=_point_tip(1.0e-3))
    model, state = scene.model.coupling, scene.state.coupling
    tissue_q = scene.state.tissue.particle_q
    corners = model.tissue_rest_q[model.surface.tri_vertices]
    on_top = np.all(corners[:, :, 2] > 0.0039, axis=1)
    off_centre = np.linalg.norm(corners.mean(axis=1)[:, :2] - 0.01, axis=1)
    tri = int(np.argmin(np.where(on_top, off_centre, np.inf)))
    state.tip_anchor_tri = tri
    state.tip_anchor_bary[:] = (0.2, 0.3, 0.5)
    state.tip_force = 49.0  # N, what the taper's rows read in the fuzzer's WoundClosure episode
    state.tip_slid = slid
    anchor = state.tip_anchor_bary @ tissue_q[model.surface.tri_vertices[tri]]
    eps = model.params.resistance_eps
    tip = anchor + np.array([0.0, 0.0, eps])  # resting on the surface, normal +z
    tip_patch(model, state, tissue_q, tip)
    count = state.tip_patch_count
    held = state.tip_patch_weight[:count] @ tissue_q[state.tip_patch_vertex[:count]] + state.tip_patch_offset
    deflection = state.tip_patch_compliance * state.tip_force if slid else 0.0
    assert state.tip_patch_compliance > 0.0
    np.testing.assert_allclose(held, anchor + np.array([0.0, 0.0, deflection]), atol=1e-12)
