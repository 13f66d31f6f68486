"""DAgger (Ross, Gordon and Bagnell, AISTATS 2011) with the scripted surgeon as the oracle.

Behaviour cloning trains on the states the expert visits; the cloned policy drifts off them and meets states
it never saw, where its errors compound (a needle a millimetre off the planned circle after a few hundred
steps of a 1,300-step stitch). DAgger rolls the learner out, asks the oracle what it would have done in every
state the learner visited, adds those labels to the data and refits: the policy is trained on its own state
distribution. The oracle must label any state, so it is :class:`suture_gym.baselines.expert.FeedbackExpert` (the
expert's turn closed on the measured tip), not the clock-driven :class:`~suture_gym.baselines.expert.ExpertPolicy`.

Iteration ``i`` (0-based) runs ``episodes_per_iteration`` episodes in which each step's executed action is the
oracle's with probability ``beta * beta_decay ** i`` and the learner's (deterministic mean) otherwise; every
visited observation is stored with the oracle's label. After each iteration the policy's mean is refitted on all
the data so far (:func:`suture_gym.baselines.imitation.behaviour_clone`, which also fits the value head to the rollouts'
returns, so PPO can fine-tune the result); with ``normalize``, the observation statistics are those of all the
data so far, updated before each refit (statistics of the expert's states alone make the learner's own states
extreme: the needle's off-plane coordinates vary by 16 um in the expert's SutureThrow episodes). An episode
whose needle has stopped moving ends early (:data:`STALL_DISTANCE`) and counts as a failure. With the default
``beta_decay: 0`` iteration 0 is the expert's
demonstrations and every later iteration is the learner alone: its episodes are then an evaluation of the
policy fitted one iteration before, on env seeds no other iteration uses, and they are the run's learning curve.

The rollouts may run on several processes (``workers``), each with its own env and oracle, given the learner's
weights and statistics at every iteration; the refit stays in the calling process, and the run is the same for any
number of workers (:func:`train_dagger`).

The learner is an SB3 :class:`~stable_baselines3.PPO` model (``MlpPolicy``), saved like every other run of
:func:`suture_gym.baselines.training.train` (``final_model.zip``, ``final_vecnormalize.pkl``, ``checkpoints/``,
``eval/evaluations.npz``, ``learning_curve.png``, ``summary.json``), so ``scripts/evaluate.py`` and PPO's
``--resume`` read it. ``best_model.zip`` is the checkpoint whose learner-alone iteration succeeded most often
(the later one on ties), with its own statistics in ``best_vecnormalize.pkl``.

Why by hand: the ``imitation`` library's DAgger pins its own SB3 and Gymnasium versions (see
:mod:`suture_gym.baselines.imitation`), and the loop is short.
"""

from __future__ import annotations

import json
import math
import pickle
import shutil
import sys
import time
from pathlib import Path
from typing import Any

import numpy as np

#: Keys of a config's ``dagger`` mapping and their defaults: iterations (>= 1), episodes per iteration (>= 1),
#: the oracle's share of the executed actions in iteration 0 (``beta``, in [0, 1]) and its decay per iteration
#: (``beta_decay``, in [0, 1]), the refit's passes over all data (``epochs``), minibatch size and Adam step, the
#: oracle's ``lead`` (rad) and ``gain`` (:class:`suture_gym.baselines.expert.FeedbackExpert`), and the steps after which
#: a still needle ends a rollout (``stall_steps``, see :data:`STALL_DISTANCE`).
DAGGER_KEYS: dict[str, Any] = {"iterations": 8, "episodes_per_iteration": 10, "beta": 1.0, "beta_decay": 0.0,
                               "epochs": 10, "batch_size": 256, "learning_rate": 1e-3, "lead": 0.02,
                               "gain": 1.0, "stall_steps": 100}
