"""Tasks as the unit of extension: a new task is one class (this module) and one ``register_task`` line, and
gets its env id, time limit, env class with its documentation, config defaults and config section from it;
every registered id documents itself in ``help(env.unwrapped)``."""

from __future__ import annotations

import math
import pydoc
from dataclasses import dataclass

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.utils.env_checker import check_env

from suture_gym.envs import (
    ENV_IDS,
    GOAL_ENV_IDS,
    MAX_EPISODE_STEPS,
    default_config,
    load_config,
    register_task,
    registered_tasks,
)
from suture_gym.envs.docs import SECTIONS
from suture_gym.tasks import Observables, StepContext, Task


@dataclass(frozen=True)
class TouchParams:
    """TouchEntry's own config section (``task_params``)."""

    weight: float = 0.1  # reward per step at full distance
    scale: float = 2.0e-3  # m, distance at which the touch term is half its weight

    def __post_init__(self) -> None:
        for name in ("weight", "scale"):
            value = getattr(self, name)
            if not (isinstance(value, float) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"{name} must be a positive number, got {value!r}")


class TouchEntry(Task):
    """Touch the first stitch's planned entry marker with the needle tip (a toy task of the tests).

    Success: the tip within ``reward.access_tolerance`` of the planned entry point.
    """

    NAME = "touch_entry"
    ENV_ID = "SutureGymTest/TouchEntry-v0"
    MAX_EPISODE_STEPS = 150
    CONFIG = {"scene": {"size": (0.008, 0.024, 0.006)}, "plan": {"start_angle": 0.5}}
    PARAMS = TouchParams
    TERMS = ("touch", "success", "failure", "action")
    GOAL_SIZE = 3
    GOAL_LAYOUT = (("tip_x", "m"), ("tip_y", "m"), ("tip_z", "m"))

    def term_touch(self, ctx: StepContext) -> float:
        """``-w d / (d + scale)``, ``d`` the tip's distance (m) to the planned entry; ``w``, ``scale`` from
        ``task_params``."""
        d = float(np.linalg.norm(ctx.obs.tip_pos - self.arcs[0].entry))
        return -self.params.weight * d / (d + self.params.scale)

    def achieved_goal(self, obs: Observables) -> np.ndarray:
        return obs.tip_pos.copy()

    def desired_goal(self) -> np.ndarray:
        return self.arcs[0].entry.copy()

    def goal_reached(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return np.linalg.norm(achieved - desired, axis=1) <= self.reward.access_tolerance

    def goal_distance(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        d = np.linalg.norm(achieved - desired, axis=1)
        return d / (d + self.reward.access_tolerance)


register_task(TouchEntry)


def test_the_new_task_gets_its_id_time_limit_and_config_defaults():
    assert "touch_entry" in registered_tasks()
    assert ENV_IDS[TouchEntry.ENV_ID] == "touch_entry" and TouchEntry.ENV_ID not in GOAL_ENV_IDS
    assert MAX_EPISODE_STEPS["touch_entry"] == 150
    assert gym.spec(TouchEntry.ENV_ID).max_episode_steps == 150
    cfg = default_config("touch_entry")
    assert cfg.scene.size == (0.008, 0.024, 0.006) and cfg.task_params == TouchParams()
    assert load_config("touch_entry", {"task_params": {"weight": 0.5}}).task_params.weight == 0.5
    with pytest.raises(ValueError, match="task_params.*weight"):
        load_config("touch_entry", {"task_params": {"weight": -1.0}})
    with pytest.raises(ValueError, match="'task_params.size'"):
        load_config("touch_entry", {"task_params": {"size": 1.0}})
    with pytest.raises(ValueError, match="task_params"):
        load_config("needle_insert", {"task_params": {"weight": 0.5}})


def test_the_new_task_passes_check_env_and_steps():
    env = gym.make(TouchEntry.ENV_ID)
    check_env(env.unwrapped, skip_render_check=True)
    obs, info = env.reset(seed=0)
    assert obs.shape == env.observation_space.shape and info["phase"] == "approach"
    assert set(k for k in info if k.startswith("reward_")) == {f"reward_{t}" for t in TouchEntry.TERMS}
    entry = env.unwrapped.sim.arcs[0].entry
    distance = [float(np.linalg.norm(env.unwrapped.sim.tip_position() - entry))]
    steps, terminated, truncated = 0, False, False
    while not (terminated or truncated):
        grip, quat = env.unwrapped.sim.grip_pose()
        tip = env.unwrapped.sim.tip_position()
        obs, reward, terminated, truncated, info = env.step(env.unwrapped.action_toward(grip + (entry - tip), quat))
        steps += 1
        d = float(np.linalg.norm(env.unwrapped.sim.tip_position() - entry))
        distance.append(d)
        assert reward == math.fsum(info[f"reward_{t}"] for t in TouchEntry.TERMS)
        assert info["reward_touch"] == pytest.approx(-0.1 * d / (d + 2.0e-3), rel=1e-12)
    assert info["is_success"] and terminated and info["reward_success"] == 5.0
    assert distance[-1] <= 1.5e-3 < distance[0] and steps < 150
    with pytest.raises(ValueError, match="no goal-conditioned variant"):
        from suture_gym.envs import make_env

        make_env("touch_entry", goal_conditioned=True)


def test_registration_rejects_incomplete_or_clashing_tasks():
    class NoTerm(TouchEntry):
        NAME, ENV_ID = "no_term", "SutureGymTest/NoTerm-v0"
        TERMS = ("touch", "wiggle")

    class NoLimit(TouchEntry):
        NAME, ENV_ID, MAX_EPISODE_STEPS = "no_limit", "SutureGymTest/NoLimit-v0", 0

    class SameId(TouchEntry):
        NAME = "same_id"

    class SameName(TouchEntry):
        ENV_ID = "SutureGymTest/SameName-v0"

    with pytest.raises(ValueError, match="term_<name>"):
        register_task(NoTerm)
    with pytest.raises(ValueError, match="MAX_EPISODE_STEPS"):
        register_task(NoLimit)
    with pytest.raises(ValueError, match="already registered"):
        register_task(SameId)
    with pytest.raises(ValueError, match="already registered"):
        register_task(SameName)
    with pytest.raises(ValueError, match="Task subclass"):
        register_task(dict)
    assert register_task(TouchEntry) is TouchEntry  # the same class again: nothing happens
    assert not {"no_term", "no_limit", "same_id"} & set(registered_tasks())


@pytest.mark.parametrize("env_id", [*list(ENV_IDS), *list(GOAL_ENV_IDS)])
def test_every_id_documents_itself(env_id):
    env = gym.make(env_id)
    cls = type(env.unwrapped)
    text = pydoc.render_doc(env.unwrapped, renderer=pydoc.plaintext)
    assert env_id in cls.__doc__ and env_id in text
    positions = [cls.__doc__.index(f"\n{title}\n{'-' * len(title)}\n") for title in SECTIONS]
    assert positions == sorted(positions)
    task = env.unwrapped.task
    terms = task.GOAL_TERMS if env_id in GOAL_ENV_IDS else task.TERMS
    for term in terms:
        assert f"* ``{term}``" in cls.__doc__
    for row in ("tip_pos_x", "tip_force", "N m"):
        assert row in cls.__doc__
    assert f"{task.MAX_EPISODE_STEPS} steps" in cls.__doc__
    assert cls.TASK == task.NAME and cls().config.task == task.NAME
    env.close()



class GentleTouch(TouchEntry):
    """TouchEntry that fails as soon as the needle moves faster than ``MAX_SPEED`` (a task's own termination
    rule, through the ``failure`` hook)."""

    NAME, ENV_ID = "gentle_touch", "SutureGymTest/GentleTouch-v0"
    MAX_SPEED = 2.0e-3  # m/s

    def failure(self, obs: Observables, outside: bool, missed: bool) -> bool:
        return super().failure(obs, outside, missed) or float(np.linalg.norm(obs.needle_vel)) > self.MAX_SPEED


register_task(GentleTouch)


def test_a_task_adds_its_own_failure_through_the_hook():
    env = gym.make(GentleTouch.ENV_ID)
    env.reset(seed=0)
    sim = env.unwrapped.sim
    speeds = []
    for _ in range(GentleTouch.MAX_EPISODE_STEPS):
        grip, quat = sim.grip_pose()
        _, _, terminated, truncated, info = env.step(env.unwrapped.action_toward(grip + [0.0, 0.0, 0.01], quat))
        speeds.append(float(np.linalg.norm(sim.state.needle.body_vel)))
        if terminated or truncated:
            break
    assert terminated and not truncated and not info["is_success"]
    assert speeds[-1] > GentleTouch.MAX_SPEED and all(v <= GentleTouch.MAX_SPEED for v in speeds[:-1])
    assert info["reward_failure"] < 0.0
    env.close()
