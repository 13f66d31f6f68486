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
* ``extreme``: random signs times magnitudes from 1 to 1e300 (outside the box: the env clips them);
* ``scripted_abort``: the scripted surgeon (:class:`~suture_gym.baselines.surgeon.ScriptedSurgeon`) for ``k``
  steps, ``k`` uniform in ``[0, episode length)``, then one abort held to the end: ``push`` (full force down,
  into the tissue), ``pull`` (full force up), ``twist`` (full torque about a random axis, either sense) or
  ``yank`` (full force along a random corner's direction) -- the states a policy that learnt the procedure
  could then drive the tissue into.

Every episode's return (the sum of its rewards) is kept; ``failure_return_max`` is the largest return of any
episode that ended in a failure (a tear, the tip out of the workspace, a miss, a divergence), with its reproducer
and how it ended: a failure should never pay more than nothing.

Counted: exceptions from ``reset`` or ``step`` (the first few with their traceback), non-finite
observations, rewards and ``info`` numbers, contract violations (an observation outside its space, a reward that
is not the exact sum of its terms, a step after ``terminated`` that the env did not refuse), divergences and how
episodes ended. Exits 1 if there was any exception, non-finite value, violation or divergence (every action acts
in the box, and in-box actions must never diverge), or if an episode that ended in a failure returned more than 0,
else 0.

Every event (exception, non-finite value, violation, divergence) is listed in ``events`` with its reproducer:
the env id, config file, action mode, strategy, the episode's seed and the step (1-based within the episode).
Each episode's env is reset with that seed and its actions are drawn from ``np.random.default_rng([seed, 1])``,
so one event replays alone::

    python scripts/fuzz.py --replay '{"id": "SutureGym/NeedleInsert-v3", "config": "needle_insert.yaml",
        "action_mode": "wrench", "strategy": "random", "seed": 123, "step": 45}'

(any event object of the JSON works, as a string or ``@file.json``); it plays the episode up to that step and
prints what happened there as JSON, exiting 1 if the event happened again. ``--only`` restricts a run to the
cases whose name (``"<id> <action mode> <config>"``) contains each given string, keeping each case's random
stream, so a long hunt on one case finds what the full run would.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
import traceback
from dataclasses import dataclass
from pathlib import Path

from _common import configure

configure(threads=1)

import gymnasium as gym  # noqa: E402
import numpy as np  # noqa: E402
import yaml  # noqa: E402
from tqdm import tqdm  # noqa: E402

from suture_gym.baselines.evaluation import episode_end  # noqa: E402
from suture_gym.configs import ENV_DIR  # noqa: E402
from suture_gym.envs import ENV_IDS, GOAL_ENV_IDS  # noqa: E402
from suture_gym.envs.config import ACTION_MODES  # noqa: E402

#: Action strategies, one per episode (module docstring).
STRATEGIES = ("random", "corner", "bang_bang", "tiny", "extreme", "scripted_abort")
#: The aborts of ``scripted_abort``, each a constant action in the box.
ABORTS = ("push", "pull", "twist", "yank")
#: How an episode ends that counts as a failure (:func:`_end_reason`).
FAILURE_ENDS = ("tear", "out_of_workspace", "missed", "diverged", "crushed", "terminated")
#: Exceptions reported with their traceback (the rest are counted, and listed in ``events``).
EXCEPTION_SAMPLES = 10
#: Events listed with their reproducers (the rest are counted).
EVENT_SAMPLES = 1000
#: The ``info`` entries that must be finite numbers.
FINITE_INFO = ("tip_force", "haptic_wrench", "wound_gap", "cost")


CONFIG_DIR = ENV_DIR


def cases(config_dir: Path = CONFIG_DIR) -> list[dict]:
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


def abort_action(abort: str, rng: np.random.Generator) -> np.ndarray:
    """The constant ``(6,)`` action of ``abort`` (one of :data:`ABORTS`), its random axis or signs from ``rng``."""
    action = np.zeros(6)
    if abort == "push":
        action[2] = -1.0
    elif abort == "pull":
        action[2] = 1.0
    elif abort == "twist":
        action[3 + int(rng.integers(3))] = rng.choice([-1.0, 1.0])
    elif abort == "yank":
        action[:3] = rng.choice([-1.0, 1.0], size=3)
    else:
        raise ValueError(f"abort must be one of {ABORTS}, got {abort!r}")
    return action


