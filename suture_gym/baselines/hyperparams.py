"""rl-zoo-style agent configuration: ``suture_gym/configs/agents/<algo>.yml``, one top-level key per env id.

Conventions (as in rl-baselines3-zoo, without its ``eval()``):

- ``n_timesteps`` (int, env steps), ``policy`` (SB3 policy name), ``n_envs`` (int), ``normalize`` (bool or
  a mapping of ``VecNormalize`` keyword arguments), ``env_kwargs`` (mapping passed to ``gym.make``; ``config`` is a
  YAML path or the name of a shipped env config, :func:`suture_gym.configs.env_config_path`), ``behaviour_cloning``
  (mapping: warm start from the scripted expert, see :data:`BC_KEYS` and :mod:`suture_gym.baselines.imitation`),
  ``dagger`` (mapping,
  ``configs/agents/dagger.yml`` only: see :data:`suture_gym.baselines.dagger.DAGGER_KEYS`), and any keyword argument of
  the algorithm's constructor
  (PPO's for ``dagger``, whose learner is a PPO model).
- Schedules are strings ``lin_<value>`` (linear decay from ``value`` to 0 over training).
- ``policy_kwargs`` is a mapping; ``activation_fn`` names a torch module (``tanh``, ``relu``, ``elu``,
  ``leaky_relu``); ``net_arch`` is a list or a dict ``{pi: [...], vf: [...]}`` / ``{pi: [...], qf: [...]}``.
- ``replay_buffer_class: HerReplayBuffer`` with ``replay_buffer_kwargs`` selects HER for goal-conditioned envs.
- Top-level keys starting with ``_`` hold shared settings for YAML anchors (``<<: *name``); they are not env ids.
"""

from __future__ import annotations

import copy
from pathlib import Path
from typing import Any

import yaml

from suture_gym.configs import AGENT_DIR as CONFIG_DIR
from suture_gym.configs import env_config_path

#: Keys consumed by the training script rather than passed to the algorithm.
SCRIPT_KEYS = ("n_timesteps", "policy", "n_envs", "normalize", "env_kwargs", "behaviour_cloning", "dagger")
#: Keys of ``behaviour_cloning`` and their defaults: expert episodes recorded (env seeds ``seed + 2000 ...``),
#: passes over them, minibatch size, Adam step size, and ``dataset``: the id of a Minari dataset of the same env
#: id to clone instead of recording (:func:`suture_gym.baselines.imitation.load_minari_demos`; looked up in
#: ``$MINARI_DATASETS_PATH``, else ``~/.minari/datasets``); ``expert`` and ``action_noise``: the recording's
#: scripted expert and the noise added to the actions it executes
#: (:func:`suture_gym.baselines.expert.expert_episodes`).
BC_KEYS = {"expert_episodes": 40, "epochs": 30, "batch_size": 256, "learning_rate": 1e-3, "dataset": None,
           "expert": "clock", "action_noise": 0.0}

_ACTIVATIONS = ("tanh", "relu", "elu", "leaky_relu")


def algorithms() -> list[str]:
    """Algorithm names with a config file (``ppo``, ``sac``, ``tqc`` ...)."""
    return sorted(p.stem for p in CONFIG_DIR.glob("*.yml"))


def load_hyperparams(algo: str, env_id: str, config_dir: Path = CONFIG_DIR) -> dict[str, Any]:
    """The raw hyperparameters of ``algo`` for ``env_id`` (a deep copy of the YAML mapping).

    Raises:
        ValueError: no config file for ``algo``, or no entry for ``env_id`` in it (the message lists the
            algorithms / env ids that exist).
    """
    path = Path(config_dir) / f"{algo}.yml"
    if not path.exists():
        raise ValueError(f"no agent config for algo {algo!r}; known: {algorithms()}")
    with open(path) as fh:
        table = {key: value for key, value in (yaml.safe_load(fh) or {}).items() if not key.startswith("_")}
    if env_id not in table:
        raise ValueError(f"{path.name} has no entry for env {env_id!r}; it has {sorted(table)}")
    return copy.deepcopy(table[env_id])


