"""The Gymnasium environments on the real coupled simulator: check_env (Gymnasium and SB3) for every id, random
rollouts including the corners of the action box, determinism, exact reward sums, snapshots, action errors,
divergence, start phases, privileged observations, pose-delta mode, goal rewards, rendering and configs."""

import itertools
import math
import warnings
from dataclasses import replace
from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import suture_gym.envs  # noqa: F401  (registers the ids)
from suture_gym.configs import ENV_DIR
from suture_gym.envs import ENV_IDS, GOAL_ENV_IDS, SutureEnv, SutureGoalEnv

ALL_IDS = list(ENV_IDS) + list(GOAL_ENV_IDS)
CONFIGS = ENV_DIR
INFO_KEYS = ("is_success", "punctured", "tip_force", "haptic_wrench", "wound_gap", "diverged", "cost")
_ENVS: dict = {}


def _env(env_id: str) -> gym.Env:
    """One shared unwrapped env per id (building a scene takes a while; every test resets it)."""
    if env_id not in _ENVS:
        _ENVS[env_id] = gym.make(env_id).unwrapped
    return _ENVS[env_id]


def _terms(env) -> tuple:
    return env.task_cls.GOAL_TERMS if isinstance(env, SutureGoalEnv) else env.task_cls.TERMS


def _plain(info: dict) -> list:
    """``info`` as a sorted, comparable list (arrays as their bytes)."""
    return sorted((k, v.tobytes() if isinstance(v, np.ndarray) else v) for k, v in info.items())


def _check_step(env, obs, reward, info):
    assert env.observation_space.contains(obs)
    flat = [obs] if isinstance(obs, np.ndarray) else list(obs.values())
    assert all(np.all(np.isfinite(v)) for v in flat)
    assert math.isfinite(reward)
    for key in INFO_KEYS:
        assert key in info
    assert info["cost"] >= 0.0
    wrench = info["haptic_wrench"]
    assert wrench.shape == (6,) and wrench.dtype == np.float64 and np.all(np.isfinite(wrench))
    np.testing.assert_array_equal(wrench, env.unwrapped.sim.state.needle_reaction)
    terms = [info[f"reward_{t}"] for t in _terms(env)]
    assert math.fsum(terms) == reward


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_gymnasium_check_env(env_id):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is.*")
        check_env(_env(env_id), skip_render_check=True)


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_sb3_check_env(env_id):
    env_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    env_checker.check_env(_env(env_id), warn=False)


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_random_rollouts_with_box_corners_stay_finite(env_id):
    env = _env(env_id)
    rng = np.random.default_rng(0)
    corners = [np.array(c, dtype=np.float32) for c in itertools.product((-1.0, 1.0), repeat=6)]
    actions = [c for c in corners for _ in range(2)] + [rng.uniform(-1, 1, 6).astype(np.float32) for _ in range(60)]
    obs, info = env.reset(seed=1)
    episodes = 1
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a)
        _check_step(env, obs, reward, info)
        if terminated or truncated:
            obs, info = env.reset()
            episodes += 1
    assert episodes >= 1


def _flat(obs) -> np.ndarray:
    return obs["observation"] if isinstance(obs, dict) else obs


@pytest.mark.parametrize("env_id", ALL_IDS)
def test_every_id_randomises_by_default_and_a_seed_repeats_its_episode(env_id):
    env = _env(env_id)
    a, info_a = env.reset(seed=11)
    b, info_b = env.reset(seed=12)
    again, info_again = env.reset(seed=11)
    assert not np.array_equal(_flat(a), _flat(b)) and info_a["params"] != info_b["params"]
    np.testing.assert_array_equal(_flat(a), _flat(again))
    assert info_a["params"] == info_again["params"]
    assert env.observation_space.contains(a)


@pytest.mark.parametrize("task", ["needle_insert", "suture_throw"])
def test_the_observation_space_does_not_depend_on_the_randomisation(task):
    spaces = [SutureEnv(task, config=cfg).observation_space for cfg in (
        None, {"randomization": {"enabled": False}},
        {"randomization": {"youngs_modulus_scale": [1.0, 1.0], "needle_position_noise": 0.0}},
    )]
    assert spaces[0] == spaces[1] == spaces[2]
    assert np.all(np.isfinite(spaces[0].low)) and np.all(np.isfinite(spaces[0].high))
    nominal = SutureEnv(task, config={"randomization": {"enabled": False}})
    first, info = nominal.reset(seed=1)
    second, info2 = nominal.reset(seed=2)
    np.testing.assert_array_equal(first, second)
    assert info["params"] == info2["params"]


