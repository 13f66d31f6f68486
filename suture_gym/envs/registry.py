"""The task registry: a task class registers once (:func:`register_task`) and everything else derives from it.

From the class's attributes (see :class:`~suture_gym.tasks.Task`) registration makes the env id ``ENV_ID`` (and
``GOAL_ENV_ID``, the goal-conditioned variant, when set) with the time limit ``MAX_EPISODE_STEPS``, an env class
of its own whose docstring documents the id (``help(env.unwrapped)``), and the config defaults (the typed
defaults overridden by ``CONFIG``, :func:`~suture_gym.envs.config.default_config`). Adding a task is its own
file plus one ``register_task(MyTask)`` line.

The ids register no ``vector_entry_point``: Gymnasium refuses ``wrappers`` in that mode, so
``gym.make_vec(id, n, wrappers=[...])`` builds its ``SyncVectorEnv`` (or, with ``vectorization_mode="async"``,
``AsyncVectorEnv``) of wrapped envs. The natively batched env is
:func:`suture_gym.envs.vector.make_vector_env` (and, for Stable-Baselines3, ``suture_gym.envs.sb3.make_sb3_vec_env``).
"""

from __future__ import annotations

import sys

import gymnasium as gym

from suture_gym.tasks.base import Task

#: Config task name -> task class, in registration order.
TASK_CLASSES: dict[str, type[Task]] = {}
#: Registered flat env ids -> config task name.
ENV_IDS: dict[str, str] = {}
#: Registered goal-conditioned env ids -> config task name.
GOAL_ENV_IDS: dict[str, str] = {}
#: Time limit of each task, env steps.
MAX_EPISODE_STEPS: dict[str, int] = {}
#: Config task name -> (flat env class, goal-conditioned env class or None).
ENV_CLASSES: dict[str, tuple[type, type | None]] = {}


def registered_tasks() -> tuple[str, ...]:
    """Names of the registered tasks, in registration order."""
    return tuple(TASK_CLASSES)


def task_class(name: str) -> type[Task]:
    """The task class registered as ``name``; ValueError naming the registered ones otherwise."""
    cls = TASK_CLASSES.get(name)
    if cls is None:
        raise ValueError(f"task must be one of {list(TASK_CLASSES)}, got {name!r}")
    return cls


def env_id_task(env_id: str) -> tuple[str, bool]:
    """``(task name, goal_conditioned)`` of the registered SutureGym env id ``env_id``.

    Raises:
        ValueError: ``env_id`` is not a registered SutureGym id; the message names it and lists the registered
            ids (and, for a task name, says which id it has).
    """
    if env_id in ENV_IDS:
        return ENV_IDS[env_id], False
    if env_id in GOAL_ENV_IDS:
        return GOAL_ENV_IDS[env_id], True
    hint = ""
    if isinstance(env_id, str) and env_id in TASK_CLASSES:
        hint = f" ({env_id!r} is a task name; its env id is {TASK_CLASSES[env_id].ENV_ID!r})"
    raise ValueError(f"env_id must be a registered SutureGym env id, one of {[*ENV_IDS, *GOAL_ENV_IDS]}; "
                     f"got {env_id!r}{hint}")


def _check_task_class(cls) -> None:
    if not (isinstance(cls, type) and issubclass(cls, Task)):
        raise ValueError(f"register_task needs a Task subclass, got {cls!r}")
    if not cls.NAME or not cls.ENV_ID:
        raise ValueError(f"{cls.__name__} must set NAME and ENV_ID")
    steps = cls.MAX_EPISODE_STEPS
    if isinstance(steps, bool) or not isinstance(steps, int) or steps < 1:
        raise ValueError(f"{cls.__name__}.MAX_EPISODE_STEPS must be an integer >= 1, got {steps!r}")
    if not cls.TERMS or not all(callable(getattr(cls, f"term_{t}", None)) for t in cls.TERMS):
        raise ValueError(f"{cls.__name__}.TERMS must name terms that have a term_<name> method")
    if not cls.PHASES:
        raise ValueError(f"{cls.__name__}.PHASES must list at least the default start phase")


def register_task(cls: type[Task]) -> type[Task]:
    """Register the task class ``cls``: its env ids, time limit, env classes and config defaults.

    Registering the same class again does nothing; another class under a registered name or id raises
    ValueError. Returns ``cls`` (usable as a class decorator).
    """
    _check_task_class(cls)
    known = TASK_CLASSES.get(cls.NAME)
    if known is cls:
        return cls
    ids = [cls.ENV_ID] + ([cls.GOAL_ENV_ID] if cls.GOAL_ENV_ID else [])
    taken = [i for i in ids if i in gym.registry] + ([cls.NAME] if known is not None else [])
    if taken:
        raise ValueError(f"cannot register {cls.__name__}: {taken} already registered")
    from suture_gym.envs.docs import env_class

    TASK_CLASSES[cls.NAME] = cls
    MAX_EPISODE_STEPS[cls.NAME] = cls.MAX_EPISODE_STEPS
    flat = env_class(cls, goal_conditioned=False)
    goal = env_class(cls, goal_conditioned=True) if cls.GOAL_ENV_ID else None
    ENV_CLASSES[cls.NAME] = (flat, goal)
    module = sys.modules[__name__]
    for env_cls in (flat, goal):
        if env_cls is not None:
            env_cls.__module__ = __name__
            setattr(module, env_cls.__name__, env_cls)
    for env_id, goal_conditioned, table in ((cls.ENV_ID, False, ENV_IDS), (cls.GOAL_ENV_ID, True, GOAL_ENV_IDS)):
        if not env_id:
            continue
        table[env_id] = cls.NAME
        gym.register(
            id=env_id,
            entry_point=f"{__name__}:make_env",
            max_episode_steps=cls.MAX_EPISODE_STEPS,
            kwargs={"task": cls.NAME, "goal_conditioned": goal_conditioned},
        )
    return cls


def make_env(task: str = "needle_insert", goal_conditioned: bool = False, config=None, render_mode=None,
             action_mode=None):
    """One env of ``task``: an instance of the task's own env class (flat, or goal-conditioned)."""
    task_class(task)
    flat, goal = ENV_CLASSES[task]
    if goal_conditioned and goal is None:
        raise ValueError(f"task {task!r} has no goal-conditioned variant (GOAL_ENV_ID is not set)")
    cls = goal if goal_conditioned else flat
    return cls(task, config=config, render_mode=render_mode, action_mode=action_mode)


__all__ = [
    "ENV_IDS",
    "GOAL_ENV_IDS",
    "MAX_EPISODE_STEPS",
    "TASK_CLASSES",
    "env_id_task",
    "make_env",
    "register_task",
    "registered_tasks",
    "task_class",
]
