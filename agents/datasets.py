"""Demonstrations as Minari datasets, the Farama standard for offline RL (``pip install 'suture_gym[data]'``).

A dataset is written by :func:`agents.expert.record_minari` (the scripted expert) and read back for behaviour
cloning by :func:`agents.imitation.load_minari_demos`; any Minari user reads it with
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
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

#: Per-step ``info`` entries recorded in a SutureGym dataset: name -> (value when absent, dtype). ``tip_force``
#: is the needle tip's force (N), ``cost`` the tissue-force cost (>= 0), ``is_success`` the task's success flag.
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
    so datasets of different physics never share an id), e.g. ``suture_gym/NeedleInsert-v2/expert-v0``."""
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
