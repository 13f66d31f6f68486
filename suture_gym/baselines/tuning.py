"""Hyperparameter search with Optuna, in the rl-baselines3-zoo style (``scripts/tune.py`` is the command line).

Each trial samples hyperparameters (:data:`SAMPLERS`), merges them into the agent config of the env id
(``configs/agents/<algo>.yml``, the format of :mod:`suture_gym.baselines.hyperparams`), trains for a short budget and
evaluates the deterministic policy ``n_evaluations`` times on the way; each evaluation's mean return is reported to
Optuna,
whose median pruner stops trials that fall behind, and the last one is the trial's value (maximised). The
trial's success rate at that evaluation and the full hyperparameters it trained with (a mapping to paste into
the agent config) are stored as the trial's user attributes ``success_rate`` and ``hyperparams``.

Studies live in a relational database through SQLAlchemy (:func:`open_study`): SQLite by default
(``sqlite:///runs/tune.db``), or any SQLAlchemy URL (``postgresql://user@host/db``), so that several machines
running ``scripts/tune.py`` with the same ``--storage`` and ``--study-name`` share one study. A study is resumed
when it exists (``load_if_exists``); a trial whose process died stops sending heartbeats and is marked failed,
and retried once, by the next run (``heartbeat_interval`` / ``grace_period``, seconds).
"""

from __future__ import annotations

import math
import tempfile
import warnings
from collections.abc import Callable, Collection
from pathlib import Path
from typing import Any

import numpy as np

#: Actor and critic hidden layers of the sampled ``net_arch`` choices.
NET_ARCHS = {"small": [64, 64], "medium": [128, 128], "large": [256, 256]}
#: Seconds between a running trial's heartbeats, and since the last one after which another run marks the trial
#: failed (its process died) and retries it.
HEARTBEAT_INTERVAL_S = 60
GRACE_PERIOD_S = 180


def sample_ppo_params(trial, fixed: Collection[str] = ()) -> dict[str, Any]:
    """PPO hyperparameters for ``trial`` in the agent-config format (rl-zoo's search space, narrowed to what
    trains in a short budget); keys in ``fixed`` are not sampled.

    Optuna parameters: ``n_steps``, ``batch_size``, ``gamma``, ``learning_rate`` (log-uniform) with
    ``lr_schedule`` (``constant`` or ``linear``, written ``lin_<value>``), ``ent_coef`` (log-uniform),
    ``clip_range``, ``n_epochs``, ``gae_lambda``, ``max_grad_norm``, ``vf_coef`` and, as ``policy_kwargs``,
    ``net_arch`` (:data:`NET_ARCHS`, the same for actor and critic), ``activation_fn`` and ``log_std_init``.
    """
    out: dict[str, Any] = {}
    choices = {
        "n_steps": [64, 128, 256, 512, 1024, 2048],
        "batch_size": [32, 64, 128, 256, 512],
        "gamma": [0.95, 0.98, 0.99, 0.995, 0.999],
        "clip_range": [0.1, 0.2, 0.3],
        "n_epochs": [5, 10, 20],
        "gae_lambda": [0.9, 0.95, 0.98, 1.0],
        "max_grad_norm": [0.3, 0.5, 1.0, 2.0],
    }
    for key, values in choices.items():
        if key not in fixed:
            out[key] = trial.suggest_categorical(key, values)
    if "learning_rate" not in fixed:
        rate = trial.suggest_float("learning_rate", 1e-5, 1e-3, log=True)
        linear = trial.suggest_categorical("lr_schedule", ["constant", "linear"]) == "linear"
        out["learning_rate"] = f"lin_{rate}" if linear else rate
    if "ent_coef" not in fixed:
        out["ent_coef"] = trial.suggest_float("ent_coef", 1e-8, 1e-2, log=True)
    if "vf_coef" not in fixed:
        out["vf_coef"] = trial.suggest_float("vf_coef", 0.2, 1.0)
    if "policy_kwargs" not in fixed:
        arch = NET_ARCHS[trial.suggest_categorical("net_arch", list(NET_ARCHS))]
        out["policy_kwargs"] = {"net_arch": {"pi": list(arch), "vf": list(arch)},
                                "activation_fn": trial.suggest_categorical("activation_fn", ["tanh", "relu"]),
                                "log_std_init": trial.suggest_float("log_std_init", -3.0, 0.0)}
    return out


#: Algorithm name -> ``sampler(trial, fixed) -> hyperparameters``.
SAMPLERS: dict[str, Callable[..., dict[str, Any]]] = {"ppo": sample_ppo_params}


def trial_hyperparams(algo: str, base: dict[str, Any], trial, overrides: dict[str, Any]) -> dict[str, Any]:
    """``base`` (an agent config entry) with the trial's samples and then ``overrides`` merged in; an override
    of None removes the key. ``batch_size`` is capped at one rollout (``n_steps * n_envs``)."""
    if algo not in SAMPLERS:
        raise ValueError(f"no search space for algo {algo!r}; known: {sorted(SAMPLERS)}")
    params = {**base, **SAMPLERS[algo](trial, fixed=set(overrides)), **overrides}
    params = {key: value for key, value in params.items() if value is not None}
    if "batch_size" in params and "n_steps" in params:
        params["batch_size"] = min(int(params["batch_size"]), int(params["n_steps"]) * int(params.get("n_envs", 1)))
    return params


