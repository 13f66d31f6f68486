"""Evaluate a policy: random, the scripted expert, or a saved model (docs/usage.md, "Training and evaluating").

Usage::

    suture-gym evaluate --env SutureGym/NeedleInsert-v3 --policy random --episodes 20 --json
    suture-gym evaluate --env SutureGym/NeedleInsert-v3 --policy runs/ppo_NeedleInsert_s0/best_model.zip
    suture-gym evaluate --policy elsewhere/model.zip --vecnormalize elsewhere/vecnormalize.pkl
    suture-gym evaluate --env SutureGym/WoundClosure-v3 --policy expert --episodes 100 --workers 2

A saved model is evaluated with the VecNormalize statistics saved beside it (``final_vecnormalize.pkl``, or a
checkpoint's ``model_vecnormalize_<N>_steps.pkl``) unless ``--vecnormalize`` names others; when there are none
it warns on stderr and evaluates on raw observations.

Prints ``success_rate, mean_return, mean_episode_length, mean_tip_force, mean_final_gap`` (and more; the
per-episode records with ``--per-episode``). A progress bar counts the episodes on stderr, with ``--json`` too
(stdout holds the summary alone); ``--no-progress`` hides it.
"""

from __future__ import annotations

import argparse
import json
import sys

from suture_gym.baselines.evaluation import SCRIPTED, evaluate


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="suture-gym evaluate", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--env", default="SutureGym/NeedleInsert-v3", help="Gymnasium env id")
    parser.add_argument("--policy", default="random",
                        help="'random', 'expert', 'feedback_expert' (DAgger's oracle) or a path to a model .zip")
    parser.add_argument("--episodes", type=int, default=20)
    parser.add_argument("--seed", type=int, default=0, help="episode k uses env seed seed + k")
    parser.add_argument("--config", default=None,
                        help="env config overrides: a shipped config's name or a YAML path (default: a model's "
                             "training config)")
    parser.add_argument("--vecnormalize", default=None, metavar="PATH",
                        help="VecNormalize statistics (.pkl) of a saved model (default: those saved beside it; "
                             "a warning when there are none)")
    parser.add_argument("--workers", type=int, default=1,
                        help="processes to run the episodes on (the same summary; one per free core)")
    parser.add_argument("--json", action="store_true", help="print JSON")
    parser.add_argument("--per-episode", action="store_true", help="include per-episode records")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar (stderr)")
    parser.add_argument("--records", default=None,
                        help="append each episode's record to this file as a JSON line as soon as it ends")
    args = parser.parse_args(argv)
    if args.episodes <= 0:
        parser.error(f"--episodes must be positive, got {args.episodes}")
    if args.workers < 1:
        parser.error(f"--workers must be at least 1, got {args.workers}")

    env_kwargs = {"config": args.config} if args.config is not None else None
    if args.vecnormalize is not None and args.policy in SCRIPTED:
        parser.error(f"--vecnormalize applies to a saved model, not to --policy {args.policy}")
    summary = evaluate(args.env, args.policy, args.episodes, seed=args.seed, env_kwargs=env_kwargs,
                       progress=not args.no_progress, records_path=args.records, vecnormalize=args.vecnormalize,
                       workers=args.workers)
    if not args.per_episode:
        summary.pop("per_episode")
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key, value in summary.items():
            print(f"{key:22s} {value}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
