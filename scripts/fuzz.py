"""Fuzz the environments: every registered id, both action modes and every shipped config, driven by random,
corner, bang-bang, tiny and extreme (out-of-box) actions.

Usage::

    python scripts/fuzz.py --steps 20000 --json --seed 0

The step budget is shared evenly by the cases (id x action mode x the configs of the id's task in
``configs/envs/``); each case plays episodes of at most ``--max-episode-steps`` steps, each episode with one
action strategy:

* ``random``: uniform in the box ``[-1, 1]^6``;
* ``corner``: a random corner of the box, redrawn every step;
* ``bang_bang``: a random corner held for 1-20 steps, then its sign flipped;
* ``tiny``: uniform in ``[-1e-6, 1e-6]^6``;
* ``extreme``: random signs times magnitudes from 1 to 1e300 (outside the box: the env clips them).

Counted: exceptions from ``reset`` or ``step`` (the first few with their case and traceback), non-finite
observations, rewards and ``info`` numbers, contract violations (an observation outside its space, a reward that
is not the exact sum of its terms, a step after ``terminated`` that the env did not refuse), divergences and how
episodes ended. Exits 1 if there was any exception, non-finite value or violation, else 0.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback
from pathlib import Path

from _common import ROOT, configure

configure(threads=1)

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from tqdm import tqdm  # noqa: E402

from suture_gym.envs import ENV_IDS, GOAL_ENV_IDS  # noqa: E402
from suture_gym.envs.config import ACTION_MODES  # noqa: E402

#: Action strategies, one per episode (module docstring).
STRATEGIES = ("random", "corner", "bang_bang", "tiny", "extreme")
#: Exceptions reported in full (the rest are counted).
EXCEPTION_SAMPLES = 10
#: The ``info`` entries that must be finite numbers.
FINITE_INFO = ("tip_force", "haptic_wrench", "wound_gap", "cost")


def cases(config_dir: Path = ROOT / "configs" / "envs") -> list[dict]:
    """Every (env id, action mode, shipped config of the id's task), in a fixed order."""
    configs: dict[str, list[Path]] = {}
    for path in sorted(config_dir.glob("*.yaml")):
        configs.setdefault(yaml.safe_load(path.read_text())["task"], []).append(path)
    out = []
    for env_id, task in [*ENV_IDS.items(), *GOAL_ENV_IDS.items()]:
        for mode in ACTION_MODES:
            for path in configs.get(task, []):
                out.append({"id": env_id, "action_mode": mode, "config": path.name, "path": path})
    return out


class ActionStream:
    """The actions of one episode under ``strategy``, drawn from ``rng``."""

    def __init__(self, strategy: str, rng: np.random.Generator) -> None:
        self.strategy = strategy
        self.rng = rng
        self.held = self._corner()
        self.hold_left = 0

    def _corner(self) -> np.ndarray:
        return self.rng.choice([-1.0, 1.0], size=6)

    def __call__(self) -> np.ndarray:
        rng = self.rng
        if self.strategy == "random":
            return rng.uniform(-1.0, 1.0, 6).astype(np.float32)
        if self.strategy == "corner":
            return self._corner().astype(np.float32)
        if self.strategy == "bang_bang":
            if self.hold_left == 0:
                self.held = -self.held
                self.hold_left = int(rng.integers(1, 21))
            self.hold_left -= 1
            return self.held.astype(np.float32)
        if self.strategy == "tiny":
            return rng.uniform(-1e-6, 1e-6, 6).astype(np.float32)
        return self._corner() * 10.0 ** rng.uniform(0.0, 300.0, 6)


def _finite(value) -> bool:
    if isinstance(value, dict):
        return all(_finite(v) for v in value.values())
    return bool(np.all(np.isfinite(np.asarray(value, dtype=np.float64))))


def _contract_violations(env: gym.Env, obs, reward: float, info: dict) -> list[str]:
    """What the step broke of the env's contract: its observation space, and the reward being exactly the sum of
    its terms (``compute_reward`` of the goals for a goal-conditioned id)."""
    found = []
    if not env.observation_space.contains(obs):
        found.append("observation outside observation_space")
    unwrapped = env.unwrapped
    if isinstance(obs, dict):
        expected = unwrapped.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
    else:
        expected = math.fsum(info[f"reward_{t}"] for t in unwrapped.task_cls.TERMS)
    if expected != reward and not (math.isnan(expected) and math.isnan(reward)):
        found.append(f"reward {reward!r} is not the sum of its terms, {expected!r}")
    return found


class Tally:
    """Counts of one fuzz run, overall and in each case's record (``{"case": name, "steps": ..., ...}``)."""

    def __init__(self) -> None:
        self.totals = dict(steps=0, episodes=0, exceptions=0, non_finite_obs=0, non_finite_reward=0,
                           non_finite_info=0, violations=0, divergences=0)
        self.ends: dict[str, int] = {}
        self.strategies = dict.fromkeys(STRATEGIES, 0)
        self.exception_samples: list[dict] = []
        self.violation_samples: list[dict] = []
        self.cases: list[dict] = []

    def add(self, key: str, record: dict, count: int = 1) -> None:
        self.totals[key] += count
        record[key] = record.get(key, 0) + count

    def exception(self, record: dict, where: str, step: int, error: BaseException) -> None:
        self.add("exceptions", record)
        if len(self.exception_samples) < EXCEPTION_SAMPLES:
            self.exception_samples.append({
                "case": record["case"], "where": where, "step": step, "type": type(error).__name__,
                "message": str(error)[:500], "traceback": traceback.format_exc(limit=-4)[-2000:],
            })

    def violation(self, record: dict, step: int, what: str) -> None:
        self.add("violations", record)
        if len(self.violation_samples) < EXCEPTION_SAMPLES:
            self.violation_samples.append({"case": record["case"], "step": step, "what": what})

    def end(self, reason: str) -> None:
        self.ends[reason] = self.ends.get(reason, 0) + 1


def _name(case: dict) -> str:
    return f"{case['id']} {case['action_mode']} {case['config']}"


def _end_reason(info: dict, terminated: bool) -> str:
    for reason, key in (("success", "is_success"), ("diverged", "diverged"), ("tear", "tear"),
                        ("out_of_workspace", "out_of_workspace"), ("missed", "missed")):
        if info.get(key):
            return reason
    return "terminated" if terminated else "truncated"


def run_case(case: dict, steps: int, max_episode_steps: int, rng: np.random.Generator, tally: Tally,
             bar: tqdm) -> None:
    """Play ``steps`` env steps of ``case``, counting into ``tally`` (and its per-case record)."""
    record = {"case": _name(case), "steps": 0, "episodes": 0}
    tally.cases.append(record)
    try:
        env = gym.make(case["id"], config=case["path"], action_mode=case["action_mode"])
    except Exception as error:
        tally.exception(record, "make", 0, error)
        bar.update(steps)
        return
    done_steps = 0
    while done_steps < steps:
        try:
            env.reset(seed=int(rng.integers(2**31)))
        except Exception as error:
            tally.exception(record, "reset", done_steps, error)
            bar.update(steps - done_steps)
            break
        strategy = STRATEGIES[int(rng.integers(len(STRATEGIES)))]
        actions = ActionStream(strategy, rng)
        tally.strategies[strategy] += 1
        tally.add("episodes", record)
        length = min(max_episode_steps, steps - done_steps)
        for _ in range(length):
            done_steps += 1
            tally.add("steps", record)
            bar.update(1)
            try:
                obs, reward, terminated, truncated, info = env.step(actions())
            except Exception as error:
                tally.exception(record, f"step ({strategy})", done_steps, error)
                break
            if not _finite(obs):
                tally.add("non_finite_obs", record)
            if not math.isfinite(reward):
                tally.add("non_finite_reward", record)
            if not all(_finite(info[key]) for key in FINITE_INFO):
                tally.add("non_finite_info", record)
            for what in _contract_violations(env, obs, reward, info):
                tally.violation(record, done_steps, what)
            if info["diverged"]:
                tally.add("divergences", record)
            if terminated or truncated:
                tally.end(_end_reason(info, terminated))
                if terminated:
                    try:
                        env.step(actions())
                        tally.violation(record, done_steps, "a step after terminated was not refused")
                    except RuntimeError:
                        pass
                break
        else:
            tally.end("fuzz_episode_cap")
    env.close()


def fuzz(steps: int, seed: int = 0, max_episode_steps: int = 200, progress: bool = True) -> dict:
    """Fuzz every case for a shared budget of ``steps`` env steps; returns the summary (module docstring)."""
    all_cases = cases()
    share = [steps // len(all_cases) + (1 if k < steps % len(all_cases) else 0) for k in range(len(all_cases))]
    tally = Tally()
    start = time.perf_counter()
    with tqdm(total=steps, desc="fuzz", unit="step", file=sys.stderr, disable=None if progress else True) as bar:
        for k, (case, budget) in enumerate(zip(all_cases, share, strict=True)):
            if budget:
                bar.set_postfix_str(_name(case), refresh=False)
                run_case(case, budget, max_episode_steps, np.random.default_rng([seed, k]), tally, bar)
    return {
        "seed": seed,
        "steps_budget": steps,
        "max_episode_steps": max_episode_steps,
        "cases": len(all_cases),
        **tally.totals,
        "seconds": round(time.perf_counter() - start, 1),
        "episode_ends": dict(sorted(tally.ends.items())),
        "episodes_per_strategy": tally.strategies,
        "exception_samples": tally.exception_samples,
        "violation_samples": tally.violation_samples,
        "per_case": tally.cases,
    }


def failed(summary: dict) -> bool:
    """Whether the run found a bug: an exception, a non-finite value or a contract violation."""
    keys = ("exceptions", "non_finite_obs", "non_finite_reward", "non_finite_info", "violations")
    return any(summary[k] for k in keys)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=5000, help="env steps in all, shared by the cases")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-episode-steps", type=int, default=200, help="steps before the fuzzer resets")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)
    if args.steps < 1:
        parser.error(f"--steps must be positive, got {args.steps}")
    if args.max_episode_steps < 1:
        parser.error(f"--max-episode-steps must be positive, got {args.max_episode_steps}")
    summary = fuzz(args.steps, args.seed, args.max_episode_steps, progress=not args.no_progress)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key in ("cases", "steps", "episodes", "exceptions", "non_finite_obs", "non_finite_reward",
                    "non_finite_info", "violations", "divergences", "seconds"):
            print(f"{key:>18s}  {summary[key]}")
        print(f"{'episode_ends':>18s}  {summary['episode_ends']}")
        for sample in summary["exception_samples"] + summary["violation_samples"]:
            print(json.dumps(sample))
    return 1 if failed(summary) else 0


if __name__ == "__main__":
    sys.exit(main())
