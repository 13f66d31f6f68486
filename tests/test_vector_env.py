"""The batched vector env (``make_vector_env``), ``gym.make_vec`` with wrappers, and the Stable-Baselines3 adapter:
equality with single envs, both autoreset modes, time limits, reset masks, snapshots, and SB3's VecEnv conventions
(PPO and HER smoke runs); worker faults (a killed or stopped worker raises WorkerError within the timeout, or is
restarted and its episode truncated)."""

import os
import signal
import threading
import time

import gymnasium as gym
import numpy as np
import pytest
from gymnasium.vector import AutoresetMode

import suture_gym.envs  # noqa: F401  (registers the ids)
from suture_gym.envs import MAX_EPISODE_STEPS, SutureEnv, SutureVectorEnv, WorkerError, make_vector_env
from suture_gym.envs.vector import default_workers

N = 3


def test_make_vector_env_builds_the_native_env_of_an_id():
    env = make_vector_env("SutureGym/NeedleInsert-v3", N)
    assert isinstance(env, SutureVectorEnv) and env.num_envs == N
    assert env.workers == default_workers(N) and 0 <= env.workers <= N  # parallel by default
    assert env.max_episode_steps == MAX_EPISODE_STEPS["needle_insert"]
    assert env.observation_space.shape == (N, *env.single_observation_space.shape)
    goal = make_vector_env("SutureGym/SutureThrowGoal-v3", 2, max_episode_steps=7, workers=0)
    assert set(goal.single_observation_space.spaces) == {"observation", "achieved_goal", "desired_goal"}
    assert goal.max_episode_steps == 7
    env.close()
    goal.close()


@pytest.mark.parametrize(("env_id", "message"), [
    ("needle_insert", r"got 'needle_insert' \('needle_insert' is a task name; its env id is "
                      r"'SutureGym/NeedleInsert-v3'\)"),
    ("SutureGym/NeedleInsert-v9", r"SutureGym/NeedleInsert-v3.*SutureGym/NeedleInsertGoal-v3.*got "
                                  r"'SutureGym/NeedleInsert-v9'"),
])
def test_a_bad_env_id_is_named_with_the_valid_ones(env_id, message):
    with pytest.raises(ValueError, match=message):
        make_vector_env(env_id, 1)


def test_make_vec_applies_wrappers_in_the_default_mode():
    def seven(env):
        return gym.wrappers.TransformReward(env, lambda r: 7.0)

    envs = gym.make_vec("SutureGym/NeedleInsert-v3", num_envs=2, wrappers=[seven])
    assert all(isinstance(e, gym.wrappers.TransformReward) for e in envs.envs)
    envs.reset(seed=0)
    _, rewards, *_ = envs.step(np.zeros((2, 6), np.float32))
    assert rewards.tolist() == [7.0, 7.0]
    assert envs.envs[0].spec.max_episode_steps == MAX_EPISODE_STEPS["needle_insert"]
    envs.close()


@pytest.mark.parametrize("workers", [0, 2])
def test_batch_equals_single_envs_bit_for_bit(workers):
    vec = SutureVectorEnv("needle_insert", N, workers=workers)
    assert vec.workers == workers
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
    vec.close()


def test_next_step_autoreset_and_time_limit():
    vec = SutureVectorEnv("needle_insert", 2, max_episode_steps=3, workers=0)
    vec.reset(seed=0)
    zeros = np.zeros((2, 6), np.float32)
    for _ in range(2):
        _, _, _, truncations, _ = vec.step(zeros)
        assert not truncations.any()
    _, _, terminations, truncations, _ = vec.step(zeros)
    assert truncations.all() and not terminations.any()
    obs, rewards, terminations, truncations, infos = vec.step(zeros)  # the autoreset step
    assert not (terminations.any() or truncations.any()) and not rewards.any()
    first, _ = SutureVectorEnv("needle_insert", 2, workers=0).reset(seed=0)
    assert obs.shape == first.shape and np.all(np.isfinite(obs))


@pytest.mark.parametrize("workers", [0, 2])
def test_same_step_autoreset_reports_the_final_observation(workers):
    vec = SutureVectorEnv("needle_insert", 2, max_episode_steps=2, autoreset_mode=AutoresetMode.SAME_STEP,
                          workers=workers)
    start, _ = vec.reset(seed=0)
    zeros = np.zeros((2, 6), np.float32)
    vec.step(zeros)
    obs, _, _, truncations, infos = vec.step(zeros)
    assert truncations.all() and infos["_final_obs"].all()
    assert infos["final_obs"][0].shape == vec.single_observation_space.shape
    assert not np.array_equal(infos["final_obs"][0], obs[0])
    assert infos["final_info"]["is_success"].shape == (2,)
    vec.close()


@pytest.mark.parametrize("workers", [0, 2])
def test_reset_mask_and_snapshots(workers):
    vec = SutureVectorEnv("needle_insert", 2, workers=workers)
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
    vec.close()


