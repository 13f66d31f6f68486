"""Scripted expert for the SutureGym tasks, and demonstration recording.

:class:`ExpertPolicy` is the package's scripted surgeon, :class:`~suture_gym.tasks.surgeon.ScriptedSurgeon`
(turn the needle about its own centre along each planned stitch, pull the thread, carry the needle to the next
stitch), acting through the env's action space only, so it works in both ``wrench`` and ``pose_delta`` action
modes. Its default speeds are the task's (``SURGEON_TURN_RATE``, ``SURGEON_PULL_SPEED``). The env's start phases
and the measurements drive the same surgeon (:mod:`suture_gym.tasks.surgeon`).

Recording: ``python -m agents.expert --env ID --episodes N --out demos.npz`` writes the observations, actions,
rewards, tip forces and episode boundaries of N seeded expert episodes (see :func:`record`).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import gymnasium as gym
import numpy as np

from suture_gym.tasks.surgeon import ScriptedSurgeon


class ExpertPolicy(ScriptedSurgeon):
    """Scripted expert: a callable ``obs -> action`` (``(6,) float32`` in [-1, 1]) with :meth:`reset`; see
    :class:`~suture_gym.tasks.surgeon.ScriptedSurgeon` for the plan and the arguments (``env``, ``turn_rate``
    rad/s, ``pull_speed`` m/s)."""


def record(env_id: str, episodes: int, out: str | Path, seed: int = 0, env_kwargs: dict | None = None,
           progress: bool = True) -> dict:
    """Run ``episodes`` expert episodes of ``env_id`` (env seeds ``seed, seed + 1, ...``) and save them to ``out``.

    The ``.npz`` holds, over all T steps concatenated: ``observations (T, D) float32`` (the observation each
    action was taken on; for Dict spaces one array per key, ``observations_<key>``), ``next_observations``
    likewise, ``actions (T, 6) float32``, ``rewards (T,) float64``, ``tip_forces (T,) float64`` (N),
    ``tissue_costs (T,) float64``, ``terminated (T,) bool``, ``truncated (T,) bool``, ``episode_starts (E,)
    int64`` (index of each episode's first step), ``episode_lengths (E,) int64``, ``episode_success (E,)
    bool``, ``episode_seeds (E,) int64``, and ``env_id``.

    Returns:
        ``{episodes, steps, success_rate, out}``.
    """
    import suture_gym  # noqa: F401  (registers the ids)

    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    env = gym.make(env_id, **(env_kwargs or {}))
    expert = ExpertPolicy(env)
    obs_rows: list = []
    next_rows: list = []
    columns: dict[str, list] = {k: [] for k in ("actions", "rewards", "tip_forces", "tissue_costs", "terminated",
                                                 "truncated")}
    starts, lengths, success, seeds = [], [], [], []
    iterator = range(episodes)
    if progress:
        from tqdm import tqdm

        iterator = tqdm(iterator, desc=f"expert {env_id}", unit="episode", file=sys.stderr)
    for k in iterator:
        obs, info = env.reset(seed=seed + k)
        expert.reset()
        starts.append(len(columns["actions"]))
        seeds.append(seed + k)
        done, length = False, 0
        while not done:
            action = expert(obs)
            next_obs, reward, terminated, truncated, info = env.step(action)
            obs_rows.append(obs)
            next_rows.append(next_obs)
            columns["actions"].append(action)
            columns["rewards"].append(float(reward))
            columns["tip_forces"].append(float(info.get("tip_force", 0.0)))
            columns["tissue_costs"].append(float(info.get("cost", 0.0)))
            columns["terminated"].append(bool(terminated))
            columns["truncated"].append(bool(truncated))
            obs = next_obs
            length += 1
            done = terminated or truncated
        lengths.append(length)
        success.append(bool(info.get("is_success", False)))
    env.close()
    arrays: dict[str, np.ndarray] = {
        "actions": np.asarray(columns["actions"], dtype=np.float32),
        "rewards": np.asarray(columns["rewards"], dtype=np.float64),
        "tip_forces": np.asarray(columns["tip_forces"], dtype=np.float64),
        "tissue_costs": np.asarray(columns["tissue_costs"], dtype=np.float64),
        "terminated": np.asarray(columns["terminated"], dtype=bool),
        "truncated": np.asarray(columns["truncated"], dtype=bool),
        "episode_starts": np.asarray(starts, dtype=np.int64),
        "episode_lengths": np.asarray(lengths, dtype=np.int64),
        "episode_success": np.asarray(success, dtype=bool),
        "episode_seeds": np.asarray(seeds, dtype=np.int64),
        "env_id": np.asarray(env_id),
    }
    if isinstance(obs_rows[0], dict):
        for key in obs_rows[0]:
            arrays[f"observations_{key}"] = np.asarray([o[key] for o in obs_rows], dtype=np.float32)
            arrays[f"next_observations_{key}"] = np.asarray([o[key] for o in next_rows], dtype=np.float32)
    else:
        arrays["observations"] = np.asarray(obs_rows, dtype=np.float32)
        arrays["next_observations"] = np.asarray(next_rows, dtype=np.float32)
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    np.savez_compressed(out, **arrays)
    return {"episodes": episodes, "steps": int(arrays["actions"].shape[0]),
            "success_rate": float(np.mean(success)), "out": str(out)}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description="Record scripted-expert demonstrations to an .npz file.")
    parser.add_argument("--env", required=True, help="env id, e.g. SutureGym/NeedleInsert-v1")
    parser.add_argument("--episodes", type=int, default=10)
    parser.add_argument("--seed", type=int, default=0, help="env seed of the first episode")
    parser.add_argument("--out", required=True, help="output .npz path")
    args = parser.parse_args(argv)
    summary = record(args.env, args.episodes, args.out, seed=args.seed)
    print(f"{summary['episodes']} episodes, {summary['steps']} steps, success rate "
          f"{summary['success_rate']:.2f} -> {summary['out']}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
