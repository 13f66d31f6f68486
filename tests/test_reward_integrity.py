"""No reward can be farmed: an episode that ends in failure returns at most its penalties (never more than 0),
whatever the actions; the wound gap is never negative and a crushed wound is a failing end."""

import math

import gymnasium as gym
import numpy as np
import pytest

import suture_gym  # noqa: F401
from suture_gym.baselines.expert import ExpertPolicy

#: Abort actions after a scripted start: push, pull, twist, yank (the corners of the box a fuzzer reaches).
ABORTS = {
    "push_down": [0.0, 0.0, -1.0, 0.0, 0.0, 0.0],
    "pull_up": [0.0, 0.0, 1.0, 0.0, 0.0, 0.0],
    "yank_sideways": [0.0, 1.0, 0.0, 0.0, 0.0, 0.0],
    "twist": [0.0, 0.0, 0.0, 1.0, 1.0, 1.0],
}


def _scripted_then_abort(env_id, seed, k, abort, max_steps):
    """Follow the scripted expert for ``k`` steps, then hold ``abort``; returns (return, last info, gaps, failed)."""
    env = gym.make(env_id, max_episode_steps=max_steps)
    obs, info = env.reset(seed=seed)
    expert = ExpertPolicy(env.unwrapped)
    expert.reset()
    total, gaps, t = 0.0, [info["wound_gap"]], 0
    while True:
        action = expert(obs) if t < k else np.asarray(abort, dtype=np.float32)
        obs, reward, terminated, truncated, info = env.step(action)
        total += reward
        gaps.append(info["wound_gap"])
        assert math.fsum(v for key, v in info.items() if key.startswith("reward_")) == reward
        t += 1
        if terminated or truncated:
            env.close()
            return total, info, np.array(gaps), terminated and not info["is_success"]


@pytest.mark.parametrize("abort", sorted(ABORTS))
def test_a_needle_insert_episode_that_fails_after_scripted_progress_returns_at_most_zero(abort):
    failures = 0
    for k in (40, 90, 140):  # before the puncture, inside the tissue, near the exit
        total, info, _, failed = _scripted_then_abort("SutureGym/NeedleInsert-v3", 1000 + k, k, ABORTS[abort], 400)
        if failed:
            failures += 1
            assert total <= 0.0, (k, total, {key: v for key, v in info.items() if key.startswith("reward_")})
    assert failures >= 1, f"{abort} never ended an episode in failure: the check would be empty"


def test_crushing_the_wound_after_scripted_stitches_is_a_failure_that_pays_nothing():
    """The reproducer: the scripted surgeon's first stitches (600 steps), then pushing down without let-up."""
    total, info, gaps, failed = _scripted_then_abort("SutureGym/WoundClosure-v3", 11, 600, ABORTS["push_down"], 1200)
    assert np.all(gaps >= 0.0)
    assert failed, info
    assert total <= 0.0, total
    assert info["reward_forfeit"] < 0.0


def test_the_closure_term_pays_at_most_its_weight_over_an_episode():
    from suture_gym.tasks.wound_closure import WoundClosure
    from tests.test_tasks import _obs, _task

    task = _task(WoundClosure, kind="wound", stitches=3, gap_rest=0.004)
    task.reset(_obs([0.0, 0.0, 0.02], gap=0.006))  # opened wider than at rest: nothing is owed for closing to g0
    paid = [task.step(_obs([0.0, 0.0, 0.02], gap=g), np.zeros(6)).terms["closure"] for g in (0.004, 0.002, 0.0)]
    assert math.fsum(paid) == pytest.approx(task.reward.closure)
    crushed = task.step(_obs([0.0, 0.0, 0.02], gap=0.0, overlap=0.002), np.zeros(6))
    assert crushed.crushed and crushed.failed
    assert crushed.terms["forfeit"] == pytest.approx(-task.reward.closure)
