"""The surgeon's motions: how a curved needle is driven along the planned stitches.

A surgeon turns a curved needle about its own centre, so the tip follows the needle's circle (the planned arc,
:class:`~suture_gym.tasks.PlannedArc`); once the swage is out it pulls the thread, the needle's orientation
held. This module holds the geometry of those motions and the env's start phases
(:meth:`~suture_gym.tasks.Task.start_phase` calls :func:`run_start_phase`): the simulation's virtual coupling
pulls the needle toward the turning pose every substep (:func:`turn`), then a constant force pulls the thread
(:func:`pull_thread`). The simulation ``sim`` they drive is the env's
:class:`~suture_gym.envs.simulation.Simulation`, used through its methods only (this module imports nothing
above :mod:`suture_gym.tasks`).

The same motions are used by the scripted surgeon acting through the env's action space
(:class:`suture_gym.baselines.surgeon.ScriptedSurgeon`) and by the bare-scene stitch of
:mod:`suture_gym.measure.interaction`, which turns the needle on the schedule of :func:`turn_angles` toward the
poses of :func:`circle_grip_target`, then pulls with :func:`pull_wrench`.
"""

from __future__ import annotations

import math

import numpy as np

from suture_gym.sim.needle import NeedleModel, NeedleState, VirtualCoupling, needle_point_velocity
from suture_gym.sim.quat import quat_conj, quat_mul, quat_rotate, quat_rotation_vector
from suture_gym.sim.scenes import needle_circle_pose
from suture_gym.tasks.geometry import PlannedArc

#: Turn rate of the start-phase script, rad/s.
TURN_RATE = 1.0
#: How far (rad) the tip is turned past the exit (``exited``), and the swage past the exit before a pull.
CLEARANCE = 0.3
#: Force and damping with which the start-phase script pulls the thread once the needle is out, per newton of
#: the action's ``max_force`` (so they scale with the tissue's forces: 3 N and 200 N s/m at the defaults), and
#: the longest it pulls (s).
PULL_FORCE_PER_MAX_FORCE = 0.6
PULL_DAMPING_PER_MAX_FORCE = 40.0  # s/m
PULL_TIME = 3.0
def start_angle(arc: PlannedArc, lead: float) -> float:
    """Tip angle (rad) of the approach pose: ``lead`` rad (``plan.start_angle``) before ``arc``'s entry."""
    return arc.entry_angle - lead


def swage_out_angle(arc: PlannedArc, needle_arc: float) -> float:
    """Tip angle (rad) at which the swage of a needle spanning ``needle_arc`` rad is :data:`CLEARANCE` past the
    exit: where turning ends and pulling starts."""
    return arc.exit_angle + needle_arc + CLEARANCE


def turn_angles(start: float, end: float, dt: float, rate: float = TURN_RATE) -> list[float]:
    """The turn's schedule: tip angles (rad) from ``start`` to ``end`` advancing at most ``rate`` rad/s, one per
    control period of ``dt`` s (the first one period after ``start``, the last ``end``)."""
    steps = max(1, int(math.ceil(abs(end - start) / (rate * dt))))
    return [start + (end - start) * i / steps for i in range(1, steps + 1)]


def circle_grip_target(needle: NeedleModel, center, axis, u, tip_angle: float) -> tuple[np.ndarray, np.ndarray]:
    """The turn's target: grip pose ``(position (3,) m, orientation (4,))`` of ``needle`` lying on the circle
    centred at ``center`` (3,) m of normal ``axis`` and angle origin ``u`` with its tip at ``tip_angle`` rad
    (:func:`~suture_gym.sim.scenes.needle_circle_pose`)."""
    pos, quat = needle_circle_pose(needle, center, axis, u, tip_angle)
    return pos + quat_rotate(quat, needle.grip_pos_body), quat