#: A rollout whose needle tip moved less than this (m) over the last ``stall_steps`` steps ends there (the
#: scripted surgeon never holds still, so a still needle is a learner stuck, e.g. pushing too weakly against the
#: tissue's friction; its labels past that point would repeat the same state).
STALL_DISTANCE = 2.0e-4
#: Env seeds of a run with seed ``s``: episode ``k`` (counted over all iterations) uses ``SEED_BASE + 10_000 s +
#: k``, clear of the evaluation seeds (``scripts/evaluate.py`` starts at 0, ``make run`` at 10,000).
SEED_BASE = 100_000


def dagger_settings(value: Any) -> dict[str, Any]:
    """``value`` (a config's ``dagger`` mapping) completed with :data:`DAGGER_KEYS`' defaults and checked.

    Raises:
        ValueError: not a mapping, an unknown key, or a value out of range (the message names it).
    """
    if not isinstance(value, dict):
        raise ValueError(f"dagger must be a mapping of {sorted(DAGGER_KEYS)}, got {value!r}")
    unknown = sorted(set(value) - set(DAGGER_KEYS))
    if unknown:
        raise ValueError(f"dagger has unknown keys {unknown}; known: {sorted(DAGGER_KEYS)}")
    out = {**DAGGER_KEYS, **value}
    for key in ("iterations", "episodes_per_iteration", "epochs", "batch_size", "stall_steps"):
        if isinstance(out[key], bool) or not isinstance(out[key], int) or out[key] < 1:
            raise ValueError(f"dagger.{key} must be an integer >= 1, got {out[key]!r}")
    for key in ("beta", "beta_decay"):
        if isinstance(out[key], bool) or not isinstance(out[key], (int, float)) or not 0.0 <= out[key] <= 1.0:
            raise ValueError(f"dagger.{key} must lie in [0, 1], got {out[key]!r}")
    if isinstance(out["gain"], bool) or not isinstance(out["gain"], (int, float)) or not 0.0 < out["gain"] <= 1.0:
        raise ValueError(f"dagger.gain must lie in (0, 1], got {out['gain']!r}")
    for key in ("learning_rate", "lead"):
        if isinstance(out[key], bool) or not isinstance(out[key], (int, float)) or not (
                math.isfinite(out[key]) and out[key] > 0.0):
            raise ValueError(f"dagger.{key} must be > 0, got {out[key]!r}")
    return out


