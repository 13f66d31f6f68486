"""DAgger (suture_gym/baselines/dagger.py) and its oracle, the feedback expert (suture_gym/baselines/expert.py), on
NeedleInsert (and WoundClosure for the transit between stitches)."""

import json

import gymnasium as gym
import numpy as np
import pytest

from suture_gym.tasks import NeedleInsert, SutureThrow, WoundClosure

pytest.importorskip("stable_baselines3")

import suture_gym  # noqa: E402,F401
from suture_gym.baselines.dagger import DAGGER_KEYS, dagger_settings  # noqa: E402
from suture_gym.baselines.evaluation import evaluate  # noqa: E402
from suture_gym.baselines.expert import ExpertPolicy, FeedbackExpert  # noqa: E402
from suture_gym.baselines.hyperparams import load_hyperparams, resolve  # noqa: E402
from suture_gym.baselines.surgeon import LIFT, TRANSIT_SPEED, WAYPOINT_TOLERANCE
from suture_gym.baselines.training import train  # noqa: E402
from suture_gym.tasks.surgeon import start_angle  # noqa: E402

NOMINAL = {"config": "configs/envs/needle_insert_deterministic.yaml"}


@pytest.fixture(scope="module")
def env():
    env = gym.make("SutureGym/NeedleInsert-v3", **NOMINAL)
    yield env
    env.close()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("iterations: 3", "dagger must be a mapping"),
        ({"rounds": 3}, "rounds"),
        ({"iterations": 0}, "dagger.iterations"),
        ({"episodes_per_iteration": 1.5}, "dagger.episodes_per_iteration"),
        ({"beta": 1.5}, "dagger.beta"),
        ({"beta_decay": -0.1}, "dagger.beta_decay"),
        ({"lead": 0.0}, "dagger.lead"),
        ({"learning_rate": float("nan")}, "dagger.learning_rate"),
        ({"stall_steps": 0}, "dagger.stall_steps"),
        ({"gain": 1.5}, "dagger.gain"),
    ],
)
def test_dagger_settings_name_bad_values(change, message):
    with pytest.raises(ValueError, match=message):
        dagger_settings(change)


def test_every_task_has_a_dagger_recipe():
    for task in (NeedleInsert, SutureThrow, WoundClosure):
        script, _ = resolve(load_hyperparams("dagger", task.ENV_ID))
        assert set(script["dagger"]) == set(DAGGER_KEYS)


def test_feedback_expert_labels_the_state_not_its_history(env):
    """A feedback expert that drove the needle for 60 steps and one created at that state command the same pose
    (the clock expert's fresh copy would command its first clock step again)."""
    obs, _ = env.reset(seed=0)
    driver = FeedbackExpert(env)
    for _ in range(60):
        obs, *_ = env.step(driver(obs))
    fresh = FeedbackExpert(env)
    np.testing.assert_allclose(fresh(obs), driver(obs), atol=1e-6)
    assert fresh.angle == pytest.approx(driver.angle, abs=1e-12)
    clock = ExpertPolicy(env)
    clock(obs)
    assert driver.angle - clock.angle > 0.2  # 60 steps on, the needle is far past the clock's first command


def test_feedback_expert_inserts_the_needle(env):
    obs, _ = env.reset(seed=0)
    expert = FeedbackExpert(env)
    done = False
    while not done:
        obs, _, terminated, truncated, info = env.step(expert(obs))
        done = terminated or truncated
    assert info["is_success"] and terminated


def test_feedback_expert_names_a_bad_lead_or_gain(env):
    with pytest.raises(ValueError, match="lead"):
        FeedbackExpert(env, lead=-0.01)
    with pytest.raises(ValueError, match="gain"):
        FeedbackExpert(env, gain=0.0)


def test_a_softer_feedback_expert_commands_a_proportionally_softer_wrench(env):
    """The turn's label is the env's coupling wrench toward the commanded pose, scaled by ``gain``."""
    obs, _ = env.reset(seed=0)
    for _ in range(40):
        obs, *_ = env.step(FeedbackExpert(env)(obs))
    soft = FeedbackExpert(env, gain=0.25)
    label = soft(obs)
    sim = env.unwrapped.sim
    wrench = sim.coupling_spring.wrench(sim.model.needle, sim.state.needle, *sim.arc_grip_target(sim.arcs[0],
                                                                                                 soft.angle))
    np.testing.assert_allclose(label, env.unwrapped.action_for_wrench(0.25 * wrench), atol=1e-6)
    assert 0.0 < np.abs(label).max() < 1.0