def test_scaled_observation_is_the_raw_one_over_its_scale_within_its_bounds():
    scaled_env = SutureEnv("needle_insert")
    raw_env = SutureEnv("needle_insert", config={"observation": {"scaled": False}})
    assert np.all(np.isinf(raw_env.observation_space.high)) and raw_env.observation_space.shape == (
        scaled_env.observation_space.shape)
    scaled, _ = scaled_env.reset(seed=5)
    raw, _ = raw_env.reset(seed=5)
    actions = np.random.default_rng(0).uniform(-1.0, 1.0, (30, 6)).astype(np.float32)
    for action in actions:
        scaled, *_ = scaled_env.step(action)
        raw, *_ = raw_env.step(action)
    expected = np.clip(raw.astype(np.float64) / scaled_env.obs_scale, -scaled_env.obs_bound, scaled_env.obs_bound)
    np.testing.assert_allclose(scaled, expected, rtol=1e-5, atol=1e-6)
    index = scaled_env.obs_index
    assert scaled_env.obs_scale[index["tip_force"]][0] == scaled_env.config.action.max_force
    assert scaled_env.obs_scale[index["tip_pos"]][0] == 0.01
    assert np.abs(scaled).max() <= scaled_env.obs_bound.max()


@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_same_seed_same_actions_bit_identical(env_id):
    rng = np.random.default_rng(4)
    actions = rng.uniform(-0.3, 0.3, (40, 6)).astype(np.float32)
    runs = []
    for _ in range(2):
        env = _env(env_id)
        obs, _ = env.reset(seed=7)
        record = [obs.tobytes()]
        for a in actions:
            obs, reward, terminated, truncated, info = env.step(a)
            record.append((obs.tobytes(), reward, terminated, truncated, _plain(info)))
            if terminated or truncated:
                break
        runs.append(record)
    assert runs[0] == runs[1]


def _expert_record(env, seed: int, steps: int, options: dict | None = None) -> list:
    """The scripted expert's episode from ``env.reset(seed=seed, options=options)`` for at most ``steps`` steps:
    the raw bytes of every observation and each step's reward, for bit-for-bit comparison."""
    from suture_gym.baselines.expert import ExpertPolicy

    expert = ExpertPolicy(env)
    obs, _ = env.reset(seed=seed, options=options)
    expert.reset()
    record = [obs.tobytes()]
    for _ in range(steps):
        obs, reward, terminated, truncated, _ = env.step(expert(obs))
        record.append((obs.tobytes(), reward))
        if terminated or truncated:
            break
    return record


def test_an_episode_does_not_depend_on_the_episodes_before_it():
    """The same seed and actions replay the same episode bit for bit in a fresh env and in one that has run
    another episode first (the nominal config keeps the tissue integrator, and its cached columns of the rest
    system's inverse, across resets)."""
    from suture_gym.baselines.expert import ExpertPolicy

    config = ENV_DIR / "needle_insert_deterministic.yaml"
    fresh = gym.make("SutureGym/NeedleInsert-v3", config=str(config)).unwrapped
    used = gym.make("SutureGym/NeedleInsert-v3", config=str(config)).unwrapped
    expert, noise = ExpertPolicy(used), np.random.default_rng(3)
    obs, _ = used.reset(seed=3)  # first a noisy insertion, which touches other vertices in another order
    expert.reset()
    for _ in range(300):
        action = np.clip(expert(obs) + noise.normal(0.0, 0.3, 6), -1.0, 1.0).astype(np.float32)
        obs, _, terminated, truncated, _ = used.step(action)
        if terminated or truncated:
            break
    assert _expert_record(fresh, 5, 250) == _expert_record(used, 5, 250)


def test_observations_do_not_alias_internal_arrays():
    env = _env("SutureGym/NeedleInsert-v3")
    obs, _ = env.reset(seed=0)
    kept = obs.copy()
    obs[:] = 123.0
    obs2, *_ = env.step(np.zeros(6, np.float32))
    assert not np.shares_memory(obs2, env._obs_buffer)
    state = env.get_state()
    assert np.array_equal(state.last_observation, obs2) and not np.shares_memory(state.last_observation, obs2)
    env.reset(seed=0)
    assert np.array_equal(env.last_observation, kept)