def train_dagger(env_id: str, seed: int, run_dir: Path, total: int, script: dict[str, Any], kwargs: dict[str, Any],
                 progress_bar: bool = True, verbose: int = 0, workers: int = 1) -> dict[str, Any]:
    """Run DAgger on ``env_id`` into ``run_dir`` (see the module docstring); returns the run's summary.

    Args:
        env_id: registered SutureGym id with flat observations.
        seed: seeds the policy's initialisation, the executed-action draws and the env seeds
            (:data:`SEED_BASE`).
        run_dir: the run directory (exists, ``config.yaml`` already written by
            :func:`suture_gym.baselines.training.train`).
        total: env-step budget: no iteration starts once it is spent (an iteration started runs to its end).
        script: the config's script settings (:func:`suture_gym.baselines.hyperparams.resolve`): ``policy``,
            ``normalize``, ``env_kwargs`` and the ``dagger`` mapping (:func:`dagger_settings`).
        kwargs: the PPO constructor's keyword arguments (``policy_kwargs``, and those a later PPO fine-tuning
            would use).
        progress_bar: a tqdm bar over env steps on stderr.
        verbose: 1 prints one line per iteration on stderr.
        workers: processes the rollouts run on (each with its own env and oracle, given the learner's weights
            and statistics at every iteration); the refit stays in this process. The run is the same for any
            number: episode ``k``'s env seed and executed-action draws depend on ``seed`` and ``k`` alone.

    Returns:
        ``{timesteps, wall_s, iterations: [{iteration, beta, episodes, steps, success_rate, mean_return,
        stalled_episodes, data_steps, action_mse, env_seeds, checkpoint_steps}], best_iteration,
        last_eval_mean_return, last_eval_success_rate}``;
        ``last_eval_*`` are those of the last learner-alone iteration (None without one).
    """
    import gymnasium as gym
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv, VecNormalize

    from suture_gym.baselines.imitation import behaviour_clone

    settings = dagger_settings(script.get("dagger", {}))
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ValueError(f"workers must be an integer >= 1, got {workers!r}")
    env_kwargs = script.get("env_kwargs", {})
    rollouts = _Rollouts(env_id, env_kwargs, settings)
    env = rollouts.env
    if not isinstance(env.observation_space, gym.spaces.Box):
        raise ValueError(f"DAgger needs flat (Box) observations, {env_id} has {env.observation_space}")
    normalize = script.get("normalize", False)
    norm_kwargs = {**(normalize if isinstance(normalize, dict) else {}), "norm_reward": False}
    vec_env = DummyVecEnv([lambda: env])
    if normalize:
        vec_env = VecNormalize(vec_env, **norm_kwargs)
        vec_env.training = False  # its statistics are updated with each iteration's data below, not by stepping
    model = PPO(script["policy"], vec_env, seed=seed, device="cpu", verbose=0, **kwargs)
    pool = None
    if workers > 1:
        from suture_gym.baselines.workers import worker_pool

        pool = worker_pool(workers, _start_worker, (env_id, env_kwargs, settings, script["policy"], kwargs))

    columns: dict[str, list] = {"observations": [], "actions": [], "rewards": []}
    starts: list[int] = []
    history: list[dict[str, Any]] = []
    curve: dict[str, list] = {"timesteps": [], "results": [], "ep_lengths": [], "successes": []}
    steps = episode = 0
    bar = None
    if progress_bar:
        from tqdm import tqdm

        bar = tqdm(total=total, desc=f"dagger {env_id}", unit="step", file=sys.stderr)
    t0 = time.perf_counter()
    try:
        for iteration in range(settings["iterations"]):
            if steps >= total:
                break
            beta = settings["beta"] * settings["beta_decay"] ** iteration if iteration else settings["beta"]
            seeds = [SEED_BASE + 10_000 * seed + episode + k for k in range(settings["episodes_per_iteration"])]
            draws = [(seed, episode + k) for k in range(len(seeds))]
            if pool is None:
                learner = lambda obs: _act(model, vec_env, obs)  # noqa: E731
                done = _one_thread(rollouts(s, beta, d, learner) for s, d in zip(seeds, draws, strict=True))
            else:  # the learner as it is now, for every worker
                weights = {k: v.cpu().numpy() for k, v in model.policy.state_dict().items()}
                normalizer = pickle.dumps(vec_env) if normalize else None
                done = (f.result() for f in [pool.submit(_worker_rollout, s, beta, d, weights, normalizer)
                                             for s, d in zip(seeds, draws, strict=True)])
            returns, lengths, successes, stalls = [], [], [], 0
            for rollout in done:
                starts.append(len(columns["actions"]))
                columns["observations"].extend(rollout["observations"])
                columns["actions"].extend(rollout["labels"])
                columns["rewards"].extend(rollout["rewards"])
                steps += rollout["length"]
                episode += 1
                stalls += int(rollout["stalled"])
                if bar is not None:
                    bar.update(rollout["length"])
                returns.append(rollout["return"])
                lengths.append(rollout["length"])
                successes.append(rollout["success"])
            demos = {"observations": np.asarray(columns["observations"]), "actions": np.asarray(columns["actions"]),
                     "rewards": np.asarray(columns["rewards"]), "episode_starts": np.asarray(starts)}
            if normalize:  # the statistics of all the data so far: the expert's states and the learner's
                vec_env.obs_rms.update(demos["observations"][starts[-len(returns)]:])
            fit = behaviour_clone(model, demos, epochs=settings["epochs"], batch_size=settings["batch_size"],
                                  learning_rate=settings["learning_rate"], seed=seed + iteration,
                                  update_statistics=False)
            model.save(run_dir / "checkpoints" / f"model_{steps}_steps.zip")
            if normalize:
                vec_env.save(str(run_dir / "checkpoints" / f"model_vecnormalize_{steps}_steps.pkl"))
            record = {"iteration": iteration, "beta": beta, "episodes": len(returns), "steps": int(sum(lengths)),
                      "success_rate": float(np.mean(successes)), "mean_return": float(np.mean(returns)),
                      "stalled_episodes": stalls, "data_steps": fit["steps"], "action_mse": fit["action_mse"],
                      "env_seeds": seeds,
                      "checkpoint_steps": steps}
            history.append(record)
            if beta == 0.0:  # the learner alone: an evaluation of the previous iteration's policy
                curve["timesteps"].append(steps - record["steps"])
                curve["results"].append(returns)
                curve["ep_lengths"].append(lengths)
                curve["successes"].append(successes)
            if verbose:
                print(json.dumps({k: v for k, v in record.items() if k != "env_seeds"}), file=sys.stderr)
    finally:
        if pool is not None:
            pool.shutdown(cancel_futures=True)
    if bar is not None:
        bar.close()
    wall = time.perf_counter() - t0

    model.save(run_dir / "final_model.zip")
    if normalize:
        vec_env.save(str(run_dir / "final_vecnormalize.pkl"))
    env.close()
    best = _best_iteration(history)
    if best is not None:
        steps_best = history[best - 1]["checkpoint_steps"]
        shutil.copyfile(run_dir / "checkpoints" / f"model_{steps_best}_steps.zip", run_dir / "best_model.zip")
        if normalize:  # the statistics change every iteration: the best model's are its checkpoint's
            shutil.copyfile(run_dir / "checkpoints" / f"model_vecnormalize_{steps_best}_steps.pkl",
                            run_dir / "best_vecnormalize.pkl")
    last_return = last_success = None
    if curve["timesteps"]:
        (run_dir / "eval").mkdir(exist_ok=True)
        np.savez(run_dir / "eval" / "evaluations.npz", **{k: np.asarray(v) for k, v in curve.items()})
        from suture_gym.baselines.plotting import plot_learning_curve

        plot_learning_curve(run_dir / "eval" / "evaluations.npz", run_dir / "learning_curve.png",
                            title=f"DAgger on {env_id}")
        last_return = float(np.mean(curve["results"][-1]))
        last_success = float(np.mean(curve["successes"][-1]))
    return {"timesteps": steps, "wall_s": round(wall, 1), "iterations": history, "best_iteration": best,
            "last_eval_mean_return": last_return, "last_eval_success_rate": last_success}


