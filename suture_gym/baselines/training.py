"""Train a Stable-Baselines3 agent on a Gymnasium env id, with evaluation, checkpoints and a learning curve.

A run directory holds everything needed to reproduce and inspect the run::

    <run>/config.yaml          algo, env id, seed, the agent hyperparameters as written in the YAML, versions
    <run>/demos.npz            expert demonstrations of the behaviour-cloning warm start (when configured and not
                               read from a Minari dataset, ``behaviour_cloning.dataset``)
    <run>/tb/                  TensorBoard logs
    <run>/checkpoints/         periodic checkpoints (model, VecNormalize statistics, replay buffer for off-policy)
    <run>/eval/evaluations.npz periodic evaluation results (timesteps, returns, lengths, successes)
    <run>/best_model.zip       best model by mean evaluation return
    <run>/final_model.zip      model at the end of training (+ final_vecnormalize.pkl when normalising)
    <run>/learning_curve.png   mean return and success rate against env steps
"""

from __future__ import annotations

import json
import platform
import re
import sys
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from suture_gym.baselines.hyperparams import load_hyperparams, resolve

ALGOS = ("ppo", "sac", "tqc", "a2c", "td3", "dagger")


def algo_class(algo: str):
    """The SB3 (or sb3-contrib) class for ``algo``; ``dagger`` (:mod:`suture_gym.baselines.dagger`) trains a PPO
    model."""
    if algo not in ALGOS:
        raise ValueError(f"unknown algo {algo!r}; expected one of {ALGOS}")
    if algo == "dagger":
        algo = "ppo"
    if algo == "tqc":
        from sb3_contrib import TQC

        return TQC
    import stable_baselines3 as sb3

    return getattr(sb3, algo.upper())


@dataclass
class TrainResult:
    """Where a run put its outputs and what its last evaluation measured."""

    run_dir: Path
    model_path: Path
    timesteps: int
    wall_s: float
    last_eval_mean_return: float | None
    last_eval_success_rate: float | None


def run_name(algo: str, env_id: str, seed: int) -> str:
    """``<algo>_<EnvName>_s<seed>`` with the namespace and version stripped, e.g. ``ppo_NeedleInsert_s0``."""
    name = env_id.split("/")[-1]
    name = re.sub(r"-v\d+$", "", name)
    return f"{algo}_{name}_s{seed}"


def make_vec_env(env_id: str, n_envs: int, seed: int, env_kwargs: dict | None = None):
    """An SB3 ``VecEnv`` of ``n_envs`` copies of ``env_id`` (each wrapped in ``Monitor``), seeded ``seed + i``."""
    from stable_baselines3.common.env_util import make_vec_env as sb3_make_vec_env
    from stable_baselines3.common.vec_env import DummyVecEnv

    import suture_gym  # noqa: F401  (registers the SutureGym ids)

    return sb3_make_vec_env(env_id, n_envs=n_envs, seed=seed, env_kwargs=env_kwargs or {}, vec_env_cls=DummyVecEnv)


def make_train_envs(env_id: str, n_envs: int, seed: int, env_kwargs: dict, normalize) -> tuple:
    """``(training VecEnv, evaluation VecEnv)`` of ``env_id``: ``n_envs`` envs seeded from ``seed`` and one seeded
    ``seed + 1000``, both in ``VecNormalize`` when ``normalize`` (True or its keyword arguments; the evaluation
    copy neither updates the statistics nor normalises rewards). With a ``Dict`` observation (the pixel and
    point-cloud modes, goal-conditioned ids) the normalised keys default to
    :func:`~suture_gym.envs.sb3.norm_obs_keys`: every key but the ``uint8`` images."""
    from stable_baselines3.common.vec_env import VecNormalize

    from suture_gym.envs.sb3 import norm_obs_keys

    env = make_vec_env(env_id, n_envs, seed, env_kwargs)
    eval_env = make_vec_env(env_id, 1, seed + 1000, env_kwargs)
    if normalize:
        norm_kwargs = normalize if isinstance(normalize, dict) else {}
        if norm_obs_keys(env.observation_space) is not None:
            norm_kwargs = {"norm_obs_keys": norm_obs_keys(env.observation_space), **norm_kwargs}
        env = VecNormalize(env, **norm_kwargs)
        eval_env = VecNormalize(eval_env, **{**norm_kwargs, "training": False, "norm_reward": False})
    return env, eval_env


