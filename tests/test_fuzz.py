"""A short run of ``scripts/fuzz.py``: every id, action mode and shipped config, random to extreme actions, with
no exception, non-finite value, contract violation or divergence; its exit status when something breaks; and
the reproducer it records for every event, which replays the event alone."""

import json
from pathlib import Path

import pytest
from conftest import import_script

from suture_gym.configs import ENV_DIR

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture
def fuzz(monkeypatch):
    return import_script(monkeypatch, "fuzz")


def test_a_short_fuzz_run_finds_nothing(fuzz, capsys):
    status = fuzz.main(["--steps", "360", "--json", "--seed", "0", "--no-progress"])
    summary = json.loads(capsys.readouterr().out)
    assert status == 0, summary["events"]
    shipped = list(ENV_DIR.glob("*.yaml"))
    # every shipped config is played by its task's flat and goal-conditioned id, in both action modes
    assert summary["steps"] == 360 and summary["cases"] == len(summary["per_case"]) == 2 * 2 * len(shipped)
    assert {c["case"].split()[1] for c in summary["per_case"]} == {"wrench", "pose_delta"}
    assert summary["exceptions"] == summary["non_finite_obs"] == summary["violations"] == 0
    assert summary["divergences"] == 0 and summary["events"] == []


def _break_actions(monkeypatch, fuzz, after: int):
    """Make the env's action check raise from its ``after + 1``-th call on (counted across envs)."""
    from suture_gym.envs.base import SutureEnv

    calls = []
    check = SutureEnv._check_action

    def broken(action):
        calls.append(1)
        if len(calls) > after:
            raise ArithmeticError("broken on purpose")
        return check(action)

    monkeypatch.setattr(SutureEnv, "_check_action", staticmethod(broken))
    return calls


def test_an_exception_makes_the_run_fail(fuzz, monkeypatch, capsys):
    first = fuzz.cases()[:1]
    monkeypatch.setattr(fuzz, "cases", lambda: first)
    _break_actions(monkeypatch, fuzz, after=0)
    status = fuzz.main(["--steps", "5", "--json", "--no-progress"])
    summary = json.loads(capsys.readouterr().out)
    assert status == 1 and summary["exceptions"] == 5
    assert summary["exception_samples"][0]["type"] == "ArithmeticError"


def test_every_event_records_a_reproducer_that_replays_it(fuzz, monkeypatch, capsys):
    first = fuzz.cases()[:1]
    monkeypatch.setattr(fuzz, "cases", lambda: first)
    calls = _break_actions(monkeypatch, fuzz, after=6)  # the 7th step raises
    status = fuzz.main(["--steps", "9", "--json", "--no-progress", "--max-episode-steps", "100"])
    summary = json.loads(capsys.readouterr().out)
    assert status == 1 and summary["exceptions"] == 3 and len(summary["events"]) == 3  # then 1 per episode
    event = summary["events"][0]
    case = first[0]
    assert {k: event[k] for k in ("kind", "id", "config", "action_mode", "step", "where")} == {
        "kind": "exceptions", "id": case["id"], "config": case["config"], "action_mode": case["action_mode"],
        "step": 7, "where": "step"}
    assert event["strategy"] in fuzz.STRATEGIES and isinstance(event["seed"], int)
    # replayed alone: the episode up to its 7th step, where the action check raises again
    calls.clear()
    result = fuzz.replay(event)
    assert result["reproduced"] and len(calls) == 7
    assert result["events"][0]["type"] == "ArithmeticError"
    # the command line takes the event as JSON and exits 1 when it happens again
    calls.clear()
    assert fuzz.main(["--replay", json.dumps(event)]) == 1
    assert json.loads(capsys.readouterr().out)["reproduced"]
    # without the fault, the same step replays cleanly
    monkeypatch.undo()
    monkeypatch.syspath_prepend(str(SCRIPTS))
    assert not fuzz.replay(event)["reproduced"]


def test_replay_names_what_an_event_lacks(fuzz):
    with pytest.raises(ValueError, match=r"lacks \['seed', 'step'\]"):
        fuzz.replay({"id": "SutureGym/NeedleInsert-v3", "config": "needle_insert.yaml", "action_mode": "wrench",
                     "strategy": "random"})


def test_scripted_abort_follows_the_surgeon_then_holds_one_abort(fuzz):
    import gymnasium as gym
    import numpy as np

    from suture_gym.baselines.surgeon import ScriptedSurgeon

    env = gym.make("SutureGym/NeedleInsert-v3")
    env.reset(seed=4)
    stream = fuzz.ActionStream("scripted_abort", np.random.default_rng([4, 1]), env, 30)
    scripted, surgeon = stream.scripted_left, ScriptedSurgeon(env)
    assert 0 <= scripted < 30 and stream.abort in fuzz.ABORTS
    for k in range(30):
        action = stream()
        expected = surgeon(None) if k < scripted else stream.held
        np.testing.assert_array_equal(action, np.asarray(expected, np.float32))
        env.step(action)
    assert fuzz.abort_action("push", np.random.default_rng(0)).tolist() == [0, 0, -1, 0, 0, 0]
    twist = fuzz.abort_action("twist", np.random.default_rng(0))
    assert not twist[:3].any() and np.abs(twist[3:]).sum() == 1.0
    assert np.abs(fuzz.abort_action("yank", np.random.default_rng(0))[:3]).tolist() == [1, 1, 1]
    with pytest.raises(ValueError, match="abort must be one of .*got 'shake'"):
        fuzz.abort_action("shake", np.random.default_rng(0))


def test_the_largest_failure_return_is_reported_with_a_reproducer(fuzz, monkeypatch, capsys):
    monkeypatch.setattr(fuzz, "STRATEGIES", ("scripted_abort",))
    status = fuzz.main(["--steps", "300", "--max-episode-steps", "100", "--json", "--no-progress", "--only",
                        "NeedleInsert-v3 wrench needle_insert.yaml"])
    summary = json.loads(capsys.readouterr().out)
    worst = summary["failure_return_max"]
    assert worst["strategy"] == "scripted_abort" and worst["abort"] in fuzz.ABORTS
    assert worst["reason"] in fuzz.FAILURE_ENDS and worst["max_episode_steps"] == 100
    assert status == (1 if worst["return"] > 0 else 0)
    replayed = fuzz.replay(worst)  # the reproducer plays the same episode to its failing end
    assert replayed["return"] == worst["return"]
    assert {"kind": "end", "terminated": True, "truncated": False, "reason": worst["reason"]} in replayed["events"]
