"""The task sections of the env config: action scaling, the plan, randomisation, rewards and termination."""

from __future__ import annotations

import math
from dataclasses import dataclass, fields
from typing import ClassVar

from suture_gym.envs.config.checks import _choice, _count, _fail, _range, _real, _Section
from suture_gym.envs.config.physics import FORCE_SCALE
from suture_gym.sim.needle import VirtualCoupling

#: Action modes: a wrench on the needle holder, or a pose change of the holder through the virtual coupling.
ACTION_MODES: tuple[str, ...] = ("wrench", "pose_delta")
#: Action frames: the world's axes, or the needle's own (:class:`ActionConfig`).
ACTION_FRAMES: tuple[str, ...] = ("world", "needle")
#: Goal rewards of the goal-conditioned variants.
GOAL_REWARDS: tuple[str, ...] = ("sparse", "dense")


@dataclass(frozen=True)
class ActionConfig(_Section):
    """How the 6 action components in [-1, 1] become a command.

    ``wrench``: ``[force (3) N, torque (3) N m]`` on the needle holder = action times ``(max_force x3,
    max_torque x3)``, world frame, torque about the grip point, held over the env step.
    ``pose_delta``: the holder's target pose moves by ``action[:3] * max_translation`` (m, world frame) and
    turns by the rotation vector ``action[3:] * max_rotation`` (rad, world frame, about the grip point) each
    env step; the virtual coupling (spring-damper with the stiffnesses below) pulls the needle towards it.
    Finite actions outside [-1, 1] are clipped to it, so these scales are the largest command.
    ``frame``: ``world`` reads both modes' vectors in the world frame as above; ``needle`` reads them in the
    needle's body frame at the step (:class:`~suture_gym.sim.needle.NeedleModel`: ``z`` the normal of the
    needle's plane; turning about ``-z`` drives the tip forward along its circle) and turns about the centre of the
    needle's circle instead of the grip point: a torque there (wrench mode) or a turn of the holder's target
    about it (pose_delta), so one action component drives the needle along its own arc; turns about its x and y
    axes, which tilt the needle's plane, are scaled by ``max_tilt`` instead of ``max_rotation``.
    """

    SECTION: ClassVar[str] = "action"

    mode: str = "wrench"  # "wrench" or "pose_delta"
    frame: str = "world"  # "world" or "needle": the axes (and, for turns, the centre) the action is read in
    max_force: float = 5.0  # N per component (half the tear force)
    max_torque: float = 0.02  # N m per component
    max_translation: float = 2.0e-4  # m per env step and component (pose_delta)
    max_rotation: float = 0.03  # rad per env step and component (pose_delta)
    max_tilt: float = 0.03  # rad per env step about the needle's x and y axes (pose_delta, frame needle)
    # the virtual coupling (pose_delta, and the scripted surgeon): VirtualCoupling's defaults times FORCE_SCALE,
    # like the holder's mass and inertia (the same response time and damping ratio)
    coupling_linear_stiffness: float = FORCE_SCALE * VirtualCoupling.linear_stiffness  # N/m
    coupling_linear_damping: float = FORCE_SCALE * VirtualCoupling.linear_damping  # N s/m
    coupling_angular_stiffness: float = FORCE_SCALE * VirtualCoupling.angular_stiffness  # N m/rad
    coupling_angular_damping: float = FORCE_SCALE * VirtualCoupling.angular_damping  # N m s/rad

    def validate(self, path: str) -> None:
        _choice(f"{path}.mode", self.mode, ACTION_MODES)
        _choice(f"{path}.frame", self.frame, ACTION_FRAMES)
        for f in fields(self):
            if f.name not in ("mode", "frame"):
                _real(f"{path}.{f.name}", getattr(self, f.name), low=0.0, strict_low=True)


@dataclass(frozen=True)
class PlanConfig(_Section):
    """The planned stitches: each is the needle's own circle turned about its centre (module tasks.geometry).

    The circle lies in a plane ``x = const`` (normal along the wound), its centre ``center_height`` (as a
    fraction of the needle's curvature radius) above the top surface; for a wound it is centred over the gap.
    Stitch ``i`` of ``stitches`` lies at ``x = size_x (i + 1) / (stitches + 1)``.
    """

    SECTION: ClassVar[str] = "plan"

    center_height: float = 0.5  # fraction of the curvature radius, in (0, 1)
    stitches: int = 1  # planned stitches along x
    start_angle: float = 0.15  # rad, the tip starts this far before the entry point along the circle
    thread_target: float = 0.01  # m, thread to pull through each stitch (tasks with a thread)
    closure_target: float = 0.6  # fraction of the initial wound gap to reach (wound_closure)

    def validate(self, path: str) -> None:
        _real(f"{path}.center_height", self.center_height, low=0.0, high=1.0, strict_low=True, strict_high=True)
        _count(f"{path}.stitches", self.stitches, 1)
        _real(f"{path}.start_angle", self.start_angle, low=0.0)
        _real(f"{path}.thread_target", self.thread_target, low=0.0, strict_low=True)
        _real(f"{path}.closure_target", self.closure_target, low=0.0, high=1.0, strict_low=True)


