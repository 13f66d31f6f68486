"""The whole env config (:class:`EnvConfig`), a task's defaults, and overrides from YAML files or mappings."""

from __future__ import annotations

import os
import re
import types
import typing
from dataclasses import dataclass, field, fields, is_dataclass, replace
from typing import Any

from suture_gym.configs import env_config_path
from suture_gym.envs.config.checks import _fail, _field_types
from suture_gym.envs.config.physics import (
    CouplingConfig,
    NeedleConfig,
    SceneConfig,
    SolverConfig,
    SutureConfig,
    TissueConfig,
)
from suture_gym.envs.config.sensing import ObservationConfig, RenderConfig
from suture_gym.envs.config.task import ActionConfig, PlanConfig, RandomizationConfig, RewardConfig, TerminationConfig
from suture_gym.envs.registry import task_class
from suture_gym.sim.mesh import BYTES_PER_TET_IMPLICIT, BYTES_PER_TET_XPBD, check_tet_budget


@dataclass(frozen=True)
class EnvConfig:
    """Everything an environment needs; see each section's class for its fields and units."""

    task: str = "needle_insert"
    tissue: TissueConfig = field(default_factory=TissueConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    needle: NeedleConfig = field(default_factory=NeedleConfig)
    suture: SutureConfig = field(default_factory=SutureConfig)
    coupling: CouplingConfig = field(default_factory=CouplingConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    action: ActionConfig = field(default_factory=ActionConfig)
    plan: PlanConfig = field(default_factory=PlanConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    termination: TerminationConfig = field(default_factory=TerminationConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    #: The task's own section (an instance of its class's ``PARAMS``; None: its defaults, or none).
    task_params: Any = None

    def __post_init__(self) -> None:
        cls = task_class(self.task)
        if cls.PARAMS is None:
            if self.task_params is not None:
                _fail("task_params", f"must be empty: task {self.task!r} has no parameters of its own")
        elif self.task_params is None:
            object.__setattr__(self, "task_params", cls.PARAMS())
        elif type(self.task_params) is not cls.PARAMS:
            _fail("task_params", f"must be a {cls.PARAMS.__name__}, got {type(self.task_params).__name__}")
        for f in fields(self):
            section = getattr(self, f.name)
            if f.name not in ("task", "task_params") and type(section) is not _field_types(EnvConfig)[f.name]:
                _fail(f.name, f"must be a {_field_types(EnvConfig)[f.name].__name__}, got {type(section).__name__}")
        scene = self.scene
        implicit = self.solver.tissue_integrator != "xpbd"
        if not implicit and self.tissue.poisson_ratio >= 0.5:
            _fail("tissue.poisson_ratio", f"= {self.tissue.poisson_ratio:g} (incompressible) with "
                  "solver.tissue_integrator = 'xpbd': the tets' volume constraint is then rigid and the tissue "
                  "diverges within a few steps; use tissue.poisson_ratio <= 0.49")
        check_tet_budget(scene.tets, f"scene.cell_size = {scene.cell_size:g} m over scene.size = {list(scene.size)} m",
                         scene.max_tets, "scene.max_tets", BYTES_PER_TET_IMPLICIT if implicit else BYTES_PER_TET_XPBD)
        noise, margin = self.randomization.needle_position_noise, self.termination.workspace_margin
        if noise >= margin:
            _fail("randomization.needle_position_noise", f"= {noise} m must be below termination.workspace_margin = "
                  f"{margin} m, or the needle can start outside the workspace")
        cls.check_config(self)


def default_config(task: str) -> EnvConfig:
    """The defaults of the registered ``task``: the typed defaults overridden by the task class's ``CONFIG``
    (what the registered ids use)."""
    return apply_overrides(EnvConfig(), {"task": task, **task_class(task).CONFIG})


def _coerce(path: str, value: Any, kind: Any, current: Any) -> Any:
    """``value`` converted to the field type ``kind`` (nested dataclasses merge into ``current``)."""
    if is_dataclass(kind):
        if not isinstance(value, dict):
            _fail(path, f"must be a mapping of {kind.__name__} fields, got {type(value).__name__}")
        return _merge(path + ".", current, value)
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        return _coerce_union(path, value, typing.get_args(kind))
    if origin is tuple:
        args = typing.get_args(kind)
        if len(args) == 2 and args[1] is Ellipsis:  # tuple[X, ...]: any length
            if not isinstance(value, (list, tuple)):
                _fail(path, f"must be a list, got {value!r}")
            return tuple(_coerce(f"{path}[{k}]", v, args[0], None) for k, v in enumerate(value))
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            _fail(path, f"must be a list of {len(args)} numbers, got {value!r}")
        return tuple(_coerce(f"{path}[{k}]", v, a, None) for k, (v, a) in enumerate(zip(value, args, strict=True)))
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            _fail(path, f"must be a number, got {value!r}")
        return float(value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            _fail(path, f"must be an integer, got {value!r}")
        return value
    if kind is bool:
        if not isinstance(value, bool):
            _fail(path, f"must be true or false, got {value!r}")
        return value
    if kind is str:
        if not isinstance(value, str):
            _fail(path, f"must be a string, got {value!r}")
        return value
    raise TypeError(f"{path}: unsupported config field type {kind!r}")


def _coerce_union(path: str, value: Any, kinds: tuple) -> Any:
    """``value`` as the first of ``kinds`` it converts to (ValueError naming ``path`` if none)."""
    for kind in kinds:
        try:
            return _coerce(path, value, kind, None)
        except ValueError:
            continue
    _fail(path, f"must be one of {[getattr(k, '__name__', str(k)) for k in kinds]}, got {value!r}")


def _named(prefix: str, cls: type, error: ValueError, changed) -> ValueError:
    """``error`` raised by a section's own checks (a simulator dataclass's), renamed after its dotted key:
    ``<prefix><field>: <message>`` with the field the message names, the ``changed`` ones first."""
    message = str(error)
    if not prefix or message.startswith(prefix) or message.startswith("unknown config key"):
        return error
    candidates = [*changed, *(f.name for f in fields(cls) if f.name not in changed)]
    named = [name for name in candidates if re.search(rf"\b{name}\b", message)]
    key = prefix + named[0] if named else prefix.rstrip(".")
    return ValueError(f"{key}: {message}")


def _merge(prefix: str, base: Any, overrides: dict) -> Any:
    """A copy of dataclass ``base`` with ``overrides`` applied; unknown keys raise ValueError naming them."""
    types = _field_types(type(base))
    unknown = sorted(str(k) for k in overrides if k not in types)
    if unknown:
        names = ", ".join(f"'{prefix}{k}'" for k in unknown)
        raise ValueError(f"unknown config key(s) {names}; known keys here: {sorted(types)}")
    changes = {key: _coerce(prefix + key, value, types[key], getattr(base, key))
               for key, value in overrides.items() if key != "task_params"}
    if isinstance(base, EnvConfig):
        changes["task_params"] = _task_params(base, changes.get("task", base.task), overrides)
    try:
        return replace(base, **changes)
    except ValueError as error:
        raise _named(prefix, type(base), error, list(overrides)) from None


def _task_params(base: EnvConfig, task: str, overrides: dict) -> Any:
    """The ``task_params`` section of ``task`` after ``overrides``: the task class's ``PARAMS`` (kept from
    ``base`` when the task does not change) with ``overrides["task_params"]`` merged in."""
    params_cls = task_class(task).PARAMS
    value = overrides.get("task_params")
    if params_cls is None:
        if value:
            _fail("task_params", f"must be empty: task {task!r} has no parameters of its own")
        return None
    current = base.task_params if task == base.task and base.task_params is not None else params_cls()
    if value is None:
        return current
    if not isinstance(value, dict):
        _fail("task_params", f"must be a mapping of {params_cls.__name__} fields, got {type(value).__name__}")
    try:
        return _merge("task_params.", current, value)
    except ValueError as error:
        raise ValueError(f"task_params ({task}): {error}") from None


def apply_overrides(config: EnvConfig, overrides: dict) -> EnvConfig:
    """``config`` with the nested mapping ``overrides`` applied (validated; unknown keys raise ValueError)."""
    if not isinstance(overrides, dict):
        raise ValueError(f"config overrides must be a mapping, got {type(overrides).__name__}")
    return _merge("", config, overrides)


def read_yaml(path: str | os.PathLike) -> dict:
    """The mapping stored in the YAML file ``path`` (an empty file is an empty mapping)."""
    import yaml

    with open(path, encoding="utf-8") as stream:
        data = yaml.safe_load(stream)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"{path} must hold a mapping of config sections, got {type(data).__name__}")
    return data


def load_config(task: str, source: EnvConfig | dict | str | os.PathLike | None = None) -> EnvConfig:
    """The config of ``task``: its defaults, overridden by ``source``.

    Args:
        task: a registered task (:func:`~suture_gym.envs.registry.registered_tasks`).
        source: None (defaults), an :class:`EnvConfig` (used as is; its ``task`` must match), a nested mapping,
            the path of a YAML file holding one, or the name of a shipped one (:mod:`suture_gym.configs`). A ``task``
            key, if present, must name ``task``.

    Raises:
        ValueError: unknown keys (named by dotted path), wrong types, out-of-range values, or a task mismatch.
    """
    if isinstance(source, EnvConfig):
        config = source
    else:
        overrides = {}
        if isinstance(source, (str, os.PathLike)):
            overrides = read_yaml(env_config_path(source))
        elif isinstance(source, dict):
            overrides = source
        elif source is not None:
            kind = type(source).__name__
            raise ValueError(f"config must be None, an EnvConfig, a mapping or a YAML path, got {kind}")
        config = apply_overrides(default_config(task), overrides)
    if config.task != task:
        raise ValueError(f"config task is {config.task!r} but the environment is {task!r}")
    return config


def config_to_dict(config: Any) -> dict:
    """The config as plain nested dicts, lists and scalars (JSON/YAML-serialisable)."""

    def plain(value):
        if is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in fields(value)}
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return value

    return plain(config)


def save_config(config: EnvConfig, path: str | os.PathLike) -> None:
    """Write the resolved ``config`` to ``path`` as YAML (load it back with :func:`load_config`)."""
    import yaml

    with open(path, "w", encoding="utf-8") as stream:
        yaml.safe_dump(config_to_dict(config), stream, sort_keys=False)
