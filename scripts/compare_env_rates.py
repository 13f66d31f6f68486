"""Time env ids of this checkout against env ids of an earlier commit, on this machine, with one workload.

Issue 13 asks that the environments at 100 kPa and up run at least as many env steps per second as the 3 kPa ones
measured before the change, on the same machine. ``scripts/bench.py`` times only this checkout; this script checks
the earlier commit out into a temporary git worktree and times each pair of ids, ``OLD=NEW``, in separate processes
(each with its own numba cache), alternating old and new for ``--rounds`` rounds. Both run on this checkout's
virtual environment, so the earlier commit must import with today's dependencies.

Workload (the one ``env_*_stiff`` in ``scripts/bench.py`` uses, its constants read from this checkout:
``suture_gym.measure.envs.WARMUP_STEPS``, ``TIMED_STEPS``, ``suture_gym.measure.tissue_stiff.ENV_RATE_ROUNDS``,
``ENV_RATE_SEEDS``): the registered default config, 50 seeded random warm-up steps, then 3 timed runs of 600 seeded
random steps from each of the env and action seeds 0, 1 and 2 (resets included); an id's figure is its best run,
and the pair's ``ratio`` is new over old of the best over all rounds.

Usage::

    python scripts/compare_env_rates.py --ref 5eedff7 \\
        SutureGym/NeedleInsert-v0=SutureGym/NeedleInsert-v3 SutureGym/WoundClosure-v0=SutureGym/WoundClosure-v3
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

from tqdm import tqdm

ROOT = Path(__file__).resolve().parents[1]

#: The timing run, executed with ``python -c`` in the checkout under test. It repeats the ``env_*_stiff`` workload
#: (``suture_gym.measure.tissue_stiff``) rather than importing it: the earlier commit has no such function, and both
#: sides must run the same code; the workload's sizes come from this checkout (:func:`workload`, ``argv[2]``). It
#: uses only Gymnasium's API. The new side is this working tree (``new_commit`` is its HEAD, uncommitted changes
#: included).
TIMING = """
import json, sys, time
import gymnasium as gym
import suture_gym.envs
workload = json.loads(sys.argv[2])
env = gym.make(sys.argv[1])
env.action_space.seed(1)
env.reset(seed=1)
for _ in range(workload["warmup"]):
    *_, terminated, truncated, _ = env.step(env.action_space.sample())
    if terminated or truncated:
        env.reset()
rates = []
for _ in range(workload["rounds"]):
    elapsed = 0.0
    for seed in workload["seeds"]:
        env.action_space.seed(seed)
        env.reset(seed=seed)
        start = time.perf_counter()
        for _ in range(workload["steps"]):
            *_, terminated, truncated, _ = env.step(env.action_space.sample())
            if terminated or truncated:
                env.reset()
        elapsed += time.perf_counter() - start
    rates.append(workload["steps"] * len(workload["seeds"]) / elapsed)
print(json.dumps(rates))
"""


def workload() -> dict:
    """The ``env_*_stiff`` benchmark's workload (its constants in this checkout), handed to :data:`TIMING`."""
    from suture_gym.measure.envs import TIMED_STEPS, WARMUP_STEPS
    from suture_gym.measure.tissue_stiff import ENV_RATE_ROUNDS, ENV_RATE_SEEDS

    return {"warmup": WARMUP_STEPS, "rounds": ENV_RATE_ROUNDS, "seeds": list(ENV_RATE_SEEDS), "steps": TIMED_STEPS}


def time_id(env_id: str, checkout: Path, cache: Path, work: dict) -> list[float]:
    """Env steps per second of ``env_id``'s timed runs of ``work`` (:func:`workload`), imported from ``checkout``
    (numba cache ``cache``)."""
    env = {**os.environ, "PYTHONPATH": str(checkout), "NUMBA_CACHE_DIR": str(cache), "NUMBA_NUM_THREADS": "1"}
    done = subprocess.run([sys.executable, "-c", TIMING, env_id, json.dumps(work)], cwd=checkout, env=env,
                          capture_output=True, text=True)  # fmt: skip
    if done.returncode != 0:
        raise RuntimeError(f"timing {env_id} in {checkout} failed:\n{done.stderr[-2000:]}")
    return json.loads(done.stdout.strip().splitlines()[-1])


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--ref", required=True, help="the earlier commit (any git revision)")
    parser.add_argument("pairs", nargs="+", metavar="OLD=NEW", help="an id of --ref and an id of this checkout")
    parser.add_argument("--rounds", type=int, default=2, help="alternating rounds (default 2)")
    parser.add_argument("--no-progress", action="store_true", help="hide the progress bar (stderr)")
    args = parser.parse_args(argv)
    if args.rounds < 1:
        parser.error(f"--rounds must be >= 1, got {args.rounds}")
    pairs = []
    for pair in args.pairs:
        old, sep, new = pair.partition("=")
        if not sep or not old or not new:
            parser.error(f"a pair is OLD_ID=NEW_ID, got {pair!r}")
        pairs.append((old, new))
    commit = subprocess.run(["git", "rev-parse", "--verify", f"{args.ref}^{{commit}}"], cwd=ROOT,
                            capture_output=True, text=True)  # fmt: skip
    if commit.returncode != 0:
        parser.error(f"--ref {args.ref!r} is not a commit of this repository")
    sha = commit.stdout.strip()
    with tempfile.TemporaryDirectory(prefix="suture_gym_compare_") as tmp:
        worktree = Path(tmp) / "old"
        subprocess.run(["git", "worktree", "add", "--detach", str(worktree), sha], cwd=ROOT, check=True,
                       capture_output=True)  # fmt: skip
        try:
            work = workload()
            rates = {pair: {"old": [], "new": []} for pair in pairs}
            with tqdm(total=2 * len(pairs) * args.rounds, desc="timing", disable=args.no_progress) as bar:
                for _ in range(args.rounds):
                    for old, new in pairs:
                        rates[old, new]["old"] += time_id(old, worktree, Path(tmp) / "cache_old", work)
                        bar.update()
                        rates[old, new]["new"] += time_id(new, ROOT, Path(tmp) / "cache_new", work)
                        bar.update()
        finally:
            subprocess.run(["git", "worktree", "remove", "--force", str(worktree)], cwd=ROOT, capture_output=True)
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=ROOT, capture_output=True, text=True).stdout.strip()
    results = [
        {
            "old_id": old,
            "new_id": new,
            "old_commit": sha,
            "new_commit": head,
            "old_env_steps_per_s": max(r["old"]),
            "new_env_steps_per_s": max(r["new"]),
            "ratio": max(r["new"]) / max(r["old"]),
            "old_runs": r["old"],
            "new_runs": r["new"],
        }
        for (old, new), r in rates.items()
    ]
    print(json.dumps(results, indent=2))
    return 0


if __name__ == "__main__":
    sys.exit(main())
