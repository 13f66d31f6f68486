"""The batched vector env (``gym.make_vec``) and the Stable-Baselines3 adapter: equality with single envs, both
autoreset modes, time limits, reset masks, snapshots, and SB3's VecEnv conventions (PPO and HER smoke runs)."""

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import suture_gym.envs  # noqa: F401  (registers the ids)
from suture_gym.envs import MAX_EPISODE_STEPS, SutureEnv, SutureVectorEnv

N = 3


def test_make_vec_uses_the_native_vector_env():
    env = gym.make_vec("SutureGym/NeedleInsert-v1", num_envs=N)
    assert isinstance(env, SutureVectorEnv) and env.num_envs == N
    assert env.max_episode_steps == MAX_EPISODE_STEPS["needle_insert"]
    assert env.observation_space.shape == (N, *env.single_observation_space.shape)
    goal = gym.make_vec("SutureGym/SutureThrowGoal-v2", num_envs=2)
    assert set(goal.single_observation_space.spaces) == {"observation", "achieved_goal", "desired_goal"}
    env.close()
    goal.close()


def test_batch_equals_single_envs_bit_for_bit():
    vec = SutureVectorEnv("needle_insert", N)
    singles = [SutureEnv("needle_insert") for _ in range(N)]
    rng = np.random.default_rng(2)
    obs, _ = vec.reset(seed=10)
    single_obs = [e.reset(seed=10 + i)[0] for i, e in enumerate(singles)]
    np.testing.assert_array_equal(obs, np.stack(single_obs))
    for _ in range(15):
        actions = rng.uniform(-0.05, 0.05, (N, 6)).astype(np.float32)
        obs, rewards, terminations, truncations, infos = vec.step(actions)
        for i, e in enumerate(singles):
            o, r, te, tr, info = e.step(actions[i])
            assert o.tobytes() == obs[i].tobytes() and r == rewards[i]
            assert (te, tr) == (terminations[i], truncations[i])
            assert info["reward_progress"] == infos["reward_progress"][i]
        if (terminations | truncations).any():
            break


def test_next_step_autoreset_and_time_limit():
    vec = SutureVectorEnv("needle_insert", 2, max_episode_steps=3)
    vec.reset(seed=0)
    zeros = np.zeros((2, 6), np.float32)
    for _ in range(2):
        _, _, _, truncations, _ = vec.step(zeros)
        assert not truncations.any()
    _, _, terminations, truncations, _ = vec.step(zeros)
    assert truncations.all() and not terminations.any()
    obs, rewards, terminations, truncations, infos = vec.step(zeros)  # the autoreset step
    assert not (terminations.any() or truncations.any()) and not rewards.any()
    first, _ = SutureVectorEnv("needle_insert", 2).reset(seed=0)
    assert obs.shape == first.shape and np.all(np.isfinite(obs))


def test_same_step_autoreset_reports_the_final_observation():
    vec = SutureVectorEnv("needle_insert", 2, max_episode_steps=2, autoreset_mode=AutoresetMode.SAME_STEP)
    start, _ = vec.reset(seed=0)
    zeros = np.zeros((2, 6), np.float32)
    vec.step(zeros)
    obs, _, _, truncations, infos = vec.step(zeros)
    assert truncations.all() and infos["_final_obs"].all()
    assert infos["final_obs"][0].shape == vec.single_observation_space.shape
    assert not np.array_equal(infos["final_obs"][0], obs[0])
    assert infos["final_info"]["is_success"].shape == (2,)


def test_reset_mask_and_snapshots():
    vec = SutureVectorEnv("needle_insert", 2)
    obs0, _ = vec.reset(seed=1)
    moved, *_ = vec.step(np.full((2, 6), 0.2, np.float32))
    obs, infos = vec.reset(options={"reset_mask": np.array([True, False])})
    np.testing.assert_array_equal(obs[1], moved[1])
    assert infos["_is_success"].tolist() == [True, False]
    state = vec.get_state()
    rng = np.random.default_rng(0)
    actions = rng.uniform(-0.3, 0.3, (10, 2, 6)).astype(np.float32)
    first = [vec.step(a)[0].tobytes() for a in actions]
    vec.set_state(state)
    assert [vec.step(a)[0].tobytes() for a in actions] == first
    with pytest.raises(ValueError, match="shape"):
        vec.step(np.zeros((3, 6)))


def test_sb3_adapter_follows_vecenv_conventions():
    pytest.importorskip("stable_baselines3")
    from suture_gym.envs.sb3 import make_sb3_vec_env

    env = make_sb3_vec_env("needle_insert", 2, monitor=False, max_episode_steps=3)
    env.seed(5)
    obs = env.reset()
    assert obs.shape == (2, *env.observation_space.shape)
    zeros = np.zeros((2, 6), np.float32)
    for _ in range(3):
        obs, rewards, dones, infos = env.step(zeros)
    assert dones.all() and rewards.dtype == np.float32
    for info in infos:
        assert info["TimeLimit.truncated"] and info["terminal_observation"].shape == env.observation_space.shape
    assert env.get_attr("render_mode") == [None, None]
    assert env.env_method("scripted_action", -2.7, indices=[1])[0].shape == (6,)
    env.close()


def test_sb3_ppo_and_her_smoke():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO, SAC, HerReplayBuffer

    from suture_gym.envs.sb3 import make_sb3_vec_env

    env = make_sb3_vec_env("needle_insert", 2, max_episode_steps=20)
    PPO("MlpPolicy", env, n_steps=16, batch_size=16, n_epochs=1, seed=0, device="cpu").learn(32)
    goal_env = make_sb3_vec_env("needle_insert", 1, goal_conditioned=True, max_episode_steps=10)
    model = SAC("MultiInputPolicy", goal_env, replay_buffer_class=HerReplayBuffer, learning_starts=20,
                replay_buffer_kwargs={"copy_info_dict": True}, batch_size=16, seed=0, device="cpu")
    model.learn(40)
    env.close()
    goal_env.close()