def test_workers_hand_back_errors_and_close():
    vec = SutureVectorEnv("needle_insert", 3, workers=2, max_episode_steps=5)
    vec.reset(seed=0)
    processes = list(vec._workers.processes)
    with pytest.raises(AttributeError, match="live in the worker processes"):
        vec.envs  # noqa: B018
    assert vec.get_attr("render_mode") == (None, None, None)
    assert vec.call("scripted_action", -2.7, indices=[2])[0].shape == (6,)
    vec.set_attr("render_mode", ["a", "b"], indices=[0, 2])
    assert vec.get_attr("render_mode") == ("a", None, "b")
    with pytest.raises(TypeError, match="dtype") as raised:  # the env's own check, raised in a worker
        vec.step(np.full((3, 6), "x"))
    assert "Traceback" in str(raised.value.__cause__)  # the worker's traceback
    _, rewards, *_ = vec.step(np.zeros((3, 6), np.float32))  # the pipes are still in step
    assert rewards.shape == (3,)
    with pytest.raises(ValueError, match=r"workers must be an integer from 0 to num_envs = 3, got 4"):
        SutureVectorEnv("needle_insert", 3, workers=4)
    vec.close()
    assert not any(p.is_alive() for p in processes)


def test_sb3_adapter_follows_vecenv_conventions():
    pytest.importorskip("stable_baselines3")
    from suture_gym.envs.sb3 import make_sb3_vec_env

    env = make_sb3_vec_env("SutureGym/NeedleInsert-v3", 2, monitor=False, max_episode_steps=3, workers=2)
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
    default = make_sb3_vec_env("SutureGym/NeedleInsert-v3", 1, monitor=False)
    assert default.vector_env.max_episode_steps == MAX_EPISODE_STEPS["needle_insert"]  # the id's time limit
    default.close()
    with pytest.raises(ValueError, match=r"got 'needle_insert' \('needle_insert' is a task name"):
        make_sb3_vec_env("needle_insert", 1)
    with pytest.raises(ValueError, match=r"do not pass \['goal_conditioned'\]"):
        make_sb3_vec_env("SutureGym/NeedleInsert-v3", 1, goal_conditioned=True)


def test_sb3_ppo_and_her_smoke():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO, SAC, HerReplayBuffer

    from suture_gym.envs.sb3 import make_sb3_vec_env

    env = make_sb3_vec_env("SutureGym/NeedleInsert-v3", 2, max_episode_steps=20)
    PPO("MlpPolicy", env, n_steps=16, batch_size=16, n_epochs=1, seed=0, device="cpu").learn(32)
    goal_env = make_sb3_vec_env("SutureGym/NeedleInsertGoal-v3", 1, max_episode_steps=10)
    model = SAC("MultiInputPolicy", goal_env, replay_buffer_class=HerReplayBuffer, learning_starts=20,
                replay_buffer_kwargs={"copy_info_dict": True}, batch_size=16, seed=0, device="cpu")
    model.learn(40)
    env.close()
    goal_env.close()


ZEROS = np.zeros((3, 6), np.float32)


def _pid(vec, worker: int) -> int:
    return vec._workers.processes[worker].pid


def test_a_worker_killed_between_steps_is_named_with_its_signal_and_last_actions():
    vec = SutureVectorEnv("needle_insert", 3, workers=2, worker_timeout=10)
    vec.reset(seed=0)
    actions = np.full((3, 6), 0.25, np.float32)
    vec.step(actions)
    os.kill(_pid(vec, 1), signal.SIGKILL)
    with pytest.raises(WorkerError) as raised:
        vec.step(actions)
    error = raised.value
    assert (error.worker, error.env_indices, error.exitcode, error.signal) == (1, (2,), -9, "SIGKILL")
    assert "worker 1 (env 2" in str(error) and "killed by SIGKILL" in str(error)
    assert "env 2: [0.25, 0.25, 0.25, 0.25, 0.25, 0.25]" in str(error)
    assert "__main__" not in str(error)  # the hint is for a worker that fails to start, not for a signal
    with pytest.raises(WorkerError, match="worker 1 .*killed by SIGKILL.*the worker is gone"):
        vec.reset(seed=1)  # every later request names the same fault
    vec.close()


def test_a_worker_killed_mid_step_raises_at_once():
    vec = SutureVectorEnv("needle_insert", 3, workers=2, worker_timeout=30, config={"solver": {"substeps": 100}})
    vec.reset(seed=0)
    threading.Timer(0.05, os.kill, (_pid(vec, 0), signal.SIGKILL)).start()
    start = time.monotonic()
    with pytest.raises(WorkerError, match=r"worker 0 \(envs 0-1.*killed by SIGKILL \(exit code -9\)") as raised:
        vec.step(ZEROS)  # 100 substeps: the kill lands while the worker steps
    assert time.monotonic() - start < 30 and raised.value.env_indices == (0, 1)
    vec.close()


