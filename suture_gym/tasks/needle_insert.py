"""``SutureGym/NeedleInsert-v3``: pierce at the marked entry, follow the planned arc, exit at the marked exit."""

from __future__ import annotations

import numpy as np

from suture_gym.tasks.base import BUILTIN_VERSION_HISTORY, Observables, Task


class NeedleInsert(Task):
    """One bite through a tissue pad along the planned arc.

    Success: the first puncture lies within ``access_tolerance`` of the planned entry and the tip came out
    within ``access_tolerance`` of the planned exit. Start phases: ``approach`` (tip just before the entry
    point, on the planned circle) and ``inserted`` (the needle driven along the plan until the tip is halfway
    along the arc).

    Goal (8,): ``[entry (3) m, exit (3) m, punctured, exited]``; achieved: the recorded first puncture and
    exit (the tip position before each happens) and whether they happened (0/1); desired: the planned points
    and 1, 1. Reached when both points are within ``access_tolerance`` and both events happened.
    """

    NAME = "needle_insert"
    ENV_ID = "SutureGym/NeedleInsert-v3"
    GOAL_ENV_ID = "SutureGym/NeedleInsertGoal-v3"
    MAX_EPISODE_STEPS = 600
    VERSION_HISTORY = BUILTIN_VERSION_HISTORY
    CONFIG = {}
    TERMS = ("path", "progress", "entry", "exit", "puncture", "success", "failure", "forfeit", "tissue_force",
             "action")
    PHASES = ("approach", "inserted")
    NEEDS_PLANNED_ACCESS = True
    GOAL_SIZE = 8
    GOAL_LAYOUT = (("entry_x", "m"), ("entry_y", "m"), ("entry_z", "m"), ("exit_x", "m"), ("exit_y", "m"),
                   ("exit_z", "m"), ("punctured", "1"), ("exited", "1"))

    def achieved_goal(self, obs: Observables) -> np.ndarray:
        return self._position_goal(obs)

    def desired_goal(self) -> np.ndarray:
        return self._position_desired()

    def goal_reached(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return self._positions_reached(achieved, desired)

    def goal_distance(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return self._positions_distance(achieved, desired)
