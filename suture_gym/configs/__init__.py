"""The shipped configurations, installed with the package.

* ``envs/<name>.yaml``: env config overrides (the keys of :class:`~suture_gym.envs.config.EnvConfig`), passed to
  ``gym.make(id, config=...)`` by name (``config="needle_insert_deterministic"``) or by path;
* ``agents/<algo>.yml``: rl-zoo-style agent hyperparameters, one top-level key per env id
  (:mod:`suture_gym.baselines.hyperparams`).

This module reads files only; it imports nothing else of the package.
"""

from __future__ import annotations

import os
from pathlib import Path

#: Folder of the env configs (``<name>.yaml``).
ENV_DIR = Path(__file__).resolve().parent / "envs"
#: Folder of the agent configs (``<algo>.yml``).
AGENT_DIR = Path(__file__).resolve().parent / "agents"


def env_config_names() -> list[str]:
    """The names of the shipped env configs (``needle_insert``, ``wound_closure_paper`` ...), sorted."""
    return sorted(p.stem for p in ENV_DIR.glob("*.yaml"))


def env_config_path(source: str | os.PathLike) -> Path:
    """The YAML file that ``source`` names: an existing file path, or the name of a shipped env config (with or
    without ``.yaml``, or as ``configs/envs/<name>.yaml``, the repository-relative path of earlier releases).

    Raises:
        ValueError: ``source`` is neither an existing file nor a shipped config's name (the message lists them).
    """
    path = Path(source)
    if path.is_file():
        return path
    name = path.name[: -len(".yaml")] if path.name.endswith(".yaml") else path.name
    shipped = ENV_DIR / f"{name}.yaml"
    if path.parent.as_posix() in (".", "configs/envs") and shipped.is_file():
        return shipped
    raise ValueError(f"env config {str(source)!r} is neither a file nor a shipped config; the shipped ones are "
                     f"{env_config_names()}")