@dataclass(frozen=True)
class RandomizationConfig(_Section):
    """Seeded domain randomisation, sampled at every reset from the env's ``np_random`` in a fixed order.

    On by default (ids v2), like Gymnasium's ``reset_noise_scale``: every episode starts from a slightly
    different pose on slightly different tissue, so seeded evaluations are not one episode repeated.
    ``enabled: false`` gives the nominal episode at every reset (for debugging; the random stream is drawn
    the same). Scale ranges ``(lo, hi)`` multiply the nominal value by a log-uniform factor (``(1, 1)``
    disables one); noises are half-widths of uniform offsets per axis (0 disables). The sampled values are in
    ``info["params"]`` at reset and, with ``observation.privileged``, appended to the observation (whose size
    never depends on these settings).
    """

    SECTION: ClassVar[str] = "randomization"

    enabled: bool = True  # false: every episode has the nominal parameters
    youngs_modulus_scale: tuple[float, float] = (0.7, 1.3)  # factor on tissue.youngs_modulus
    puncture_force_scale: tuple[float, float] = (0.8, 1.25)  # factor on coupling.puncture_force
    gap_scale: tuple[float, float] = (0.9, 1.1)  # factor on scene.gap (wound scenes)
    needle_position_noise: float = 0.0005  # m, per axis, of the needle's start pose
    needle_rotation_noise: float = 0.05  # rad, per rotation-vector component of the start orientation

    def validate(self, path: str) -> None:
        if not isinstance(self.enabled, bool):
            _fail(f"{path}.enabled", f"must be true or false, got {self.enabled!r}")
        for name in ("youngs_modulus_scale", "puncture_force_scale", "gap_scale"):
            _range(f"{path}.{name}", getattr(self, name), low=0.0)
        _real(f"{path}.needle_position_noise", self.needle_position_noise, low=0.0)
        _real(f"{path}.needle_rotation_noise", self.needle_rotation_noise, low=0.0, high=math.pi)


@dataclass(frozen=True)
class RewardConfig(_Section):
    """Weights (dimensionless reward per unit of each term's measure) and tolerances of the reward terms.

    See :mod:`suture_gym.tasks` for each term's formula; a term whose weight is 0 is reported as 0.
    """

    SECTION: ClassVar[str] = "reward"

    path: float = 0.05  # per step at full deviation: -w d / (d + path_scale)
    path_scale: float = 1.0e-3  # m
    progress: float = 5.0  # per unit of arc progress (potential-based)
    entry: float = 2.0  # once, at the first puncture of a stitch: w max(0, 1 - e / tolerance)
    exit: float = 2.0  # once, when the tip comes out: w max(0, 1 - e / tolerance)
    puncture: float = 1.0  # once per puncture: +w at a planned access point, -w elsewhere
    thread: float = 2.0  # per target length of thread pulled through
    closure: float = 5.0  # per initial wound gap closed
    success: float = 5.0  # once, when the task succeeds
    # once, when the episode ends in failure; must exceed path / (1 - gamma) of the agent (tasks set their own)
    failure: float = 10.0
    tissue_force: float = 0.5  # per step at cost 1
    action: float = 0.01  # per step: -w mean(a^2)
    access_tolerance: float = 1.5e-3  # m, how close a puncture or exit must be to its planned point
    safe_force: float = 2.0  # N, coupling force below which the tissue-force cost is 0
    goal: str = "sparse"  # goal-conditioned variants: "sparse" (-1 until the goal is met, else 0) or "dense"

    def validate(self, path: str) -> None:
        for f in fields(self):
            if f.name in ("goal",):
                continue
            strict = f.name in ("path_scale", "access_tolerance", "safe_force")
            _real(f"{path}.{f.name}", getattr(self, f.name), low=0.0, strict_low=strict)
        _choice(f"{path}.goal", self.goal, GOAL_REWARDS)


@dataclass(frozen=True)
class TerminationConfig(_Section):
    """Episode ends besides success and the time limit (which registration sets)."""

    SECTION: ClassVar[str] = "termination"

    workspace_margin: float = 0.015  # m, the tip must stay within the tissue's box grown by this margin
    end_on_tear: bool = True  # terminate when the tissue tears (a strand's row at coupling.tear_force)
    # terminate once the task cannot succeed: a stitch entered or exited farther than reward.access_tolerance from
    # the plan, in tasks that need every stitch on it (NeedleInsert, SutureThrow); never in the goal-conditioned ids
    end_on_miss: bool = True

    def validate(self, path: str) -> None:
        _real(f"{path}.workspace_margin", self.workspace_margin, low=0.0, strict_low=True)
        for name in ("end_on_tear", "end_on_miss"):
            if not isinstance(getattr(self, name), bool):
                _fail(f"{path}.{name}", f"must be true or false, got {getattr(self, name)!r}")
