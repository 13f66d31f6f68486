"""The trained models committed under models/ (README results): each loads with its run config and
normalisation statistics and drives a short episode of the env it was trained on."""

import json
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

import suture_gym  # noqa: E402,F401
from agents.evaluation import make_policy, model_vecnormalize, run_config, trained_env_kwargs  # noqa: E402

MODELS = sorted((Path(__file__).resolve().parents[1] / "models").glob("*/seed*/final_model.zip"))


def test_there_are_committed_models():
    assert MODELS, "models/ holds no final_model.zip"


@pytest.mark.parametrize("path", MODELS, ids=lambda p: f"{p.parent.parent.name}-{p.parent.name}")
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