class ActionStream:
    """The actions of one episode under ``strategy``, drawn from ``rng``; ``env`` (reset for the episode) and
    ``length`` (its steps) are what ``scripted_abort`` needs: the surgeon acts on the env's state and the abort
    starts within the episode."""

    def __init__(self, strategy: str, rng: np.random.Generator, env: gym.Env | None = None, length: int = 1) -> None:
        self.strategy = strategy
        self.rng = rng
        self.held = self._corner()
        self.hold_left = 0
        if strategy == "scripted_abort":
            from suture_gym.baselines.surgeon import ScriptedSurgeon

            self.surgeon = ScriptedSurgeon(env)
            self.scripted_left = int(rng.integers(max(1, length)))
            self.abort = ABORTS[int(rng.integers(len(ABORTS)))]
            self.held = abort_action(self.abort, rng)

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
        if self.strategy == "scripted_abort":
            if self.scripted_left > 0:
                self.scripted_left -= 1
                return self.surgeon(None)
            return self.held.astype(np.float32)
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
    """Counts of one fuzz run, overall and in each case's record (``{"case": name, "steps": ..., ...}``), and the
    events with their reproducers."""

    def __init__(self) -> None:
        self.totals = dict(steps=0, episodes=0, exceptions=0, non_finite_obs=0, non_finite_reward=0,
                           non_finite_info=0, violations=0, divergences=0)
        self.ends: dict[str, int] = {}
        self.strategies = dict.fromkeys(STRATEGIES, 0)
        self.exception_samples: list[dict] = []
        self.events: list[dict] = []
        self.cases: list[dict] = []
        #: The failure ending with the largest return: ``{"return", "reason", "abort", **reproducer}``, or None.
        self.failure_return_max: dict | None = None

    def add(self, key: str, record: dict, count: int = 1) -> None:
        self.totals[key] += count
        record[key] = record.get(key, 0) + count

    def event(self, kind: str, record: dict, episode: Episode, step: int, **details) -> None:
        """Count an event of ``kind`` (a key of :attr:`totals`) at ``step`` (1-based; 0 for ``make`` and
        ``reset``) of ``episode`` and list it with its reproducer."""
        self.add(kind, record)
        if len(self.events) < EVENT_SAMPLES:
            self.events.append({"kind": kind, **episode.reproducer(), "step": step, **details})

    def exception(self, record: dict, episode: Episode, where: str, step: int, error: BaseException) -> None:
        details = {"where": where, "type": type(error).__name__, "message": str(error)[:500]}
        self.event("exceptions", record, episode, step, **details)
        if len(self.exception_samples) < EXCEPTION_SAMPLES:
            self.exception_samples.append({**episode.reproducer(), "step": step, **details,
                                           "traceback": traceback.format_exc(limit=-4)[-2000:]})

    def end(self, reason: str) -> None:
        self.ends[reason] = self.ends.get(reason, 0) + 1

    def episode_return(self, episode: Episode, step: int, total: float, reason: str, actions: ActionStream) -> None:
        """Keep the episode's return ``total`` if it ended (at ``step``) in a failure paying more than any so far."""
        if reason in FAILURE_ENDS and (self.failure_return_max is None or total > self.failure_return_max["return"]):
            self.failure_return_max = {"return": total, "reason": reason, "abort": getattr(actions, "abort", None),
                                       **episode.reproducer(), "step": step}


@dataclass(frozen=True)
class Episode:
    """One fuzz episode: the env reset with ``seed`` and the actions of ``strategy`` drawn from
    ``np.random.default_rng([seed, 1])``; with the case, all it takes to replay it (:func:`replay`). ``seed`` is
    None (and ``strategy`` empty) for the env's construction, before any episode; ``max_episode_steps`` is the
    run's cap (``scripted_abort`` draws its abort step below it)."""

    case: dict
    strategy: str
    seed: int | None
    max_episode_steps: int = 200

    def actions(self, env: gym.Env | None = None) -> ActionStream:
        """The episode's actions (``env`` reset with :attr:`seed`)."""
        return ActionStream(self.strategy, np.random.default_rng([self.seed, 1]), env, self.max_episode_steps)

    def reproducer(self) -> dict:
        c = self.case
        return {"id": c["id"], "config": c["config"], "action_mode": c["action_mode"], "strategy": self.strategy,
                "seed": self.seed, "max_episode_steps": self.max_episode_steps}


def _name(case: dict) -> str:
    return f"{case['id']} {case['action_mode']} {case['config']}"


def _end_reason(info: dict, terminated: bool) -> str:
    return episode_end(info, terminated, not terminated)


def _make(case: dict) -> gym.Env:
    return gym.make(case["id"], config=case["path"], action_mode=case["action_mode"])


def _check_step(env: gym.Env, obs, reward: float, info: dict) -> list[tuple[str, dict]]:
    """The events of one step: ``(kind, details)`` for each non-finite value, violation and divergence."""
    found = []
    if not _finite(obs):
        found.append(("non_finite_obs", {}))
    if not math.isfinite(reward):
        found.append(("non_finite_reward", {"reward": repr(reward)}))
    bad = [key for key in FINITE_INFO if not _finite(info[key])]
    if bad:
        found.append(("non_finite_info", {"keys": bad}))
    found.extend(("violations", {"what": what}) for what in _contract_violations(env, obs, reward, info))
    if info["diverged"]:
        found.append(("divergences", {}))
    return found