def test_a_stopped_worker_times_out_with_a_named_error():
    vec = SutureVectorEnv("needle_insert", 3, workers=2, worker_timeout=3)
    vec.reset(seed=0)
    process = vec._workers.processes[0]
    os.kill(process.pid, signal.SIGSTOP)
    start = time.monotonic()
    with pytest.raises(WorkerError, match=r"worker 0 .*did not answer within worker_timeout = 3 s \(process "
                                          r"state: T \(stopped\)\) and was killed.*step with actions") as raised:
        vec.step(ZEROS)
    assert 3 <= time.monotonic() - start < 10
    assert raised.value.exitcode is None and raised.value.signal is None
    vec.close()
    assert not process.is_alive()
    with pytest.raises(ValueError, match=r"worker_timeout must be None or a finite number of seconds > 0, got 0"):
        SutureVectorEnv("needle_insert", 2, workers=1, worker_timeout=0)


@pytest.mark.parametrize("mode", [AutoresetMode.NEXT_STEP, AutoresetMode.SAME_STEP])
def test_restart_workers_truncates_the_episode_and_carries_on(mode):
    vec = SutureVectorEnv("needle_insert", 3, workers=2, worker_timeout=10, restart_workers=True,
                          autoreset_mode=mode)
    vec.reset(seed=5)
    for _ in range(2):
        last, *_ = vec.step(ZEROS)
    old = _pid(vec, 1)
    os.kill(old, signal.SIGKILL)
    with pytest.warns(RuntimeWarning, match="worker 1 .*killed by SIGKILL.*restarting it"):
        obs, rewards, terminations, truncations, infos = vec.step(ZEROS)
    assert _pid(vec, 1) != old and vec.restarts.tolist() == [0, 0, 1]
    assert truncations.tolist() == [False, False, True] and not terminations.any() and rewards[2] == 0.0
    assert infos["_worker_restarted"].tolist() == [False, False, True] and infos["worker_restarted"][2]
    assert "killed by SIGKILL" in infos["worker_error"][2]
    fresh = SutureEnv("needle_insert").reset(seed=vec.restart_seed(2))[0]  # the derived seed's first observation
    if mode == AutoresetMode.SAME_STEP:
        np.testing.assert_array_equal(infos["final_obs"][2], last[2])
        np.testing.assert_array_equal(obs[2], fresh)
        obs, _, _, truncations, _ = vec.step(ZEROS)
        assert not truncations.any()
    else:
        np.testing.assert_array_equal(obs[2], last[2])  # the episode's last observation, then the autoreset
        obs, rewards, _, truncations, infos = vec.step(ZEROS)
        np.testing.assert_array_equal(obs[2], fresh)
        assert rewards[2] == 0.0 and not truncations.any() and infos["worker_restarted"][2]
    for _ in range(3):
        obs, *_ = vec.step(ZEROS)
    assert np.all(np.isfinite(obs))
    vec.close()


def test_restart_workers_retries_a_reset_and_recovers_a_stopped_worker():
    vec = SutureVectorEnv("needle_insert", 3, workers=2, worker_timeout=3, restart_workers=True)
    first, _ = vec.reset(seed=3)
    os.kill(_pid(vec, 0), signal.SIGSTOP)
    with pytest.warns(RuntimeWarning, match="did not answer within worker_timeout = 3 s"):
        again, infos = vec.reset(seed=3)
    np.testing.assert_array_equal(again, first)  # the same seeds on the new worker: the same episodes
    assert infos["worker_restarted"].tolist() == [True, True, False]
    os.kill(_pid(vec, 1), signal.SIGKILL)
    with pytest.warns(RuntimeWarning), pytest.raises(WorkerError, match="worker 1"):
        vec.get_attr("render_mode")  # any other request: the worker is restarted and the error raised
    assert vec.get_attr("render_mode") == (None, None, None)
    _, _, _, truncations, infos = vec.step(ZEROS)  # the interrupted env's episode ends at its next step
    assert truncations.tolist() == [False, False, True] and infos["worker_restarted"][2]
    vec.close()


def test_sb3_ppo_learns_through_a_killed_worker():
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO
    from stable_baselines3.common.callbacks import BaseCallback

    from suture_gym.envs.sb3 import make_sb3_vec_env

    class KillOnce(BaseCallback):
        def _on_step(self) -> bool:
            if self.num_timesteps == 40:
                os.kill(_pid(self.training_env.unwrapped.vector_env, 1), signal.SIGKILL)
            return True

    env = make_sb3_vec_env("SutureGym/NeedleInsert-v3", 2, max_episode_steps=30, workers=2, worker_timeout=30,
                           restart_workers=True)
    model = PPO("MlpPolicy", env, n_steps=64, batch_size=64, n_epochs=1, seed=0, device="cpu")
    with pytest.warns(RuntimeWarning, match="worker 1 .*killed by SIGKILL"):
        model.learn(256, callback=KillOnce())
    assert model.num_timesteps >= 256 and env.unwrapped.vector_env.restarts.tolist() == [0, 1]
    env.close()
