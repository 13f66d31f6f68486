"""Demonstrations as Minari datasets, the Farama standard for offline RL (``pip install 'suture_gym[data]'``).

A dataset is written by :func:`write_minari` from :class:`RecordedEpisode` records: the scripted expert's
(:func:`suture_gym.baselines.expert.record_minari`) or a human's teleoperated ones (:mod:`suture_gym.viewer`). It is
read back for behaviour cloning by :func:`suture_gym.baselines.imitation.load_minari_demos`; any Minari user reads it
with
``minari.load_dataset(dataset_id)`` (and rebuilds the env with ``dataset.recover_environment()`` after
``import suture_gym``).

Where datasets live: the ``root`` argument when given, else ``$MINARI_DATASETS_PATH``, else Minari's default
``~/.minari/datasets``; a dataset is the folder ``<root>/<dataset_id>/`` (HDF5 data and metadata). Minari itself
reads only the environment variable, so a ``root`` given here is passed to it by setting that variable for the
duration of the call (:func:`minari_root`; not thread-safe).

Every step of a SutureGym dataset records, besides Minari's observations, actions, rewards, terminations and
truncations, the infos of :data:`INFO_KEYS`; the reset's are recorded too (Minari stores ``T + 1`` infos and
observations per episode of ``T`` steps). The env seed of each episode is Minari's own ``seed`` field.
"""

from __future__ import annotations

import os
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

#: Per-step ``info`` entries recorded in a SutureGym dataset: name -> (value when absent, dtype). ``tip_force``
#: is the needle tip's force (N), ``cost`` the tissue-force cost (>= 0), ``is_success`` the task's success flag.
#: The info key under which a dataset stores the demonstrator's chosen action of each step, ``(T + 1, A)``
#: float32 (the reset's row zero), where the action taken differs from it (noise added to it).
EXPERT_ACTION_KEY = "expert_action"
INFO_KEYS: dict[str, tuple[object, type]] = {
    "tip_force": (0.0, np.float64),
    "cost": (0.0, np.float64),
    "is_success": (False, np.bool_),
}


def datasets_root(root: str | Path | None = None) -> Path:
    """The folder datasets are written to and read from: ``root``, else ``$MINARI_DATASETS_PATH``, else
    ``~/.minari/datasets`` (Minari's default)."""
    if root is not None:
        return Path(root)
    env = os.environ.get("MINARI_DATASETS_PATH")
    return Path(env) if env else Path.home() / ".minari" / "datasets"


@contextmanager
def minari_root(root: str | Path | None) -> Iterator[Path]:
    """Point Minari at :func:`datasets_root` ``(root)`` while the block runs (sets ``MINARI_DATASETS_PATH``, then
    restores it); yields that folder."""
    folder = datasets_root(root)
    before = os.environ.get("MINARI_DATASETS_PATH")
    os.environ["MINARI_DATASETS_PATH"] = str(folder)
    try:
        yield folder
    finally:
        if before is None:
            del os.environ["MINARI_DATASETS_PATH"]
        else:
            os.environ["MINARI_DATASETS_PATH"] = before


def default_dataset_id(env_id: str, name: str = "expert") -> str:
    """Minari id ``suture_gym/<Task>-v<k>/<name>-v0`` of a dataset of ``env_id`` (the env id's version kept,
    so datasets of different physics never share an id), e.g. ``suture_gym/NeedleInsert-v3/expert-v0``."""
    return f"suture_gym/{env_id.split('/')[-1]}/{name}-v0"


def load_dataset(dataset_id: str, root: str | Path | None = None):
    """The :class:`minari.MinariDataset` ``dataset_id`` under :func:`datasets_root` ``(root)``.

    Raises:
        FileNotFoundError: no such dataset there; the message names the id and the folder and lists the datasets
            it holds.
    """
    import minari

    with minari_root(root) as folder:
        if not (folder / dataset_id / "data").is_dir():
            known = sorted(minari.list_local_datasets()) if folder.is_dir() else []
            raise FileNotFoundError(f"no Minari dataset {dataset_id!r} in {str(folder)!r}; it holds {known}")
        return minari.load_dataset(dataset_id)