def run_case(case: dict, steps: int, max_episode_steps: int, rng: np.random.Generator, tally: Tally,
             bar: tqdm) -> None:
    """Play ``steps`` env steps of ``case``, counting into ``tally`` (and its per-case record); ``rng`` draws
    each episode's seed and strategy."""
    record = {"case": _name(case), "steps": 0, "episodes": 0}
    tally.cases.append(record)
    try:
        env = _make(case)
    except Exception as error:
        tally.exception(record, Episode(case, "", None, max_episode_steps), "make", 0, error)
        bar.update(steps)
        return
    done_steps = 0
    while done_steps < steps:
        episode = Episode(case, STRATEGIES[int(rng.integers(len(STRATEGIES)))], int(rng.integers(2**31)),
                          max_episode_steps)
        try:
            env.reset(seed=episode.seed)
        except Exception as error:
            tally.exception(record, episode, "reset", 0, error)
            bar.update(steps - done_steps)
            break
        length = min(max_episode_steps, steps - done_steps)
        actions = episode.actions(env)
        tally.strategies[episode.strategy] += 1
        tally.add("episodes", record)
        total = 0.0
        for step in range(1, length + 1):
            done_steps += 1
            tally.add("steps", record)
            bar.update(1)
            try:
                obs, reward, terminated, truncated, info = env.step(actions())
            except Exception as error:
                tally.exception(record, episode, "step", step, error)
                break
            for kind, details in _check_step(env, obs, reward, info):
                tally.event(kind, record, episode, step, **details)
            total += float(reward)
            if terminated or truncated:
                tally.end(_end_reason(info, terminated))
                tally.episode_return(episode, step, total, _end_reason(info, terminated), actions)
                if terminated:
                    try:
                        env.step(actions())
                        tally.event("violations", record, episode, step + 1,
                                    what="a step after terminated was not refused")
                    except RuntimeError:
                        pass
                break
        else:
            tally.end("fuzz_episode_cap")
    env.close()


def select(all_cases: list[dict], only: list[str] | None) -> list[tuple[int, dict]]:
    """``(index in all_cases, case)`` of the cases whose name contains every string of ``only`` (all if None);
    ValueError if none does."""
    chosen = [(k, c) for k, c in enumerate(all_cases) if not only or all(o in _name(c) for o in only)]
    if not chosen:
        raise ValueError(f"no case matches {only}; cases: {[_name(c) for c in all_cases]}")
    return chosen