def _act(model, vec_env, obs: np.ndarray) -> np.ndarray:
    """The learner's deterministic action on the raw observation ``obs`` (normalised when ``vec_env`` is a
    ``VecNormalize``, whose ``normalize_obs`` a plain VecEnv lacks)."""
    normalize = getattr(vec_env, "normalize_obs", None)
    action, _ = model.predict(normalize(obs) if normalize is not None else obs, deterministic=True)
    return action


class _Rollouts:
    """DAgger's rollouts on one env: ``rollouts(env_seed, beta, draw_seed, learner)`` runs an episode from
    ``env.reset(seed=env_seed)`` in which each step executes the oracle's label with probability ``beta`` (draws
    from ``np.random.default_rng(draw_seed)``) and ``learner(obs)`` otherwise, until it ends or the needle stalls
    (:data:`STALL_DISTANCE`); returns ``{observations (L, O) float32, labels (L, A), rewards (L,), return, length,
    success, stalled}``, the labels the oracle's at every visited observation."""

    def __init__(self, env_id: str, env_kwargs: dict[str, Any], settings: dict[str, Any]):
        import gymnasium as gym

        import suture_gym  # noqa: F401  (registers the ids)
        from suture_gym.baselines.expert import FeedbackExpert

        self.env = gym.make(env_id, **env_kwargs)
        self.oracle = FeedbackExpert(self.env, lead=settings["lead"], gain=settings["gain"])
        self.stall_steps = settings["stall_steps"]

    def __call__(self, env_seed: int, beta: float, draw_seed, learner) -> dict[str, Any]:
        env, oracle, stall_steps = self.env, self.oracle, self.stall_steps
        rng = np.random.default_rng(draw_seed)
        obs, _ = env.reset(seed=env_seed)
        oracle.reset()
        observations, labels, rewards = [], [], []
        total_reward, done, stalled, info = 0.0, False, False, {}
        tips = [env.unwrapped.sim.tip_position()]
        while not done:
            label = oracle(obs)
            action = label if rng.random() < beta else learner(obs)
            observations.append(np.asarray(obs, dtype=np.float32))
            labels.append(label)
            obs, reward, terminated, truncated, info = env.step(action)
            rewards.append(float(reward))
            total_reward += float(reward)
            tips.append(env.unwrapped.sim.tip_position())
            stalled = len(tips) > stall_steps and np.linalg.norm(tips[-1] - tips[-1 - stall_steps]) < STALL_DISTANCE
            done = terminated or truncated or stalled
        return {"observations": observations, "labels": labels, "rewards": rewards, "return": total_reward,
                "length": len(rewards), "success": bool(info.get("is_success", False)), "stalled": bool(stalled)}