@pytest.mark.parametrize("env_id", list(ENV_IDS))
def test_snapshot_restore_replays_identically(env_id):
    env = _env(env_id)
    env.reset(seed=3)
    rng = np.random.default_rng(9)
    for _ in range(10):
        env.step(rng.uniform(-0.2, 0.2, 6).astype(np.float32))
    saved = env.get_state()
    actions = rng.uniform(-0.2, 0.2, (15, 6)).astype(np.float32)

    def play():
        out = []
        for a in actions:
            obs, reward, terminated, truncated, info = env.step(a)
            out.append((obs.tobytes(), reward, terminated, truncated, _plain(info)))
        return out

    first = play()
    env.set_state(saved)
    assert play() == first
    with pytest.raises(ValueError, match="EnvState"):
        env.set_state("not a state")


def test_non_finite_and_misshapen_actions_raise():
    env = _env("SutureGym/NeedleInsert-v3")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=r"finite.*\[2\]"):
        env.step(np.array([0.0, 0.0, np.nan, 0.0, 0.0, 0.0]))
    with pytest.raises(ValueError, match="finite"):
        env.step(np.array([np.inf, 0.0, 0.0, 0.0, 0.0, -np.inf]))
    with pytest.raises(ValueError, match="shape"):
        env.step(np.zeros(5))


@pytest.mark.parametrize("action_mode", ["wrench", "pose_delta"])
def test_actions_outside_the_box_act_as_the_box_edge(action_mode):
    env = SutureEnv("needle_insert", action_mode=action_mode)
    env.reset(seed=0)
    for _ in range(3):
        env.step(np.full(6, 0.2))
    start = env.get_state()
    edge = np.array([1.0, -1.0, 1.0, 0.5, -1.0, 1.0])
    extreme = np.array([1e6, -1e9, 3.0, 0.5, -1.0 - 1e-9, 1e300])
    runs = []
    for action in (edge, extreme):
        env.set_state(start)
        out = []
        for _ in range(3):
            obs, reward, terminated, truncated, info = env.step(action)
            out.append((obs.tobytes(), reward, terminated, truncated, _plain(info)))
        runs.append(out)
    assert runs[0] == runs[1]
    info = dict(runs[1][0][4])
    assert not info["diverged"] and info["reward_action"] == pytest.approx(-env.config.reward.action * np.mean(edge**2))

@pytest.mark.parametrize(
    "action",
    [["0.1"] * 6, np.full(6, "1"), np.full(6, 0.1 + 0.1j), np.array([0.1] * 5 + [None], dtype=object),
     np.ones(6, dtype=bool)],
    ids=["str-list", "str-array", "complex", "object", "bool"],
)
def test_actions_that_are_not_real_numbers_raise_naming_the_dtype(action):
    env = _env("SutureGym/NeedleInsert-v3")
    env.reset(seed=0)
    with pytest.raises(TypeError, match=f"dtype {np.asarray(action).dtype}"):
        env.step(action)
    env.step(np.zeros(6, dtype=np.int64))  # integers are real numbers


def test_step_after_the_end_raises_until_reset(monkeypatch):
    env = SutureEnv("needle_insert")
    monkeypatch.setattr(env.task_cls, "failure", lambda self, obs, outside, missed: outside)
    monkeypatch.setattr(env.task_cls, "success", lambda self, obs: False)
    env.reset(seed=0)
    env.sim.state.needle.body_pos[:] += [0.0, 0.0, 0.05]  # lift the needle out of the workspace
    _, _, terminated, _, info = env.step(np.zeros(6))
    assert terminated and info["out_of_workspace"]
    ended = env.get_state()
    with pytest.raises(RuntimeError, match=r"ended.*call reset\(\)"):
        env.step(np.zeros(6))
    env.reset(seed=0)
    started = env.get_state()
    env.set_state(ended)
    with pytest.raises(RuntimeError, match="ended"):
        env.step(np.zeros(6))
    env.set_state(started)
    env.step(np.zeros(6))


