"""The Gymnasium environments: :class:`SutureEnv` (flat observation) and :class:`SutureGoalEnv` (goal-conditioned).

An env is a :class:`~suture_gym.envs.simulation.Simulation` (the physics facade), a task from
:mod:`suture_gym.tasks` (reward terms, success) and the spaces.

Action: ``Box(-1, 1, (6,), float32)``, scaled by the config (:class:`~suture_gym.envs.config.ActionConfig`):
a wrench on the needle holder, or (``action_mode="pose_delta"``) a change of the holder's target pose reached
through the virtual coupling. An action that is not real numbers (strings, complex, objects, booleans) raises
TypeError naming its dtype, a non-finite one ValueError; finite actions outside the box are clipped to it (a
component of 1e6 acts, and is penalised, as 1).

Observation: float32 vector laid out in :mod:`suture_gym.envs.spaces` (one row per index, with units), each
entry its SI value divided by its field's scale and clipped to its finite bound (``observation.scaled: false``:
raw SI values, infinite bounds), or for the goal-conditioned variant a Dict with ``observation``,
``achieved_goal`` and ``desired_goal`` (the goals in SI units). ``observation.mode`` ``rgb``, ``depth``,
``rgbd`` or ``point_cloud`` makes it a Dict of camera images ``rgb`` ``(H, W, 3) uint8`` and ``depth``
``(H, W, 1) float32`` m (background: ``observation.camera.far``), or a point cloud ``point_cloud`` ``(N, 3)
float32`` m in the world frame, with the vector as ``state`` (unless ``observation.include_state`` is false); the
goal-conditioned variant adds those keys beside its own (:mod:`suture_gym.envs.sensors`).

Episode end: ``terminated`` on success, on a tear (a row holding the needle or thread in the tissue at the tear
force, unless ``termination.end_on_tear`` is off), when the tip leaves the workspace, (flat ids, unless
``termination.end_on_miss`` is off) once NeedleInsert or SutureThrow can no longer succeed because the stitch was
entered or exited off the plan, and when the simulation diverges (the solver's flag: a non-finite position or a
speed above ``solver.max_speed``; or a non-finite observation or reward): a failure like a tear, with
``info["diverged"] = True``, the last finite observation, and the failure terms of
:meth:`~suture_gym.tasks.Task.diverged` (``-w_failure`` and the banked progress handed back, every other term 0).
``truncated`` at the time limit, which comes from registration (``TimeLimit``). Once the env has ended an
episode (``terminated``), ``step`` raises RuntimeError until ``reset``; Gymnasium's
``TimeLimit`` does not stop a step after its own truncation. ``render`` before the first ``reset`` raises
RuntimeError too, and so do ``reset``, ``step`` and the snapshots after ``close``.

Rendering: ``render_mode="rgb_array"``: :meth:`~SutureEnv.render` returns an image from the offline renderer
(:mod:`suture_gym.render`). ``render_mode="human"``: a live 3D view in the browser
(:class:`suture_gym.render.live.LiveView`, viser, the ``viewer`` extra), served on ``render.viewer_host`` and
``render.viewer_port`` from the first ``reset`` on and updated by every ``reset`` and ``step`` (at most
``render.viewer_fps`` frames per second; the env never waits for a browser); ``close`` stops it.

``info`` at every step: ``is_success``, ``punctured``, ``tip_force`` (N), ``haptic_wrench`` (``(6,) float64``
``[N, N m]``: the reaction the tissue and thread exert on the needle, about the grip point, at the step's last
substep; a haptic device renders its opposite; zeros if not finite), ``wound_gap`` (m, >= 0, 0 without a
wound), ``wound_overlap`` (m, how far the wound's faces passed through each other), ``diverged``, ``cost``
(tissue-force cost >= 0, for safe RL), ``tear``, ``out_of_workspace``, ``missed``, ``crushed`` (the faces through
each other by more than the limit: a failing end), ``stitch`` and ``reward_<term>`` for each term of the task,
with ``math.fsum`` of the terms equal to the reward exactly. ``reset`` adds ``params`` (the sampled episode
parameters) and ``phase``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np

from suture_gym.envs.config import EnvConfig, apply_overrides, load_config
from suture_gym.envs.randomization import EpisodeParams, nominal_params, sample_params
from suture_gym.envs.registry import task_class
from suture_gym.envs.simulation import Simulation, SimulationSnapshot
from suture_gym.envs.spaces import (
    SDIST_CLIP,
    ObsField,
    observation_layout,
    observation_scale,
    observation_size,
    sensor_spaces,
)
from suture_gym.sim.quat import (
    quat_conj,
    quat_from_rotation_vector,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_rotation_vector,
    quat_to_matrix,
)
from suture_gym.tasks import Observables, Task, TaskState

#: Keys ``reset(options=...)`` accepts.
RESET_OPTIONS = ("phase", "params")


@dataclass(frozen=True)
class EnvState:
    """A snapshot of everything that decides an env's future (see :meth:`SutureEnv.get_state`).

    Attributes:
        simulation: the physics snapshot.
        task: the task's bookkeeping.
        target_pos: ``(3,)`` holder target position, m (pose_delta mode; the grip pose otherwise).
        target_quat: ``(4,)`` holder target orientation (w, x, y, z).
        last_observation: the last observation returned (the fallback when the simulation diverges).
        rng_state: the bit-generator state of ``np_random``.
        ended: the episode had ended (``step`` raises until ``reset``).
    """

    simulation: SimulationSnapshot
    task: TaskState
    target_pos: np.ndarray
    target_quat: np.ndarray
    last_observation: Any
    rng_state: dict
    ended: bool


def _layout(obs):
    """The shapes of an observation or observation space: an array's shape, or a dict's keys with theirs."""
    if isinstance(obs, (dict, gym.spaces.Dict)):
        return {k: _layout(v) for k, v in obs.items()}
    return tuple(obs.shape) if isinstance(obs, gym.spaces.Space) else tuple(np.shape(obs))


def _copy_obs(obs):
    if isinstance(obs, dict):
        return {k: v.copy() for k, v in obs.items()}
    return obs.copy()


class SutureEnv(gym.Env):
    """A suturing task on the XPBD simulator (module docstring for spaces, ends and ``info``).

    Args:
        task: a registered task name (``"needle_insert"``, ``"suture_throw"``, ``"wound_closure"``, ...);
            default the class's :attr:`TASK`.
        config: None (the task's defaults), an :class:`~suture_gym.envs.config.EnvConfig`, a nested mapping of
            overrides or the path of a YAML file of overrides (a shipped one by name, :mod:`suture_gym.configs`).
        render_mode: None, ``"rgb_array"`` (images) or ``"human"`` (live view in the browser, needs viser).
        action_mode: shortcut overriding ``config.action.mode`` (``"wrench"`` or ``"pose_delta"``).
    """

    metadata = {"render_modes": ["rgb_array", "human"], "render_fps": 50}
    #: Goal-conditioned variant: a miss never ends its episodes (the relabelled goals may still be reachable).
    _GOAL_CONDITIONED = False
    #: Task of an env class made for one id (:func:`~suture_gym.envs.docs.env_class`), the default ``task``.
    TASK = "needle_insert"

    def __init__(self, task: str | None = None, config=None, render_mode: str | None = None,
                 action_mode: str | None = None) -> None:
        super().__init__()
        cfg = load_config(self.TASK if task is None else task, config)
        if action_mode is not None:
            cfg = apply_overrides(cfg, {"action": {"mode": action_mode}})
        if render_mode is not None and render_mode not in self.metadata["render_modes"]:
            raise ValueError(f"render_mode must be None or one of {self.metadata['render_modes']}, got {render_mode!r}")
        if render_mode == "human":
            from suture_gym.render.live import require_viser

            require_viser()  # fail here, naming the extra to install, rather than at the first reset
        self.config: EnvConfig = cfg
        self.render_mode = render_mode
        self.sim = Simulation(cfg)
        self.task_cls: type[Task] = task_class(cfg.task)
        self.task: Task = self._make_task()
        self.layout: tuple[ObsField, ...] = observation_layout(cfg)
        self.obs_index: dict[str, slice] = {f.name: f.slice for f in self.layout}
        size = observation_size(self.layout)
        self.obs_scale, self.obs_bound = observation_scale(self.layout)
        self.action_space = gym.spaces.Box(-1.0, 1.0, (6,), np.float32)
        bound = self.obs_bound.astype(np.float32)
        #: The observation vector's space (the whole observation in ``state`` mode).
        self.state_space = gym.spaces.Box(-bound, bound, (size,), np.float32)
        #: The camera images or point cloud (:mod:`suture_gym.envs.sensors`; None in ``state`` mode).
        self.sensors = None
        if cfg.observation.mode != "state":
            from suture_gym.envs.sensors import Sensors

            self.sensors = Sensors(cfg, self.sim)
        self.observation_space = self.state_space
        if self.sensors is not None:
            state = {"state": self.state_space} if cfg.observation.include_state else {}
            self.observation_space = gym.spaces.Dict({**sensor_spaces(cfg), **state})
        self.metadata = {**self.metadata, "render_fps": max(1, int(round(1.0 / self.sim.control_dt)))}
        a = cfg.action
        self._wrench_scale = np.array([a.max_force] * 3 + [a.max_torque] * 3)
        tilt = a.max_tilt if a.frame == "needle" else a.max_rotation
        self._rotation_scale = np.array([tilt, tilt, a.max_rotation])  # rad per step (pose_delta)
        self._obs_buffer = np.zeros(size)
        self._target_pos = np.zeros(3)
        self._target_quat = np.array([1.0, 0.0, 0.0, 0.0])
        self._last_obs = None
        self._ended = False
        self._renderer = None
        self._live = None
        self._closed = False
        #: (seed, steps, return, last info, ended) of the episode, for the live view (``render_mode="human"``).
        self._live_episode: tuple = (None, 0, 0.0, {}, False)

    # ------------------------------------------------------------------------------------------------------
    # Gymnasium API
    # ------------------------------------------------------------------------------------------------------

    def reset(self, *, seed: int | None = None, options: dict | None = None):
        """Start an episode: sample the parameters, rebuild the physics if they changed, place the needle.

        Options: ``phase`` (one of the task's ``PHASES``; default the first, ``"approach"``) starts later in the
        procedure for curricula; ``params`` (mapping) overrides sampled :class:`EpisodeParams` fields.
        Unknown options raise ValueError.
        """
        self._check_open()
        super().reset(seed=seed)
        options = {} if options is None else options
        if not isinstance(options, dict):
            raise ValueError(f"options must be a mapping, got {type(options).__name__}")
        unknown = sorted(str(k) for k in options if k not in RESET_OPTIONS)
        if unknown:
            raise ValueError(f"unknown reset option(s) {unknown}; known: {list(RESET_OPTIONS)}")
        phase = options.get("phase", self.task_cls.PHASES[0])
        if phase not in self.task_cls.PHASES:
            raise ValueError(f"phase must be one of {list(self.task_cls.PHASES)} for {self.config.task}, got {phase!r}")
        params = sample_params(self.config, self.np_random)
        if "params" in options:
            params = params.with_overrides(options["params"])
        self.sim.reset(params, phase)
        self.task = self._make_task()
        sim_obs = self.sim.observables()
        self.task.reset(sim_obs)
        self._target_pos, self._target_quat = self.sim.grip_pose()
        obs = self._observation(sim_obs)
        self._last_obs = _copy_obs(obs)
        self._ended = False
        info = self._info(sim_obs, obs, None, diverged=False)
        info["params"] = params.to_dict()
        info["phase"] = phase
        if self.render_mode == "human":
            self._live_episode = (seed, 0, 0.0, info, False)
            self._show_live(force=True)
        return obs, info

    def step(self, action):
        """Apply ``action`` for one control period (``solver.substeps`` substeps) and score it."""
        self._check_open()
        if self._last_obs is None:
            raise RuntimeError("call reset() before step()")
        if self._ended:
            raise RuntimeError("the episode has ended (terminated): call reset() before step()")
        a = self._check_action(action)
        cfg = self.config.action
        if cfg.mode == "wrench":
            self.sim.step(self._world_wrench(a * self._wrench_scale))
        else:
            rot, centre = self._action_frame()
            move = rot @ (a[:3] * cfg.max_translation)
            turn = quat_from_rotation_vector(rot @ (a[3:] * self._rotation_scale))
            if centre is not None:  # turn the target about the needle's circle centre
                self._target_pos = centre + quat_rotate(turn, self._target_pos - centre)
            self._target_pos = self._target_pos + move
            self._target_quat = quat_normalize(quat_mul(turn, self._target_quat))
            self.sim.step_toward(self._target_pos, self._target_quat)
        sim_obs = self.sim.observables()
        diverged = sim_obs.diverged
        if not diverged:
            before = self.task.get_state()
            outcome = self.task.step(sim_obs, a)
            obs = self._observation(sim_obs)
            diverged = not self._finite(obs) or not math.isfinite(outcome.reward)
            if diverged:
                self.task.set_state(before)
        if diverged:
            outcome = self.task.diverged()
            obs = _copy_obs(self._last_obs)
        else:
            self._last_obs = _copy_obs(obs)
        terminated = outcome.success or outcome.failed
        self._ended = terminated
        info = self._info(sim_obs, obs, outcome, diverged)
        reward = self._reward(obs, outcome, info)
        if self.render_mode == "human":
            seed, steps, total, _, _ = self._live_episode
            self._live_episode = (seed, steps + 1, total + reward, info, terminated)
            self._show_live(force=terminated)
        return obs, reward, bool(terminated), False, info

    def render(self):
        """``render_mode="rgb_array"``: a ``(height, width, 3) uint8`` image of the scene. ``"human"``: push the
        current state to the live view now (``reset`` and ``step`` do so already); returns None. No render mode:
        None."""
        if self.render_mode is None:
            return None
        if self._last_obs is None:
            raise RuntimeError("call reset() before render()")
        if self.render_mode == "human":
            self._show_live(force=True)
            return None
        from suture_gym.render import SceneRenderer

        if self._renderer is None:
            r = self.config.render
            self._renderer = SceneRenderer(r.width, r.height, ssaa=r.ssaa)
            self._renderer.fit_camera(self.sim.view_points(), direction=(1.0, -0.35, 0.9), margin=1.02)
        return self._renderer.render(self.view_frame())

    def close(self) -> None:
        """Release the renderer and the live view; ``reset``, ``step``, ``get_state`` and ``set_state`` raise
        RuntimeError afterwards (closing again is allowed)."""
        self._closed = True
        self._renderer = None
        if self._live is not None:
            self._live.close()
            self._live = None
        super().close()

    def view_frame(self):
        """The current state as a :class:`~suture_gym.render.RenderFrame` (tissue surface, needle, thread, the
        planned entry and exit markers, tip force and a caption), what both the offline renderer and the live
        view draw."""
        caption = f"{self.config.task.replace('_', ' ')}  t={self.sim.time:.2f}s"
        return self.sim.render_frame(self._markers(), caption)

    def planned_arc_points(self, samples: int = 48) -> list[np.ndarray]:
        """The planned stitches' arcs from entry to exit: one ``(samples, 3)`` polyline per stitch, m."""
        if isinstance(samples, bool) or not isinstance(samples, int) or samples < 2:
            raise ValueError(f"samples must be an integer >= 2, got {samples!r}")
        return [np.array([arc.point(a) for a in np.linspace(arc.entry_angle, arc.exit_angle, samples)])
                for arc in self.sim.arcs]

    def _show_live(self, force: bool) -> None:
        """Push the episode to the live view (``render_mode="human"``), starting its server on first use."""
        from suture_gym.render.live import EpisodeStatus, LiveView

        r = self.config.render
        if self._live is None:
            self._live = LiveView(r.viewer_host, r.viewer_port, r.viewer_fps, self.config.action.max_force,
                                  label=f"suture_gym {self.spec.id if self.spec else self.config.task}")
        seed, steps, total, info, ended = self._live_episode
        state = ("success" if info.get("is_success") else "ended") if ended else "running"
        status = EpisodeStatus(seed, steps, self.sim.time, total, state, "env")
        self._live.show(self.view_frame(), self.planned_arc_points(), self.sim.grip_pose()[0], info, status,
                        force=force)

    def action_toward(self, target_pos: np.ndarray, target_quat: np.ndarray) -> np.ndarray:
        """``(6,) float32`` action in [-1, 1] that moves the holder toward the grip pose ``target_pos`` (3,) m,
        ``target_quat`` (4,): in ``wrench`` mode the virtual coupling's wrench toward it divided by the action
        scale; in ``pose_delta`` mode the change of the holder target toward it divided by the per-step
        limits. Clipped to [-1, 1]."""
        target_pos = np.asarray(target_pos, dtype=np.float64)
        target_quat = np.asarray(target_quat, dtype=np.float64)
        if self.config.action.mode == "wrench":
            return self.action_for_wrench(self.sim.coupling_spring.wrench(
                self.sim.model.needle, self.sim.state.needle, target_pos, target_quat))
        cfg = self.config.action
        rot, centre = self._action_frame()
        turn = quat_mul(target_quat, quat_conj(self._target_quat))
        turned = self._target_pos if centre is None else centre + quat_rotate(turn, self._target_pos - centre)
        action = np.concatenate([rot.T @ (target_pos - turned) / cfg.max_translation,
                                 rot.T @ quat_rotation_vector(turn) / self._rotation_scale])
        return np.clip(action, -1.0, 1.0).astype(np.float32)

    def action_for_wrench(self, wrench: np.ndarray) -> np.ndarray:
        """``(6,) float32`` action in [-1, 1] of ``wrench`` mode that applies the grip wrench ``wrench`` ``(6,)``
        [N, N m] (force, then torque about the grip point), clipped to the action limits."""
        if self.config.action.mode != "wrench":
            raise ValueError(f"action_for_wrench needs action.mode 'wrench', the env has {self.config.action.mode!r}")
        wrench = np.asarray(wrench, dtype=np.float64)
        if wrench.shape != (6,):
            raise ValueError(f"wrench must have shape (6,), got {wrench.shape}")
        rot, centre = self._action_frame()
        force, torque = wrench[:3], wrench[3:]
        if centre is not None:  # the same wrench about the circle's centre, in the needle's axes
            torque = torque - np.cross(centre - self.sim.grip_pose()[0], force)
            force, torque = rot.T @ force, rot.T @ torque
        return np.clip(np.concatenate([force, torque]) / self._wrench_scale, -1.0, 1.0).astype(np.float32)

    def _action_frame(self) -> tuple[np.ndarray, np.ndarray | None]:
        """``(R (3, 3), centre (3,) m or None)``: the axes the action is read in (columns, world frame) and the
        point it turns about (None: the grip point, world frame) for ``action.frame``."""
        if self.config.action.frame == "world":
            return np.eye(3), None
        needle = self.sim.state.needle
        rot = quat_to_matrix(needle.body_quat)
        return rot, needle.body_pos + rot @ self.sim.model.needle.arc_center_body

    def _world_wrench(self, wrench: np.ndarray) -> np.ndarray:
        """The grip wrench ``(6,)`` [N, N m] (world frame, torque about the grip) of the action's ``wrench``."""
        rot, centre = self._action_frame()
        if centre is None:
            return wrench
        force, torque = rot @ wrench[:3], rot @ wrench[3:]
        return np.concatenate([force, torque + np.cross(centre - self.sim.grip_pose()[0], force)])

    def scripted_action(self, tip_angle: float, stitch: int | None = None) -> np.ndarray:
        """:meth:`action_toward` the needle lying on stitch ``stitch``'s planned circle (default: the current
        stitch) with its tip at ``tip_angle`` (rad, :class:`~suture_gym.tasks.PlannedArc` convention): how a
        surgeon drives a curved needle, about its own centre. A scripted surgeon advances ``tip_angle`` a
        little every step."""
        arc = self.sim.arcs[self.task.state.stitch if stitch is None else stitch]
        return self.action_toward(*self.sim.arc_grip_target(arc, tip_angle))

    # ------------------------------------------------------------------------------------------------------
    # Snapshots
    # ------------------------------------------------------------------------------------------------------

    def get_state(self) -> EnvState:
        """A deep snapshot of the episode (physics, task bookkeeping, holder target, last observation and the
        random generator). Wrappers' own counters (``TimeLimit``'s elapsed steps) are not part of it."""
        self._check_open()
        if self._last_obs is None:
            raise RuntimeError("call reset() before get_state()")
        return EnvState(
            simulation=self.sim.snapshot(),
            task=self.task.get_state(),
            target_pos=self._target_pos.copy(),
            target_quat=self._target_quat.copy(),
            last_observation=_copy_obs(self._last_obs),
            rng_state=self.np_random.bit_generator.state,
            ended=self._ended,
        )

    def set_state(self, state: EnvState) -> None:
        """Restore a :meth:`get_state` snapshot; replaying the same actions then gives identical results.

        Raises:
            ValueError: ``state`` is not an :class:`EnvState`, or is one of another task, scene or observation
                layout (an env of another id or config), naming what differs; the env is left unchanged.
        """
        self._check_open()
        if not isinstance(state, EnvState):
            raise ValueError(f"state must be an EnvState from get_state(), got {type(state).__name__}")
        if _layout(state.last_observation) != _layout(self.observation_space):
            raise ValueError(f"state's observation has the layout {_layout(state.last_observation)}, this env's "
                             f"{_layout(self.observation_space)}: the state is of another id or config")
        self.sim.restore(state.simulation)
        self.task = self._make_task()
        self.task.set_state(state.task)
        self._target_pos = state.target_pos.copy()
        self._target_quat = state.target_quat.copy()
        self._last_obs = _copy_obs(state.last_observation)
        self._ended = state.ended
        self.np_random.bit_generator.state = state.rng_state

    # ------------------------------------------------------------------------------------------------------
    # Helpers
    # ------------------------------------------------------------------------------------------------------

    @property
    def last_observation(self):
        """A copy of the last observation returned (None before the first reset)."""
        return None if self._last_obs is None else _copy_obs(self._last_obs)

    @property
    def params(self) -> EpisodeParams:
        """The current episode's parameters (nominal ones before the first reset)."""
        return self.sim.params if self.sim.params is not None else nominal_params(self.config)

    def _make_task(self) -> Task:
        cfg = self.config
        return self.task_cls(
            arcs=self.sim.arcs,
            reward=cfg.reward,
            tear_force=cfg.coupling.tear_force,
            thread_target=cfg.plan.thread_target,
            closure_target=cfg.plan.closure_target,
            workspace=self.sim.workspace,
            gap_rest=self.sim.gap_rest,
            end_on_tear=cfg.termination.end_on_tear,
            end_on_miss=cfg.termination.end_on_miss and not self._GOAL_CONDITIONED,
            params=cfg.task_params,
        )

    def _check_open(self) -> None:
        if self._closed:
            raise RuntimeError(f"this {self.config.task} env was closed (close() was called); make a new one")

    @staticmethod
    def _check_action(action) -> np.ndarray:
        a = np.asarray(action)
        if a.dtype.kind not in "iuf":
            raise TypeError(f"action must hold real numbers (a float or integer array), got dtype {a.dtype}")
        a = a.astype(np.float64)
        if a.shape != (6,):
            raise ValueError(f"action must have shape (6,), got {a.shape}")
        if not np.all(np.isfinite(a)):
            bad = [i for i in range(6) if not math.isfinite(a[i])]
            raise ValueError(f"action must be finite; components {bad} are {[float(a[i]) for i in bad]}")
        return np.clip(a, -1.0, 1.0)

    @staticmethod
    def _finite(obs) -> bool:
        if isinstance(obs, dict):
            return all(bool(np.all(np.isfinite(v))) for v in obs.values())
        return bool(np.all(np.isfinite(obs)))

    def _reward(self, obs, outcome, info) -> float:
        return outcome.reward

    def _vector(self, o: Observables) -> np.ndarray:
        """The flat float32 observation of ``o`` (layout, scales and bounds in :mod:`suture_gym.envs.spaces`)."""
        buf = self._obs_buffer
        ix = self.obs_index
        arc = self.task.arc
        st = self.task.state
        c = arc.center
        buf[ix["tip_pos"]] = o.tip_pos - c
        buf[ix["tip_dir"]] = o.tip_dir
        buf[ix["needle_normal"]] = o.needle_normal
        buf[ix["grip_pos"]] = o.grip_pos - c
        buf[ix["needle_vel"]] = o.needle_vel
        buf[ix["needle_omega"]] = o.needle_omega
        buf[ix["entry_rel"]] = arc.entry - o.tip_pos
        buf[ix["exit_rel"]] = arc.exit - o.tip_pos
        buf[ix["arc_progress"]] = arc.progress(o.tip_pos)
        buf[ix["arc_distance"]] = arc.distance(o.tip_pos)
        buf[ix["tip_sdist"]] = min(max(o.tip_sdist, -SDIST_CLIP), SDIST_CLIP)
        buf[ix["punctured"]] = float(o.punctured)
        buf[ix["stitch"]] = float(st.stitch)
        buf[ix["stitch_exited"]] = float(st.exited)
        buf[ix["tip_force"]] = o.tip_force
        buf[ix["tissue_force"]] = o.tissue_force
        buf[ix["haptic_force"]] = o.haptic_wrench[:3]
        buf[ix["haptic_torque"]] = o.haptic_wrench[3:]
        buf[ix["wound_gap"]] = o.wound_gap
        buf[ix["thread_through"]] = o.thread_through
        if "suture_samples" in ix:
            buf[ix["suture_samples"]] = (o.suture_samples - c).ravel()
        if "target_offset" in ix:
            grip_pos, grip_quat = self.sim.grip_pose()
            buf[ix["target_offset"]] = self._target_pos - grip_pos
            buf[ix["target_rotation"]] = quat_rotation_vector(quat_mul(self._target_quat, quat_conj(grip_quat)))
        if "params" in ix:
            buf[ix["params"]] = self.params.as_array()
        return np.clip(buf / self.obs_scale, -self.obs_bound, self.obs_bound).astype(np.float32)

    def _observation(self, o: Observables):
        if self.sensors is None:
            return self._vector(o)
        obs = self.sensors.observe(self.sim, self._markers())
        if self.config.observation.include_state:
            obs["state"] = self._vector(o)
        return obs

    def _info(self, o: Observables, obs, outcome, diverged: bool) -> dict:
        """The step's ``info`` from the observables ``o``, the observation returned ``obs``, the task's outcome
        (None at reset) and whether the simulation diverged."""
        terms = self._term_names()
        info = {
            "is_success": bool(outcome.success) if outcome is not None else False,
            "punctured": bool(o.punctured),
            "tip_force": float(o.tip_force) if math.isfinite(o.tip_force) else 0.0,
            "haptic_wrench": (
                o.haptic_wrench.copy() if np.all(np.isfinite(o.haptic_wrench)) else np.zeros(6)
            ),
            "wound_gap": float(o.wound_gap) if math.isfinite(o.wound_gap) else 0.0,
            "diverged": bool(diverged),
            "cost": float(outcome.cost) if outcome is not None else 0.0,
            "tear": bool(outcome.tear) if outcome is not None else False,
            "out_of_workspace": bool(outcome.out_of_workspace) if outcome is not None else False,
            "missed": bool(outcome.missed) if outcome is not None else False,
            "crushed": bool(outcome.crushed) if outcome is not None else False,
            "wound_overlap": float(o.wound_overlap) if math.isfinite(o.wound_overlap) else 0.0,
            "stitch": int(self.task.state.stitch),
        }
        for name in terms:
            info[f"reward_{name}"] = 0.0
        if outcome is not None:
            for name in terms:
                if name in outcome.terms:
                    info[f"reward_{name}"] = float(outcome.terms[name])
        return info

    def _term_names(self) -> tuple[str, ...]:
        return self.task_cls.TERMS

    def _markers(self) -> np.ndarray:
        """``(P, 3)`` planned entry and exit of every stitch, m (drawn as markers, entry green, exit red)."""
        return np.concatenate([[arc.entry, arc.exit] for arc in self.sim.arcs])


class SutureGoalEnv(SutureEnv):
    """Goal-conditioned variant for hindsight experience replay (HER).

    Observation: ``Dict(observation=Box(...), achieved_goal=Box(G), desired_goal=Box(G))`` with the task's
    ``GOAL_LAYOUT``. Reward terms: ``goal`` (sparse: -1 until the goal is reached, else 0; or dense, see
    ``reward.goal``), ``failure``, ``tissue_force`` and ``action`` (as in :class:`SutureEnv`).
    :meth:`compute_reward` recomputes the reward of any (achieved, desired) pair, batched, from the goals and
    ``info``'s ``reward_failure``, ``reward_tissue_force`` and ``reward_action``; the env's reward is exactly
    that value.
    """

    _GOAL_CONDITIONED = True

    def __init__(self, task: str | None = None, config=None, render_mode: str | None = None,
                 action_mode: str | None = None) -> None:
        super().__init__(task, config, render_mode, action_mode)
        if not self.config.observation.include_state:
            raise ValueError("observation.include_state = false is not available in the goal-conditioned ids: their "
                             "'observation' key is the state vector")
        size = self.task_cls.GOAL_SIZE
        self.observation_space = gym.spaces.Dict(
            {
                "observation": self.state_space,
                "achieved_goal": gym.spaces.Box(-np.inf, np.inf, (size,), np.float32),
                "desired_goal": gym.spaces.Box(-np.inf, np.inf, (size,), np.float32),
                **sensor_spaces(self.config),
            }
        )

    def _observation(self, o: Observables):
        obs = {
            "observation": self._vector(o),
            "achieved_goal": self.task.achieved_goal(o).astype(np.float32),
            "desired_goal": self.task.desired_goal().astype(np.float32),
        }
        if self.sensors is not None:
            obs.update(self.sensors.observe(self.sim, self._markers()))
        return obs

    def _term_names(self) -> tuple[str, ...]:
        return self.task_cls.GOAL_TERMS

    def _info(self, o: Observables, obs, outcome, diverged: bool) -> dict:
        info = super()._info(o, obs, outcome, diverged)
        if outcome is not None:
            info["reward_goal"] = float(self._goal_term(obs["achieved_goal"][None, :], obs["desired_goal"][None, :])[0])
        return info

    def _reward(self, obs, outcome, info) -> float:
        return float(self.compute_reward(obs["achieved_goal"], obs["desired_goal"], info))

    def _goal_term(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return self.task.goal_term(achieved.astype(np.float64), desired.astype(np.float64))

    def compute_reward(self, achieved_goal, desired_goal, info):
        """Reward of ``achieved_goal`` against ``desired_goal``: ``math.fsum`` of the goal term and ``info``'s
        ``reward_failure``, ``reward_tissue_force`` and ``reward_action``.

        Args:
            achieved_goal, desired_goal: ``(G,)`` or ``(B, G)`` arrays.
            info: one info dict, or a sequence of B of them (HER passes an array of dicts). A missing term
                counts as 0: SB3's ``HerReplayBuffer`` passes empty dicts unless it is built with
                ``replay_buffer_kwargs={"copy_info_dict": True}``, which keeps the failure, tissue-force and
                action terms in relabelled rewards.

        Returns:
            A float for ``(G,)`` goals, else a ``(B,) float64`` array.
        """
        achieved = np.asarray(achieved_goal, dtype=np.float64)
        desired = np.asarray(desired_goal, dtype=np.float64)
        single = achieved.ndim == 1
        achieved = np.atleast_2d(achieved)
        desired = np.atleast_2d(desired)
        if achieved.shape != desired.shape:
            raise ValueError(f"achieved_goal {achieved.shape} and desired_goal {desired.shape} differ in shape")
        infos = [info] * achieved.shape[0] if isinstance(info, dict) else list(info)
        if len(infos) != achieved.shape[0]:
            raise ValueError(f"info holds {len(infos)} dicts for {achieved.shape[0]} goals")
        goal = self._goal_term(achieved, desired)
        read_back = self.task_cls.GOAL_TERMS[1:]
        rewards = np.array([math.fsum([float(g), *(i.get(f"reward_{t}", 0.0) for t in read_back)])
                            for g, i in zip(goal, infos, strict=True)])
        return float(rewards[0]) if single else rewards