def pull_wrench(needle: NeedleModel, state: NeedleState, hold_quat: np.ndarray, force: np.ndarray, damping: float,
                spring: VirtualCoupling) -> np.ndarray:
    """Grip wrench ``(6,) [N, N m]`` of a constant pull: ``force (3,) N - damping (N s/m) * grip velocity``, and
    the orientation held at ``hold_quat`` (4,) by ``spring``'s angular spring-damper."""
    velocity = needle_point_velocity(needle, state, needle.grip_pos_body)
    turn = quat_rotation_vector(quat_mul(hold_quat, quat_conj(state.body_quat)))
    torque = spring.angular_stiffness * turn - spring.angular_damping * state.body_omega
    return np.concatenate([force - damping * velocity, torque])


def thread_pull_wrench(sim, hold_quat: np.ndarray, direction: np.ndarray, spring: VirtualCoupling | None = None,
                       ) -> np.ndarray:
    """Grip wrench ``(6,) [N, N m]`` of the thread pull on ``sim``'s needle: :func:`pull_wrench` with
    :data:`PULL_FORCE_PER_MAX_FORCE` times the action's ``max_force`` along the unit ``direction`` (3,), damped by
    :data:`PULL_DAMPING_PER_MAX_FORCE` times it (so the grip settles at 15 mm/s when nothing resists), the
    orientation held at ``hold_quat`` (4,) by ``spring`` (default the simulation's coupling)."""
    max_force = sim.config.action.max_force
    return pull_wrench(sim.model.needle, sim.state.needle, hold_quat, PULL_FORCE_PER_MAX_FORCE * max_force * direction,
                       PULL_DAMPING_PER_MAX_FORCE * max_force, sim.coupling_spring if spring is None else spring)


def turn(sim, arc: PlannedArc, start: float, end: float) -> None:
    """Turn ``sim``'s needle target about ``arc``'s centre from tip angle ``start`` to ``end`` (rad) at
    :data:`TURN_RATE`, one :func:`turn_angles` target per env step; stops early if the simulation diverges."""
    for angle in turn_angles(start, end, sim.control_dt):
        sim.step_toward(*circle_grip_target(sim.model.needle, arc.center, arc.axis, arc.u, angle))
        if sim.state.diverged:
            return


def pull_thread(sim, arc: PlannedArc, tip_angle: float, target: float) -> None:
    """Pull ``sim``'s needle along ``arc.pull_direction`` with :data:`PULL_FORCE_PER_MAX_FORCE` times the
    action's ``max_force`` (damped by :data:`PULL_DAMPING_PER_MAX_FORCE` times it; orientation held at the pose
    of ``tip_angle`` rad) until ``target`` m of thread is through, for at most :data:`PULL_TIME` s."""
    _, hold = circle_grip_target(sim.model.needle, arc.center, arc.axis, arc.u, tip_angle)
    for _ in range(int(math.ceil(PULL_TIME / sim.control_dt))):
        if sim.thread_through() >= target or sim.state.diverged:
            return
        for _ in range(sim.substeps):
            sim.substep(thread_pull_wrench(sim, hold, arc.pull_direction))


def run_start_phase(sim, phase: str) -> None:
    """Drive ``sim`` from the approach state to the start of ``phase`` along the first planned stitch:
    ``inserted`` (tip halfway along the arc), ``exited`` (tip :data:`CLEARANCE` past the exit) or
    ``first_bite`` (swage out, then the thread pulled through by ``plan.thread_target``)."""
    arc = sim.arcs[0]
    start = start_angle(arc, sim.config.plan.start_angle)
    if phase == "inserted":
        turn(sim, arc, start, 0.5 * (arc.entry_angle + arc.exit_angle))
    elif phase == "exited":
        turn(sim, arc, start, arc.exit_angle + CLEARANCE)
    elif phase == "first_bite":
        clear = swage_out_angle(arc, sim.model.needle.shape.arc_angle)
        turn(sim, arc, start, clear)
        pull_thread(sim, arc, clear, sim.config.plan.thread_target)
    else:
        raise ValueError(f"unknown start phase {phase!r}")