@dataclass
class RecordedEpisode:
    """One recorded episode of ``T`` steps: ``reset_obs``/``reset_info`` from ``env.reset(seed=seed)``, then per
    step the action taken, the observation, reward, flags and info ``env.step`` returned; ``expert_actions``,
    when recorded, the action the demonstrator chose at each step (it differs from the one taken when noise was
    added to it; :func:`~suture_gym.baselines.expert.expert_episodes`)."""

    seed: int
    reset_obs: object
    reset_info: dict
    actions: list[np.ndarray] = field(default_factory=list)
    observations: list = field(default_factory=list)
    rewards: list[float] = field(default_factory=list)
    terminated: list[bool] = field(default_factory=list)
    truncated: list[bool] = field(default_factory=list)
    infos: list[dict] = field(default_factory=list)
    expert_actions: list[np.ndarray] = field(default_factory=list)


def write_minari(dataset_id: str, episodes: Sequence[RecordedEpisode], env, root: str | Path | None = None,
                 algorithm_name: str | None = None, description: str | None = None, author: str | None = None,
                 author_email: str | None = None, code_permalink: str | None = None) -> Path:
    """Write ``episodes`` as the Minari dataset ``dataset_id`` under :func:`datasets_root` ``(root)``.

    Each episode holds Minari's ``observations`` (``T + 1``: the reset's, then each step's), ``actions (T, A)
    float32``, ``rewards``, ``terminations``, ``truncations``, the infos of :data:`INFO_KEYS` (``T + 1``), the
    demonstrator's own actions as the info :data:`EXPERT_ACTION_KEY` (``T + 1``, the reset's row zero) when the
    episodes record them, and its env seed. ``env`` (made by ``gym.make``) gives the recorded env spec, so
    ``dataset.recover_environment()`` rebuilds it after ``import suture_gym``; its ``env_kwargs`` must then be
    JSON data (a config path, not an ``EnvConfig``). ``algorithm_name``, ``description``, ``author``,
    ``author_email`` and ``code_permalink`` go to the dataset's metadata. Needs ``pip install 'suture_gym[data]'``.

    Raises:
        ValueError: no episode, an episode without a step, or a dataset ``dataset_id`` exists there already
            (Minari never overwrites one).

    Returns:
        The datasets folder written to.
    """
    import minari
    from minari.data_collector import EpisodeBuffer

    if not episodes:
        raise ValueError(f"no episode to write to the Minari dataset {dataset_id!r}")
    buffers = []
    for k, episode in enumerate(episodes):
        if not episode.actions:
            raise ValueError(f"episode {k} (env seed {episode.seed}) has no step")
        infos = [episode.reset_info, *episode.infos]
        columns = {key: np.asarray([i.get(key, default) for i in infos], dtype=dtype)
                   for key, (default, dtype) in INFO_KEYS.items()}
        if episode.expert_actions:
            chosen = np.asarray(episode.expert_actions, dtype=np.float32)
            columns[EXPERT_ACTION_KEY] = np.concatenate([np.zeros_like(chosen[:1]), chosen])
        buffers.append(EpisodeBuffer(
            id=k, seed=episode.seed, observations=_stack([episode.reset_obs, *episode.observations]),
            actions=np.asarray(episode.actions, dtype=np.float32), rewards=episode.rewards,
            terminations=episode.terminated, truncations=episode.truncated, infos=columns))
    with minari_root(root) as folder:
        minari.create_dataset_from_buffers(
            dataset_id, buffers, env=env, eval_env=env, algorithm_name=algorithm_name, author=author,
            author_email=author_email, code_permalink=code_permalink, description=description)
    return folder


def _stack(observations: list):
    """``(T + 1, D) float32`` of flat observations, or a dict of such arrays for Dict observations."""
    if isinstance(observations[0], dict):
        return {key: np.asarray([o[key] for o in observations], dtype=np.float32) for key in observations[0]}
    return np.asarray(observations, dtype=np.float32)