def open_study(study_name: str, storage: str, seed: int = 0, n_startup_trials: int = 5, n_warmup_steps: int = 1):
    """Create or load (``load_if_exists``) the study ``study_name`` in the SQLAlchemy database ``storage``
    (a SQLite file's folder is created), maximising, with a TPE sampler seeded ``seed`` plus the number of trials
    already in the study, and a median pruner that starts after ``n_startup_trials`` trials and
    ``n_warmup_steps`` evaluations. ValueError naming ``storage`` when it is not an SQLAlchemy URL."""
    import optuna
    from optuna.storages import RDBStorage, RetryHeartbeatStaleTrialCallback
    from sqlalchemy.engine import make_url
    from sqlalchemy.exc import ArgumentError

    try:
        url = make_url(storage)
    except ArgumentError as exc:
        raise ValueError(f"storage must be an SQLAlchemy URL such as sqlite:///runs/tune.db, got {storage!r}") from exc
    if url.get_backend_name() == "sqlite" and url.database not in (None, "", ":memory:"):
        Path(url.database).parent.mkdir(parents=True, exist_ok=True)
    with warnings.catch_warnings():  # heartbeats and their retry callback are flagged experimental
        warnings.simplefilter("ignore", optuna.exceptions.ExperimentalWarning)
        rdb = RDBStorage(storage, heartbeat_interval=HEARTBEAT_INTERVAL_S, grace_period=GRACE_PERIOD_S,
                         heartbeat_stale_trial_callback=RetryHeartbeatStaleTrialCallback(max_retry=1))
    study = optuna.create_study(
        storage=rdb, study_name=study_name, direction="maximize", load_if_exists=True,
        pruner=optuna.pruners.MedianPruner(n_startup_trials=n_startup_trials, n_warmup_steps=n_warmup_steps))
    # Seeded by the trials already there, so a resumed study continues sampling instead of repeating its first
    # trials (the sampler's state is not stored in the database).
    study.sampler = optuna.samplers.TPESampler(n_startup_trials=n_startup_trials, seed=seed + len(study.trials))
    return study


def objective(trial, algo: str, env_id: str, base: dict[str, Any], overrides: dict[str, Any], n_timesteps: int,
              n_evaluations: int, eval_episodes: int, seed: int) -> float:
    """Train ``algo`` on ``env_id`` for ``n_timesteps`` env steps with the trial's hyperparameters
    (:func:`trial_hyperparams`), evaluating ``eval_episodes`` episodes ``n_evaluations`` times on the way;
    returns the last evaluation's mean return, or raises ``optuna.TrialPruned``. A behaviour-cloning warm start
    in the config runs as in training (better from a Minari dataset, ``behaviour_cloning.dataset``, than by
    recording expert episodes for every trial)."""
    import optuna
    from stable_baselines3.common.callbacks import EvalCallback

    from suture_gym.baselines.hyperparams import resolve
    from suture_gym.baselines.training import _warm_start, algo_class, make_train_envs

    params = trial_hyperparams(algo, base, trial, overrides)
    trial.set_user_attr("hyperparams", params)
    script, kwargs = resolve(params)
    n_envs = int(script.get("n_envs", 1))
    env_kwargs = script.get("env_kwargs", {})
    env, eval_env = make_train_envs(env_id, n_envs, seed, env_kwargs, script.get("normalize", False))
    model = algo_class(algo)(script["policy"], env, seed=seed, device="cpu", verbose=0, **kwargs)
    if "behaviour_cloning" in script:
        with tempfile.TemporaryDirectory() as run_dir:
            _warm_start(model, env_id, env_kwargs, script["behaviour_cloning"], Path(run_dir), seed, False)

    class TrialEval(EvalCallback):
        """Reports each evaluation's mean return to the trial and stops training when Optuna prunes it."""

        pruned = False
        evaluations = 0

        def _on_step(self) -> bool:
            keep_going = super()._on_step()
            if self.eval_freq > 0 and self.n_calls % self.eval_freq == 0:
                trial.report(float(self.last_mean_reward), self.evaluations)
                self.evaluations += 1
                success = float(np.mean(self._is_success_buffer)) if self._is_success_buffer else math.nan
                trial.set_user_attr("success_rate", None if math.isnan(success) else success)
                if trial.should_prune():
                    self.pruned = True
                    return False
            return keep_going

    eval_freq = max(n_timesteps // (n_evaluations * n_envs), 1)
    callback = TrialEval(eval_env, n_eval_episodes=eval_episodes, eval_freq=eval_freq, deterministic=True,
                         verbose=0)
    try:
        model.learn(total_timesteps=n_timesteps, callback=callback)
    finally:
        env.close()
        eval_env.close()
    if callback.pruned:
        raise optuna.TrialPruned()
    if callback.evaluations == 0:
        raise ValueError(f"n_timesteps {n_timesteps} left no evaluation (n_evaluations {n_evaluations})")
    value = float(callback.last_mean_reward)
    if not math.isfinite(value):
        raise ValueError(f"trial {trial.number}: evaluation mean return is {value}")
    return value


def study_summary(study, trials_run: int) -> dict[str, Any]:
    """``{study_name, trials, trials_this_run, complete, pruned, failed, best}`` of ``study``; ``best`` is
    ``{number, value, params, success_rate, hyperparams}`` of the best complete trial, or None."""
    from optuna.trial import TrialState

    trials = study.get_trials(deepcopy=False)
    count = {state: sum(t.state == state for t in trials) for state in (TrialState.COMPLETE, TrialState.PRUNED,
                                                                         TrialState.FAIL)}
    best = None
    if count[TrialState.COMPLETE]:
        trial = study.best_trial
        best = {"number": trial.number, "value": trial.value, "params": trial.params,
                "success_rate": trial.user_attrs.get("success_rate"),
                "hyperparams": trial.user_attrs.get("hyperparams")}
    return {"study_name": study.study_name, "trials": len(trials), "trials_this_run": trials_run,
            "complete": count[TrialState.COMPLETE], "pruned": count[TrialState.PRUNED],
            "failed": count[TrialState.FAIL], "best": best}
