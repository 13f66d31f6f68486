"""Train a Stable-Baselines3 baseline on a SutureGym task (rl-zoo-style configs in suture_gym/configs/agents/).

Usage::

    suture-gym train --algo ppo --env SutureGym/NeedleInsert-v3 --seed 0
    suture-gym train --algo sac --env SutureGym/NeedleInsert-v3 --n-timesteps 20000
    suture-gym train --algo dagger --env SutureGym/SutureThrow-v3 --workers 2   # rollouts on 2 cores
    suture-gym train --algo ppo --env SutureGym/NeedleInsert-v3 --from-scratch --n-timesteps 18700
    suture-gym train --algo ppo --env SutureGym/NeedleInsert-v3 \
        --resume runs/ppo_NeedleInsert_s0/checkpoints/model_50000_steps.zip

Writes runs/<algo>_<Task>_s<seed>/ (config.yaml, TensorBoard logs, checkpoints, evaluations, best and final
models, learning_curve.png, summary.json); see suture_gym/baselines/training.py.
"""

from __future__ import annotations

import argparse
import json
import sys

from suture_gym.baselines.hyperparams import algorithms, load_hyperparams
from suture_gym.baselines.training import train


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="suture-gym train", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="ppo", choices=algorithms(),
                        help="algorithm (suture_gym/configs/agents/*.yml)")
    parser.add_argument("--env", default="SutureGym/NeedleInsert-v3", help="Gymnasium env id")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--n-timesteps", type=int, default=None, help="override the config's total env steps")
    parser.add_argument("--out", default="runs", help="parent directory of the run directory")
    parser.add_argument("--eval-freq", type=int, default=10_000, help="env steps between evaluations (0: none)")
    parser.add_argument("--eval-episodes", type=int, default=20)
    parser.add_argument("--checkpoint-freq", type=int, default=50_000, help="env steps between checkpoints")
    parser.add_argument("--resume", default=None, help="checkpoint .zip to continue from")
    parser.add_argument("--from-scratch", action="store_true",
                        help="leave out the config's behaviour-cloning warm start (PPO, SAC, TQC)")
    parser.add_argument("--workers", type=int, default=1,
                        help="DAgger: processes its rollouts run on (the same run; one per free core)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar")
    parser.add_argument("-v", "--verbose", type=int, default=0)
    args = parser.parse_args(argv)
    if args.n_timesteps is not None and args.n_timesteps <= 0:
        parser.error(f"--n-timesteps must be positive, got {args.n_timesteps}")
    if args.workers < 1 or (args.workers > 1 and args.algo != "dagger"):
        parser.error(f"--workers must be >= 1 and applies to --algo dagger only, got {args.workers} with {args.algo}")
    hyperparams = None
    if args.from_scratch:
        if args.algo == "dagger":
            parser.error("--from-scratch applies to PPO, SAC and TQC; DAgger learns from the expert by design")
        hyperparams = load_hyperparams(args.algo, args.env)
        hyperparams.pop("behaviour_cloning", None)

    result = train(
        args.algo,
        args.env,
        seed=args.seed,
        out_dir=args.out,
        n_timesteps=args.n_timesteps,
        eval_freq=args.eval_freq,
        eval_episodes=args.eval_episodes,
        checkpoint_freq=args.checkpoint_freq,
        resume=args.resume,
        progress_bar=not args.no_progress,
        verbose=args.verbose,
        hyperparams=hyperparams,
        workers=args.workers,
    )
    print(json.dumps({"run_dir": str(result.run_dir), "model": str(result.model_path),
                      "timesteps": result.timesteps, "wall_s": round(result.wall_s, 1),
                      "last_eval_mean_return": result.last_eval_mean_return,
                      "last_eval_success_rate": result.last_eval_success_rate}, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