def fuzz(steps: int, seed: int = 0, max_episode_steps: int = 200, progress: bool = True,
         only: list[str] | None = None) -> dict:
    """Fuzz every case (or those :func:`select` picks with ``only``) for a shared budget of ``steps`` env steps;
    returns the summary (module docstring). Case ``k`` of :func:`cases` draws from
    ``np.random.default_rng([seed, k])`` whatever ``only`` picks."""
    chosen = select(cases(), only)
    share = [steps // len(chosen) + (1 if k < steps % len(chosen) else 0) for k in range(len(chosen))]
    tally = Tally()
    start = time.perf_counter()
    with tqdm(total=steps, desc="fuzz", unit="step", file=sys.stderr, disable=None if progress else True) as bar:
        for (k, case), budget in zip(chosen, share, strict=True):
            if budget:
                bar.set_postfix_str(_name(case), refresh=False)
                run_case(case, budget, max_episode_steps, np.random.default_rng([seed, k]), tally, bar)
    return {
        "seed": seed,
        "steps_budget": steps,
        "max_episode_steps": max_episode_steps,
        "only": only,
        "cases": len(chosen),
        **tally.totals,
        "seconds": round(time.perf_counter() - start, 1),
        "episode_ends": dict(sorted(tally.ends.items())),
        "failure_return_max": tally.failure_return_max,
        "episodes_per_strategy": tally.strategies,
        "events": tally.events,
        "events_left_out": sum(tally.totals[k] for k in FAILURES) - len(tally.events),
        "exception_samples": tally.exception_samples,
        "per_case": tally.cases,
    }


def replay(event: dict, config_dir: Path = CONFIG_DIR) -> dict:
    """Play the episode of ``event`` (a reproducer from a run's ``events``: ``id``, ``config`` (a file of
    ``config_dir`` or a path), ``action_mode``, ``strategy``, ``seed``, ``step``) up to its step and return what
    happened there: ``{**reproducer, "events": [{kind, ...details}], "return": the episode's return up to that
    step, "reproduced": bool}``, ``reproduced`` when
    an event of the same ``kind`` (if the event names one) happened at that step."""
    missing = [k for k in ("id", "config", "action_mode", "strategy", "seed", "step") if k not in event]
    if missing:
        raise ValueError(f"the event lacks {missing} (it needs id, config, action_mode, strategy, seed, step)")
    if event["step"] > 0 and (event["strategy"] not in STRATEGIES or event["seed"] is None):
        raise ValueError(f"a step past 0 needs a strategy of {STRATEGIES} and a seed, got strategy "
                         f"{event['strategy']!r} and seed {event['seed']!r}")
    path = Path(event["config"])
    case = {"id": event["id"], "action_mode": event["action_mode"], "config": event["config"],
            "path": path if path.is_file() else config_dir / path}
    episode = Episode(case, event["strategy"], None if event["seed"] is None else int(event["seed"]),
                      int(event.get("max_episode_steps", 200)))
    step = int(event["step"])
    found: list[dict] = []
    total = 0.0
    try:
        env = _make(case)
        if episode.seed is not None:
            env.reset(seed=episode.seed)
            actions = episode.actions(env)
        for k in range(1, step + 1):
            obs, reward, terminated, truncated, info = env.step(actions())
            total += float(reward)
            if k == step:
                found = [{"kind": kind, **details} for kind, details in _check_step(env, obs, reward, info)]
                found.append({"kind": "end", "terminated": terminated, "truncated": truncated,
                              "reason": _end_reason(info, terminated) if terminated or truncated else None})
            elif terminated or truncated:
                found = [{"kind": "ended_before", "step": k, "reason": _end_reason(info, terminated)}]
                break
    except Exception as error:
        found = [{"kind": "exceptions", "type": type(error).__name__, "message": str(error)[:500]}]
    kinds = {f["kind"] for f in found}
    reproduced = event["kind"] in kinds if "kind" in event else bool(kinds & set(FAILURES))
    return {**episode.reproducer(), "step": step, "events": found, "return": total, "reproduced": reproduced}


#: The counts of which any makes a run fail.
FAILURES = ("exceptions", "non_finite_obs", "non_finite_reward", "non_finite_info", "violations", "divergences")


def failed(summary: dict) -> bool:
    """Whether the run found a bug: an exception, a non-finite value, a contract violation, a divergence, or a
    failure ending with a positive return."""
    worst = summary["failure_return_max"]
    return any(summary[k] for k in FAILURES) or (worst is not None and worst["return"] > 0.0)


def _load_event(text: str) -> dict:
    if text.startswith("@"):
        text = Path(text[1:]).read_text()
    try:
        event = json.loads(text)
    except json.JSONDecodeError as error:
        raise ValueError(f"--replay takes an event as JSON (or @file.json): {error}") from None
    if not isinstance(event, dict):
        raise ValueError(f"--replay takes one event object, got {type(event).__name__}")
    return event


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--steps", type=int, default=5000, help="env steps in all, shared by the cases")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--max-episode-steps", type=int, default=200, help="steps before the fuzzer resets")
    parser.add_argument("--only", nargs="+", metavar="TEXT", help="only the cases whose name contains each TEXT")
    parser.add_argument("--replay", metavar="EVENT", help="replay one event (JSON or @file.json) and exit")
    parser.add_argument("--json", action="store_true", help="print the summary as JSON")
    parser.add_argument("--no-progress", action="store_true", help="no progress bar on stderr")
    args = parser.parse_args(argv)
    if args.replay is not None:
        try:
            result = replay(_load_event(args.replay))
        except ValueError as error:
            parser.error(str(error))
        print(json.dumps(result, indent=2))
        return 1 if result["reproduced"] else 0
    if args.steps < 1:
        parser.error(f"--steps must be positive, got {args.steps}")
    if args.max_episode_steps < 1:
        parser.error(f"--max-episode-steps must be positive, got {args.max_episode_steps}")
    try:
        select(cases(), args.only)
    except ValueError as error:
        parser.error(str(error))
    summary = fuzz(args.steps, args.seed, args.max_episode_steps, progress=not args.no_progress, only=args.only)
    if args.json:
        print(json.dumps(summary, indent=2))
    else:
        for key in ("cases", "steps", "episodes", *FAILURES, "seconds"):
            print(f"{key:>18s}  {summary[key]}")
        print(f"{'episode_ends':>18s}  {summary['episode_ends']}")
        print(f"{'failure_return_max':>18s}  {json.dumps(summary['failure_return_max'])}")
        for event in summary["events"]:
            print(json.dumps(event))
    return 1 if failed(summary) else 0


if __name__ == "__main__":
    sys.exit(main())
