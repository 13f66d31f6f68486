"""A natively batched :class:`gymnasium.vector.VectorEnv`: N simulators stepped in one process.

:func:`make_vector_env` builds one from an env id (``gym.make_vec`` builds Gymnasium's ``SyncVectorEnv`` instead,
so that its ``wrappers`` argument works; see :mod:`suture_gym.envs.registry`). It holds N unwrapped
:class:`~suture_gym.envs.base.SutureEnv` (or :class:`~suture_gym.envs.base.SutureGoalEnv`) instances, steps them
in turn, batches their observations into fresh arrays and enforces the time limit itself. Autoreset follows
gymnasium's modes: ``NEXT_STEP`` (the default: the step after an episode ends resets that env and returns its
first observation with reward 0) or ``SAME_STEP`` (the env resets within the step that ended it; the last
observation and info are in ``infos["final_obs"]`` and ``infos["final_info"]``, as SB3 expects).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from gymnasium.vector.utils import batch_space, concatenate, create_empty_array

from suture_gym.envs.base import EnvState
from suture_gym.envs.registry import MAX_EPISODE_STEPS, env_id_task, make_env


@dataclass(frozen=True)
class StepResult:
    """One env's share of a vector step (unbatched).

    Attributes:
        obs: the observation returned (after an autoreset in ``SAME_STEP`` mode, the new episode's first one).
        reward, terminated, truncated, info: the step's results (reward 0 and both flags False for the step
            that autoresets in ``NEXT_STEP`` mode; ``info`` is then the reset's).
        final_obs, final_info: the finished episode's last observation and info (``SAME_STEP`` mode, when
            the episode ended this step), else None.
    """

    obs: Any
    reward: float
    terminated: bool
    truncated: bool
    info: dict
    final_obs: Any
    final_info: dict | None


@dataclass(frozen=True)
class VectorEnvState:
    """Snapshot of a :class:`SutureVectorEnv`: each env's :class:`~suture_gym.envs.base.EnvState`, the
    steps taken in each episode and which envs reset on the next step (``NEXT_STEP`` mode)."""

    envs: tuple[EnvState, ...]
    elapsed: np.ndarray
    pending_reset: np.ndarray


class SutureVectorEnv(gym.vector.VectorEnv):
    """N suturing envs of one task, batched (module docstring).

    Args:
        task: a registered task name (``"needle_insert"``, ``"suture_throw"``, ``"wound_closure"``, ...).
        num_envs: N >= 1.
        config: as for :class:`~suture_gym.envs.base.SutureEnv` (shared by all N).
        render_mode: None or ``"rgb_array"`` (:meth:`render` returns one image per env).
        action_mode: as for :class:`~suture_gym.envs.base.SutureEnv`.
        goal_conditioned: batch :class:`~suture_gym.envs.base.SutureGoalEnv` instead.
        max_episode_steps: truncate episodes after this many steps (None: no limit); :func:`make_vector_env`
            passes the id's registered limit.
        autoreset_mode: :class:`gymnasium.vector.AutoresetMode` ``NEXT_STEP`` or ``SAME_STEP``.
    """

    def __init__(self, task: str = "needle_insert", num_envs: int = 1, config=None, render_mode: str | None = None,
                 action_mode: str | None = None, goal_conditioned: bool = False, max_episode_steps: int | None = None,
                 autoreset_mode: AutoresetMode | str = AutoresetMode.NEXT_STEP) -> None:
        if isinstance(num_envs, bool) or not isinstance(num_envs, int) or num_envs < 1:
            raise ValueError(f"num_envs must be an integer >= 1, got {num_envs!r}")
        if max_episode_steps is not None and (
            isinstance(max_episode_steps, bool) or not isinstance(max_episode_steps, int) or max_episode_steps < 1
        ):
            raise ValueError(f"max_episode_steps must be None or an integer >= 1, got {max_episode_steps!r}")
        mode = AutoresetMode(autoreset_mode)
        if mode not in (AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP):
            raise ValueError(f"autoreset_mode must be NEXT_STEP or SAME_STEP, got {mode!r}")
        self.envs = [make_env(task, goal_conditioned, config, render_mode, action_mode) for _ in range(num_envs)]
        first = self.envs[0]
        self.num_envs = num_envs
        self.render_mode = render_mode
        self.max_episode_steps = max_episode_steps
        self.single_observation_space = first.observation_space
        self.single_action_space = first.action_space
        self.observation_space = batch_space(self.single_observation_space, num_envs)
        self.action_space = batch_space(self.single_action_space, num_envs)
        self.metadata = {**first.metadata, "autoreset_mode": mode}
        self._elapsed = np.zeros(num_envs, dtype=np.int64)
        self._pending_reset = np.zeros(num_envs, dtype=np.bool_)

    @property
    def config(self):
        """The shared :class:`~suture_gym.envs.config.EnvConfig`."""
        return self.envs[0].config

    def reset(self, *, seed: int | list[int | None] | None = None, options: dict | None = None):
        """Reset the envs: ``seed`` int gives env ``i`` the seed ``seed + i``; a list gives one per env.

        ``options`` go to every env's reset, except ``reset_mask`` ((N,) bool), which resets only those envs
        (the others keep their state and return their last observation).
        """
        if seed is None or isinstance(seed, int):
            seeds = [None if seed is None else seed + i for i in range(self.num_envs)]
        else:
            seeds = list(seed)
            if len(seeds) != self.num_envs:
                raise ValueError(f"seed must be None, an int or a list of {self.num_envs} seeds, got {len(seeds)}")
        options = dict(options or {})
        mask = np.asarray(options.pop("reset_mask", np.ones(self.num_envs, dtype=bool)))
        if mask.shape != (self.num_envs,) or mask.dtype != np.bool_:
            raise ValueError(f"options['reset_mask'] must be a ({self.num_envs},) bool array")
        results = self.reset_each(seeds, [options if m else None for m in mask])
        infos: dict = {}
        observations = []
        for i, result in enumerate(results):
            if result is None:
                observations.append(self.envs[i].last_observation)
            else:
                observations.append(result[0])
                infos = self._add_info(infos, result[1], i)
        return self.batch(observations), infos

    def reset_each(self, seeds: list, options: list) -> list:
        """Reset env ``i`` with ``seeds[i]`` and ``options[i]`` unless ``options[i]`` is None; returns the
        ``(obs, info)`` of each reset env and None for the others."""
        results = []
        for env, seed, opts in zip(self.envs, seeds, options, strict=True):
            results.append(None if opts is None else env.reset(seed=seed, options=opts))
        for i, result in enumerate(results):
            if result is not None:
                self._elapsed[i] = 0
                self._pending_reset[i] = False
        return results

    def step(self, actions):
        """Step every env with its row of ``actions`` (N, 6); see the module docstring for autoreset."""
        results = self.step_each(actions)
        rewards = np.array([r.reward for r in results], dtype=np.float64)
        terminations = np.array([r.terminated for r in results], dtype=np.bool_)
        truncations = np.array([r.truncated for r in results], dtype=np.bool_)
        infos: dict = {}
        for i, r in enumerate(results):
            if r.final_info is not None:
                infos = self._add_info(infos, {"final_obs": r.final_obs, "final_info": r.final_info}, i)
            infos = self._add_info(infos, r.info, i)
        return self.batch([r.obs for r in results]), rewards, terminations, truncations, infos

    def step_each(self, actions) -> list[StepResult]:
        """Step every env and apply the autoreset mode; one :class:`StepResult` per env, unbatched."""
        actions = np.asarray(actions)
        if actions.shape != (self.num_envs, 6):
            raise ValueError(f"actions must have shape ({self.num_envs}, 6), got {actions.shape}")
        same_step = self.metadata["autoreset_mode"] == AutoresetMode.SAME_STEP
        results = []
        for i, env in enumerate(self.envs):
            if self._pending_reset[i]:
                obs, info = env.reset()
                self._elapsed[i] = 0
                self._pending_reset[i] = False
                results.append(StepResult(obs, 0.0, False, False, info, None, None))
                continue
            obs, reward, terminated, truncated, info = env.step(actions[i])
            self._elapsed[i] += 1
            if self.max_episode_steps is not None and self._elapsed[i] >= self.max_episode_steps:
                truncated = True
            final_obs = final_info = None
            if terminated or truncated:
                if same_step:
                    final_obs, final_info = obs, info
                    obs, info = env.reset()
                    self._elapsed[i] = 0
                else:
                    self._pending_reset[i] = True
            results.append(StepResult(obs, float(reward), bool(terminated), bool(truncated), info, final_obs,
                                      final_info))
        return results

    def render(self):
        """One ``(H, W, 3) uint8`` image per env (``render_mode="rgb_array"``), else None."""
        if self.render_mode is None:
            return None
        return tuple(env.render() for env in self.envs)

    def close_extras(self, **kwargs) -> None:
        for env in self.envs:
            env.close()

    def call(self, name: str, *args, **kwargs) -> tuple:
        """Call method ``name`` (or read attribute ``name``) of every env; returns the N results."""
        results = []
        for env in self.envs:
            attr = getattr(env, name)
            results.append(attr(*args, **kwargs) if callable(attr) else attr)
        return tuple(results)

    def get_attr(self, name: str) -> tuple:
        """Attribute ``name`` of every env."""
        return tuple(getattr(env, name) for env in self.envs)

    def set_attr(self, name: str, values) -> None:
        """Set attribute ``name`` of env ``i`` to ``values[i]`` (a list of N), or of all to ``values``."""
        if not isinstance(values, (list, tuple)):
            values = [values] * self.num_envs
        if len(values) != self.num_envs:
            raise ValueError(f"values must hold {self.num_envs} entries, got {len(values)}")
        for env, value in zip(self.envs, values, strict=True):
            setattr(env, name, value)

    def get_state(self) -> VectorEnvState:
        """Snapshot of every env and of the vector bookkeeping (restore with :meth:`set_state`)."""
        return VectorEnvState(tuple(env.get_state() for env in self.envs), self._elapsed.copy(),
                              self._pending_reset.copy())

    def set_state(self, state: VectorEnvState) -> None:
        """Restore a :meth:`get_state` snapshot."""
        if not isinstance(state, VectorEnvState) or len(state.envs) != self.num_envs:
            raise ValueError(f"state must be a VectorEnvState of {self.num_envs} envs")
        for env, env_state in zip(self.envs, state.envs, strict=True):
            env.set_state(env_state)
        self._elapsed[:] = state.elapsed
        self._pending_reset[:] = state.pending_reset

    def batch(self, observations: list):
        """Fresh batched observation (array or dict of arrays) of N single observations."""
        out = create_empty_array(self.single_observation_space, self.num_envs)
        return concatenate(self.single_observation_space, observations, out)


def make_vector_env(env_id: str, num_envs: int = 1, **kwargs) -> SutureVectorEnv:
    """A :class:`SutureVectorEnv` of ``num_envs`` envs of the registered SutureGym id ``env_id`` (flat or
    goal-conditioned), truncating at the id's time limit unless ``max_episode_steps`` is given.

    Keyword arguments go to :class:`SutureVectorEnv` (``config``, ``render_mode``, ``action_mode``,
    ``max_episode_steps``, ``autoreset_mode``); the id decides ``task`` and ``goal_conditioned``.

    Raises:
        ValueError: ``env_id`` is not a registered SutureGym id (the message lists them), or ``task`` /
            ``goal_conditioned`` were passed.
    """
    task, goal_conditioned = env_id_task(env_id)
    clash = sorted({"task", "goal_conditioned"} & set(kwargs))
    if clash:
        raise ValueError(f"make_vector_env takes the task from the env id {env_id!r}; do not pass {clash}")
    kwargs.setdefault("max_episode_steps", MAX_EPISODE_STEPS[task])
    return SutureVectorEnv(task, num_envs, goal_conditioned=goal_conditioned, **kwargs)
