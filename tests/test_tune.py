"""``scripts/tune.py``: Optuna trials on NeedleInsert into a SQLite study, resumed by a second run that sees the
first run's trials and samples new hyperparameters; bad arguments are named. Tiny budgets (64 env steps of
20-step episodes per trial)."""

import json

import pytest
from conftest import import_script

pytest.importorskip("optuna")
pytest.importorskip("stable_baselines3")

TINY = ["--n-timesteps", "64", "--n-evaluations", "2", "--eval-episodes", "1", "--no-progress", "--json",
        "--hyperparams", "n_envs=1", "n_steps=32", "batch_size=32", "n_epochs=1", "policy_kwargs={net_arch: [16]}",
        "behaviour_cloning=null", "env_kwargs={max_episode_steps: 20}"]


@pytest.fixture
def tune(monkeypatch):
    return import_script(monkeypatch, "tune")


def test_a_study_is_stored_in_sqlite_and_resumed(tune, tmp_path, capsys):
    import optuna

    storage = f"sqlite:///{tmp_path}/nested/tune.db"
    assert tune.main(["--n-trials", "2", "--storage", storage, *TINY]) == 0
    first = json.loads(capsys.readouterr().out)
    assert first["study_name"] == "ppo_NeedleInsert-v3" and first["trials"] == first["trials_this_run"] == 2
    assert first["complete"] + first["pruned"] == 2 and first["failed"] == 0
    best = first["best"]
    assert best["hyperparams"]["n_steps"] == 32 and "behaviour_cloning" not in best["hyperparams"]
    assert best["hyperparams"]["gamma"] == best["params"]["gamma"]  # sampled, and written in the agent format

    assert tune.main(["--n-trials", "1", "--storage", storage, *TINY]) == 0
    second = json.loads(capsys.readouterr().out)
    assert (second["trials"], second["trials_this_run"]) == (3, 1)
    trials = optuna.load_study(study_name="ppo_NeedleInsert-v3", storage=storage).trials
    assert [t.number for t in trials] == [0, 1, 2]
    assert trials[2].params != trials[0].params  # the resumed sampler does not repeat the first trial


def test_bad_arguments_are_named(tune, tmp_path, capsys):
    with pytest.raises(ValueError, match="not-a-url"):
        tune.main(["--n-trials", "1", "--storage", "not-a-url", *TINY])
    with pytest.raises(SystemExit):
        tune.main(["--algo", "sac", "--storage", f"sqlite:///{tmp_path}/t.db"])
    assert "'sac' has no search space" in capsys.readouterr().err
    with pytest.raises(ValueError, match="sigmoid"):
        tune.main(["--storage", f"sqlite:///{tmp_path}/t.db", *TINY, "policy_kwargs={activation_fn: sigmoid}"])
