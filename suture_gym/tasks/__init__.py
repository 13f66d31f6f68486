"""Suturing tasks: small classes with named reward terms that read :class:`Observables` only.

* :class:`NeedleInsert` (``SutureGym/NeedleInsert-v3``), :class:`SutureThrow` (``SutureGym/SutureThrow-v3``),
  :class:`WoundClosure` (``SutureGym/WoundClosure-v3``), registered in :mod:`suture_gym.envs`
  (:func:`~suture_gym.envs.registry.register_task`).
* A task is the unit of extension: its reward terms (``term_<name>`` methods), config defaults (``CONFIG``),
  config check, episode initialisation (``initial_suture``, ``start_phase``) and termination are its own.
* :mod:`.surgeon`: the scripted surgeon (start phases, expert, measurements).
* :class:`PlannedArc`, :func:`plan_stitches` and :func:`plan_across_incision` (:mod:`.geometry`): the planned
  needle paths.
* The reward terms are documented in :mod:`suture_gym.tasks.base`.
"""

from suture_gym.tasks.base import Observables, StepContext, Task, TaskOutcome, TaskState
from suture_gym.tasks.geometry import PlannedArc, plan_across_incision, plan_stitches
from suture_gym.tasks.needle_insert import NeedleInsert
from suture_gym.tasks.suture_throw import SutureThrow
from suture_gym.tasks.wound_closure import WoundClosure

__all__ = [
    "NeedleInsert",
    "Observables",
    "PlannedArc",
    "StepContext",
    "SutureThrow",
    "Task",
    "TaskOutcome",
    "TaskState",
    "WoundClosure",
    "plan_across_incision",
    "plan_stitches",
]
