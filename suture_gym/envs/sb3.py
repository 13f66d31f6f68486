"""Adapter from :class:`~suture_gym.envs.vector.SutureVectorEnv` to Stable-Baselines3's ``VecEnv``.

Stable-Baselines3 (and torch) are an optional extra (``pip install suture_gym[train]``); this is the only module
of the package that imports them.

:func:`make_sb3_vec_env` builds the batched env of an env id in ``SAME_STEP`` autoreset mode and wraps it: SB3's
conventions follow (an env that finishes resets within the step, its last observation is
``infos[i]["terminal_observation"]`` and ``infos[i]["TimeLimit.truncated"]`` marks a time-limit end), and
``monitor=True`` adds SB3's ``VecMonitor`` so episode returns and lengths reach the logger. Goal-conditioned ids
work with ``HerReplayBuffer``: ``env_method("compute_reward", ...)`` reaches the envs' batched ``compute_reward``.
The pixel and point-cloud observation modes give ``Dict`` observations for ``MultiInputPolicy``; wrap them in
``VecNormalize`` with ``norm_obs_keys=norm_obs_keys(env.observation_space)`` (:func:`norm_obs_keys`), so the
images are left to the policy's own scaling.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import Any

import gymnasium as gym
import numpy as np
from gymnasium.vector import AutoresetMode
from stable_baselines3.common.vec_env import VecEnv, VecMonitor

from suture_gym.envs.vector import SutureVectorEnv, make_vector_env


class SB3VecEnv(VecEnv):
    """SB3 ``VecEnv`` view of a :class:`~suture_gym.envs.vector.SutureVectorEnv` in ``SAME_STEP`` mode.

    Args:
        vector_env: the batched env; its ``metadata["autoreset_mode"]`` must be ``SAME_STEP``.
    """

    def __init__(self, vector_env: SutureVectorEnv) -> None:
        if not isinstance(vector_env, SutureVectorEnv):
            raise ValueError(f"vector_env must be a SutureVectorEnv, got {type(vector_env).__name__}")
        if vector_env.metadata["autoreset_mode"] != AutoresetMode.SAME_STEP:
            raise ValueError("vector_env must use AutoresetMode.SAME_STEP (make_sb3_vec_env builds one)")
        self.vector_env = vector_env
        self._actions: np.ndarray | None = None
        super().__init__(vector_env.num_envs, vector_env.single_observation_space, vector_env.single_action_space)

    def reset(self):
        """Reset every env with the seeds and options set through ``seed()`` / ``set_options()``."""
        options = [dict(o) for o in self._options]
        results = self.vector_env.reset_each(list(self._seeds), options)
        for i, (_, info) in enumerate(results):
            self.reset_infos[i] = info
        self._reset_seeds()
        self._reset_options()
        return self.vector_env.batch([obs for obs, _ in results])

    def step_async(self, actions: np.ndarray) -> None:
        self._actions = np.asarray(actions)

    def step_wait(self):
        if self._actions is None:
            raise RuntimeError("step_async must be called before step_wait")
        results = self.vector_env.step_each(self._actions)
        self._actions = None
        infos: list[dict[str, Any]] = []
        for i, r in enumerate(results):
            if r.final_info is not None:
                info = dict(r.final_info)
                info["terminal_observation"] = r.final_obs
                info["TimeLimit.truncated"] = bool(r.truncated and not r.terminated)
                self.reset_infos[i] = r.info
            else:
                info = dict(r.info)
            infos.append(info)
        obs = self.vector_env.batch([r.obs for r in results])
        rewards = np.array([r.reward for r in results], dtype=np.float32)
        dones = np.array([r.terminated or r.truncated for r in results], dtype=np.bool_)
        return obs, rewards, dones, infos

    def close(self) -> None:
        self.vector_env.close()

    def get_images(self) -> Sequence[np.ndarray | None]:
        return list(self.vector_env.call("render"))

    def get_attr(self, attr_name: str, indices=None) -> list[Any]:
        return list(self.vector_env.get_attr(attr_name, indices=indices))

    def set_attr(self, attr_name: str, value: Any, indices=None) -> None:
        targets = self.vector_env._indices(indices)
        self.vector_env.set_attr(attr_name, [value] * len(targets), indices=targets)

    def env_method(self, method_name: str, *method_args, indices=None, **method_kwargs) -> list[Any]:
        return list(self.vector_env.call(method_name, *method_args, indices=indices, **method_kwargs))

    def env_is_wrapped(self, wrapper_class, indices=None) -> list[bool]:
        return [False for _ in self.vector_env._indices(indices)]


def norm_obs_keys(observation_space: gym.spaces.Space) -> list[str] | None:
    """The keys of a ``Dict`` observation space that ``VecNormalize`` should normalise: all but the ``uint8``
    images (``rgb``), which SB3's policies scale by 1/255 themselves (normalised, they would turn into float
    vectors that SB3 no longer treats as images); the state vector, a depth image (per pixel) and a point cloud
    (per row) are normalised. None for any other space (``VecNormalize`` then takes no keys)."""
    if not isinstance(observation_space, gym.spaces.Dict):
        return None
    return [key for key, space in observation_space.spaces.items()
            if not (isinstance(space, gym.spaces.Box) and space.dtype == np.uint8 and len(space.shape) == 3)]


def make_sb3_vec_env(env_id: str, num_envs: int = 1, *, monitor: bool = True, **kwargs) -> VecEnv:
    """An SB3 ``VecEnv`` of ``num_envs`` batched envs of the registered SutureGym id ``env_id``.

    Args:
        env_id: a registered id, flat (``"SutureGym/NeedleInsert-v3"``) or goal-conditioned
            (``"SutureGym/NeedleInsertGoal-v3"``, for HER); anything else raises ValueError listing the ids.
        num_envs: N >= 1.
        monitor: wrap the result in SB3's ``VecMonitor`` (episode returns and lengths in ``info["episode"]``).
        **kwargs: go to :func:`~suture_gym.envs.vector.make_vector_env` (``config``, ``action_mode``,
            ``render_mode``, ``max_episode_steps``, the id's time limit by default; ``workers``,
            ``worker_timeout``, ``restart_workers``). With ``restart_workers=True`` a worker that dies or stops
            answering is replaced and its envs' episodes end as time-limit truncations
            (``infos[i]["TimeLimit.truncated"]``, ``infos[i]["worker_restarted"]``, the last observation as
            ``terminal_observation``), so training loses those episodes, not the run.
    """
    if "autoreset_mode" in kwargs:
        raise ValueError("make_sb3_vec_env always uses AutoresetMode.SAME_STEP; do not pass autoreset_mode")
    vector_env = make_vector_env(env_id, num_envs, autoreset_mode=AutoresetMode.SAME_STEP, **kwargs)
    env = SB3VecEnv(vector_env)
    return VecMonitor(env) if monitor else env
