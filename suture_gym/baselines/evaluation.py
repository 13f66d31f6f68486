"""Evaluate a policy on a Gymnasium env id: random, the scripted expert, or a saved SB3 model.

The summary's fields (docs/usage.md, "Training and evaluating baselines"): ``success_rate, mean_return,
mean_episode_length, mean_tip_force, mean_final_gap`` (plus spreads and the per-episode records).
``tip_force`` (N) and ``wound_gap`` (m) are read from the env's ``info``; envs that do not report them give
``None``.
"""

from __future__ import annotations

import json
import math
import warnings
from collections.abc import Callable
from dataclasses import asdict, dataclass
from pathlib import Path

import gymnasium as gym
import numpy as np

from suture_gym.baselines.workers import worker_pool


@dataclass
class Episode:
    """One evaluated episode: return, length (env steps), success, mean |tip force| (N), the largest force of the
    haptic reaction on the needle (``|info["haptic_wrench"][:3]|``, N), final gap (m), and how it ended
    (:func:`episode_end`)."""

    seed: int
    episode_return: float
    length: int
    success: bool
    mean_tip_force: float
    max_haptic_force: float
    final_gap: float
    truncated: bool
    diverged: bool
    end: str


#: Why an episode ended, in the order :func:`episode_end` checks the last step's ``info``.
#: Policy names that are not saved models: a random policy, the scripted expert and its feedback variant
#: (:class:`suture_gym.baselines.expert.FeedbackExpert`, DAgger's oracle).
SCRIPTED = ("random", "expert", "feedback_expert")
ENDS = ("success", "diverged", "crushed", "tear", "out_of_workspace", "missed", "time_limit", "terminated")


def episode_end(info: dict, terminated: bool, truncated: bool) -> str:
    """One of :data:`ENDS` for an episode whose last step returned ``info``, ``terminated``, ``truncated``:
    the SutureGym flags first (``is_success``, ``diverged``, ``crushed``, ``tear``, ``out_of_workspace``,
    ``missed``), then
    ``time_limit`` for a truncation, else ``terminated`` (an env without those flags)."""
    for name, key in (("success", "is_success"), ("diverged", "diverged"), ("crushed", "crushed"),
                      ("tear", "tear"), ("out_of_workspace", "out_of_workspace"), ("missed", "missed")):
        if info.get(key, False):
            return name
    return "time_limit" if truncated and not terminated else "terminated"


def make_policy(policy: str, env: gym.Env, seed: int,
                vecnormalize: str | Path | None = None) -> Callable[[object], np.ndarray]:
    """A callable ``obs -> action`` for ``policy``: ``random``, ``expert``, ``feedback_expert`` or a path to an
    SB3 ``.zip``.

    ``vecnormalize`` is the path of the ``VecNormalize`` statistics a saved model's observations are normalised
    with (see :func:`model_vecnormalize`); None: the model sees raw observations.
    """
    if policy in SCRIPTED and vecnormalize is not None:
        raise ValueError(f"VecNormalize statistics apply to a saved model, not to policy {policy!r}")
    if policy == "random":
        space = env.action_space
        space.seed(seed)
        return lambda obs: space.sample()
    if policy == "expert":
        from suture_gym.baselines.expert import ExpertPolicy

        return ExpertPolicy(env)
    if policy == "feedback_expert":
        from suture_gym.baselines.expert import FeedbackExpert

        return FeedbackExpert(env)
    return _saved_model_policy(Path(policy), env, vecnormalize)


def model_vecnormalize(policy: str, vecnormalize: str | Path | None = None) -> Path | None:
    """The ``VecNormalize`` statistics to evaluate the saved model ``policy`` with.

    ``vecnormalize`` given: that file (FileNotFoundError naming it if it does not exist). Otherwise the
    statistics saved with the model: a checkpoint's ``model_vecnormalize_<N>_steps.pkl`` beside
    ``model_<N>_steps.zip``, a ``best_model.zip``'s ``best_vecnormalize.pkl`` (DAgger writes one, its statistics
    being the best checkpoint's), else ``final_vecnormalize.pkl`` beside the model. When neither exists the model is
    evaluated on raw observations, with a ``UserWarning`` unless the model's run config says it was trained
    without normalisation (a model trained with it acts on meaningless inputs without its statistics).
    ``random`` and ``expert`` take none (None).
    """
    if vecnormalize is not None:
        path = Path(vecnormalize)
        if not path.is_file():
            raise FileNotFoundError(f"VecNormalize statistics {str(path)!r} do not exist")
        return path
    if policy in SCRIPTED:
        return None
    from suture_gym.baselines.training import _sibling

    model = Path(policy)
    if not model.exists():
        return None  # make_policy names the missing model
    found = _sibling(model, "vecnormalize", ".pkl")
    best = model.parent / "best_vecnormalize.pkl"
    if found is None and model.name == "best_model.zip" and best.is_file():
        found = best
    final = model.parent / "final_vecnormalize.pkl"
    if found is None and final.is_file():
        found = final
    if found is None:
        hyperparams = run_config(model).get("hyperparams")
        if hyperparams is None or hyperparams.get("normalize"):
            why = "its run config says it was" if hyperparams else "it has no run config.yaml to say whether it was"
            warnings.warn(f"no VecNormalize statistics found for {str(model)!r} (looked for its checkpoint's "
                          f"model_vecnormalize_<N>_steps.pkl and {str(final)!r}) and {why} trained with "
                          "VecNormalize: evaluating on raw observations; pass the statistics with --vecnormalize "
                          "PATH", UserWarning, stacklevel=2)
    return found


