"""The main job (``make run``): train the default baseline on NeedleInsert, evaluate it, plot and film it.

Steps:

1. train PPO (``configs/agents/ppo.yml``) on ``SutureGym/NeedleInsert-v2`` (randomised by default) for
   ``--n-timesteps`` env steps with a progress bar, evaluating every ``--eval-freq`` steps
   (``agents.training.train``; run directory ``<out>/ppo_NeedleInsert_s<seed>/``). The config warm-starts the
   policy by behaviour cloning 80 scripted-expert episodes (recorded first, about three minutes);
2. evaluate the final model on ``--episodes`` seeded episodes of the same env config, and the scripted expert
   and random actions on the same seeds for scale (``agents.evaluation.evaluate``) -> ``<run>/evaluation.json``;
3. the learning curve -> ``<run>/learning_curve.png`` (written by the training);
4. a video of one episode of the trained policy -> ``<run>/policy.mp4``.

Budget: recording and cloning the demonstrations takes about a minute and the default 100 000 PPO env steps
about 7-10 minutes on a 2-core laptop (200-300 env steps/s with 4 envs, evaluations included); the final
evaluations and the video a few more. Prints one JSON summary at the end.

Usage::

    python scripts/main_job.py                      # the defaults above
    python scripts/main_job.py --n-timesteps 20000  # a quick look
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

from _common import ROOT, configure

configure(threads=1)

import gymnasium as gym  # noqa: E402

import suture_gym  # noqa: E402, F401  (registers the ids)
from agents.evaluation import evaluate, make_policy, trained_env_kwargs  # noqa: E402
from agents.training import train  # noqa: E402
from suture_gym.render import write_video  # noqa: E402

ENV_ID = "SutureGym/NeedleInsert-v2"
ALGO = "ppo"
#: Env steps per video frame (the default 5 ms env step gives 25 fps at real time).
VIDEO_EVERY = 8


def record_policy_video(env_id: str, policy: str, path: Path, seed: int) -> dict:
    """Film one episode of ``policy`` (``random``, ``expert`` or a model ``.zip``) on ``env_id``, env seed
    ``seed``, into ``path`` (real time). Returns ``{path, frames, steps, success, return}``."""
    env = gym.make(env_id, render_mode="rgb_array", **trained_env_kwargs(policy))
    act = make_policy(policy, env, seed)
    summary = {"steps": 0, "success": False, "return": 0.0}

    def frames():
        obs, _ = env.reset(seed=seed)
        done = False
        while not done:
            if summary["steps"] % VIDEO_EVERY == 0:
                yield env.render()
            obs, reward, terminated, truncated, info = env.step(act(obs))
            summary["steps"] += 1
            summary["return"] += float(reward)
            summary["success"] = bool(info.get("is_success", False))
            done = terminated or truncated
        yield env.render()

    fps = 1.0 / (VIDEO_EVERY * env.unwrapped.sim.control_dt)
    count = write_video(frames(), path, fps=fps, quality=7.0)
    env.close()
    return {"path": str(path), "frames": count, **summary}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--n-timesteps", type=int, default=100_000, help="PPO env steps")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes of each policy")
    parser.add_argument("--eval-freq", type=int, default=10_000, help="env steps between learning-curve points")
    parser.add_argument("--out", default=str(ROOT / "runs"), help="parent directory of the run directory")
    args = parser.parse_args(argv)
    if args.n_timesteps <= 0 or args.episodes <= 0:
        parser.error("--n-timesteps and --episodes must be positive")

    start = time.perf_counter()
    print(f"[1/3] training {ALGO.upper()} on {ENV_ID} for {args.n_timesteps} env steps", flush=True)
    result = train(ALGO, ENV_ID, seed=args.seed, out_dir=args.out, n_timesteps=args.n_timesteps,
                   eval_freq=args.eval_freq, eval_episodes=5, checkpoint_freq=args.eval_freq, progress_bar=True)
    print(f"[2/3] evaluating on {args.episodes} seeded episodes", flush=True)
    seed = args.seed + 10_000
    env_kwargs = trained_env_kwargs(str(result.model_path))
    evaluations = {name: evaluate(ENV_ID, policy, args.episodes, seed=seed, env_kwargs=env_kwargs, progress=True)
                   for name, policy in (("trained", str(result.model_path)), ("expert", "expert"),
                                        ("random", "random"))}
    for summary in evaluations.values():
        summary.pop("per_episode")
    (result.run_dir / "evaluation.json").write_text(json.dumps(evaluations, indent=2))
    print("[3/3] recording a video of the trained policy", flush=True)
    video = record_policy_video(ENV_ID, str(result.model_path), result.run_dir / "policy.mp4", seed)
    print(json.dumps({
        "env_id": ENV_ID,
        "algo": ALGO,
        "run_dir": str(result.run_dir),
        "timesteps": result.timesteps,
        "train_wall_s": round(result.wall_s, 1),
        "total_wall_s": round(time.perf_counter() - start, 1),
        "success_rate": {name: s["success_rate"] for name, s in evaluations.items()},
        "mean_return": {name: round(s["mean_return"], 3) for name, s in evaluations.items()},
        "learning_curve": str(result.run_dir / "learning_curve.png"),
        "video": video,
    }, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
