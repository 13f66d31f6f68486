"""Training pipeline plumbing on a tiny classic-control env: config parsing, run directory, resume, evaluation.

The SutureGym smoke tests (each algorithm on the real tasks) live in test_baselines.py; this file checks the
machinery on Pendulum-v1 so a failure here points at the pipeline, not at the physics.
"""

import json

import numpy as np
import pytest
import yaml

pytest.importorskip("stable_baselines3")

from suture_gym.baselines.evaluation import episode_end, evaluate  # noqa: E402
from suture_gym.baselines.hyperparams import load_hyperparams, resolve  # noqa: E402
from suture_gym.baselines.training import run_name, train  # noqa: E402

TINY = {"policy": "MlpPolicy", "n_timesteps": 256, "n_envs": 2, "n_steps": 32, "batch_size": 32,
        "learning_rate": "lin_1e-3", "policy_kwargs": {"net_arch": [16], "activation_fn": "tanh"},
        "normalize": True}


def test_resolve_turns_strings_into_objects():
    import torch.nn as nn
    from stable_baselines3.common.utils import LinearSchedule

    script, kwargs = resolve(TINY)
    assert script["n_envs"] == 2 and script["normalize"] is True
    assert isinstance(kwargs["learning_rate"], LinearSchedule)
    assert kwargs["learning_rate"](1.0) == pytest.approx(1e-3) and kwargs["learning_rate"](0.0) == 0.0
    assert kwargs["policy_kwargs"]["activation_fn"] is nn.Tanh
    assert TINY["learning_rate"] == "lin_1e-3"  # input untouched


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"learning_rate": "lin_fast"}, "lin_fast"),
        ({"policy_kwargs": "dict(net_arch=[8])"}, "no strings to eval"),
        ({"policy_kwargs": {"activation_fn": "sigmoid"}}, "sigmoid"),
        ({"replay_buffer_class": "PrioritizedReplayBuffer"}, "PrioritizedReplayBuffer"),
        ({"behaviour_cloning": {"episodes": 3}}, "episodes"),
        ({"behaviour_cloning": {"epochs": 0}}, "behaviour_cloning.epochs"),
        ({"behaviour_cloning": {"learning_rate": -1.0}}, "behaviour_cloning.learning_rate"),
        ({"behaviour_cloning": {"dataset": 3}}, "behaviour_cloning.dataset"),
        ({"behaviour_cloning": {"expert": "oracle"}}, "behaviour_cloning.expert"),
        ({"behaviour_cloning": {"action_noise": 1.5}}, "behaviour_cloning.action_noise"),
        ({"env_kwargs": "config.yaml"}, "env_kwargs"),
    ],
)
def test_resolve_names_bad_values(change, message):
    with pytest.raises(ValueError, match=message):
        resolve({**TINY, **change})


@pytest.mark.parametrize("name", ["needle_insert", "needle_insert.yaml", "configs/envs/needle_insert.yaml"])
def test_env_config_by_name_is_the_shipped_file(name, tmp_path, monkeypatch):
    from suture_gym.configs import ENV_DIR

    monkeypatch.chdir(tmp_path)
    script, _ = resolve({**TINY, "env_kwargs": {"config": name}, "behaviour_cloning": {"epochs": 5}})
    assert script["env_kwargs"]["config"] == str(ENV_DIR / "needle_insert.yaml")
    assert script["behaviour_cloning"] == {"expert_episodes": 40, "epochs": 5, "batch_size": 256,
                                           "learning_rate": 1e-3, "dataset": None, "expert": "clock",
                                           "action_noise": 0.0}


def test_missing_policy_or_env_entry_is_named(tmp_path):
    with pytest.raises(ValueError, match="policy"):
        resolve({"n_timesteps": 10})
    (tmp_path / "ppo.yml").write_text(yaml.safe_dump({"_shared": TINY, "Pendulum-v1": TINY}))
    with pytest.raises(ValueError, match=r"CartPole-v1.*\['Pendulum-v1'\]"):  # the anchor key is no env id
        load_hyperparams("ppo", "CartPole-v1", config_dir=tmp_path)
    with pytest.raises(ValueError, match="_shared"):
        load_hyperparams("ppo", "_shared", config_dir=tmp_path)
    with pytest.raises(ValueError, match="dqn"):
        load_hyperparams("dqn", "Pendulum-v1", config_dir=tmp_path)


