"""Behaviour-cloning warm start (suture_gym/baselines/imitation.py) on Pendulum-v1: discounted returns by hand, and a
cloned policy that reproduces a known linear controller it was shown."""

import numpy as np
import pytest

pytest.importorskip("stable_baselines3")

from suture_gym.baselines.hyperparams import resolve  # noqa: E402
from suture_gym.baselines.imitation import behaviour_clone, discounted_returns  # noqa: E402


def test_discounted_returns_restart_at_each_episode():
    returns = discounted_returns(np.array([1.0, 2.0, 3.0, 10.0, 20.0]), np.array([0, 3]), gamma=0.5)
    np.testing.assert_allclose(returns, [1 + 0.5 * 2 + 0.25 * 3, 2 + 0.5 * 3, 3, 10 + 0.5 * 20, 20])


@pytest.mark.parametrize(("starts", "gamma", "message"),
                         [([1, 3], 0.9, "episode_starts"), ([0, 0], 0.9, "episode_starts"), ([0], 1.5, "gamma")])
def test_discounted_returns_names_bad_input(starts, gamma, message):
    with pytest.raises(ValueError, match=message):
        discounted_returns(np.ones(4), np.array(starts), gamma)


def _demos(rng, episodes=400, length=1):
    """A linear 'expert' a = clip(-0.5 theta_dot, -1, 1) on random Pendulum observations, reward -|a| (one-step
    episodes, so that the return is a function of the observation the value head can learn)."""
    obs = rng.uniform(-1.0, 1.0, (episodes * length, 3)).astype(np.float32)
    obs[:, 2] *= 4.0
    actions = np.clip(-0.5 * obs[:, 2:3], -1.0, 1.0).astype(np.float32)
    return {"observations": obs, "actions": actions, "rewards": -np.abs(actions[:, 0]).astype(np.float64),
            "episode_starts": np.arange(0, episodes * length, length)}


@pytest.mark.parametrize("normalize", [False, True])
def test_cloned_policy_reproduces_the_demonstrated_actions(normalize):
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env
    from stable_baselines3.common.vec_env import VecNormalize

    env = make_vec_env("Pendulum-v1", n_envs=1, seed=0)
    if normalize:
        env = VecNormalize(env, gamma=0.9)
    _, kwargs = resolve({"policy": "MlpPolicy", "n_timesteps": 1, "policy_kwargs": {"net_arch": [32, 32]}})
    model = PPO("MlpPolicy", env, gamma=0.9, seed=0, device="cpu", **kwargs)
    log_std = model.policy.log_std.detach().clone()
    demos = _demos(np.random.default_rng(0))
    test = _demos(np.random.default_rng(1), episodes=100)
    before = _mse(model, env, test)
    fit = behaviour_clone(model, demos, epochs=60, batch_size=64, learning_rate=3e-3, seed=0)
    after = _mse(model, env, test)
    assert fit["steps"] == 400 and fit["episodes"] == 400
    assert after < 0.01 < before  # held-out observations: the clone generalises the controller
    assert fit["value_explained_variance"] > 0.9
    assert np.array_equal(model.policy.log_std.detach().numpy(), log_std.numpy())  # exploration kept
    if normalize:
        assert env.obs_rms.count > 400  # statistics seeded with the demonstrations


def _mse(model, env, demos):
    from stable_baselines3.common.vec_env import VecNormalize

    obs = demos["observations"]
    if isinstance(env, VecNormalize):
        obs = env.normalize_obs(obs)
    actions, _ = model.predict(obs, deterministic=True)
    return float(np.mean((actions - demos["actions"]) ** 2))


def test_behaviour_cloning_needs_an_actor_critic_policy():
    from stable_baselines3 import SAC
    from stable_baselines3.common.env_util import make_vec_env

    model = SAC("MlpPolicy", make_vec_env("Pendulum-v1", n_envs=1, seed=0), device="cpu", learning_starts=1)
    with pytest.raises(ValueError, match="actor-critic"):
        behaviour_clone(model, _demos(np.random.default_rng(0)))


def test_cloning_fits_the_experts_own_actions_where_they_are_recorded():
    """Demonstrations recorded with action noise carry the expert's choices as ``expert_actions``: the clone
    follows them, not the noisy actions the env executed."""
    from stable_baselines3 import PPO
    from stable_baselines3.common.env_util import make_vec_env

    env = make_vec_env("Pendulum-v1", n_envs=1, seed=0)
    model = PPO("MlpPolicy", env, gamma=0.9, seed=0, device="cpu", policy_kwargs={"net_arch": [32, 32]})
    demos = _demos(np.random.default_rng(0))
    demos["expert_actions"] = demos["actions"]
    demos["actions"] = np.random.default_rng(2).uniform(-2.0, 2.0, demos["actions"].shape).astype(np.float32)
    behaviour_clone(model, demos, epochs=60, batch_size=64, learning_rate=3e-3, seed=0)
    test = _demos(np.random.default_rng(1), episodes=100)
    assert _mse(model, env, test) < 0.01
