"""Tune an agent's hyperparameters with Optuna, rl-baselines3-zoo style (suture_gym/baselines/tuning.py).

Usage::

    python scripts/tune.py --env SutureGym/NeedleInsert-v3 --n-trials 20 --n-timesteps 20000
    python scripts/tune.py --env SutureGym/NeedleInsert-v3 --n-trials 20          # resumes the same study
    python scripts/tune.py --storage postgresql://user@host/optuna --study-name shared ...   # several machines
    python scripts/tune.py --hyperparams behaviour_cloning="{dataset: suture_gym/NeedleInsert-v3/expert-v0}"

Trials start from the env id's entry in ``configs/agents/<algo>.yml``; ``--hyperparams KEY=VALUE`` (VALUE read
as YAML, ``null`` removes the key) fixes keys, which are then not sampled. The study is stored in the database
``--storage`` (any SQLAlchemy URL; SQLite file by default) under ``--study-name`` and resumed when it exists.
Prints the best trial and its hyperparameters (``--json``: the whole summary as JSON on stdout).
"""

from __future__ import annotations

import argparse
import json
import sys

from _common import configure

configure(threads=1)

import yaml  # noqa: E402


def _override(text: str) -> tuple[str, object]:
    key, sep, value = text.partition("=")
    if not sep or not key:
        raise argparse.ArgumentTypeError(f"expected KEY=VALUE, got {text!r}")
    try:
        return key, yaml.safe_load(value)
    except yaml.YAMLError as exc:
        raise argparse.ArgumentTypeError(f"{key}: {value!r} is not YAML ({exc})") from exc


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--algo", default="ppo", help="algorithm with a search space (ppo)")
    parser.add_argument("--env", default="SutureGym/NeedleInsert-v3", help="Gymnasium env id")
    parser.add_argument("--n-trials", type=int, default=10, help="trials to run now (added to the study's)")
    parser.add_argument("--timeout", type=float, default=None, help="stop starting trials after this many s")
    parser.add_argument("--n-timesteps", type=int, default=20_000, help="env steps per trial")
    parser.add_argument("--n-evaluations", type=int, default=4, help="evaluations per trial (reported for pruning)")
    parser.add_argument("--eval-episodes", type=int, default=5, help="episodes per evaluation")
    parser.add_argument("--seed", type=int, default=0, help="seeds the sampler and every trial's envs and agent")
    parser.add_argument("--storage", default="sqlite:///runs/tune.db",
                        help="SQLAlchemy database URL of the study (default: a SQLite file)")
    parser.add_argument("--study-name", default=None, help="default: <algo>_<EnvName>-v<k>")
    parser.add_argument("--hyperparams", nargs="+", type=_override, default=[], metavar="KEY=VALUE",
                        help="fixed hyperparameters (YAML values; null removes the key)")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar")
    args = parser.parse_args(argv)
    for name in ("n_trials", "n_timesteps", "n_evaluations", "eval_episodes"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")

    from suture_gym.baselines.hyperparams import load_hyperparams, resolve
    from suture_gym.baselines.tuning import SAMPLERS, objective, open_study, study_summary

    if args.algo not in SAMPLERS:
        parser.error(f"--algo {args.algo!r} has no search space; known: {sorted(SAMPLERS)}")
    base = load_hyperparams(args.algo, args.env)
    overrides = dict(args.hyperparams)
    resolve({k: v for k, v in {**base, **overrides}.items() if v is not None})  # a bad override fails here, once
    study_name = args.study_name or f"{args.algo}_{args.env.split('/')[-1]}"
    study = open_study(study_name, args.storage, seed=args.seed, n_warmup_steps=args.n_evaluations // 3)
    before = len(study.trials)
    study.optimize(
        lambda trial: objective(trial, args.algo, args.env, base, overrides, args.n_timesteps, args.n_evaluations,
                                args.eval_episodes, args.seed),
        n_trials=args.n_trials, timeout=args.timeout, catch=(ValueError,), show_progress_bar=not args.no_progress,
        gc_after_trial=True)
    summary = {"storage": args.storage, "algo": args.algo, "env_id": args.env, "n_timesteps": args.n_timesteps,
               **study_summary(study, len(study.trials) - before)}
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        best = summary.pop("best")
        for key, value in summary.items():
            print(f"{key:16s} {value}")
        if best is None:
            print("no complete trial yet")
        else:
            print(f"best trial {best['number']}: mean return {best['value']:.4g}, success rate "
                  f"{best['success_rate']}; its {args.algo}.yml entry:")
            print(yaml.safe_dump({args.env: best["hyperparams"]}, sort_keys=False))
    return 0


if __name__ == "__main__":
    sys.exit(main())