def test_train_writes_run_resumes_and_evaluates(tmp_path, capsys):
    common = dict(seed=3, out_dir=tmp_path, eval_freq=128, eval_episodes=1, checkpoint_freq=128,
                  progress_bar=False, verbose=1, hyperparams=TINY)
    first = train("ppo", "Pendulum-v1", n_timesteps=256, **common)
    run = tmp_path / run_name("ppo", "Pendulum-v1", 3)
    assert first.run_dir == run and first.timesteps == 256
    for name in ("config.yaml", "final_model.zip", "best_model.zip", "final_vecnormalize.pkl",
                 "learning_curve.png", "summary.json", "eval/evaluations.npz"):
        assert (run / name).exists(), name
    config = yaml.safe_load((run / "config.yaml").read_text())
    assert config["seed"] == 3 and config["hyperparams"]["learning_rate"] == "lin_1e-3"

    checkpoint = run / "checkpoints" / "model_256_steps.zip"
    assert (run / "checkpoints" / "model_vecnormalize_256_steps.pkl").exists()
    second = train("ppo", "Pendulum-v1", n_timesteps=512, resume=checkpoint, **common)
    assert second.timesteps == 512
    steps = np.load(run / "eval" / "evaluations.npz")["timesteps"]
    assert steps.tolist() == [128, 256, 384, 512]  # the resumed run kept the first half of the curve

    capsys.readouterr()
    summary = evaluate("Pendulum-v1", str(second.model_path), episodes=2, seed=5)
    assert capsys.readouterr().out == ""  # scripts/evaluate.py --json prints the summary alone on stdout
    assert summary["episodes"] == 2 and summary["mean_episode_length"] == 200.0
    assert np.isfinite(summary["mean_return"])
    assert summary["mean_tip_force"] is None  # Pendulum reports no tip force


def test_evaluation_uses_names_or_warns_about_vecnormalize_statistics(tmp_path, monkeypatch, capsys):
    import importlib
    import json
    import shutil
    import warnings
    from pathlib import Path

    common = dict(seed=0, n_timesteps=64, eval_freq=0, checkpoint_freq=0, progress_bar=False)
    run = train("ppo", "Pendulum-v1", out_dir=tmp_path / "norm", hyperparams=TINY, **common)
    stats = run.run_dir / "final_vecnormalize.pkl"
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        beside = evaluate("Pendulum-v1", str(run.model_path), episodes=1, seed=5)
        plain = train("ppo", "Pendulum-v1", out_dir=tmp_path / "plain", hyperparams={**TINY, "normalize": False},
                      **common)
        evaluate("Pendulum-v1", str(plain.model_path), episodes=1, seed=5)  # trained without: nothing to find
    assert beside["vecnormalize"] == str(stats)

    alone = tmp_path / "elsewhere" / "model.zip"  # a model without its run directory
    alone.parent.mkdir()
    shutil.copy(run.model_path, alone)
    with pytest.warns(UserWarning, match=r"no VecNormalize statistics found for .*model\.zip.*--vecnormalize PATH"):
        raw = evaluate("Pendulum-v1", str(alone), episodes=1, seed=5)
    assert raw["vecnormalize"] is None and raw["mean_return"] != beside["mean_return"]
    with pytest.raises(FileNotFoundError, match="nowhere.pkl"):
        evaluate("Pendulum-v1", str(alone), episodes=1, vecnormalize=tmp_path / "nowhere.pkl")

    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, "1")  # the script's configure() sets them; restored after the test
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    script = importlib.import_module("evaluate")
    capsys.readouterr()
    assert script.main(["--env", "Pendulum-v1", "--policy", str(alone), "--vecnormalize", str(stats),
                        "--episodes", "1", "--seed", "5", "--json"]) == 0
    named = json.loads(capsys.readouterr().out)
    assert named["vecnormalize"] == str(stats) and named["mean_return"] == beside["mean_return"]
    with pytest.raises(SystemExit):
        script.main(["--policy", "random", "--vecnormalize", str(stats)])
    assert "--vecnormalize applies to a saved model" in capsys.readouterr().err


def test_resume_from_missing_checkpoint_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nowhere.zip"):
        train("ppo", "Pendulum-v1", out_dir=tmp_path, resume=tmp_path / "nowhere.zip", progress_bar=False,
              hyperparams=TINY, n_timesteps=64)


def test_random_policy_evaluation_is_seeded():
    a = evaluate("Pendulum-v1", "random", episodes=2, seed=11)
    b = evaluate("Pendulum-v1", "random", episodes=2, seed=11)
    assert a["mean_return"] == b["mean_return"]


def test_an_episode_depends_on_its_env_seed_alone():
    """Episode k of a seeded evaluation is the same whether it runs first or later, alone or beside others."""
    both = evaluate("Pendulum-v1", "random", episodes=2, seed=11)["per_episode"]
    second = evaluate("Pendulum-v1", "random", episodes=1, seed=12)["per_episode"]
    assert both[1] == second[0]
    assert both[0]["episode_return"] != both[1]["episode_return"]


