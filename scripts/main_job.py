"""The main job (``make run``): train the default baseline on NeedleInsert, evaluate it, plot and film it.

Steps:

1. train DAgger (``configs/agents/dagger.yml``, :mod:`suture_gym.baselines.dagger`) on ``SutureGym/NeedleInsert-v3``
   (randomised by default) with a progress bar: the scripted surgeon's demonstrations, then iterations in which
   the learner acts alone and the surgeon labels every state it visits (run directory
   ``<out>/dagger_NeedleInsert_s<seed>/``); ``--algo ppo`` trains PPO warm-started by behaviour cloning
   (``configs/agents/ppo.yml``) instead;
2. evaluate the trained model on ``--episodes`` seeded episodes of the same env config, and on the same seeds
   the committed models of the same algorithm (``models/NeedleInsert/seed*/``, docs/results.md), the
   scripted expert and random actions (``suture_gym.baselines.evaluation.evaluate``) -> ``<run>/evaluation.json``; the
   committed models' own 100-episode figures (their ``evaluation.json``) are printed beside;
3. the learning curve -> ``<run>/learning_curve.png`` (written by the training);
4. a video of one episode of the trained policy -> ``<run>/policy.mp4``.

DAgger's rollouts and the evaluations run on ``--workers`` processes (default 2, the same results as one); the
refit, the video and the rest run in this process. Prints one JSON summary at the end.

Usage::

    python scripts/main_job.py                          # the defaults above
    python scripts/main_job.py --algo ppo --n-timesteps 20000  # PPO + behaviour cloning, a quick look
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
from suture_gym.baselines.evaluation import (  # noqa: E402
    SCRIPTED,
    evaluate,
    make_policy,
    model_vecnormalize,
    run_config,
    trained_env_kwargs,
)
from suture_gym.baselines.training import train  # noqa: E402
from suture_gym.render import write_video  # noqa: E402

ENV_ID = "SutureGym/NeedleInsert-v3"
#: The committed models of ``ENV_ID`` (docs/results.md), one directory per training seed.
COMMITTED = ROOT / "models" / "NeedleInsert"
#: Env steps per video frame (the default 5 ms env step gives 25 fps at real time).
VIDEO_EVERY = 8


def record_policy_video(env_id: str, policy: str, path: Path, seed: int) -> dict:
    """Film one episode of ``policy`` (``random``, ``expert`` or a model ``.zip``, with the statistics saved beside
    it) on ``env_id``, env seed ``seed``, into ``path`` (real time). Returns ``{path, frames, steps, success,
    return}``."""
    env = gym.make(env_id, render_mode="rgb_array", **trained_env_kwargs(policy))
    act = make_policy(policy, env, seed, None if policy in SCRIPTED else model_vecnormalize(policy))
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


def committed_models(algo: str) -> list[Path]:
    """The committed models of ``ENV_ID`` trained with ``algo`` (their run's ``config.yaml`` says), by seed."""
    return [path for path in sorted(COMMITTED.glob("seed*/final_model.zip"))
            if run_config(path).get("algo") == algo]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", choices=("dagger", "ppo"), default="dagger")
    parser.add_argument("--n-timesteps", type=int, default=None,
                        help="env-step budget (default: the algorithm's config)")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--episodes", type=int, default=20, help="evaluation episodes of each policy")
    parser.add_argument("--eval-freq", type=int, default=10_000,
                        help="PPO: env steps between learning-curve points")
    parser.add_argument("--out", default=str(ROOT / "runs"), help="parent directory of the run directory")
    parser.add_argument("--workers", type=int, default=2,
                        help="processes for DAgger's rollouts and the evaluations (the same results; one per core)")
    args = parser.parse_args(argv)
    if (args.n_timesteps is not None and args.n_timesteps <= 0) or args.episodes <= 0 or args.workers <= 0:
        parser.error("--n-timesteps, --episodes and --workers must be positive")

    start = time.perf_counter()
    print(f"[1/3] training {args.algo} on {ENV_ID}", flush=True)
    result = train(args.algo, ENV_ID, seed=args.seed, out_dir=args.out, n_timesteps=args.n_timesteps,
                   eval_freq=args.eval_freq, eval_episodes=5, checkpoint_freq=args.eval_freq, progress_bar=True,
                   workers=args.workers if args.algo == "dagger" else 1)
    print(f"[2/3] evaluating on {args.episodes} seeded episodes", flush=True)
    seed = args.seed + 10_000
    env_kwargs = trained_env_kwargs(str(result.model_path))
    committed = committed_models(args.algo)
    policies = [("trained", str(result.model_path)),
                *((f"committed_{path.parent.name}", str(path)) for path in committed),
                ("expert", "expert"), ("random", "random")]
    evaluations = {name: evaluate(ENV_ID, policy, args.episodes, seed=seed, env_kwargs=env_kwargs, progress=True,
                                  workers=args.workers)
                   for name, policy in policies}
    for summary in evaluations.values():
        summary.pop("per_episode")
    (result.run_dir / "evaluation.json").write_text(json.dumps(evaluations, indent=2))
    print("[3/3] recording a video of the trained policy", flush=True)
    video = record_policy_video(ENV_ID, str(result.model_path), result.run_dir / "policy.mp4", seed)
    reference = {}
    for path in committed:
        figure = json.loads((path.parent / "evaluation.json").read_text())
        reference[path.parent.name] = {key: figure[key] for key in ("episodes", "seed", "success_rate")}
    print(json.dumps({
        "env_id": ENV_ID,
        "algo": args.algo,
        "run_dir": str(result.run_dir),
        "timesteps": result.timesteps,
        "train_wall_s": round(result.wall_s, 1),
        "total_wall_s": round(time.perf_counter() - start, 1),
        "episodes": args.episodes,
        "success_rate": {name: s["success_rate"] for name, s in evaluations.items()},
        "mean_return": {name: round(s["mean_return"], 3) for name, s in evaluations.items()},
        "committed_models_own_evaluation": reference,
        "learning_curve": str(result.run_dir / "learning_curve.png"),
        "video": video,
    }, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
