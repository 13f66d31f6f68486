"""The scripted surgeon acting through an env's action space (wrench or pose_delta), the base of the expert
(:class:`~suture_gym.baselines.expert.ExpertPolicy`) and of the benchmarks' scripted workload.

It reads the env's privileged state (planned arcs, stitch bookkeeping, grip pose) and follows the motions of
:mod:`suture_gym.tasks.surgeon`: turn along the stitch's circle, pull the thread, and over a running suture lift
the needle and carry it to the next stitch.
"""

from __future__ import annotations

import math

import numpy as np

from suture_gym.envs import SutureEnv
from suture_gym.tasks.geometry import PlannedArc
from suture_gym.tasks.surgeon import start_angle, swage_out_angle

#: Closest approach (m) of the needle tip to the workspace's walls that the expert's pull may make.
WORKSPACE_INSET = 0.002
#: Height of the expert's transit between stitches above the approach pose, m.
LIFT = 0.01
#: Holder speed during the transit, m/s.
TRANSIT_SPEED = 0.05
#: Distance (m) at which a transit waypoint counts as reached.
WAYPOINT_TOLERANCE = 1.0e-3


class ScriptedSurgeon:
    """The scripted surgeon acting through an env's action space: a callable ``obs -> action`` (``(6,)
    float32`` in [-1, 1]) with :meth:`reset`.

    1. ``turn``: the needle is turned about its own centre along the current stitch's planned circle, the tip
       angle advancing ``turn_rate`` rad/s from the approach pose until the swage is
       :data:`~suture_gym.tasks.surgeon.CLEARANCE` rad past the exit
       (:meth:`~suture_gym.envs.SutureEnv.scripted_action`, the env's command toward that pose).
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
