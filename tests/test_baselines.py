"""Baselines on the real SutureGym ids: each algorithm's config trains briefly, saves, loads and evaluates; the
scripted expert solves every task; expert demonstrations round-trip through ``.npz``."""

from __future__ import annotations

import math

import gymnasium as gym
import numpy as np
import pytest

pytest.importorskip("stable_baselines3")
pytest.importorskip("sb3_contrib")

import suture_gym  # noqa: E402, F401  (registers the ids)
from suture_gym.baselines.evaluation import evaluate  # noqa: E402
from suture_gym.baselines.expert import ExpertPolicy, record  # noqa: E402
from suture_gym.baselines.hyperparams import load_hyperparams  # noqa: E402
from suture_gym.baselines.surgeon import WORKSPACE_INSET  # noqa: E402
from suture_gym.baselines.training import train  # noqa: E402

#: (algo, env id, env steps): the shipped configs with the budget, batch, warm-up and time limit shortened
#: (HER samples only finished episodes, so episodes end before learning starts).
SMOKE = (
    ("ppo", "SutureGym/NeedleInsert-v3", 128),
    ("sac", "SutureGym/NeedleInsert-v3", 150),
    ("tqc", "SutureGym/NeedleInsertGoal-v3", 150),
)


@pytest.mark.parametrize(("algo", "env_id", "steps"), SMOKE)
def test_config_trains_saves_loads_and_evaluates(tmp_path, algo, env_id, steps):
    hyperparams = load_hyperparams(algo, env_id)
    if algo == "ppo":
        hyperparams.update(n_envs=2, n_steps=64, batch_size=64, n_epochs=1,
                           behaviour_cloning={"expert_episodes": 1, "epochs": 1})
    else:
        hyperparams.update(learning_starts=100, batch_size=32, buffer_size=1000,
                           env_kwargs={"max_episode_steps": 40})
    result = train(algo, env_id, seed=0, out_dir=tmp_path, n_timesteps=steps, eval_freq=0, checkpoint_freq=0,
                   progress_bar=False, hyperparams=hyperparams)
    assert result.model_path.exists()
    assert result.timesteps >= steps
    assert (result.run_dir / "demos.npz").exists() == ("behaviour_cloning" in hyperparams)
    summary = evaluate(env_id, str(result.model_path), episodes=1, seed=5,
                       env_kwargs={"max_episode_steps": 20})
    assert summary["episodes"] == 1
    assert summary["mean_episode_length"] == 20
    assert math.isfinite(summary["mean_return"])


def test_goal_configs_use_her_with_info_dicts():
    for algo in ("sac", "tqc"):
        for env_id in ("SutureGym/NeedleInsertGoal-v3", "SutureGym/SutureThrowGoal-v3",
                       "SutureGym/WoundClosureGoal-v3"):
            hyperparams = load_hyperparams(algo, env_id)
            assert hyperparams["replay_buffer_class"] == "HerReplayBuffer"
            assert hyperparams["replay_buffer_kwargs"]["copy_info_dict"] is True
            assert hyperparams["policy"] == "MultiInputPolicy"


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_expert_inserts_needle_under_randomisation(seed):
    summary = evaluate("SutureGym/NeedleInsert-v3", "expert", episodes=1, seed=seed)  # randomised by default
    assert summary["success_rate"] == 1.0
    assert summary["diverged_episodes"] == 0


def test_expert_inserts_needle_in_pose_delta_mode():
    summary = evaluate("SutureGym/NeedleInsert-v3", "expert", episodes=1, seed=0,
                       env_kwargs={"action_mode": "pose_delta"})
    assert summary["success_rate"] == 1.0


def test_expert_throws_suture():
    summary = evaluate("SutureGym/SutureThrow-v3", "expert", episodes=1, seed=0)
    assert summary["success_rate"] == 1.0
    assert summary["diverged_episodes"] == 0


@pytest.mark.slow
def test_expert_closes_wound():
    summary = evaluate("SutureGym/WoundClosure-v3", "expert", episodes=1, seed=0)
    assert summary["success_rate"] == 1.0
    assert summary["diverged_episodes"] == 0


@pytest.mark.parametrize("env_id", ["SutureGym/NeedleInsert-v3", "SutureGym/WoundClosure-v3"])
def test_expert_speeds_default_per_task_and_reject_bad_values(env_id):
    env = gym.make(env_id)
    task = env.unwrapped.task
    expert = ExpertPolicy(env)
    assert (expert.turn_rate, expert.pull_speed) == (task.SURGEON_TURN_RATE, task.SURGEON_PULL_SPEED)
    assert ExpertPolicy(env, turn_rate=0.5).turn_rate == 0.5
    with pytest.raises(ValueError, match="-1.0"):
        ExpertPolicy(env, pull_speed=-1.0)
    with pytest.raises(ValueError, match="nan"):
        ExpertPolicy(env, turn_rate=float("nan"))


