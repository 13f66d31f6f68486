"""Loading checks of the needle on the tissue: the puncture threshold and the largest wrench.

The puncture sweeps push the tip straight onto the tissue (:func:`push_tip`): the paper's 1 kPa bars with a
threshold scaled to them, and a silicone-like suturing pad with the measured 1 N. The robustness check drives
the holder at the largest wrench into the pad and holds it there (:func:`hold_wrench`).
"""

from __future__ import annotations

from dataclasses import asdict

import numpy as np

from suture_gym.measure.interaction import DT
from suture_gym.measure.registry import CheckResult, check
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.model import Control, TissueMaterial
from suture_gym.sim.needle import NeedleModel, VirtualCoupling, needle_point_velocity
from suture_gym.sim.quat import (
    quat_conj,
    quat_from_axis_angle,
    quat_mul,
    quat_normalize,
    quat_rotation_vector,
    quat_to_matrix,
)
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.scenes import (
    PAPER_SOLVER,
    WOUND_ARC_AXIS,
    WOUND_ARC_U,
    Scene,
    add_strands,
    needle_circle_pose,
    suturing_pad,
    two_bar_wound,
    wound_tip_angle,
)
from suture_gym.sim.solver import Solver

# ---------------------------------------------------------------------------------------------------------
# Puncture threshold sweeps
# ---------------------------------------------------------------------------------------------------------

SWEEP_FACTORS = (0.5, 0.7, 0.9, 0.95, 1.05, 1.1, 1.5, 2.0)
SWEEP_YOUNGS = 1.0e3  # Pa: the paper's (and the scenes') tissue
SWEEP_THRESHOLD = 0.05  # N: the puncture force for this tissue (1 N would dent it by centimetres)
SWEEP_DT = DT
SWEEP_RAMP = 0.5  # s
SWEEP_GAP = 0.02  # m: the needle's swage end hangs over the gap, so only the tip touches the tissue
# m: the tip over the middle of bar A (7.5 mm from its wound edge), at eps above it. Not nearer the free
# wound edge: there the 1 kPa tissue under a tip that engages its surface keeps yielding at 1.5x the
# threshold, so the damped push falls below the threshold before the load builds up.
SWEEP_ARC_CENTER = np.array([0.015, 0.0075 + NeedleModel.from_shape().shape.curvature_radius, 0.0153])
SWEEP_DAMPING = 1.0  # N s/m, vertical damping of the push (quasi-static loading, no impact)
SWEEP_HOLD = 0.4  # s

PAD_PUNCTURE_FORCE = 1.0  # N: measured suture-needle puncture forces are 0.6-0.9 N
PAD_DT = 2.5e-4  # s: the substep a 30 kPa pad of 5 mm cells needs under large loads (see the solver's notes)
PAD_RAMP = 0.3  # s
PAD_HOLD = 0.2  # s


def pad_with_needle(material: TissueMaterial | None = None, coupling_params: CouplingParams | None = None) -> Scene:
    """The default :func:`~suture_gym.sim.scenes.suturing_pad` (3 x 3 x 1 cm, 5 mm cells, bottom pinned) of
    ``material`` (default :data:`~suture_gym.sim.scenes.PAD_MATERIAL`, 30 kPa: silicone-like) with the
    default needle upright over its centre, the tip ``eps`` above the top face pointing down, and a free 2 cm
    suture straight up from the swage; ``coupling_params`` default to a 1 N puncture force."""
    base = suturing_pad(material=material)
    params = coupling_params or CouplingParams(
        puncture_force=PAD_PUNCTURE_FORCE, exit_puncture_force=0.0, cutting_force=0.0, tip_contact_radius=0.0,
        tear_force=4.0, needle_axial_friction=10.0)
    sx, sy, sz = base.settings["size_m"]
    radius = NeedleModel.from_shape().shape.curvature_radius
    return needle_over(base, np.array([0.5 * sx, 0.5 * sy + radius, sz + params.resistance_eps]), params)


def needle_over(base: Scene, center: np.ndarray, params: CouplingParams) -> Scene:
    """``base`` with the default needle upright on the circle of centre ``center`` (3,) m in the wound plane
    (:data:`WOUND_ARC_AXIS`), its tip straight below the centre pointing down, and a free 2 cm suture straight up
    from the swage, coupled with ``params``."""
    needle = NeedleModel.from_shape()
    return add_strands(
        base,
        needle_circle_pose(needle, center, WOUND_ARC_AXIS, WOUND_ARC_U, wound_tip_angle(needle)),
        suture_params=SutureParams(length=0.02, node_count=21),
        suture_direction=(0.0, 0.0, 1.0),
        coupling_params=params,
    )


