"""What an episode pays a reference policy, term by term: the learnability study of an env id and config.

Policies: ``hover`` (the zero action: in ``pose_delta`` mode the holder's target stays put, in ``wrench`` mode no
force), ``random`` (uniform in the action box), ``gauss<s>`` (zero-mean Gaussian actions of standard deviation
``s``, clipped to the box: the exploration of a fresh Gaussian policy; SB3's start at ``s = 1``), ``expert`` (the
scripted surgeon, :class:`~suture_gym.baselines.expert.ExpertPolicy`) and ``drive`` (the constant action that
turns the needle about its circle's centre at full rate, ``-1`` on the last component: meaningful with
``action.frame: needle``). Each policy plays ``episodes`` episodes on env seeds ``seed, seed + 1, ...``; the
summary is the mean return, the mean of every reward term over the episodes, how the episodes ended and their
mean length (env steps).

Usage::

    python scripts/rl_study.py --env SutureGym/NeedleInsert-v3 --episodes 20 --json
    python scripts/rl_study.py --config needle_insert_rl --policies hover gauss1 drive
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import Counter

import gymnasium as gym
import numpy as np

#: Policies :func:`study` knows (``gauss<s>`` for any standard deviation ``s``, e.g. ``gauss0.3``).
POLICIES = ("hover", "random", "gauss1", "expert", "drive")


def _end(info: dict, terminated: bool, truncated: bool) -> str:
    """How an episode ended: success, a failure's kind, or the time limit."""
    if info.get("is_success"):
        return "success"
    for key in ("diverged", "crushed", "tear", "out_of_workspace", "missed"):
        if info.get(key):
            return key
    return "time_limit" if truncated else "other"


def _actor(name: str, env, rng: np.random.Generator):
    """A callable ``obs -> (6,) action`` for the policy ``name`` (ValueError naming it if unknown)."""
    if name == "hover":
        return lambda obs: np.zeros(6, dtype=np.float32)
    if name == "random":
        return lambda obs: rng.uniform(-1.0, 1.0, 6).astype(np.float32)
    if name.startswith("gauss"):
        try:
            std = float(name[5:])
        except ValueError:
            std = -1.0
        if not std > 0.0:
            raise ValueError(f"policy {name!r}: gauss<s> needs a standard deviation s > 0, e.g. 'gauss0.3'")
        return lambda obs: np.clip(rng.normal(0.0, std, 6), -1.0, 1.0).astype(np.float32)
    if name == "drive":
        action = np.zeros(6, dtype=np.float32)
        action[5] = -1.0
        return lambda obs: action
    if name == "expert":
        from suture_gym.baselines.expert import ExpertPolicy

        expert = ExpertPolicy(env.unwrapped)
        return expert
    raise ValueError(f"unknown policy {name!r}; known: {list(POLICIES)} (gauss<s> for any s > 0)")


def study(env_id: str, policies, episodes: int = 20, seed: int = 0, env_kwargs: dict | None = None) -> dict:
    """``{policy: summary}`` of :data:`POLICIES`-style names on ``env_id`` (module docstring)."""
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes <= 0:
        raise ValueError(f"episodes must be a positive integer, got {episodes!r}")
    env = gym.make(env_id, **(env_kwargs or {}))
    results = {}
    for name in policies:
        rng = np.random.default_rng([seed, 7])
        actor = _actor(name, env, rng)
        returns, lengths, ends, terms = [], [], Counter(), Counter()
        for k in range(episodes):
            obs, info = env.reset(seed=seed + k)
            if hasattr(actor, "reset"):
                actor.reset()
            total, steps = 0.0, 0
            while True:
                obs, reward, terminated, truncated, info = env.step(actor(obs))
                total += float(reward)
                steps += 1
                for key, value in info.items():
                    if key.startswith("reward_"):
                        terms[key[7:]] += float(value)
                if terminated or truncated:
                    break
            returns.append(total)
            lengths.append(steps)
            ends[_end(info, terminated, truncated)] += 1
        results[name] = {
            "mean_return": float(np.mean(returns)),
            "std_return": float(np.std(returns)),
            "success_rate": ends["success"] / episodes,
            "mean_episode_length": float(np.mean(lengths)),
            "ends": dict(ends),
            "mean_terms": {key: value / episodes for key, value in terms.items()},
        }
    env.close()
    return {"env_id": env_id, "env_kwargs": env_kwargs or {}, "episodes": episodes, "seed": seed,
            "policies": results}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="rl_study", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SutureGym/NeedleInsert-v3")
    parser.add_argument("--config", default=None, help="env config: a shipped config's name or a YAML path")
    parser.add_argument("--action-mode", default=None, choices=("wrench", "pose_delta"))
    parser.add_argument("--policies", nargs="+", default=list(POLICIES))
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=5000, help="episode k uses env seed seed + k")
    parser.add_argument("--json", action="store_true")
    args = parser.parse_args(argv)
    kwargs = {}
    if args.config is not None:
        kwargs["config"] = args.config
    if args.action_mode is not None:
        kwargs["action_mode"] = args.action_mode
    try:
        result = study(args.env, args.policies, args.episodes, args.seed, kwargs)
    except ValueError as error:
        parser.error(str(error))
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    for name, summary in result["policies"].items():
        terms = ", ".join(f"{k} {v:+.2f}" for k, v in summary["mean_terms"].items() if abs(v) >= 0.005)
        print(f"{name:8s} return {summary['mean_return']:+7.2f}  success {summary['success_rate']:.2f}  "
              f"length {summary['mean_episode_length']:6.1f}  ends {summary['ends']}\n         {terms}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
