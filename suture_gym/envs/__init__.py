"""Gymnasium environments for suturing; importing this module registers the ids.

* ``SutureGym/NeedleInsert-v3``: pierce at the marked entry, follow the planned arc, exit at the marked exit.
* ``SutureGym/SutureThrow-v3``: one stitch across both wound edges, thread pulled through to a target length.
* ``SutureGym/WoundClosure-v3``: several stitches and thread tension close the wound gap.
* ``SutureGym/NeedleInsertGoal-v3``, ``SutureGym/SutureThrowGoal-v3``, ``SutureGym/WoundClosureGoal-v3``: the
  goal-conditioned (HER) variants (Dict observations, batched ``compute_reward``).

Each id is one line below: :func:`~suture_gym.envs.registry.register_task` derives the ids, the time limit
(:data:`MAX_EPISODE_STEPS`), the env class (``help(env.unwrapped)`` documents the id) and the config defaults
from the task class. ``gym.make(id, config=..., render_mode=..., action_mode=...)`` builds one env (a subclass
of :class:`SutureEnv` or :class:`SutureGoalEnv`); ``gym.make_vec(id, num_envs=N, wrappers=[...])`` builds
Gymnasium's ``SyncVectorEnv`` of wrapped envs; :func:`make_vector_env` builds the natively batched
:class:`SutureVectorEnv` of an id, and :func:`suture_gym.envs.sb3.make_sb3_vec_env` adapts that to
Stable-Baselines3 (optional extra).
"""

from __future__ import annotations

from suture_gym.envs.base import EnvState, SutureEnv, SutureGoalEnv
from suture_gym.envs.config import EnvConfig, default_config, load_config, save_config
from suture_gym.envs.registry import (
    ENV_IDS,
    GOAL_ENV_IDS,
    MAX_EPISODE_STEPS,
    TASK_CLASSES,
    env_id_task,
    make_env,
    register_task,
    registered_tasks,
    task_class,
)
from suture_gym.envs.vector import SutureVectorEnv, WorkerError, make_vector_env
from suture_gym.tasks import NeedleInsert, SutureThrow, WoundClosure

register_task(NeedleInsert)
register_task(SutureThrow)
register_task(WoundClosure)

__all__ = [
    "ENV_IDS",
    "GOAL_ENV_IDS",
    "MAX_EPISODE_STEPS",
    "TASK_CLASSES",
    "EnvConfig",
    "EnvState",
    "SutureEnv",
    "SutureGoalEnv",
    "SutureVectorEnv",
    "WorkerError",
    "default_config",
    "env_id_task",
    "load_config",
    "make_env",
    "make_vector_env",
    "register_task",
    "registered_tasks",
    "save_config",
    "task_class",
]