def push_tip(
    scene: Scene,
    force: float,
    dt: float,
    ramp: float,
    hold: float,
    damping: float = SWEEP_DAMPING,
    solver: Solver | None = None,
) -> dict:
    """Push the needle tip of ``scene`` straight down with a force ramped to ``force`` N over ``ramp`` s, then
    held for ``hold`` s, at substep ``dt`` s, stepped by ``solver`` (default ``Solver()``).

    The push acts at the tip (the force at the grip plus the moment ``(tip - grip) x F``, with a vertical
    damping ``damping`` N s/m of the tip's velocity), so the tip's contact does not turn the needle and the
    load is quasi-static; a virtual coupling holds the needle's lateral position and orientation. Returns
    whether it pierced, the peak tip force (N), the deepest dent before the puncture (m) and divergence.
    """
    model, state = scene.model, scene.state
    needle = model.needle
    hold_vc = VirtualCoupling()
    grip = state.needle.body_pos + quat_to_matrix(state.needle.body_quat) @ needle.grip_pos_body
    quat = state.needle.body_quat.copy()
    tip_z0 = float((state.needle.body_pos + quat_to_matrix(quat) @ needle.tip_pos_body)[2])
    solver, control = solver or PAPER_SOLVER, Control()
    peak = dent = 0.0
    for k in range(int(round((ramp + hold) / dt))):
        push = np.array([0.0, 0.0, -force * min(1.0, k * dt / ramp)])
        w = hold_vc.wrench(needle, state.needle, grip, quat)
        rotation = quat_to_matrix(state.needle.body_quat)
        tip_from_grip = rotation @ (needle.tip_pos_body - needle.grip_pos_body)
        push[2] -= damping * needle_point_velocity(needle, state.needle, needle.tip_pos_body)[2]
        control.needle_wrench = np.concatenate([[w[0], w[1], push[2]], w[3:] + np.cross(tip_from_grip, push)])
        solver.step(model, state, control, dt)
        peak = max(peak, state.coupling.tip_force)
        if state.coupling.punctures == 0:
            dent = max(dent, tip_z0 - float((state.needle.body_pos + rotation @ needle.tip_pos_body)[2]))
        if state.diverged:
            break
    return {
        "push_force_n": force,
        "pierced": bool(state.coupling.punctures > 0),
        "peak_tip_force_n": peak,
        "dent_before_puncture_m": dent,
        "diverged": bool(state.diverged),
    }


def _push(force: float, params: CouplingParams, youngs: float, dt: float = SWEEP_DT) -> dict:
    """:func:`push_tip` on bar A of two 3 x 1.5 x 1.5 cm bars of ``youngs`` Pa with a 2 cm gap over which the
    rest of the needle hangs, ramped over :data:`SWEEP_RAMP` s and held :data:`SWEEP_HOLD` s."""
    base = two_bar_wound(
        bar_size=(0.03, 0.015, 0.015), cells=(6, 3, 3), gap=SWEEP_GAP,
        material=TissueMaterial(youngs_modulus=youngs, poisson_ratio=0.49),
    )
    scene = needle_over(base, SWEEP_ARC_CENTER, params)
    return push_tip(scene, force, dt, SWEEP_RAMP, SWEEP_HOLD)


def _misclassified(runs: list[dict]) -> int:
    return sum(
        run["pierced"] != (factor > 1.0) or run["diverged"] for run, factor in zip(runs, SWEEP_FACTORS, strict=True)
    )


@check("puncture_threshold_sweep")
def check_puncture_threshold_sweep() -> CheckResult:
    """Tip pushed straight onto the default 1 kPa tissue by forces from 0.5x to 2x the puncture threshold
    (0.05 N here), ramped over 0.5 s and held 0.4 s: it must pierce iff the push exceeds the threshold.
    Measured: the number of misclassified (or diverged) pushes, reference 0."""
    params = CouplingParams(puncture_force=SWEEP_THRESHOLD, exit_puncture_force=0.0, cutting_force=0.0,
                            tip_contact_radius=0.0, tear_force=4.0, needle_axial_friction=10.0)
    runs = [_push(f * params.puncture_force, params, SWEEP_YOUNGS) for f in SWEEP_FACTORS]
    return CheckResult(
        name="puncture_threshold_sweep",
        measured=float(_misclassified(runs)),
        reference=0.0,
        tolerance=0.0,
        unit="misclassified pushes",
        settings={
            "factors": list(SWEEP_FACTORS),
            "coupling": asdict(params),
            "youngs_modulus_pa": SWEEP_YOUNGS,
            "ramp_s": SWEEP_RAMP,
            "hold_s": SWEEP_HOLD,
            "dt_s": SWEEP_DT,
            "push_damping_n_s_m": SWEEP_DAMPING,
            "scene": {
                "bar_size_m": [0.03, 0.015, 0.015],
                "cells": [6, 3, 3],
                "gap_m": SWEEP_GAP,
                "arc_center_m": SWEEP_ARC_CENTER.tolist(),
                "suture": "2 cm, 21 nodes, free",
            },
        },
        details={"runs": runs},
    )


