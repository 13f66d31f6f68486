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