def _one_thread(rollouts):
    """Yield from ``rollouts`` with torch on one thread (restored between items): a matrix product's rounding
    depends on the thread count, and the learner acts on one thread in every process, the workers' included, so a
    run does not depend on how many processes roll out."""
    import torch

    threads = torch.get_num_threads()
    iterator = iter(rollouts)
    while True:
        torch.set_num_threads(1)
        try:
            item = next(iterator)
        except StopIteration:
            return
        finally:
            torch.set_num_threads(threads)
        yield item


#: ``(rollouts, model)`` of a rollout worker process (:func:`_start_worker`): its :class:`_Rollouts` and a learner
#: of the run's architecture whose weights each task sets.
_WORKER: tuple | None = None


def _start_worker(env_id: str, env_kwargs: dict[str, Any], settings: dict[str, Any], policy: str,
                  kwargs: dict[str, Any]) -> None:
    global _WORKER
    from stable_baselines3 import PPO
    from stable_baselines3.common.vec_env import DummyVecEnv

    rollouts = _Rollouts(env_id, env_kwargs, settings)
    model = PPO(policy, DummyVecEnv([lambda: rollouts.env]), device="cpu", verbose=0, **kwargs)
    _WORKER = (rollouts, model)


def _worker_rollout(env_seed: int, beta: float, draw_seed, weights: dict[str, np.ndarray],
                    normalizer: bytes | None) -> dict[str, Any]:
    """One rollout on a worker, its learner given by ``weights`` (the policy's state dict as arrays) and
    ``normalizer`` (the pickled ``VecNormalize`` whose statistics it acts with; None: raw observations)."""
    import torch

    rollouts, model = _WORKER
    model.policy.load_state_dict({k: torch.as_tensor(v) for k, v in weights.items()})
    vec_env = pickle.loads(normalizer) if normalizer is not None else None
    return rollouts(env_seed, beta, draw_seed, lambda obs: _act(model, vec_env, obs))


def _best_iteration(history: list[dict[str, Any]]) -> int | None:
    """Index of the learner-alone iteration (after the first) that succeeded most often, the later one on ties:
    it evaluated the checkpoint of the iteration before it. None without such an iteration."""
    alone = [i for i, record in enumerate(history) if i > 0 and record["beta"] == 0.0]
    if not alone:
        return None
    return max(alone, key=lambda i: (history[i]["success_rate"], i))