@check("puncture_threshold_pad")
def check_puncture_threshold_pad() -> CheckResult:
    """The realistic case: the tip pushed straight onto the centre of a silicone-like suturing pad (30 kPa,
    nu = 0.45, 3 x 3 x 1 cm on a rigid base, :func:`pad_with_needle`) with the 1 N puncture threshold, by
    forces from 0.5x to 2x it, ramped over 0.3 s and held 0.2 s at 0.25 ms substeps: it must pierce iff the
    push exceeds the threshold. Measured: misclassified (or diverged) pushes, reference 0. The details give
    each push's peak tip force and the dent it made before piercing."""
    runs = [push_tip(pad_with_needle(), f * PAD_PUNCTURE_FORCE, PAD_DT, PAD_RAMP, PAD_HOLD) for f in SWEEP_FACTORS]
    scene = pad_with_needle()
    return CheckResult(
        name="puncture_threshold_pad",
        measured=float(_misclassified(runs)),
        reference=0.0,
        tolerance=0.0,
        unit="misclassified pushes",
        settings={
            "factors": list(SWEEP_FACTORS),
            "scene": scene.settings,
            "ramp_s": PAD_RAMP,
            "hold_s": PAD_HOLD,
            "dt_s": PAD_DT,
            "push_damping_n_s_m": SWEEP_DAMPING,
        },
        details={"runs": runs},
    )


# ---------------------------------------------------------------------------------------------------------
# The largest wrench, held
# ---------------------------------------------------------------------------------------------------------