def test_evaluation_on_worker_processes_gives_the_same_summary(tmp_path):
    records = tmp_path / "episodes.jsonl"
    alone = evaluate("Pendulum-v1", "random", episodes=3, seed=11)
    pooled = evaluate("Pendulum-v1", "random", episodes=3, seed=11, workers=2, records_path=records)
    assert json.dumps(pooled) == json.dumps(alone)  # (NaN tip forces: Pendulum reports none)
    assert sorted(json.loads(line)["seed"] for line in records.read_text().splitlines()) == [11, 12, 13]
    with pytest.raises(ValueError, match="workers must be at least 1, got 0"):
        evaluate("Pendulum-v1", "random", episodes=1, workers=0)


def test_evaluation_streams_each_episode_as_a_json_line(tmp_path):
    import json

    records = tmp_path / "episodes.jsonl"
    summary = evaluate("Pendulum-v1", "random", episodes=3, seed=11, records_path=records)
    lines = [json.loads(line) for line in records.read_text().splitlines()]
    assert [r["seed"] for r in lines] == [11, 12, 13]
    assert [r["episode_return"] for r in lines] == [r["episode_return"] for r in summary["per_episode"]]
    assert [r["end"] for r in lines] == ["time_limit"] * 3  # Pendulum only ever truncates
    assert summary["end_counts"] == {"time_limit": 3}


@pytest.mark.parametrize(("info", "terminated", "truncated", "end"), [
    ({"is_success": True, "out_of_workspace": False}, True, False, "success"),
    ({"is_success": False, "tear": True, "out_of_workspace": True}, True, False, "tear"),
    ({"is_success": False, "out_of_workspace": True}, True, False, "out_of_workspace"),
    ({"is_success": False, "missed": True}, True, False, "missed"),
    ({"diverged": True}, False, True, "diverged"),
    ({"is_success": False}, False, True, "time_limit"),
    ({}, True, False, "terminated"),
])
def test_episode_end_names_why_an_episode_ended(info, terminated, truncated, end):
    assert episode_end(info, terminated, truncated) == end


def test_learning_curves_of_one_run_and_of_several(tmp_path):
    pytest.importorskip("matplotlib")
    from suture_gym.baselines.plotting import main, plot_learning_curve

    files = []
    for k in range(2):
        path = tmp_path / f"run{k}" / "eval" / "evaluations.npz"
        path.parent.mkdir(parents=True)
        np.savez(path, timesteps=np.array([10, 20, 30]), results=np.arange(9.0).reshape(3, 3) + k,
                 ep_lengths=np.ones((3, 3)), successes=np.array([[0, 0, 1], [0, 1, 1], [1, 1, 1]]))
        files.append(path)
    one = plot_learning_curve(files[0], tmp_path / "one.png", title="one")
    assert main([str(f) for f in files] + ["--out", str(tmp_path / "two.png"), "--labels", "a", "b"]) == 0
    for png in (one, tmp_path / "two.png"):
        assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and png.stat().st_size > 5000
    with pytest.raises(ValueError, match="labels"):
        plot_learning_curve(files, tmp_path / "bad.png", labels=["only one"])


def test_learning_curves_from_dagger_summaries(tmp_path):
    pytest.importorskip("matplotlib")
    import json

    from suture_gym.baselines.plotting import load_curve, plot_learning_curve

    iterations = [{"iteration": 0, "beta": 1.0, "steps": 100, "checkpoint_steps": 100, "success_rate": 1.0,
                   "mean_return": 9.0},
                  {"iteration": 1, "beta": 0.0, "steps": 40, "checkpoint_steps": 140, "success_rate": 0.0,
                   "mean_return": -3.0},
                  {"iteration": 2, "beta": 0.0, "steps": 60, "checkpoint_steps": 200, "success_rate": 0.5,
                   "mean_return": 4.0}]
    files = []
    for k in range(2):
        path = tmp_path / f"seed{k}" / "training_summary.json"
        path.parent.mkdir()
        path.write_text(json.dumps({"timesteps": 200, "iterations": iterations}))
        files.append(path)
    curve = load_curve(files[0])  # the expert's iteration is no point; each other is plotted before its rollout
    np.testing.assert_array_equal(curve["timesteps"], [100, 140])
    np.testing.assert_array_equal(curve["results"], [[-3.0], [4.0]])
    np.testing.assert_array_equal(curve["successes"], [[0.0], [0.5]])
    png = plot_learning_curve(files, tmp_path / "seeds.png")
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"timesteps": 3}))
    with pytest.raises(ValueError, match="bad.json is not a DAgger summary"):
        load_curve(bad)
    bad.write_text(json.dumps({"iterations": iterations[:1]}))
    with pytest.raises(ValueError, match="no learner-alone iteration"):
        load_curve(bad)