def train(
    algo: str,
    env_id: str,
    seed: int = 0,
    out_dir: str | Path = "runs",
    n_timesteps: int | None = None,
    eval_freq: int = 10_000,
    eval_episodes: int = 20,
    checkpoint_freq: int = 50_000,
    resume: str | Path | None = None,
    progress_bar: bool = True,
    verbose: int = 0,
    hyperparams: dict[str, Any] | None = None,
    workers: int = 1,
) -> TrainResult:
    """Train ``algo`` on ``env_id`` and write the run directory described in the module docstring.

    Args:
        algo: ``ppo``, ``sac``, ``tqc``, ``a2c``, ``td3`` or ``dagger`` (:mod:`suture_gym.baselines.dagger`:
            imitation of the scripted surgeon on the learner's own states; ``eval_freq``, ``eval_episodes`` and
            ``checkpoint_freq`` do not apply, its learner-alone iterations are its evaluations and every
            iteration is checkpointed); hyperparameters come from ``configs/agents/<algo>.yml`` (or
            ``hyperparams``, a mapping in the same format).
        env_id: registered Gymnasium id.
        seed: seeds the algorithm, the training envs (``seed + i``) and the evaluation env (``seed + 1000``).
        out_dir: parent of the run directory ``<out_dir>/<algo>_<EnvName>_s<seed>``.
        n_timesteps: total env steps; overrides the config's ``n_timesteps``.
        eval_freq: evaluate every this many env steps (summed over the parallel envs); 0 disables.
        eval_episodes: episodes per evaluation.
        checkpoint_freq: checkpoint every this many env steps; 0 disables.
        resume: a checkpoint ``.zip`` to continue from (its VecNormalize statistics and replay buffer are
            loaded when saved beside it); training continues up to the same total ``n_timesteps``.
        progress_bar: show SB3's progress bar.
        verbose: SB3 verbosity.
        hyperparams: use this mapping instead of reading the YAML.
        workers: DAgger only: processes its rollouts run on (the same run for any number; one per free core).
            The other algorithms step ``n_envs`` envs, a hyperparameter of their config.
    """
    from stable_baselines3.common.callbacks import CallbackList, CheckpointCallback, EvalCallback
    from stable_baselines3.common.vec_env import VecNormalize

    raw = hyperparams if hyperparams is not None else load_hyperparams(algo, env_id)
    script, kwargs = resolve(raw)
    total = int(n_timesteps if n_timesteps is not None else script["n_timesteps"])
    if total <= 0:
        raise ValueError(f"n_timesteps must be positive, got {total}")
    if workers != 1 and algo != "dagger":
        raise ValueError(f"workers applies to DAgger; {algo} steps n_envs envs (its config), got workers={workers!r}")
    n_envs = int(script.get("n_envs", 1))
    env_kwargs = script.get("env_kwargs", {})

    run_dir = Path(out_dir) / run_name(algo, env_id, seed)
    (run_dir / "checkpoints").mkdir(parents=True, exist_ok=True)
    _write_config(run_dir, algo, env_id, seed, total, raw, resume)

    if algo == "dagger":
        if resume is not None:
            raise ValueError("a DAgger run cannot be resumed; fine-tune its model with PPO instead")
        from suture_gym.baselines.dagger import train_dagger

        summary = train_dagger(env_id, seed, run_dir, total, script, kwargs, progress_bar, verbose, workers)
        (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
        return TrainResult(run_dir, run_dir / "final_model.zip", summary["timesteps"], summary["wall_s"],
                           summary["last_eval_mean_return"], summary["last_eval_success_rate"])
    if "dagger" in script:
        raise ValueError(f"the 'dagger' settings belong to configs/agents/dagger.yml, not to {algo}'s config")

    normalize = script.get("normalize", False)
    env, eval_env = make_train_envs(env_id, n_envs, seed, env_kwargs, normalize)

    cls = algo_class(algo)
    if resume is not None:
        resume = Path(resume)
        if not resume.exists():
            raise FileNotFoundError(f"checkpoint {str(resume)!r} does not exist")
        stats = _sibling(resume, "vecnormalize", ".pkl")
        if normalize and stats is not None:
            env = VecNormalize.load(str(stats), env.venv)
        model = cls.load(resume, env=env, device="cpu", tensorboard_log=str(run_dir / "tb"))
        buffer = _sibling(resume, "replay_buffer", ".pkl")
        if buffer is not None and hasattr(model, "load_replay_buffer"):
            model.load_replay_buffer(buffer)
    else:
        model = cls(
            script["policy"], env, seed=seed, device="cpu", verbose=verbose,
            tensorboard_log=str(run_dir / "tb"), **kwargs,
        )
    cloning = None
    if "behaviour_cloning" in script and resume is None:
        cloning = _warm_start(model, env_id, env_kwargs, script["behaviour_cloning"], run_dir, seed, progress_bar)

    callbacks = []
    if checkpoint_freq > 0:
        callbacks.append(
            CheckpointCallback(
                save_freq=max(checkpoint_freq // n_envs, 1),
                save_path=str(run_dir / "checkpoints"),
                name_prefix="model",
                save_replay_buffer=hasattr(model, "replay_buffer"),
                save_vecnormalize=bool(normalize),
            )
        )
    eval_callback = None
    if eval_freq > 0:
        eval_callback = EvalCallback(
            eval_env,
            n_eval_episodes=eval_episodes,
            eval_freq=max(eval_freq // n_envs, 1),
            log_path=str(run_dir / "eval"),
            best_model_save_path=str(run_dir),
            deterministic=True,
            verbose=verbose,
        )
        previous = run_dir / "eval" / "evaluations.npz"
        if resume is not None and previous.exists():  # keep the curve of the run we continue
            data = np.load(previous)
            keep = data["timesteps"] <= model.num_timesteps
            eval_callback.evaluations_timesteps = data["timesteps"][keep].tolist()
            eval_callback.evaluations_results = data["results"][keep].tolist()
            eval_callback.evaluations_length = data["ep_lengths"][keep].tolist()
            if "successes" in data and len(data["successes"]):
                eval_callback.evaluations_successes = data["successes"][keep].tolist()
        callbacks.append(eval_callback)

    remaining = total - model.num_timesteps
    t0 = time.perf_counter()
    if remaining > 0:
        model.learn(
            total_timesteps=remaining,
            callback=CallbackList(callbacks),
            progress_bar=progress_bar,
            reset_num_timesteps=resume is None,
            tb_log_name=run_name(algo, env_id, seed),
        )
    wall = time.perf_counter() - t0
    model_path = run_dir / "final_model.zip"
    model.save(model_path)
    if normalize:
        env.save(str(run_dir / "final_vecnormalize.pkl"))
    env.close()
    eval_env.close()

    mean_return = success = None
    evaluations = run_dir / "eval" / "evaluations.npz"
    if evaluations.exists():
        from suture_gym.baselines.plotting import plot_learning_curve

        plot_learning_curve(evaluations, run_dir / "learning_curve.png", title=f"{algo.upper()} on {env_id}")
        data = np.load(evaluations)
        mean_return = float(data["results"][-1].mean())
        if "successes" in data and len(data["successes"]):
            success = float(np.mean(data["successes"][-1]))
    summary = {"timesteps": int(model.num_timesteps), "wall_s": round(wall, 1),
               "last_eval_mean_return": mean_return, "last_eval_success_rate": success,
               "behaviour_cloning": cloning}
    (run_dir / "summary.json").write_text(json.dumps(summary, indent=2))
    return TrainResult(run_dir, model_path, int(model.num_timesteps), wall, mean_return, success)


def _warm_start(model, env_id: str, env_kwargs: dict, settings: dict, run_dir: Path, seed: int,
                progress: bool) -> dict:
    """Clone demonstrations into ``model`` (:mod:`suture_gym.baselines.imitation`): the Minari dataset
    ``settings["dataset"]``, or else the expert's, recorded into ``<run>/demos.npz``. Returns the cloning summary with
    the time taken (s),
    the source and the demonstrations' success rate (None when the dataset records none)."""
    from suture_gym.baselines.imitation import behaviour_clone, load_demos, load_minari_demos

    t0 = time.perf_counter()
    if settings["dataset"] is not None:
        from suture_gym.baselines.datasets import load_dataset

        dataset = load_dataset(settings["dataset"])
        recorded_on = dataset.env_spec.id if dataset.env_spec is not None else None
        if recorded_on != env_id:
            raise ValueError(f"behaviour_cloning.dataset {settings['dataset']!r} was recorded on {recorded_on!r}, "
                             f"not on {env_id!r}")
        demos = load_minari_demos(dataset)
        source = {"dataset": settings["dataset"]}
    else:
        from suture_gym.baselines.expert import record

        recorded = record(env_id, settings["expert_episodes"], run_dir / "demos.npz", seed=seed + 2000,
                          env_kwargs=env_kwargs, progress=progress, expert=settings["expert"],
                          action_noise=settings["action_noise"])
        demos = load_demos(recorded["out"])
        source = {"dataset": None}
    fit = behaviour_clone(model, demos, epochs=settings["epochs"], batch_size=settings["batch_size"],
                          learning_rate=settings["learning_rate"], seed=seed)
    success = float(np.mean(demos["episode_success"])) if "episode_success" in demos else None
    return {**fit, **source, "expert_success_rate": success, "wall_s": round(time.perf_counter() - t0, 1)}


def _sibling(checkpoint: Path, kind: str, suffix: str) -> Path | None:
    """The file SB3's CheckpointCallback saves beside ``model_<N>_steps.zip`` (``model_<kind>_<N>_steps``)."""
    match = re.search(r"_(\d+)_steps$", checkpoint.stem)
    if match is None:
        return None
    prefix = checkpoint.stem[: match.start()]
    path = checkpoint.with_name(f"{prefix}_{kind}_{match.group(1)}_steps{suffix}")
    return path if path.exists() else None


def _write_config(run_dir: Path, algo: str, env_id: str, seed: int, total: int, raw: dict, resume) -> None:
    import stable_baselines3
    import torch

    import suture_gym

    config = {
        "algo": algo,
        "env_id": env_id,
        "seed": seed,
        "n_timesteps": total,
        "hyperparams": raw,
        "resumed_from": str(resume) if resume is not None else None,
        "command": " ".join(sys.argv),
        "versions": {
            "suture_gym": suture_gym.__version__,
            "stable_baselines3": stable_baselines3.__version__,
            "torch": str(torch.__version__),
            "python": platform.python_version(),
        },
    }
    with open(run_dir / "config.yaml", "w") as fh:
        yaml.safe_dump(config, fh, sort_keys=False)
