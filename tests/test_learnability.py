"""Learnability smoke test: a short run of Stable-Baselines3's PPO with its default hyperparameters (the NeedleInsert
recipe of ``configs/agents/ppo.yml``, shortened) raises NeedleInsert's mean return above the random policy's and
above holding still (the zero action, which pays the path term's cost and nothing else) on fixed held-out env
seeds. Not a timing test: it asserts what the run learnt, however long it took."""

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from suture_gym.baselines.evaluation import evaluate  # noqa: E402
from suture_gym.baselines.hyperparams import load_hyperparams  # noqa: E402
from suture_gym.baselines.training import train  # noqa: E402

ENV = "SutureGym/NeedleInsert-v3"
#: Env steps of the short run, and its time limit: shorter episodes than the id's give more of them per step.
STEPS = 24_576
EPISODE_STEPS = 150
#: Held-out env seeds of the comparison (training uses seeds 0-3, its evaluation env 1000).
EVAL_SEED, EVAL_EPISODES = 50_000, 10


@pytest.mark.slow
def test_a_short_ppo_run_beats_random_actions(tmp_path):
    hyperparams = load_hyperparams("ppo", ENV)
    hyperparams["env_kwargs"] = {**hyperparams["env_kwargs"], "max_episode_steps": EPISODE_STEPS}
    result = train("ppo", ENV, seed=0, out_dir=tmp_path, n_timesteps=STEPS, eval_freq=0, checkpoint_freq=0,
                   progress_bar=False, hyperparams=hyperparams)
    kwargs = hyperparams["env_kwargs"]
    trained = evaluate(ENV, str(result.model_path), EVAL_EPISODES, seed=EVAL_SEED, env_kwargs=kwargs)
    random = evaluate(ENV, "random", EVAL_EPISODES, seed=EVAL_SEED, env_kwargs=kwargs)
    assert trained["mean_return"] > random["mean_return"], (trained, random)
    assert trained["mean_return"] > _hold_still_return(kwargs), trained


def _hold_still_return(env_kwargs: dict) -> float:
    """Mean return of the zero action (the holder's target held where it is) on the comparison's episodes."""
    env = gym.make(ENV, **env_kwargs)
    total = 0.0
    for k in range(EVAL_EPISODES):
        env.reset(seed=EVAL_SEED + k)
        done = False
        while not done:
            _, reward, terminated, truncated, _ = env.step(np.zeros(env.action_space.shape, dtype=np.float32))
            total += float(reward)
            done = terminated or truncated
    env.close()
    return total / EVAL_EPISODES
