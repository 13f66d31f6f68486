"""The scripted surgeon: how a curved needle is driven along the planned stitches, in one place.

A surgeon turns a curved needle about its own centre, so the tip follows the needle's circle (the planned arc,
:class:`~suture_gym.tasks.PlannedArc`); once the swage is out it pulls the thread, the needle's orientation
held; over a running suture it lifts the needle and carries it to the next stitch. Three users:

* the env's start phases (:meth:`~suture_gym.tasks.Task.start_phase` calls :func:`run_start_phase`): the
  simulation's virtual coupling pulls the needle toward the turning pose every substep (:func:`turn`), then a
  constant force pulls the thread (:func:`pull_thread`);
* the expert (:class:`ScriptedSurgeon`, ``agents.expert.ExpertPolicy``) acts through the env's action space
  (wrench or pose_delta) only;
* the measurements: :mod:`suture_gym.measure.envs` through the env, and the bare-scene stitch of
  :mod:`suture_gym.measure.interaction` (``StitchController``), which turns the needle on the schedule of
  :func:`turn_angles` toward the poses of :func:`circle_grip_target`, then pulls with :func:`pull_wrench`.

The simulation ``sim`` the start-phase functions drive is a :class:`~suture_gym.envs.simulation.Simulation`.
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
#: Closest approach (m) of the needle tip to the workspace's walls that the expert's pull may make.
WORKSPACE_INSET = 0.002
#: Height of the expert's transit between stitches above the approach pose, m.
LIFT = 0.01
#: Holder speed during the transit, m/s.
TRANSIT_SPEED = 0.05
#: Distance (m) at which a transit waypoint counts as reached.
WAYPOINT_TOLERANCE = 1.0e-3


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


class ScriptedSurgeon:
    """The scripted surgeon acting through an env's action space: a callable ``obs -> action`` (``(6,)
    float32`` in [-1, 1]) with :meth:`reset`.

    1. ``turn``: the needle is turned about its own centre along the current stitch's planned circle, the tip
       angle advancing ``turn_rate`` rad/s from the approach pose until the swage is :data:`CLEARANCE` rad past
       the exit (:meth:`~suture_gym.envs.SutureEnv.scripted_action`, the env's command toward that pose).
    2. ``pull``: the holder moves along the stitch's pull direction (the last stitch of a running suture's leans
       ahead, along the suture, :meth:`_planned_pull`) at ``pull_speed`` m/s, orientation held
       (:meth:`~suture_gym.envs.SutureEnv.action_toward`), until the task moves on to the next stitch. A
       component of the pull that would take the tip within :data:`WORKSPACE_INSET` of the workspace's walls is
       dropped, so a long pull slides along the wall instead of leaving the workspace.
    3. ``transit`` (next stitch of a running suture): the holder rises :data:`LIFT` m above where it is, crosses
       to that height above the next stitch's approach pose, descends to it, and step 1 starts again.

    Args:
        env: a SutureGym env (any wrappers; ``env.unwrapped`` must be a
            :class:`~suture_gym.envs.SutureEnv`). The observation passed to ``__call__`` is not read: the
            surgeon acts on the env's privileged state (planned arcs, stitch bookkeeping, grip pose).
        turn_rate: tip-angle advance while turning, rad/s (> 0); default the task's ``SURGEON_TURN_RATE``.
        pull_speed: holder speed while pulling the thread, m/s (> 0); default the task's
            ``SURGEON_PULL_SPEED``.
    """

    def __init__(self, env, turn_rate: float | None = None, pull_speed: float | None = None) -> None:
        from suture_gym.envs import SutureEnv

        if not isinstance(env.unwrapped, SutureEnv):
            raise ValueError(f"env must be a SutureGym env, got {type(env.unwrapped).__name__}")
        task = env.unwrapped.task
        turn_rate = task.SURGEON_TURN_RATE if turn_rate is None else turn_rate
        pull_speed = task.SURGEON_PULL_SPEED if pull_speed is None else pull_speed
        if not (math.isfinite(turn_rate) and turn_rate > 0.0):
            raise ValueError(f"turn_rate must be a positive rad/s, got {turn_rate}")
        if not (math.isfinite(pull_speed) and pull_speed > 0.0):
            raise ValueError(f"pull_speed must be a positive m/s, got {pull_speed}")
        self.env = env.unwrapped
        self.turn_rate = float(turn_rate)
        self.pull_speed = float(pull_speed)
        self.reset()

    def reset(self) -> None:
        """Forget the episode; the next call plans from the env's state (call after ``env.reset``)."""
        self.phase = ""
        self.stitch = -1
        self.angle = 0.0
        self.waypoints: list[np.ndarray] = []

    def __call__(self, obs) -> np.ndarray:
        env = self.env
        sim = env.sim
        state = env.task.state
        if state.stitch != self.stitch:
            self._start_stitch(state.stitch)
        arc = sim.arcs[self.stitch]
        if self.phase == "transit":
            return self._transit(arc)
        turn_end = swage_out_angle(arc, sim.model.needle.shape.arc_angle)
        if self.phase == "turn" and self.angle >= turn_end:
            self.phase = "pull"
        if self.phase == "turn":
            self.angle = min(turn_end, self.angle + self.turn_rate * sim.control_dt)
            return env.scripted_action(self.angle, self.stitch)
        grip, quat = sim.grip_pose()
        direction = self._pull_direction(self._planned_pull(self.stitch))
        return env.action_toward(grip + self.pull_speed * sim.control_dt * direction, quat)

    def _transit(self, arc: PlannedArc) -> np.ndarray:
        """The transit's action toward the next waypoint at :data:`TRANSIT_SPEED` (the turn's first once the
        last waypoint is reached)."""
        env = self.env
        sim = env.sim
        target = self._next_waypoint()
        if target is None:
            self.phase = "turn"
            return env.scripted_action(self.angle, self.stitch)
        grip, _ = sim.grip_pose()
        _, quat = sim.arc_grip_target(arc, self.angle)
        step = TRANSIT_SPEED * sim.control_dt
        offset = target - grip
        distance = max(float(np.linalg.norm(offset)), step)
        return env.action_toward(grip + offset * (step / distance), quat)

    def _next_waypoint(self) -> np.ndarray | None:
        """The transit's current waypoint (3,) m, the reached ones (within :data:`WAYPOINT_TOLERANCE` of the grip)
        dropped; None once the last one is reached."""
        grip, _ = self.env.sim.grip_pose()
        while self.waypoints and np.linalg.norm(self.waypoints[0] - grip) <= WAYPOINT_TOLERANCE:
            self.waypoints.pop(0)
        return self.waypoints[0] if self.waypoints else None

    def _planned_pull(self, stitch: int) -> np.ndarray:
        """Unit direction (3,) in which to pull stitch ``stitch``'s thread: the arc's
        :attr:`~suture_gym.tasks.PlannedArc.pull_direction`; the last stitch of a running suture adds the
        direction in which the suture advanced (from the previous stitch's centre to this one's), which leads
        the long tightening pull away from the stitches into the free workspace beyond them."""
        arcs = self.env.sim.arcs
        direction = arcs[stitch].pull_direction
        if stitch > 0 and stitch == len(arcs) - 1:
            advance = arcs[stitch].center - arcs[stitch - 1].center
            direction = direction + advance / np.linalg.norm(advance)
        return direction / np.linalg.norm(direction)

    def _pull_direction(self, direction: np.ndarray) -> np.ndarray:
        """``direction`` (3,) less its components toward workspace walls that the tip is within
        :data:`WORKSPACE_INSET` of, rescaled to unit length (zero when nothing is left)."""
        tip = self.env.sim.tip_position()
        low, high = self.env.sim.workspace
        kept = np.where(((direction < 0.0) & (tip - low < WORKSPACE_INSET))
                        | ((direction > 0.0) & (high - tip < WORKSPACE_INSET)), 0.0, direction)
        norm = float(np.linalg.norm(kept))
        return kept / norm if norm > 0.0 else kept

    def _start_stitch(self, stitch: int) -> None:
        """Plan stitch ``stitch``: turn from the approach pose (the first one), else transit there first."""
        sim = self.env.sim
        arc = sim.arcs[stitch]
        self.angle = start_angle(arc, self.env.config.plan.start_angle)
        if self.stitch < 0:
            self.phase = "turn"
        else:
            grip, _ = sim.grip_pose()
            start, _ = sim.arc_grip_target(arc, self.angle)
            high = max(grip[2], start[2]) + LIFT
            self.waypoints = [np.array([grip[0], grip[1], high]), np.array([start[0], start[1], high]), start]
            self.phase = "transit"
        self.stitch = stitch
