"""Typed configuration of the suturing environments; YAML files only override the typed defaults.

An :class:`EnvConfig` is a tree of frozen dataclasses. The physical sections are the simulator's own parameter
dataclasses (``tissue`` is a :class:`~suture_gym.sim.model.TissueMaterial`, ``needle`` a
:class:`~suture_gym.sim.needle.NeedleShape`, ``suture`` a :class:`~suture_gym.sim.rod.SutureParams`,
``coupling`` a :class:`~suture_gym.sim.coupling.CouplingParams`, ``solver`` a
:class:`~suture_gym.sim.solver.Solver`, subclassed with the few env-scale defaults that differ and the env-only
fields), so every simulator parameter is settable from YAML and has one default.

:func:`default_config` gives the defaults of a task (the
values the registered ids use); :func:`load_config` applies overrides from a YAML file, a mapping or another
config on top of them. Every key of an override must name a field: an unknown key raises ValueError naming its
dotted path (``reward.puncture_bonus``), so a typo never passes silently. :func:`config_to_dict` gives the
resolved config as plain data, to save with every run.

Units are SI throughout (m, kg, s, N, Pa, rad); each field's comment states its unit.
"""

from suture_gym.envs.config.checks import sim_fields
from suture_gym.envs.config.loading import (
    EnvConfig,
    apply_overrides,
    config_to_dict,
    default_config,
    load_config,
    read_yaml,
    save_config,
)
from suture_gym.envs.config.physics import (
    MAX_DT,
    SCENE_KINDS,
    CouplingConfig,
    IncisionConfig,
    NeedleConfig,
    SceneConfig,
    SolverConfig,
    SutureConfig,
    TissueConfig,
)
from suture_gym.envs.config.sensing import (
    OBSERVATION_MODES,
    CameraConfig,
    ObservationConfig,
    PointCloudConfig,
    RenderConfig,
)
from suture_gym.envs.config.task import (
    ACTION_FRAMES,
    ACTION_MODES,
    GOAL_REWARDS,
    ActionConfig,
    PlanConfig,
    RandomizationConfig,
    RewardConfig,
    TerminationConfig,
)

__all__ = [
    "ACTION_FRAMES",
    "ACTION_MODES",
    "GOAL_REWARDS",
    "MAX_DT",
    "OBSERVATION_MODES",
    "SCENE_KINDS",
    "ActionConfig",
    "CameraConfig",
    "CouplingConfig",
    "EnvConfig",
    "IncisionConfig",
    "NeedleConfig",
    "ObservationConfig",
    "PlanConfig",
    "PointCloudConfig",
    "RandomizationConfig",
    "RenderConfig",
    "RewardConfig",
    "SceneConfig",
    "SolverConfig",
    "SutureConfig",
    "TerminationConfig",
    "TissueConfig",
    "apply_overrides",
    "config_to_dict",
    "default_config",
    "load_config",
    "read_yaml",
    "save_config",
    "sim_fields",
]