WRENCH_FORCE = 5.0  # N, the most the holder pushes with
WRENCH_TORQUE = 0.05  # N m, the most it turns with
WRENCH_HOLD = 2.0  # s
#: s: the end of the hold over which the needle's mean velocity and angular velocity are taken.
SETTLE_WINDOW = 0.2
#: Bounds on those means for a needle held at rest (by the tissue, the base or at its target): 1 mm and
#: 0.1 rad of net motion over :data:`SETTLE_WINDOW`. A needle driven free of the tissue moves hundreds of times
#: faster: the saturated drive (:data:`WRENCH_FORCE` on 20 g, 250 m/s^2; terminal speed 100 /s times the
#: distance to its target, about 1 m/s from 1 cm) and its torque (:data:`WRENCH_TORQUE` on 1e-6 kg m^2;
#: about 330 rad/s per rad of orientation error). A wedged needle can rattle (instantaneous angular speeds of
#: several rad/s about a fixed pose under the saturated torque); its mean velocities over the window are tiny.
SETTLED_SPEED = 0.005  # m/s
SETTLED_ANGULAR_SPEED = 0.5  # rad/s
#: (name, direction of the push, axis (world) and angle (rad) of the target turn): straight down, down while
#: driving the needle along its arc (+x), backing it out (-x), twisting it out of its plane (y, z), oblique.
WRENCH_CASES = (
    ("down", (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 0.0),
    ("down_drive", (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), 2.0),
    ("down_back", (0.0, 0.0, -1.0), (1.0, 0.0, 0.0), -2.0),
    ("down_twist_y", (0.0, 0.0, -1.0), (0.0, 1.0, 0.0), 1.5),
    ("down_twist_z", (0.0, 0.0, -1.0), (0.0, 0.0, 1.0), 1.5),
    ("oblique_y", (0.0, 1.0, -1.0), (1.0, 0.0, 0.0), 1.0),
    ("oblique_minus_y", (0.0, -1.0, -1.0), (1.0, 0.0, 0.0), 1.0),
    ("oblique_x", (1.0, 0.0, -1.0), (0.0, 1.0, 0.0), 1.0),
)


def _saturate(v: np.ndarray, limit: float) -> np.ndarray:
    norm = float(np.linalg.norm(v))
    return v if norm <= limit else v * (limit / norm)


def hold_wrench(scene: Scene, direction, axis, angle: float, dt: float = PAD_DT, duration: float = WRENCH_HOLD) -> dict:
    """Drive the needle of ``scene`` as hard as allowed towards a pose in or under the tissue and hold it there
    for ``duration`` s: a force of at most :data:`WRENCH_FORCE` N towards the point 2 cm from the start grip
    point along ``direction`` (3,) and a torque of at most :data:`WRENCH_TORQUE` N m towards the start
    orientation turned by ``angle`` rad about ``axis`` (3,) (stiff spring-dampers, saturated), the way an
    agent that pushes at full action all the time loads the simulation.

    Returns divergence, the largest tissue speed (m/s), punctures and damage, and whether the needle ends at
    rest: the magnitudes of its mean velocity (m/s) and mean angular velocity (rad/s) over the last
    :data:`SETTLE_WINDOW` s (its net motion over that window divided by it), ``settled`` when they are below
    :data:`SETTLED_SPEED` and :data:`SETTLED_ANGULAR_SPEED` (see there why), and, for information, its mean
    angular speed over the window (a wedged needle's rattle) and its final speed and angular speed."""
    model, state = scene.model, scene.state
    needle = model.needle
    rotation = quat_to_matrix(state.needle.body_quat)
    direction = np.asarray(direction, dtype=np.float64)
    target = state.needle.body_pos + rotation @ needle.grip_pos_body + 0.02 * direction / np.linalg.norm(direction)
    turn = quat_from_axis_angle(np.asarray(axis, dtype=np.float64), float(angle))
    target_quat = quat_normalize(quat_mul(turn, state.needle.body_quat))
    solver, control = PAPER_SOLVER, Control()
    tissue_speed = 0.0
    steps = int(round(duration / dt))
    window = min(steps, int(round(SETTLE_WINDOW / dt)))
    velocity_sum, omega_sum, rattle = np.zeros(3), np.zeros(3), 0.0
    for k in range(steps):
        grip = state.needle.body_pos + quat_to_matrix(state.needle.body_quat) @ needle.grip_pos_body
        velocity = needle_point_velocity(needle, state.needle, needle.grip_pos_body)
        force = _saturate(5000.0 * (target - grip) - 50.0 * velocity, WRENCH_FORCE)
        error = quat_rotation_vector(quat_mul(target_quat, quat_conj(state.needle.body_quat)))
        torque = _saturate(0.5 * error - 1.5e-3 * state.needle.body_omega, WRENCH_TORQUE)
        control.needle_wrench = np.concatenate([force, torque])
        solver.step(model, state, control, dt)
        tissue_speed = max(tissue_speed, float(np.abs(state.tissue.particle_qd).max()))
        if state.diverged:
            break
        if k >= steps - window:
            velocity_sum += state.needle.body_vel
            omega_sum += state.needle.body_omega
            rattle += float(np.linalg.norm(state.needle.body_omega))
    mean_speed = float(np.linalg.norm(velocity_sum)) / window
    mean_angular_speed = float(np.linalg.norm(omega_sum)) / window
    at_rest = mean_speed < SETTLED_SPEED and mean_angular_speed < SETTLED_ANGULAR_SPEED
    return {
        "diverged": bool(state.diverged),
        "time_s": state.time,
        "max_tissue_speed_m_s": tissue_speed,
        "needle_mean_speed_m_s": mean_speed,
        "needle_mean_angular_speed_rad_s": mean_angular_speed,
        "settled": bool(at_rest and not state.diverged),
        "needle_mean_abs_angular_speed_rad_s": rattle / window,
        "needle_final_speed_m_s": float(np.linalg.norm(state.needle.body_vel)),
        "needle_final_angular_speed_rad_s": float(np.linalg.norm(state.needle.body_omega)),
        "punctures": int(state.coupling.punctures),
        "damaged": bool(state.coupling.damaged),
    }


@check("max_wrench_hold")
def check_max_wrench_hold() -> CheckResult:
    """The holder driven at the largest wrench (5 N, 0.05 N m) into the silicone-like pad (:func:`pad_with_needle`,
    1 N puncture threshold) in eight directions (:data:`WRENCH_CASES`) and held there for 2 s at 0.25 ms
    substeps (:func:`hold_wrench`). Measured: runs that diverged or did not end at rest (the needle's mean
    velocity and angular velocity over the last :data:`SETTLE_WINDOW` s within :data:`SETTLED_SPEED` and
    :data:`SETTLED_ANGULAR_SPEED`: held by the tissue and the base or at its target, not flying free),
    reference 0; the details give each run's largest tissue speed and the needle's motion."""
    runs = {name: hold_wrench(pad_with_needle(), d, a, angle) for name, d, a, angle in WRENCH_CASES}
    return CheckResult(
        name="max_wrench_hold",
        measured=float(sum(run["diverged"] or not run["settled"] for run in runs.values())),
        reference=0.0,
        tolerance=0.0,
        unit="runs diverged or not at rest",
        settings={
            "scene": pad_with_needle().settings,
            "cases": [list(case) for case in WRENCH_CASES],
            "force_n": WRENCH_FORCE,
            "torque_n_m": WRENCH_TORQUE,
            "duration_s": WRENCH_HOLD,
            "settle_window_s": SETTLE_WINDOW,
            "settled_speed_m_s": SETTLED_SPEED,
            "settled_angular_speed_rad_s": SETTLED_ANGULAR_SPEED,
            "dt_s": PAD_DT,
            "solver": asdict(PAPER_SOLVER),
        },
        details=runs,
    )
