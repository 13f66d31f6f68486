"""Gymnasium environments for suturing; importing this module registers the ids.

* ``SutureGym/NeedleInsert-v0``: pierce at the marked entry, follow the planned arc, exit at the marked exit.
* ``SutureGym/SutureThrow-v0``: one stitch across both wound edges, thread pulled through to a target length.
* ``SutureGym/WoundClosure-v0``: several stitches and thread tension close the wound gap.
* ``SutureGym/NeedleInsertGoal-v0``, ``SutureGym/SutureThrowGoal-v0``, ``SutureGym/WoundClosureGoal-v0``: the
  goal-conditioned (HER) variants (Dict observations, batched ``compute_reward``).

Time limits are in :data:`MAX_EPISODE_STEPS`. ``gym.make(id, config=..., render_mode=..., action_mode=...)``
builds one env (:class:`SutureEnv` or :class:`SutureGoalEnv`); ``gym.make_vec(id, num_envs=N)`` builds the
batched :class:`SutureVectorEnv` (every id has a ``vector_entry_point``);
:func:`suture_gym.envs.sb3.make_sb3_vec_env` adapts that to Stable-Baselines3 (optional extra).
"""

from __future__ import annotations

import gymnasium as gym

from suture_gym.envs.base import EnvState, SutureEnv, SutureGoalEnv
from suture_gym.envs.config import EnvConfig, default_config, load_config, save_config
from suture_gym.envs.vector import SutureVectorEnv

#: Registered task ids (without the goal-conditioned variants) -> config task name.
ENV_IDS: dict[str, str] = {
    "SutureGym/NeedleInsert-v0": "needle_insert",
    "SutureGym/SutureThrow-v0": "suture_throw",
    "SutureGym/WoundClosure-v0": "wound_closure",
}
#: Goal-conditioned ids -> config task name.
GOAL_ENV_IDS: dict[str, str] = {
    "SutureGym/NeedleInsertGoal-v0": "needle_insert",
    "SutureGym/SutureThrowGoal-v0": "suture_throw",
    "SutureGym/WoundClosureGoal-v0": "wound_closure",
}
#: Time limit of each task, env steps (the default control period is ``solver.dt * solver.substeps``).
MAX_EPISODE_STEPS: dict[str, int] = {"needle_insert": 600, "suture_throw": 2000, "wound_closure": 5000}


def make_env(task: str = "needle_insert", goal_conditioned: bool = False, config=None, render_mode=None,
             action_mode=None) -> SutureEnv:
    """One env of ``task``: a :class:`SutureGoalEnv` if ``goal_conditioned``, else a :class:`SutureEnv`."""
    cls = SutureGoalEnv if goal_conditioned else SutureEnv
    return cls(task, config=config, render_mode=render_mode, action_mode=action_mode)


def _register() -> None:
    for table, goal in ((ENV_IDS, False), (GOAL_ENV_IDS, True)):
        for env_id, task in table.items():
            if env_id in gym.registry:
                continue
            gym.register(
                id=env_id,
                entry_point=make_env,
                vector_entry_point=SutureVectorEnv,
                max_episode_steps=MAX_EPISODE_STEPS[task],
                kwargs={"task": task, "goal_conditioned": goal},
            )


_register()

__all__ = [
    "ENV_IDS",
    "GOAL_ENV_IDS",
    "MAX_EPISODE_STEPS",
    "EnvConfig",
    "EnvState",
    "SutureEnv",
    "SutureGoalEnv",
    "SutureVectorEnv",
    "default_config",
    "load_config",
    "make_env",
    "save_config",
]