def resolve(hyperparams: dict[str, Any]) -> tuple[dict[str, Any], dict[str, Any]]:
    """Split hyperparameters into (script settings, algorithm keyword arguments) with schedules and
    policy keyword arguments turned into Python objects. The input is left unchanged.
    """
    from stable_baselines3.common.utils import LinearSchedule

    params = copy.deepcopy(hyperparams)
    script = {key: params.pop(key) for key in SCRIPT_KEYS if key in params}
    if "policy" not in script:
        raise ValueError("agent config needs a 'policy' (e.g. MlpPolicy or MultiInputPolicy)")
    if "n_timesteps" not in script:
        raise ValueError("agent config needs 'n_timesteps' (total env steps)")
    if "behaviour_cloning" in script:
        script["behaviour_cloning"] = _behaviour_cloning(script["behaviour_cloning"])
    if "dagger" in script:
        from suture_gym.baselines.dagger import dagger_settings

        script["dagger"] = dagger_settings(script["dagger"])
    env_kwargs = script.get("env_kwargs") or {}
    if not isinstance(env_kwargs, dict):
        raise ValueError(f"env_kwargs must be a mapping, got {type(env_kwargs).__name__}")
    if isinstance(env_kwargs.get("config"), str):
        script["env_kwargs"] = {**env_kwargs, "config": str(env_config_path(env_kwargs["config"]).resolve())}
    for key, value in list(params.items()):
        if isinstance(value, str) and value.startswith("lin_"):
            start = _number(value[4:], key)
            params[key] = LinearSchedule(start, 0.0, 1.0)
    if "policy_kwargs" in params:
        params["policy_kwargs"] = _policy_kwargs(params["policy_kwargs"])
    if "replay_buffer_class" in params:
        name = params["replay_buffer_class"]
        if name != "HerReplayBuffer":
            raise ValueError(f"replay_buffer_class must be 'HerReplayBuffer' if given, got {name!r}")
        from stable_baselines3 import HerReplayBuffer

        params["replay_buffer_class"] = HerReplayBuffer
    return script, params


def _behaviour_cloning(value: Any) -> dict[str, Any]:
    if not isinstance(value, dict):
        raise ValueError(f"behaviour_cloning must be a mapping of {sorted(BC_KEYS)}, got {value!r}")
    unknown = sorted(set(value) - set(BC_KEYS))
    if unknown:
        raise ValueError(f"behaviour_cloning has unknown keys {unknown}; known: {sorted(BC_KEYS)}")
    out = {**BC_KEYS, **value}
    for key in ("expert_episodes", "epochs", "batch_size"):
        if isinstance(out[key], bool) or not isinstance(out[key], int) or out[key] < 1:
            raise ValueError(f"behaviour_cloning.{key} must be an integer >= 1, got {out[key]!r}")
    if not isinstance(out["learning_rate"], (int, float)) or not out["learning_rate"] > 0:
        raise ValueError(f"behaviour_cloning.learning_rate must be > 0, got {out['learning_rate']!r}")
    if out["expert"] not in ("clock", "feedback"):
        raise ValueError(f"behaviour_cloning.expert must be 'clock' or 'feedback', got {out['expert']!r}")
    noise = out["action_noise"]
    if isinstance(noise, bool) or not isinstance(noise, (int, float)) or not 0.0 <= noise < 1.0:
        raise ValueError(f"behaviour_cloning.action_noise must be a standard deviation in [0, 1), got {noise!r}")
    if out["dataset"] is not None and not (isinstance(out["dataset"], str) and out["dataset"]):
        raise ValueError(f"behaviour_cloning.dataset must be a Minari dataset id, got {out['dataset']!r}")
    return out


def _number(text: str, key: str) -> float:
    try:
        return float(text)
    except ValueError as exc:
        raise ValueError(f"{key}: schedule 'lin_{text}' needs a number after 'lin_'") from exc


def _policy_kwargs(kwargs: Any) -> dict[str, Any]:
    if not isinstance(kwargs, dict):
        raise ValueError(f"policy_kwargs must be a mapping (no strings to eval), got {type(kwargs).__name__}")
    out = dict(kwargs)
    if "activation_fn" in out:
        import torch.nn as nn

        name = out["activation_fn"]
        table = {"tanh": nn.Tanh, "relu": nn.ReLU, "elu": nn.ELU, "leaky_relu": nn.LeakyReLU}
        if name not in table:
            raise ValueError(f"policy_kwargs.activation_fn must be one of {_ACTIVATIONS}, got {name!r}")
        out["activation_fn"] = table[name]
    return out