def test_expert_pull_slides_along_workspace_walls(monkeypatch):
    """Components of the pull toward a wall the tip is within WORKSPACE_INSET of are dropped; the rest keeps
    unit length; a tip cornered against every wall the pull heads for is not pulled at all."""
    env = gym.make("SutureGym/SutureThrow-v3")
    env.reset(seed=0)
    expert = ExpertPolicy(env)
    sim = env.unwrapped.sim
    low, high = sim.workspace
    centre = 0.5 * (low + high)
    direction = np.array([0.0, -2.0, 1.0]) / math.sqrt(5.0)
    monkeypatch.setattr(sim, "tip_position", lambda: centre.copy())
    np.testing.assert_allclose(expert._pull_direction(direction), direction)
    near_top = centre.copy()
    near_top[2] = high[2] - 0.5 * WORKSPACE_INSET
    monkeypatch.setattr(sim, "tip_position", lambda: near_top)
    np.testing.assert_allclose(expert._pull_direction(direction), [0.0, -1.0, 0.0], atol=1e-15)
    away = np.array([0.0, -1.0, -1.0]) / math.sqrt(2.0)  # heading away from the top wall: kept whole
    np.testing.assert_allclose(expert._pull_direction(away), away)
    cornered = near_top.copy()
    cornered[1] = low[1] + 0.5 * WORKSPACE_INSET
    monkeypatch.setattr(sim, "tip_position", lambda: cornered)
    np.testing.assert_array_equal(expert._pull_direction(direction), np.zeros(3))


def test_expert_leans_the_running_sutures_last_pull_ahead_along_the_suture():
    env = gym.make("SutureGym/WoundClosure-v3")
    env.reset(seed=0)
    expert = ExpertPolicy(env)
    arcs = env.unwrapped.sim.arcs
    for k in range(len(arcs) - 1):
        np.testing.assert_allclose(expert._planned_pull(k), arcs[k].pull_direction)
    last = expert._planned_pull(len(arcs) - 1)
    advance = (arcs[-1].center - arcs[-2].center) / np.linalg.norm(arcs[-1].center - arcs[-2].center)
    assert np.linalg.norm(last) == pytest.approx(1.0)
    assert last @ advance > 0.5 and last @ arcs[-1].pull_direction > 0.5  # ahead, and still back and up
    single = gym.make("SutureGym/SutureThrow-v3")
    single.reset(seed=0)
    np.testing.assert_allclose(ExpertPolicy(single)._planned_pull(0), single.unwrapped.sim.arcs[0].pull_direction)


def test_tip_position_matches_observation():
    env = gym.make("SutureGym/NeedleInsert-v3")
    env.reset(seed=0)
    for _ in range(5):
        env.step(env.action_space.sample())
    sim = env.unwrapped.sim
    np.testing.assert_allclose(sim.tip_position(), sim.observables().tip_pos, rtol=0, atol=1e-15)


def test_expert_rejects_foreign_env():
    with pytest.raises(ValueError, match="SutureGym"):
        ExpertPolicy(gym.make("Pendulum-v1"))


def test_demonstrations_round_trip(tmp_path):
    out = tmp_path / "demos.npz"
    summary = record("SutureGym/NeedleInsert-v3", 2, out, seed=3, progress=False)
    data = np.load(out)
    lengths = data["episode_lengths"]
    assert summary["steps"] == int(lengths.sum()) == data["actions"].shape[0]
    assert data["observations"].shape[0] == data["rewards"].shape[0] == data["tip_forces"].shape[0]
    assert list(data["episode_starts"]) == [0, int(lengths[0])]
    assert list(data["episode_seeds"]) == [3, 4]
    assert bool(np.all(data["episode_success"]))
    ends = data["episode_starts"] + lengths - 1
    done = data["terminated"] | data["truncated"]
    assert bool(np.all(done[ends])) and int(done.sum()) == 2
    assert np.array_equal(data["observations"][1:lengths[0]], data["next_observations"][:lengths[0] - 1])
    assert float(np.abs(data["actions"]).max()) <= 1.0
    env = gym.make("SutureGym/NeedleInsert-v3")
    expert = ExpertPolicy(env)
    obs, _ = env.reset(seed=3)
    replayed = 0.0
    for t in range(int(lengths[0])):
        assert np.array_equal(obs, data["observations"][t])
        obs, reward, *_ = env.step(expert(obs))
        replayed += reward
    assert replayed == pytest.approx(float(data["rewards"][: lengths[0]].sum()), rel=0, abs=1e-12)


def test_train_command_from_scratch_leaves_out_the_warm_start(tmp_path, monkeypatch, capsys):
    import yaml

    from suture_gym.cli import train as script

    def shortened(algo, env_id):
        hyperparams = load_hyperparams(algo, env_id)
        hyperparams.update(n_envs=2, n_steps=64, batch_size=64, n_epochs=1)
        return hyperparams

    monkeypatch.setattr(script, "load_hyperparams", shortened)
    assert "behaviour_cloning" in shortened("ppo", "SutureGym/SutureThrow-v3")
    assert script.main(["--algo", "ppo", "--env", "SutureGym/SutureThrow-v3", "--from-scratch", "--n-timesteps",
                        "128", "--out", str(tmp_path), "--eval-freq", "0", "--checkpoint-freq", "0",
                        "--no-progress"]) == 0
    run_dir = tmp_path / "ppo_SutureThrow_s0"
    config = yaml.safe_load((run_dir / "config.yaml").read_text())
    assert "behaviour_cloning" not in config["hyperparams"] and config["hyperparams"]["n_steps"] == 64
    assert not (run_dir / "demos.npz").exists()
    with pytest.raises(SystemExit):
        script.main(["--algo", "dagger", "--from-scratch"])
    assert "--from-scratch applies to PPO, SAC and TQC" in capsys.readouterr().err
