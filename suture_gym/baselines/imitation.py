"""Behaviour cloning from the scripted expert's demonstrations, as a warm start for on-policy RL (PPO, A2C).

Why by hand: the one well-kept library for it (HumanCompatibleAI ``imitation``) pins its own Stable-Baselines3
and Gymnasium versions; warm-starting an SB3 ``ActorCriticPolicy`` takes a few dozen lines on its own tensors.

:func:`behaviour_clone` fits, on demonstrations recorded by :func:`suture_gym.baselines.expert.record` (``.npz``,
:func:`load_demos`) or read from a Minari dataset (:func:`load_minari_demos`, e.g. one written by
:func:`suture_gym.baselines.expert.record_minari`):

* the policy's mean action to the expert's action (mean squared error; the policy's ``log_std`` is left as
  configured, so the fine-tuning still explores), and
* the value head to the demonstrations' discounted returns, in the reward units the training sees (with
  ``VecNormalize`` the returns are scaled as it will scale them), so that PPO's first updates start from a
  critic that knows the expert's returns instead of tearing the cloned policy down.

With ``VecNormalize``, its observation and return statistics are first updated with the demonstrations, so the
cloned network sees observations normalised as they will be during training.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Any

import gymnasium as gym
import numpy as np


def discounted_returns(rewards: np.ndarray, episode_starts: np.ndarray, gamma: float) -> np.ndarray:
    """``(T,) float64`` discounted return-to-go of each step, episode by episode (0 after an episode's last step).

    Args:
        rewards: ``(T,)`` rewards of all steps, episodes concatenated.
        episode_starts: ``(E,)`` increasing index of each episode's first step (the first must be 0).
        gamma: discount factor in [0, 1].
    """
    rewards = np.asarray(rewards, dtype=np.float64)
    starts = np.asarray(episode_starts, dtype=np.int64)
    if starts.ndim != 1 or len(starts) == 0 or starts[0] != 0 or np.any(np.diff(starts) <= 0) or starts[-1] >= len(
            rewards):
        raise ValueError(f"episode_starts must be increasing indices from 0 below {len(rewards)}, got {starts!r}")
    if not 0.0 <= gamma <= 1.0:
        raise ValueError(f"gamma must lie in [0, 1], got {gamma}")
    out = np.empty_like(rewards)
    ends = np.append(starts[1:], len(rewards))
    for start, end in zip(starts, ends, strict=True):
        running = 0.0
        for t in range(end - 1, start - 1, -1):
            running = rewards[t] + gamma * running
            out[t] = running
    return out


def load_demos(path: str | Path) -> dict[str, np.ndarray]:
    """The arrays of a demonstration file written by :func:`suture_gym.baselines.expert.record` (flat observations
    only)."""
    with np.load(path) as data:
        demos = {key: data[key] for key in data.files}
    if "observations" not in demos:
        raise ValueError(f"{path}: behaviour cloning needs flat observations (no Dict observation spaces)")
    return demos


def load_minari_demos(dataset, root: str | Path | None = None) -> dict[str, np.ndarray]:
    """The arrays :func:`behaviour_clone` takes, from a Minari dataset of a flat-observation env (any Minari
    dataset, not only those :func:`suture_gym.baselines.expert.record_minari` writes).

    Args:
        dataset: a :class:`minari.MinariDataset`, or the id of one under
            :func:`suture_gym.baselines.datasets.datasets_root` ``(root)``.
        root: where to look for a dataset given by id.

    Returns:
        As :func:`load_demos`, over all T steps concatenated: ``observations (T, D) float32`` (the observation each
        action was taken on), ``next_observations (T, D) float32``, ``actions (T, A) float32``, ``rewards (T,)
        float64``, ``terminated (T,) bool``, ``truncated (T,) bool``, ``episode_starts (E,) int64``,
        ``episode_lengths (E,) int64``; and, when the dataset records those infos, ``expert_actions (T, A)
        float32`` (:data:`~suture_gym.baselines.datasets.EXPERT_ACTION_KEY`), ``tip_forces (T,) float64``
        (N), ``tissue_costs (T,) float64`` and ``episode_success (E,) bool`` (the last step's ``is_success``).
    """
    from suture_gym.baselines.datasets import EXPERT_ACTION_KEY

    if isinstance(dataset, str):
        from suture_gym.baselines.datasets import load_dataset

        dataset = load_dataset(dataset, root)
    columns: dict[str, list] = {k: [] for k in ("observations", "next_observations", "actions", "expert_actions",
                                                 "rewards", "terminated", "truncated", "tip_forces",
                                                 "tissue_costs")}
    starts, lengths, success = [], [], []
    for episode in dataset.iterate_episodes():
        if isinstance(episode.observations, dict):
            raise ValueError(f"Minari dataset {dataset.id!r}: behaviour cloning needs flat "
                             "observations (no Dict observation spaces)")
        starts.append(sum(lengths))
        lengths.append(len(episode))
        columns["observations"].append(episode.observations[:-1])
        columns["next_observations"].append(episode.observations[1:])
        columns["actions"].append(episode.actions)
        columns["rewards"].append(episode.rewards)
        columns["terminated"].append(episode.terminations)
        columns["truncated"].append(episode.truncations)
        infos = episode.infos or {}
        if EXPERT_ACTION_KEY in infos:
            columns["expert_actions"].append(np.asarray(infos[EXPERT_ACTION_KEY])[1:])
        for column, key in (("tip_forces", "tip_force"), ("tissue_costs", "cost")):
            if key in infos:
                columns[column].append(np.asarray(infos[key])[1:])  # infos[0] is the reset's
        if "is_success" in infos:
            success.append(bool(np.asarray(infos["is_success"])[-1]))
    if not starts:
        raise ValueError(f"Minari dataset {dataset.id!r} holds no episodes")
    dtypes = {"observations": np.float32, "next_observations": np.float32, "actions": np.float32,
              "expert_actions": np.float32,
              "rewards": np.float64, "terminated": bool, "truncated": bool, "tip_forces": np.float64,
              "tissue_costs": np.float64}
    demos = {key: np.concatenate(parts).astype(dtypes[key]) for key, parts in columns.items()
             if len(parts) == len(starts)}
    demos["episode_starts"] = np.asarray(starts, dtype=np.int64)
    demos["episode_lengths"] = np.asarray(lengths, dtype=np.int64)
    if len(success) == len(starts):
        demos["episode_success"] = np.asarray(success, dtype=bool)
    return demos


def behaviour_clone(model, demos: dict[str, np.ndarray], epochs: int = 30, batch_size: int = 256,
                    learning_rate: float = 1e-3, seed: int = 0, update_statistics: bool = True) -> dict[str, Any]:
    """Fit ``model``'s policy mean and value head to ``demos`` in place (see the module docstring).

    Args:
        model: an SB3 on-policy model (``PPO`` or ``A2C``) built on the training env; if that env is a
            ``VecNormalize`` its statistics are updated with the demonstrations.
        demos: arrays from :func:`load_demos` or :func:`load_minari_demos` (``observations (T, D)``,
            ``actions (T, A)``, ``rewards (T,)``, ``episode_starts (E,)``); the policy is fitted to
            ``expert_actions (T, A)`` where they are recorded (the demonstrator's choices, where noise was added
            to the actions taken), else to ``actions``.
        epochs: passes over the demonstrations (>= 1).
        batch_size: minibatch size (>= 1).
        learning_rate: Adam step size.
        seed: shuffles the minibatches.
        update_statistics: update a ``VecNormalize``'s statistics with ``demos`` first (False: normalise with
            them as they are, e.g. when ``demos`` re-presents data they were already updated with).

    Returns:
        ``{steps, episodes, epochs, action_mse, value_explained_variance}``: the demonstrations' size, the final
        epoch's mean squared action error (squared action units) and ``1 - mse / var`` of the value head against
        the returns after that epoch (1: exact, 0: no better than their mean).
    """
    import torch
    from stable_baselines3.common.policies import ActorCriticPolicy
    from stable_baselines3.common.vec_env import VecNormalize

    if not isinstance(model.policy, ActorCriticPolicy):
        raise ValueError("behaviour cloning needs an actor-critic policy (PPO, A2C), got "
                         f"{type(model.policy).__name__}")
    if epochs < 1 or batch_size < 1:
        raise ValueError(f"epochs and batch_size must be >= 1, got {epochs} and {batch_size}")
    if not isinstance(model.observation_space, gym.spaces.Box):
        raise ValueError("behaviour cloning reads flat state observations (observation.mode 'state'), got a "
                         f"{type(model.observation_space).__name__} observation space")
    obs = np.asarray(demos["observations"], dtype=np.float32)
    actions = np.asarray(demos.get("expert_actions", demos["actions"]), dtype=np.float32)
    rewards = np.asarray(demos["rewards"], dtype=np.float64)
    starts = np.asarray(demos["episode_starts"], dtype=np.int64)
    if obs.shape != (len(actions), *model.observation_space.shape) or actions.shape[1:] != model.action_space.shape:
        raise ValueError(f"demonstrations of shapes {obs.shape} / {actions.shape} do not fit the model's spaces "
                         f"{model.observation_space.shape} / {model.action_space.shape}")

    gamma = float(model.gamma)
    env = model.get_env()
    if isinstance(env, VecNormalize) and update_statistics:
        if env.norm_obs:
            env.obs_rms.update(obs)
        if env.norm_reward:
            for start, end in zip(starts, np.append(starts[1:], len(rewards)), strict=True):
                running = 0.0
                for r in rewards[start:end]:
                    running = running * env.gamma + r
                    env.ret_rms.update(np.array([running]))
    if isinstance(env, VecNormalize):
        obs = env.normalize_obs(obs)
        rewards = env.normalize_reward(rewards)
    returns = discounted_returns(rewards, starts, gamma).astype(np.float32)

    policy = model.policy
    policy.set_training_mode(True)
    params = [p for name, p in policy.named_parameters() if name != "log_std"]
    optimizer = torch.optim.Adam(params, lr=learning_rate)
    obs_t = torch.as_tensor(obs, device=policy.device)
    act_t = torch.as_tensor(actions, device=policy.device)
    ret_t = torch.as_tensor(returns, device=policy.device)
    rng = np.random.default_rng(seed)
    action_mse = value_mse = math.nan
    for _ in range(epochs):
        order = rng.permutation(len(obs))
        sums = np.zeros(2)
        for i in range(0, len(order), batch_size):
            idx = torch.as_tensor(order[i:i + batch_size], device=policy.device)
            dist = policy.get_distribution(obs_t[idx])
            mean = dist.distribution.mean
            values = policy.predict_values(obs_t[idx]).flatten()
            loss_a = torch.mean((mean - act_t[idx]) ** 2)
            loss_v = torch.mean((values - ret_t[idx]) ** 2)
            optimizer.zero_grad()
            (loss_a + 0.5 * loss_v).backward()
            optimizer.step()
            sums += len(idx) * np.array([loss_a.item(), loss_v.item()])
        action_mse, value_mse = sums / len(order)
    policy.set_training_mode(False)
    variance = float(np.var(returns))
    explained = 1.0 - value_mse / variance if variance > 0.0 else math.nan
    return {"steps": int(len(obs)), "episodes": int(len(starts)), "epochs": int(epochs),
            "action_mse": float(action_mse), "value_explained_variance": float(explained)}
