"""Suturing tasks: small classes with named reward terms that read :class:`Observables` only.

* :class:`NeedleInsert` (``SutureGym/NeedleInsert-v0``), :class:`SutureThrow` (``SutureGym/SutureThrow-v0``),
  :class:`WoundClosure` (``SutureGym/WoundClosure-v0``); :data:`TASK_CLASSES` maps config task names to them.
* :class:`PlannedArc` and :func:`plan_stitches` (:mod:`.geometry`): the planned needle paths.
* The reward terms are documented in :mod:`suture_gym.tasks.base`.
"""

from suture_gym.tasks.base import Observables, Task, TaskOutcome, TaskState
from suture_gym.tasks.geometry import PlannedArc, plan_stitches
from suture_gym.tasks.needle_insert import NeedleInsert
from suture_gym.tasks.suture_throw import SutureThrow
from suture_gym.tasks.wound_closure import WoundClosure

#: Config task name -> task class.
TASK_CLASSES: dict[str, type[Task]] = {cls.NAME: cls for cls in (NeedleInsert, SutureThrow, WoundClosure)}

__all__ = [
    "TASK_CLASSES",
    "NeedleInsert",
    "Observables",
    "PlannedArc",
    "SutureThrow",
    "Task",
    "TaskOutcome",
    "TaskState",
    "WoundClosure",
    "plan_stitches",
]