def test_render_before_reset_raises():
    env = SutureEnv("needle_insert", render_mode="rgb_array")
    with pytest.raises(RuntimeError, match=r"call reset\(\) before render\(\)"):
        env.render()
    assert SutureEnv("needle_insert").render() is None  # no render mode: nothing to draw, nothing wrong


def _diverge(env):
    """Make the next substep's prediction non-finite, as a blown-up solve would."""
    env.sim.state.tissue.particle_qd[:] = np.nan


@pytest.mark.parametrize("env_id", ["SutureGym/NeedleInsert-v3", "SutureGym/NeedleInsertGoal-v3"])
def test_divergence_is_a_failure_with_the_last_finite_observation(env_id):
    env = _env(env_id)
    env.reset(seed=0, options={"phase": "inserted"})
    obs0, *_ = env.step(np.zeros(6, np.float32))
    potential = env.task.state.potential
    assert potential > 0.0
    _diverge(env)
    obs, reward, terminated, truncated, info = env.step(np.zeros(6, np.float32))
    assert terminated and not truncated and info["diverged"] and not info["is_success"]
    w = env.config.reward
    assert info["reward_failure"] == -w.failure
    if isinstance(env, SutureGoalEnv):
        assert np.array_equal(obs["observation"], obs0["observation"])
        assert reward == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
    else:
        assert np.array_equal(obs, obs0)
        assert info["reward_progress"] == -w.progress * potential
        assert reward == -w.failure - w.progress * potential
        others = [t for t in env.task_cls.TERMS if t not in ("failure", "progress")]
        assert all(info[f"reward_{t}"] == 0.0 for t in others)
    with pytest.raises(RuntimeError, match=r"call reset\(\)"):
        env.step(np.zeros(6, np.float32))


def test_a_non_finite_observation_is_a_divergence_and_leaves_the_task_as_it_was(monkeypatch):
    env = _env("SutureGym/NeedleInsert-v3")
    obs0, _ = env.reset(seed=0)
    before = env.task.get_state()
    observables = env.sim.observables
    monkeypatch.setattr(env.sim, "observables", lambda: replace(observables(), tip_force=float("nan")))
    obs, reward, terminated, truncated, info = env.step(np.zeros(6, np.float32))
    assert terminated and info["diverged"] and np.array_equal(obs, obs0)
    assert reward == -env.config.reward.failure and info["tip_force"] == 0.0
    assert env.task.state.stitch == before.stitch and env.task.state.potential == 0.0


def test_reset_options_are_checked():
    env = _env("SutureGym/NeedleInsert-v3")
    with pytest.raises(ValueError, match="unknown reset option"):
        env.reset(seed=0, options={"difficulty": 2})
    with pytest.raises(ValueError, match="phase"):
        env.reset(seed=0, options={"phase": "first_bite"})
    with pytest.raises(ValueError, match="unknown episode parameter"):
        env.reset(seed=0, options={"params": {"stiffness": 1.0}})
    _, info = env.reset(seed=0, options={"params": {"youngs_modulus": 250000.0}})
    assert info["params"]["youngs_modulus"] == 250000.0


#: A smaller wound-closure scene (two stitches, shorter bars and thread) for the first-bite phase test.
SMALL_CLOSURE = {"scene": {"size": [0.016, 0.012, 0.008]}, "plan": {"stitches": 2},
                 "suture": {"node_count": 41, "length": 0.04}}


@pytest.mark.parametrize(
    "task, config, phase, check",
    [
        ("needle_insert", None, "inserted", lambda env, info: info["punctured"]),
        ("suture_throw", None, "exited", lambda env, info: env.task.state.exited),
        ("wound_closure", SMALL_CLOSURE, "first_bite", lambda env, info: env.task.state.stitch == 1),
    ],
)
def test_start_phases(task, config, phase, check):
    env = SutureEnv(task, config=config)
    obs, info = env.reset(seed=0, options={"phase": phase})
    assert info["phase"] == phase and check(env, info)
    obs2, info2 = env.reset(seed=0, options={"phase": phase})  # cached: identical
    assert np.array_equal(obs, obs2)
    _, reward, *_ = env.step(np.zeros(6, np.float32))
    assert math.isfinite(reward)