def test_transit_velocity_rises_crosses_and_glides_onto_the_approach_pose():
    start = np.array([0.01, 0.02, 0.012])
    below = FeedbackExpert.transit_velocity(start + [0.02, 0.0, -0.002], start)
    np.testing.assert_allclose(below, [0.0, 0.0, TRANSIT_SPEED])  # LIFT + 2 mm below the crossing: straight up
    level = FeedbackExpert.transit_velocity(start + [0.02, 0.0, LIFT], start)
    np.testing.assert_allclose(level, [-TRANSIT_SPEED, 0.0, 0.0], atol=1e-12)  # at the crossing height: across
    gliding = FeedbackExpert.transit_velocity(start + [0.0025, 0.0, LIFT], start)
    assert gliding[0] < 0.0 and gliding[2] < 0.0  # within TRANSIT_GLIDE: across and down together
    np.testing.assert_allclose(FeedbackExpert.transit_velocity(start, start), 0.0, atol=1e-15)
    near = FeedbackExpert.transit_velocity(start + [1e-4, 0.0, 0.0], start)
    assert np.linalg.norm(near) < 0.05 * TRANSIT_SPEED  # slows in proportion near the pose


@pytest.mark.slow
def test_feedback_expert_carries_the_needle_to_the_next_stitch_with_soft_labels():
    """WoundClosure: after the first stitch the oracle's transit reaches the second stitch's approach pose (its
    turn starts) without saturating its labels."""
    env = gym.make("SutureGym/WoundClosure-v3")
    obs, _ = env.reset(seed=0)
    oracle = FeedbackExpert(env, lead=0.06, gain=0.25)
    sim, task = env.unwrapped.sim, env.unwrapped.task
    transit = []
    for _ in range(1500):
        label = oracle(obs)
        if oracle.phase == "transit":
            transit.append(label)
        elif transit:
            break
        obs, _, terminated, truncated, _ = env.step(label)
        assert not (terminated or truncated)
    assert task.state.stitch == 1 and oracle.phase == "turn" and len(transit) > 20
    start, _ = sim.arc_grip_target(sim.arcs[1], start_angle(sim.arcs[1], env.unwrapped.config.plan.start_angle))
    assert np.linalg.norm(sim.grip_pose()[0] - start) <= WAYPOINT_TOLERANCE
    assert np.mean(np.abs(np.asarray(transit)) >= 1.0) < 0.05
    env.close()


def test_dagger_run_writes_an_evaluable_model(tmp_path):
    hyperparams = {"policy": "MlpPolicy", "n_timesteps": 5000, "normalize": True, "env_kwargs": NOMINAL,
                   "policy_kwargs": {"net_arch": [32]},
                   "dagger": {"iterations": 3, "episodes_per_iteration": 1, "epochs": 2}}
    result = train("dagger", "SutureGym/NeedleInsert-v3", seed=1, out_dir=tmp_path, progress_bar=False,
                   hyperparams=hyperparams)
    run = result.run_dir
    for name in ("final_model.zip", "final_vecnormalize.pkl", "best_model.zip", "config.yaml", "summary.json",
                 "learning_curve.png", "eval/evaluations.npz"):
        assert (run / name).exists(), name
    import json

    summary = json.loads((run / "summary.json").read_text())
    betas = [record["beta"] for record in summary["iterations"]]
    assert betas == [1.0, 0.0, 0.0]
    steps = [record["steps"] for record in summary["iterations"]]
    assert [record["data_steps"] for record in summary["iterations"]] == list(np.cumsum(steps))
    assert summary["timesteps"] == sum(steps) == result.timesteps
    seeds = [seed for record in summary["iterations"] for seed in record["env_seeds"]]
    assert len(set(seeds)) == len(seeds) and min(seeds) >= 100_000
    curve = np.load(run / "eval" / "evaluations.npz")
    assert list(curve["timesteps"]) == [steps[0], steps[0] + steps[1]]
    report = evaluate("SutureGym/NeedleInsert-v3", str(run / "final_model.zip"), episodes=1, seed=7)
    assert report["vecnormalize"].endswith("final_vecnormalize.pkl") and report["env_kwargs"]["config"]
    best = summary["iterations"][summary["best_iteration"] - 1]["checkpoint_steps"]
    checkpoint = run / "checkpoints" / f"model_vecnormalize_{best}_steps.pkl"
    assert (run / "best_vecnormalize.pkl").read_bytes() == checkpoint.read_bytes()
    assert evaluate("SutureGym/NeedleInsert-v3", str(run / "best_model.zip"), episodes=1,
                    seed=7)["vecnormalize"].endswith("best_vecnormalize.pkl")
    with pytest.raises(ValueError, match="cannot be resumed"):
        train("dagger", "SutureGym/NeedleInsert-v3", out_dir=tmp_path, hyperparams=hyperparams,
              resume=run / "final_model.zip")