def run_config(model_path: str | Path) -> dict:
    """The ``config.yaml`` of the run a saved model belongs to (beside it, or one up for a checkpoint in
    ``<run>/checkpoints/``) as a mapping; ``{}`` when there is none."""
    import yaml

    model_path = Path(model_path)
    for folder in (model_path.parent, model_path.parent.parent):
        if (folder / "config.yaml").exists():
            return yaml.safe_load((folder / "config.yaml").read_text()) or {}
    return {}


def _saved_model_policy(path: Path, env: gym.Env, vecnormalize: Path | None) -> Callable[[object], np.ndarray]:
    from suture_gym.baselines.training import ALGOS, algo_class

    if not path.exists():
        raise FileNotFoundError(f"policy {str(path)!r} is neither 'random', 'expert' nor an existing model file")
    algo = run_config(path).get("algo")
    from stable_baselines3.common.vec_env import DummyVecEnv

    candidates = [algo] if algo else list(ALGOS)
    vec_env = DummyVecEnv([lambda: env])  # HER needs an env to load; wrapped here, SB3 prints nothing to stdout
    model = None
    for name in candidates:
        try:
            model = algo_class(name).load(path, env=vec_env, device="cpu")
            break
        except (ValueError, KeyError, RuntimeError, TypeError, AssertionError):
            continue
    if model is None:
        raise ValueError(f"{str(path)!r} is not a model of any of {candidates}")
    normalizer = None
    if vecnormalize is not None:
        import pickle

        with open(vecnormalize, "rb") as fh:
            normalizer = pickle.load(fh)

    def act(obs):
        if normalizer is not None:
            obs = normalizer.normalize_obs(obs)
        action, _ = model.predict(obs, deterministic=True)
        return action

    return act


def trained_env_kwargs(policy: str) -> dict:
    """``env_kwargs`` a saved model was trained with (from its :func:`run_config`, relative config paths
    resolved); ``{}`` for ``random``, ``expert`` or a model without one."""
    from suture_gym.baselines.hyperparams import resolve

    if policy in SCRIPTED:
        return {}
    hyperparams = run_config(policy).get("hyperparams")
    if not hyperparams:
        return {}
    return dict(resolve(hyperparams)[0].get("env_kwargs") or {})