def _state_arrays(state) -> list:
    """Every array and number of a simulator ``State`` (tissue, needle, thread, coupling, readings), in a fixed
    order, for comparing two states bit for bit."""
    from dataclasses import fields, is_dataclass

    out = []
    for part in (state.tissue, state.needle, state.suture, state.coupling, state.suture_tension,
                 state.suture_contact, state.needle_reaction, state.time):
        values = [getattr(part, f.name) for f in fields(part)] if is_dataclass(part) else [part]
        out += [np.asarray(v) for v in values]
    return out


def test_a_cached_phase_start_is_the_simulated_one(monkeypatch):
    from suture_gym.envs.randomization import nominal_params
    from suture_gym.envs.simulation import PHASE_STARTS, Simulation
    from suture_gym.tasks import NeedleInsert

    PHASE_STARTS.clear()
    nominal = {"randomization": {"enabled": False}}
    first = SutureEnv("needle_insert", config=nominal)
    obs_first, _ = first.reset(seed=0, options={"phase": "inserted"})  # simulates the approach, once
    simulated = Simulation(first.config)
    simulated.simulate_phase(nominal_params(first.config), "inserted")

    def not_again(sim, phase):
        raise AssertionError("the cached start was simulated again")

    monkeypatch.setattr(NeedleInsert, "start_phase", classmethod(not_again))
    second = SutureEnv("needle_insert", config=nominal)  # another env of the same config: the cached start
    obs, info = second.reset(seed=0, options={"phase": "inserted"})
    assert info["punctured"] and np.array_equal(obs, obs_first)
    for mine, theirs in zip(_state_arrays(second.sim.state), _state_arrays(simulated.state), strict=True):
        np.testing.assert_array_equal(mine, theirs)
    entries, exits = simulated.observables().new_entries, simulated.observables().new_exits
    assert len(entries) == 1 and np.array_equal(second.task.state.entry_point, entries[0]) and len(exits) == 0
    action = np.full(6, 0.3, np.float32)
    for _ in range(5):  # and the episode goes on as from the simulated start
        assert np.array_equal(first.step(action)[0], second.step(action)[0])


def test_a_randomised_phase_start_is_the_nominal_one_carried_over():
    """Another tissue stiffness, puncture force and wound gap: the nominal start moved with the wound's rest shape
    and settled, close to the approach simulated on those parameters."""
    from suture_gym.envs.simulation import Simulation

    env = SutureEnv("suture_throw")
    scale = {"youngs_modulus": 1.3, "puncture_force": 0.8, "gap": 1.1}
    nominal = env.params
    params = {k: getattr(nominal, k) * f for k, f in scale.items()}
    env.reset(seed=0, options={"phase": "inserted", "params": params})  # the tip in the gap, out of the near bar
    assert env.params.gap == params["gap"] and env.sim.gap_rest == pytest.approx(params["gap"], rel=1e-6)
    reference = Simulation(env.config)
    reference.simulate_phase(replace(nominal, **params), "inserted")
    events = reference.observables()
    assert len(events.new_entries) == len(events.new_exits) == 1
    task = env.task.state
    assert task.punctured_stitch and task.exits_in_stitch == 1 and not task.exited
    assert env.sim.state.coupling.path_count == reference.state.coupling.path_count == 1
    assert np.linalg.norm(env.sim.tip_position() - reference.tip_position()) < 0.5e-3
    assert np.linalg.norm(task.entry_point - events.new_entries[0]) < 0.5 * env.config.reward.access_tolerance
    speeds = np.linalg.norm(env.sim.state.tissue.particle_qd, axis=1)
    assert speeds.max() < 0.05  # settled (m/s)
    _, reward, terminated, *_ = env.step(np.zeros(6, np.float32))
    assert math.isfinite(reward) and not terminated


def test_scripted_surgeon_completes_needle_insert():
    env = _env("SutureGym/NeedleInsert-v3")
    env.reset(seed=0)
    arc = env.sim.arcs[0]
    angle = arc.entry_angle - env.config.plan.start_angle
    total, info = 0.0, {}
    for _ in range(400):
        angle = min(angle + 2.0 * env.sim.control_dt, arc.exit_angle + 0.5)
        obs, reward, terminated, truncated, info = env.step(env.scripted_action(angle))
        total += reward
        if terminated or truncated:
            break
    assert info["is_success"] and terminated and not info["tear"]
    assert total > env.config.reward.success


