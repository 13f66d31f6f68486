"""A short run of ``scripts/fuzz.py``: every id, action mode and shipped config, random to extreme actions, with
no exception, non-finite value or contract violation; and its exit status when something breaks."""

import importlib
import json
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"


@pytest.fixture
def fuzz(monkeypatch):
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, "1")  # the script's configure() sets them; restored after the test
    monkeypatch.syspath_prepend(str(SCRIPTS))
    return importlib.import_module("fuzz")


def test_a_short_fuzz_run_finds_nothing(fuzz, capsys):
    status = fuzz.main(["--steps", "360", "--json", "--seed", "0", "--no-progress"])
    summary = json.loads(capsys.readouterr().out)
    assert status == 0, summary["exception_samples"] + summary["violation_samples"]
    shipped = list((SCRIPTS.parent / "configs" / "envs").glob("*.yaml"))
    # every shipped config is played by its task's flat and goal-conditioned id, in both action modes
    assert summary["steps"] == 360 and summary["cases"] == len(summary["per_case"]) == 2 * 2 * len(shipped)
    assert {c["case"].split()[1] for c in summary["per_case"]} == {"wrench", "pose_delta"}
    assert summary["exceptions"] == summary["non_finite_obs"] == summary["violations"] == 0


def test_an_exception_makes_the_run_fail(fuzz, monkeypatch, capsys):
    from suture_gym.envs.base import SutureEnv

    def broken(action):
        raise ArithmeticError("broken on purpose")

    first = fuzz.cases()[:1]
    monkeypatch.setattr(fuzz, "cases", lambda: first)
    monkeypatch.setattr(SutureEnv, "_check_action", staticmethod(broken))
    status = fuzz.main(["--steps", "5", "--json", "--no-progress"])
    summary = json.loads(capsys.readouterr().out)
    assert status == 1 and summary["exceptions"] == 5
    assert summary["exception_samples"][0]["type"] == "ArithmeticError"