def test_rollouts_on_worker_processes_give_the_same_run(tmp_path):
    """Two rollout workers: the same episodes, labels, refits and model as one process (beta 0.5 draws the
    executed actions, so the per-episode draws are checked too)."""
    hyperparams = {"policy": "MlpPolicy", "n_timesteps": 5000, "normalize": True, "env_kwargs": NOMINAL,
                   "policy_kwargs": {"net_arch": [32]},
                   "dagger": {"iterations": 3, "episodes_per_iteration": 2, "epochs": 2, "beta": 0.5,
                              "beta_decay": 0.5, "stall_steps": 30}}
    runs = {}
    import torch
    from stable_baselines3 import PPO

    for workers in (1, 2):
        result = train("dagger", "SutureGym/NeedleInsert-v3", seed=3, out_dir=tmp_path / str(workers),
                       progress_bar=False, hyperparams=hyperparams, workers=workers)
        summary = json.loads((result.run_dir / "summary.json").read_text())
        weights = PPO.load(result.run_dir / "final_model.zip", device="cpu").policy.state_dict()
        runs[workers] = (summary["iterations"], weights)
    assert runs[1][0] == runs[2][0]
    assert [r["beta"] for r in runs[1][0]] == [0.5, 0.25, 0.125]
    assert runs[1][1].keys() == runs[2][1].keys()
    for key, value in runs[1][1].items():
        assert torch.equal(value, runs[2][1][key]), key
    with pytest.raises(ValueError, match="workers applies to DAgger"):
        train("ppo", "Pendulum-v1", out_dir=tmp_path, progress_bar=False,
              hyperparams={"policy": "MlpPolicy", "n_timesteps": 64}, workers=2)
    with pytest.raises(ValueError, match="workers must be an integer >= 1, got 0"):
        train("dagger", "SutureGym/NeedleInsert-v3", out_dir=tmp_path / "0", progress_bar=False,
              hyperparams=hyperparams, workers=0)


def test_dagger_settings_belong_to_the_dagger_config(tmp_path):
    with pytest.raises(ValueError, match="dagger.yml"):
        train("ppo", "Pendulum-v1", out_dir=tmp_path, progress_bar=False,
              hyperparams={"policy": "MlpPolicy", "n_timesteps": 64, "dagger": {}})


def test_a_learner_that_holds_still_ends_its_rollout(tmp_path):
    """An untrained learner (the refit's step is 1e-9) barely moves the needle: each of its rollouts ends once
    the tip has moved under STALL_DISTANCE over ``stall_steps`` steps, instead of running to the time limit."""
    hyperparams = {"policy": "MlpPolicy", "n_timesteps": 5000, "normalize": True, "env_kwargs": NOMINAL,
                   "policy_kwargs": {"net_arch": [32]},
                   "dagger": {"iterations": 2, "episodes_per_iteration": 2, "epochs": 1, "learning_rate": 1e-9,
                              "stall_steps": 20}}
    result = train("dagger", "SutureGym/NeedleInsert-v3", seed=0, out_dir=tmp_path, progress_bar=False,
                   hyperparams=hyperparams)
    import json

    expert, learner = json.loads((result.run_dir / "summary.json").read_text())["iterations"]
    assert expert["stalled_episodes"] == 0 and expert["success_rate"] == 1.0
    assert learner["stalled_episodes"] == 2 and learner["steps"] == 2 * 20


def test_action_for_wrench_scales_by_the_action_limits(env):
    cfg = env.unwrapped.config.action
    wrench = np.array([cfg.max_force, -0.5 * cfg.max_force, 3.0 * cfg.max_force, 0.25 * cfg.max_torque, 0.0,
                       -2.0 * cfg.max_torque])
    np.testing.assert_allclose(env.unwrapped.action_for_wrench(wrench), [1.0, -0.5, 1.0, 0.25, 0.0, -1.0])
    with pytest.raises(ValueError, match="shape"):
        env.unwrapped.action_for_wrench(np.zeros(3))
    pose = gym.make("SutureGym/NeedleInsert-v3", config={"action": {"mode": "pose_delta"}})
    with pytest.raises(ValueError, match="pose_delta"):
        pose.unwrapped.action_for_wrench(np.zeros(6))