def evaluate(
    env_id: str,
    policy: str,
    episodes: int,
    seed: int = 0,
    env_kwargs: dict | None = None,
    progress: bool = False,
    records_path: str | Path | None = None,
    vecnormalize: str | Path | None = None,
    workers: int = 1,
) -> dict:
    """Run ``episodes`` episodes (env seeds ``seed, seed + 1, ...``) and summarise them.

    A saved model is evaluated on the env it was trained on: the ``env_kwargs`` of its run's ``config.yaml``
    (the env config, say) apply unless ``env_kwargs`` overrides them; and with the ``VecNormalize`` statistics
    ``vecnormalize``, by default those saved with it (:func:`model_vecnormalize`, which warns when there are none).
    Episode ``k`` depends on ``seed + k`` alone (the random policy's actions are seeded with it too), so the
    summary is the same whichever process runs it.

    With ``records_path``, each episode's record is appended to that file as one JSON line as soon as the episode
    ends, so a long evaluation that is interrupted keeps what it measured.

    ``workers`` > 1 runs the episodes on that many processes (each builds its env and policy once and takes the
    next episode when it is done; one numba and torch thread each): the same summary, about ``workers`` times
    sooner on as many free cores.

    Returns:
        ``{env_id, env_kwargs, policy, vecnormalize, episodes, seed, success_rate, success_rate_stderr, mean_return,
        std_return, mean_episode_length, mean_tip_force, max_haptic_force (N, over all episodes),
        median_max_haptic_force (N, the median of each episode's largest), mean_final_gap, diverged_episodes,
        end_counts, per_episode}``; ``end_counts`` counts the episodes by how they ended (:data:`ENDS`, zeros left out).
    """
    if episodes <= 0:
        raise ValueError(f"episodes must be positive, got {episodes}")
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    env_kwargs = {**trained_env_kwargs(policy), **(env_kwargs or {})}
    stats = model_vecnormalize(policy, vecnormalize)
    seeds = range(seed, seed + episodes)
    if workers == 1:
        runner = _EpisodeRunner(env_id, policy, env_kwargs, stats)
        done = map(runner, seeds)
    else:
        pool = worker_pool(min(workers, episodes), _start_worker, (env_id, policy, env_kwargs, stats))
        done = _as_completed(pool, seeds)
    if progress:
        from tqdm import tqdm

        done = tqdm(done, total=episodes, desc=f"evaluate {policy}", unit="episode")
    records: list[Episode] = []
    try:
        for record in done:
            records.append(record)
            if records_path is not None:
                with open(records_path, "a") as fh:
                    fh.write(json.dumps({"env_id": env_id, "policy": policy, **asdict(record)}) + "\n")
    finally:
        if workers == 1:
            runner.close()
        else:
            pool.shutdown(cancel_futures=True)
    records.sort(key=lambda r: r.seed)
    successes = np.array([r.success for r in records], dtype=float)
    returns = np.array([r.episode_return for r in records])
    return {
        "env_id": env_id,
        "env_kwargs": {k: v for k, v in env_kwargs.items() if isinstance(v, (str, int, float, bool))},
        "policy": policy,
        "vecnormalize": None if stats is None else str(stats),
        "episodes": episodes,
        "seed": seed,
        "success_rate": float(successes.mean()),
        "success_rate_stderr": float(successes.std(ddof=1) / math.sqrt(episodes)) if episodes > 1 else None,
        "mean_return": float(returns.mean()),
        "std_return": float(returns.std()),
        "mean_episode_length": float(np.mean([r.length for r in records])),
        "mean_tip_force": _nanmean([r.mean_tip_force for r in records]),
        "max_haptic_force": float(max(r.max_haptic_force for r in records)),
        "median_max_haptic_force": float(np.median([r.max_haptic_force for r in records])),
        "mean_final_gap": _nanmean([r.final_gap for r in records]),
        "diverged_episodes": int(sum(r.diverged for r in records)),
        "end_counts": {name: count for name in ENDS if (count := sum(r.end == name for r in records))},
        "per_episode": [asdict(r) for r in records],
    }


class _EpisodeRunner:
    """Runs single episodes of one env id and policy: ``runner(env_seed) -> Episode``. Builds the env and the
    policy once (a random policy is re-seeded with each episode's env seed)."""

    def __init__(self, env_id: str, policy: str, env_kwargs: dict, vecnormalize: Path | None):
        import suture_gym  # noqa: F401  (registers the SutureGym ids)

        self.policy = policy
        self.env = gym.make(env_id, **env_kwargs)
        self.act = make_policy(policy, self.env, 0, vecnormalize)

    def __call__(self, env_seed: int) -> Episode:
        env = self.env
        if self.policy == "random":
            env.action_space.seed(env_seed)
        obs, info = env.reset(seed=env_seed)
        if hasattr(self.act, "reset"):
            self.act.reset()
        total, length, forces, haptic, done = 0.0, 0, [], 0.0, False
        terminated = truncated = False
        while not done:
            obs, reward, terminated, truncated, info = env.step(self.act(obs))
            total += float(reward)
            length += 1
            if "tip_force" in info:
                forces.append(abs(float(info["tip_force"])))
            if "haptic_wrench" in info:
                haptic = max(haptic, float(np.linalg.norm(info["haptic_wrench"][:3])))
            done = terminated or truncated
        return Episode(
            seed=env_seed,
            episode_return=total,
            length=length,
            success=bool(info.get("is_success", False)),
            mean_tip_force=float(np.mean(forces)) if forces else math.nan,
            max_haptic_force=haptic,
            final_gap=float(info.get("wound_gap", math.nan)),
            truncated=bool(truncated),
            diverged=bool(info.get("diverged", False)),
            end=episode_end(info, terminated, truncated),
        )

    def close(self) -> None:
        self.env.close()


#: The :class:`_EpisodeRunner` of an evaluation worker process (set by :func:`_start_worker`).
_WORKER_RUNNER: _EpisodeRunner | None = None


def _start_worker(env_id: str, policy: str, env_kwargs: dict, vecnormalize: Path | None) -> None:
    global _WORKER_RUNNER
    _WORKER_RUNNER = _EpisodeRunner(env_id, policy, env_kwargs, vecnormalize)


def _worker_episode(env_seed: int) -> Episode:
    return _WORKER_RUNNER(env_seed)


def _as_completed(pool, seeds: range):
    """The episodes of ``seeds`` run on ``pool``, yielded as they finish."""
    from concurrent.futures import as_completed

    futures = [pool.submit(_worker_episode, s) for s in seeds]
    for future in as_completed(futures):
        yield future.result()


def _nanmean(values: list[float]) -> float | None:
    finite = [v for v in values if math.isfinite(v)]
    return float(np.mean(finite)) if finite else None
