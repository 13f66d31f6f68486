"""The trained models committed under models/ (docs/results.md): each loads with its run config and
normalisation statistics and drives a short episode of the env it was trained on."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import suture_gym  # noqa: E402,F401
from suture_gym.baselines.evaluation import make_policy, model_vecnormalize, run_config, trained_env_kwargs  # noqa: E402

ROOT = Path(__file__).resolve().parents[1] / "models"
MODELS = sorted(ROOT.glob("**/seed*/final_model.zip"))


def test_there_are_committed_models():
    assert MODELS, "models/ holds no final_model.zip"


@pytest.mark.parametrize("path", MODELS, ids=lambda p: "-".join(p.parent.relative_to(ROOT).parts))
def test_committed_model_runs_with_its_statistics(path):
    config = run_config(path)
    evaluation = json.loads((path.parent / "evaluation.json").read_text())
    env_id = config["env_id"]
    assert evaluation["env_id"] == env_id and evaluation["episodes"] >= 100
    stats = model_vecnormalize(str(path))
    if config["hyperparams"].get("normalize"):
        assert stats is not None and stats.parent == path.parent
    env = gym.make(env_id, **trained_env_kwargs(str(path)))
    act = make_policy(str(path), env, seed=0, vecnormalize=stats)
    obs, _ = env.reset(seed=123)
    for _ in range(20):
        action = act(obs)
        assert action.shape == env.action_space.shape and np.all(np.isfinite(action))
        obs, _, terminated, truncated, _ = env.step(action)
        if terminated or truncated:
            break
    env.close()


def test_main_job_films_a_committed_model_with_its_statistics(tmp_path, monkeypatch):
    """``make run``'s video of a saved model acts on normalised observations, as the evaluation does (on raw
    ones the committed NeedleInsert model fails every episode)."""
    import importlib

    pytest.importorskip("imageio_ffmpeg")
    for var in ("NUMBA_NUM_THREADS", "OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
        monkeypatch.setenv(var, "1")  # the script's configure() sets them; restored after the test
    monkeypatch.syspath_prepend(str(Path(__file__).resolve().parents[1] / "scripts"))
    main_job = importlib.import_module("main_job")
    model = next(path for path in MODELS if run_config(path)["env_id"] == main_job.ENV_ID)
    video = main_job.record_policy_video(main_job.ENV_ID, str(model), tmp_path / "policy.mp4", seed=10_000)
    assert video["success"] and video["frames"] > 1 and (tmp_path / "policy.mp4").stat().st_size > 0
