"""``SutureGym/WoundClosure-v3``: several stitches and thread tension close the wound gap."""

from __future__ import annotations

import numpy as np

from suture_gym.sim.rod import RodModel, RodState
from suture_gym.sim.scenes import tent_rod
from suture_gym.tasks.base import THREAD_VERSION_HISTORY, WOUND_KINDS, Observables, Task
from suture_gym.tasks.geometry import PlannedArc

#: Distance outside the first entry at which the thread's free end starts, m.
TAIL_OFFSET = 8.0e-3


class WoundClosure(Task):
    """A running suture: ``plan.stitches`` stitches along the wound, each pulled through by
    ``plan.thread_target`` before the next becomes current; a stopper knot near the thread's tail
    (``suture.knot_tail``) holds it at the first entry, so pulling it draws the wound edges together.

    Success: every planned stitch made (the last one's final exit done) and the mean wound gap at most
    ``plan.closure_target`` times its rest value (:meth:`success`). Start phases: ``approach`` and
    ``first_bite`` (the first stitch made and its thread pulled through).

    Goal (1,): ``[mean wound gap (m)]``; met when the achieved gap is at most the desired one. The goal variant's
    reward reads the gap alone (a relabelled goal carries no stitch count); its ``info["is_success"]`` is
    :meth:`success`.
    """

    NAME = "wound_closure"
    ENV_ID = "SutureGym/WoundClosure-v3"
    GOAL_ENV_ID = "SutureGym/WoundClosureGoal-v3"
    MAX_EPISODE_STEPS = 5000
    VERSION_HISTORY = THREAD_VERSION_HISTORY
    CONFIG = {
        "scene": {"kind": "wound", "size": (0.03, 0.012, 0.008)},
        "suture": {"node_count": 86, "length": 0.085, "knot_tail": 0.008},
        "plan": {"stitches": 3},
        "observation": {"suture_samples": 4},
        "reward": {"failure": 30.0},
    }
    SCENE_KINDS = WOUND_KINDS
    NEEDS_THREAD = True
    #: The running suture's three stitches (about 7 rad of turning each) must fit, with their transits and the
    #: final tightening pull, into the 25 s time limit: the surgeon turns and pulls twice as fast.
    SURGEON_TURN_RATE = 2.0
    SURGEON_PULL_SPEED = 0.04
    TERMS = ("path", "progress", "entry", "exit", "puncture", "thread", "closure", "success", "failure",
             "forfeit", "tissue_force", "action")
    PHASES = ("approach", "first_bite")
    GOAL_SIZE = 1
    GOAL_LAYOUT = (("wound_gap", "m"),)

    @classmethod
    def initial_suture(cls, suture: RodModel, swage: np.ndarray, arcs: tuple[PlannedArc, ...]) -> RodState:
        """The thread laid from the swage up and back (along ``(0, -1, 1)``) and down to a free end
        :data:`TAIL_OFFSET` outside the first entry point (and a quarter of that above it), in two straight legs
        (:func:`~suture_gym.sim.scenes.tent_rod`)."""
        tail = arcs[0].entry + np.array([0.0, -TAIL_OFFSET, 0.25 * TAIL_OFFSET])
        return tent_rod(suture, swage, tail, np.array([0.0, -1.0, 1.0]))

    def success(self, obs: Observables) -> bool:
        """The wound closed by the suture: the last planned stitch has its final exit and the mean gap is at most
        ``closure_target`` times its rest value. The gap alone is not enough: a needle pressing on a wound edge
        can close it with no stitch (on the abdominal wall with its fat at a third of the skin's modulus the
        scripted surgeon's first bite did, at env step 120)."""
        st = self.state
        return st.stitch == len(self.arcs) - 1 and st.exited and super().success(obs)

    def achieved_goal(self, obs: Observables) -> np.ndarray:
        return np.array([obs.wound_gap])

    def desired_goal(self) -> np.ndarray:
        return np.array([self.closure_target * self.gap_rest])

    def goal_reached(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        return achieved[:, 0] <= desired[:, 0]

    def goal_distance(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        excess = np.maximum(achieved[:, 0] - desired[:, 0], 0.0)
        return excess / (excess + self.gap_rest)