def test_privileged_observation_holds_the_sampled_parameters():
    cfg = {"observation": {"privileged": True}, "randomization": {"youngs_modulus_scale": [0.8, 1.2],
                                                                   "needle_position_noise": 5e-4}}
    env = SutureEnv("needle_insert", config=cfg)
    obs, info = env.reset(seed=2)
    params = obs[env.obs_index["params"]]
    p = info["params"]
    expected = [p["youngs_modulus"], p["puncture_force"], p["gap"], *p["needle_position_offset"],
                *p["needle_rotation_offset"]]
    nominal = env.config
    scale = [nominal.tissue.youngs_modulus, nominal.coupling.puncture_force, nominal.scene.gap, *[0.01] * 3, *[1.0] * 3]
    np.testing.assert_allclose(params, np.array(expected) / scale, rtol=1e-6)
    _, info2 = env.reset(seed=3)
    assert info2["params"] != info["params"]


def test_pose_delta_mode_holds_still_and_follows_the_script():
    env = SutureEnv("needle_insert", action_mode="pose_delta")
    obs, _ = env.reset(seed=0)
    assert "target_offset" in env.obs_index and env.config.action.mode == "pose_delta"
    for _ in range(10):
        obs, *_ = env.step(np.zeros(6, np.float32))
    assert np.linalg.norm(obs[env.obs_index["target_offset"]]) < 1e-4
    arc = env.sim.arcs[0]
    angle = arc.entry_angle - env.config.plan.start_angle
    for _ in range(60):
        angle += 1.0 * env.sim.control_dt
        obs, reward, terminated, truncated, info = env.step(env.scripted_action(angle))
    assert arc.distance(env.sim.observables().tip_pos) < 1e-3


@pytest.mark.parametrize("env_id", list(GOAL_ENV_IDS))
def test_goal_env_reward_is_compute_reward(env_id):
    env = _env(env_id)
    obs, _ = env.reset(seed=0)
    rng = np.random.default_rng(1)
    batch_ag, batch_dg, infos, rewards = [], [], [], []
    for _ in range(5):
        obs, reward, terminated, truncated, info = env.step(rng.uniform(-0.2, 0.2, 6).astype(np.float32))
        assert reward == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
        batch_ag.append(obs["achieved_goal"])
        batch_dg.append(obs["desired_goal"])
        infos.append(info)
        rewards.append(reward)
    batched = env.compute_reward(np.array(batch_ag), np.array(batch_dg), np.array(infos))
    np.testing.assert_array_equal(batched, rewards)
    relabelled = env.compute_reward(np.array(batch_ag), np.array(batch_ag), infos)
    own = [math.fsum([i["reward_failure"], i["reward_tissue_force"], i["reward_action"]]) for i in infos]
    np.testing.assert_array_equal(relabelled, own)  # an achieved goal is always reached


def test_a_miss_ends_flat_episodes_only():
    """Relabelled goals of the goal-conditioned variant may still be reachable after a miss, so only the flat
    ids end on it (``termination.end_on_miss``)."""
    flat = gym.make("SutureGym/NeedleInsert-v3").unwrapped
    goal = gym.make("SutureGym/NeedleInsertGoal-v3").unwrapped
    off = gym.make("SutureGym/NeedleInsert-v3", config={"termination": {"end_on_miss": False}}).unwrapped
    for env in (flat, goal, off):
        env.reset(seed=0)
    assert flat.task.end_on_miss and not goal.task.end_on_miss and not off.task.end_on_miss


def test_render_rgb_array_and_record_video(tmp_path):
    pytest.importorskip("moviepy")
    from gymnasium.wrappers import RecordVideo

    env = gym.make("SutureGym/NeedleInsert-v3", render_mode="rgb_array")
    env = RecordVideo(env, str(tmp_path / "videos"), episode_trigger=lambda k: True, disable_logger=True)
    env.reset(seed=0)
    frame = env.unwrapped.render()
    r = env.unwrapped.config.render
    assert frame.shape == (r.height, r.width, 3) and frame.dtype == np.uint8 and frame.std() > 5
    for _ in range(5):
        env.step(env.action_space.sample())
    env.close()
    videos = list((tmp_path / "videos").glob("*.mp4"))
    assert videos and videos[0].stat().st_size > 0


