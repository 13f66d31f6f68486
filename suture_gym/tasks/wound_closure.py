"""``SutureGym/WoundClosure-v0``: several stitches and thread tension close the wound gap."""

from __future__ import annotations

import numpy as np

from suture_gym.tasks.base import Observables, Task


class WoundClosure(Task):
    """A running suture: ``plan.stitches`` stitches along the wound, each pulled through by
    ``plan.thread_target`` before the next becomes current; a stopper knot near the thread's tail
    (``suture.knot_tail``) holds it at the first entry, so pulling it draws the wound edges together.

    Success: the mean wound gap at most ``plan.closure_target`` times its rest value. Start phases:
    ``approach`` and ``first_bite`` (the first stitch made and its thread pulled through).

    Goal (1,): ``[mean wound gap (m)]``; met when the achieved gap is at most the desired one.
    """

    NAME = "wound_closure"
    TERMS = ("path", "progress", "entry", "exit", "puncture", "thread", "closure", "success", "failure",
             "tissue_force", "action")
    PHASES = ("approach", "first_bite")
    GOAL_SIZE = 1
    GOAL_LAYOUT = (("wound_gap", "m"),)

    def achieved_goal(self, obs: Observables) -> np.ndarray:
        return np.array([obs.wound_gap])

    def desired_goal(self) -> np.ndarray:
        return np.array([self.closure_target * self.gap_rest])

    def goal_reached(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return achieved[:, 0] <= desired[:, 0]

    def goal_distance(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        excess = np.maximum(achieved[:, 0] - desired[:, 0], 0.0)
        return excess / (excess + self.gap_rest)
