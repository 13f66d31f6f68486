"""``SutureGym/SutureThrow-v3``: one full stitch across both wound edges, thread pulled through to a target."""

from __future__ import annotations

import numpy as np

from suture_gym.tasks.base import THREAD_VERSION_HISTORY, WOUND_KINDS, Observables, Task


class SutureThrow(Task):
    """One stitch across a wound: in at the marked entry on the near edge, across the gap, out at the marked
    exit on the far edge, then ``plan.thread_target`` of thread pulled out of the exit.

    Success: first puncture and final exit each within ``access_tolerance`` of the plan, and the thread
    through. Start phases: ``approach``, ``inserted`` (tip halfway along the arc) and ``exited`` (the needle
    driven along the plan until the tip is out at the far edge).

    Goal (9,): ``[entry (3) m, exit (3) m, punctured, exited, thread (m)]`` (as NeedleInsert's, plus the
    thread pulled through, capped at the target); met when both points are within tolerance, both events
    happened and the thread reaches the desired length.
    """

    NAME = "suture_throw"
    ENV_ID = "SutureGym/SutureThrow-v3"
    GOAL_ENV_ID = "SutureGym/SutureThrowGoal-v3"
    MAX_EPISODE_STEPS = 2000
    VERSION_HISTORY = THREAD_VERSION_HISTORY
    CONFIG = {
        "scene": {"kind": "wound", "size": (0.012, 0.012, 0.008)},
        "suture": {"node_count": 31, "length": 0.03},
        "observation": {"suture_samples": 4},
        "reward": {"failure": 20.0},
    }
    SCENE_KINDS = WOUND_KINDS
    NEEDS_THREAD = True
    TERMS = ("path", "progress", "entry", "exit", "puncture", "thread", "success", "failure", "forfeit",
             "tissue_force", "action")
    PHASES = ("approach", "inserted", "exited")
    NEEDS_PLANNED_ACCESS = True
    GOAL_SIZE = 9
    GOAL_LAYOUT = (("entry_x", "m"), ("entry_y", "m"), ("entry_z", "m"), ("exit_x", "m"), ("exit_y", "m"),
                   ("exit_z", "m"), ("punctured", "1"), ("exited", "1"), ("thread", "m"))

    def achieved_goal(self, obs: Observables) -> np.ndarray:
        return np.concatenate([self._position_goal(obs), [self._thread(obs)]])

    def desired_goal(self) -> np.ndarray:
        return np.concatenate([self._position_desired(), [self.thread_target]])

    def goal_reached(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return self._positions_reached(achieved, desired) & (achieved[:, 8] >= desired[:, 8])

    def goal_distance(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        missing = np.maximum(desired[:, 8] - achieved[:, 8], 0.0)
        thread = missing / (missing + self.thread_target)
        return (4.0 * self._positions_distance(achieved, desired) + thread) / 5.0