def test_yaml_config_reaches_the_env():
    env = gym.make("SutureGym/NeedleInsert-v3", config=CONFIGS / "needle_insert_deterministic.yaml").unwrapped
    assert not env.config.randomization.enabled and env.config.randomization.youngs_modulus_scale != (1.0, 1.0)
    with pytest.raises(ValueError, match="'reward.bonus'"):
        gym.make("SutureGym/NeedleInsert-v3", config={"reward": {"bonus": 1.0}})


def test_record_video_script_films_the_expert(tmp_path):
    pytest.importorskip("imageio_ffmpeg")
    import json
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[1] / "scripts" / "record_video.py"
    done = subprocess.run([sys.executable, str(script), "--env", "SutureGym/NeedleInsert-v3", "--out", str(tmp_path),
                           "--seconds", "0.1", "--every", "5", "--speed", "0.5", "--size", "160x120"],
                          capture_output=True, text=True, check=True, timeout=600)
    line = json.loads(done.stdout.strip().splitlines()[-1])
    video = tmp_path / "needle_insert.mp4"
    assert line["path"] == str(video) and video.stat().st_size == line["bytes"] > 0
    assert line["fps"] == pytest.approx(20.0)  # half real time: 0.5 / (5 steps x 5 ms)
    assert line["steps"] == 20 and line["frames"] == 4 + 20  # a frame every 5 of 20 steps, then 1 s of the last
    import imageio.v3 as iio

    assert iio.imread(video, index=0).shape == (120, 160, 3)
    bad = subprocess.run([sys.executable, str(script), "--size", "big"], capture_output=True, text=True, timeout=600)
    assert bad.returncode == 2 and "'big'" in bad.stderr
    assert line["success"] is False  # 0.1 s is far too short to stitch


def test_a_start_phase_episode_does_not_depend_on_the_episodes_before_it():
    """A reset into a start phase (the cached nominal start carried over to the episode's randomised tissue and
    settled) replays bit for bit in a fresh env and in one that has run a random episode and another phase reset
    first."""
    inserted = {"phase": "inserted"}
    fresh = gym.make("SutureGym/NeedleInsert-v3").unwrapped
    used = gym.make("SutureGym/NeedleInsert-v3").unwrapped
    used.action_space.seed(1)
    used.reset(seed=1)
    for _ in range(120):
        _, _, terminated, truncated, _ = used.step(used.action_space.sample())
        if terminated or truncated:
            break
    _expert_record(used, 2, 40, inserted)
    assert _expert_record(fresh, 7, 120, inserted) == _expert_record(used, 7, 120, inserted)


def test_set_state_refuses_another_tasks_state_and_leaves_the_env_unchanged():
    needle = SutureEnv("needle_insert")
    needle.reset(seed=0)
    throw = SutureEnv("suture_throw")
    throw.reset(seed=0)
    before = needle.get_state()
    with pytest.raises(ValueError, match=r"another id or config|of task 'suture_throw'; this simulation is of task "
                                         r"'needle_insert'"):
        needle.set_state(throw.get_state())
    with pytest.raises(ValueError, match=r"the snapshot is of task 'suture_throw'; this simulation is of task "
                                         r"'needle_insert'"):
        needle.sim.restore(throw.sim.snapshot())
    obs, *_ = needle.step(np.zeros(6))  # unchanged: steps on from its own state
    needle.set_state(before)
    assert needle.step(np.zeros(6))[0].tobytes() == obs.tobytes()


def test_reset_step_and_snapshots_after_close_raise():
    env = SutureEnv("needle_insert")
    env.reset(seed=0)
    state = env.get_state()
    env.close()
    env.close()  # closing twice is fine
    for call in (lambda: env.step(np.zeros(6)), lambda: env.reset(seed=1), env.get_state,
                 lambda: env.set_state(state)):
        with pytest.raises(RuntimeError, match="this needle_insert env was closed"):
            call()


def test_incompressible_tissue_with_the_xpbd_integrator_is_refused_at_construction():
    with pytest.raises(ValueError, match=r"tissue\.poisson_ratio = 0\.5 \(incompressible\) with "
                                         r"solver\.tissue_integrator = 'xpbd'"):
        SutureEnv("needle_insert", config={"tissue": {"poisson_ratio": 0.5}, "solver": {"tissue_integrator": "xpbd"}})
    SutureEnv("needle_insert", config={"tissue": {"poisson_ratio": 0.49}, "solver": {"tissue_integrator": "xpbd"}})
