"""Per-id env classes and their documentation, generated from the task class at registration.

:func:`env_class` makes the env class of one registered id (a subclass of
:class:`~suture_gym.envs.base.SutureEnv` or :class:`~suture_gym.envs.base.SutureGoalEnv` that adds nothing but
its docstring), so ``help(env.unwrapped)`` shows a Gymnasium-MuJoCo-v5-style page: Action Space, Observation
Space (every index with its unit, default config), Rewards (each term's formula and default weight), Starting
State, Episode End and Arguments. The text is built from the task class (its docstring, ``TERMS`` and their
``term_<name>`` docstrings, ``PHASES``, ``MAX_EPISODE_STEPS``) and its default config, so it cannot drift from
what the env does.
"""

from __future__ import annotations

import inspect
from dataclasses import fields

from suture_gym.envs.simulation import PHASE_SETTLE_STEPS
from suture_gym.tasks.base import Task

#: Section titles of the generated docstrings, in order.
SECTIONS = (
    "Action Space", "Observation Space", "Rewards", "Starting State", "Episode End", "Arguments", "Version History",
)  # fmt: skip


def _section(title: str, lines: list[str]) -> list[str]:
    return ["", title, "-" * len(title), *lines]


def _action_lines(config) -> list[str]:
    a = config.action
    return [
        "``Box(-1, 1, (6,), float32)``; an action that is not real numbers raises TypeError naming its dtype, a "
        "non-finite one ValueError; finite ones outside the box are clipped to it (acted on and penalised as the "
        "box's edge).",
        f"* ``wrench`` (default ``action.mode = {a.mode!r}``): ``[force (3) N, torque (3) N m]`` on the needle "
        f"holder = action times ``({a.max_force} N x3, {a.max_torque} N m x3)``, world frame, torque about the "
        "grip point, held over the env step.",
        f"* ``pose_delta``: the holder's target moves by ``action[:3] * {a.max_translation}`` m and turns by the "
        f"rotation vector ``action[3:] * {a.max_rotation}`` rad per step; a virtual coupling "
        f"({a.coupling_linear_stiffness} N/m, {a.coupling_angular_stiffness} N m/rad) pulls the needle to it.",
        f"One env step is ``solver.substeps = {config.solver.substeps}`` substeps of ``solver.dt = "
        f"{config.solver.dt}`` s.",
    ]


def _observation_lines(task: type[Task], config, goal_conditioned: bool) -> list[str]:
    from suture_gym.envs.spaces import observation_layout, observation_size, observation_table

    layout = observation_layout(config)
    size = observation_size(layout)
    head = f"``Box(-bound, bound, ({size},), float32)`` with the default config (positions relative to the current "
    head += "planned arc's centre; thread samples, ``pose_delta`` and ``observation.privileged`` add entries, the "
    head += "randomisation's settings none). Each entry is its raw value (in ``unit``) divided by ``scale`` and "
    head += "clipped to ``[-bound, bound]``; ``observation.scaled: false`` gives the raw SI values (``Box(-inf, "
    head += "inf)``):"
    rule = "=====  ==============================  =======  ==========  ======  ==================================="
    lines = [head, "", rule, "index  name                            unit     scale       bound   description", rule]
    for index, name, unit, scale, bound, description in observation_table(layout):
        lines.append(f"{index:<5d}  {name:<30s}  {unit:<7s}  {scale:<10.4g}  {bound:<6.4g}  {description}")
    lines.append(rule)
    if goal_conditioned:
        goal = ", ".join(f"{name} ({unit})" for name, unit in task.GOAL_LAYOUT)
        lines += ["", f"Goal-conditioned: ``Dict(observation=<the above>, achieved_goal=Box({task.GOAL_SIZE}), "
                  f"desired_goal=Box({task.GOAL_SIZE}))``, goal entries: {goal}."]
    return lines + ["", _sensor_text(config, goal_conditioned)]


def _sensor_text(config, goal_conditioned: bool) -> str:
    """The paragraph on the pixel and point-cloud modes, with the default config's camera and point counts."""
    from suture_gym.envs.spaces import POINT_CLOUD_BOUND

    obs = config.observation
    cam, pc = obs.camera, obs.point_cloud
    thread = (f" + {pc.suture} on the thread's centreline (swage to free end)" if config.suture.node_count else
              f" (+ ``point_cloud.suture = {pc.suture}`` on the thread's centreline in a scene with a thread)")
    beside = ("added beside ``observation``, ``achieved_goal`` and ``desired_goal``" if goal_conditioned else
              "with the vector above as ``state`` unless ``observation.include_state`` is false")
    return (
        f"Visual observations: ``observation.mode`` (default ``{obs.mode!r}``, the vector above) ``'rgb'``, "
        "``'depth'``, ``'rgbd'`` or ``'point_cloud'`` gives a ``Dict`` of ``rgb`` ``Box(0, 255, (H, W, 3), "
        "uint8)`` (the tissue, needle, thread and the planned entry/exit markers, no caption or gauge) and/or "
        f"``depth`` ``Box(0, far, (H, W, 1), float32)`` (m along the camera's optical axis to the nearest tissue, "
        f"needle or thread surface; ``far = {cam.far}`` m where there is none), from a camera fixed when the env is "
        f"built (``observation.camera``: H x W = {cam.height} x {cam.width} px, rendered without supersampling, "
        f"``fov_y = {cam.fov_y}`` deg, its eye along ``direction = {list(cam.direction)}`` from the centre of "
        "the tissue and the needle's start from the distance that frames them, unless ``look_at``, ``eye`` or "
        f"``distance`` say otherwise); or ``point_cloud`` ``Box(-{POINT_CLOUD_BOUND:g}, {POINT_CLOUD_BOUND:g}, (N, "
        "3), float32)`` (m, world frame) whose rows are, in order, "
        f"``point_cloud.tissue = {pc.tissue}`` fixed material points on the tissue surface, "
        f"``point_cloud.needle = {pc.needle}`` on the needle's centreline (tip to swage){thread}; {beside} "
        "(:mod:`suture_gym.envs.sensors`)."
    )


def _reward_lines(task: type[Task], config, goal_conditioned: bool) -> list[str]:
    weights = {f.name: getattr(config.reward, f.name) for f in fields(config.reward)}
    lines = ["The reward is ``math.fsum`` of the terms below, each reported as ``info['reward_<term>']``; "
             "``w_<term>`` is the ``reward.<term>`` weight (default in brackets)."]
    terms = task.GOAL_TERMS if goal_conditioned else task.TERMS
    for name in terms:
        if name == "goal":
            doc = ("sparse ``-1`` until the goal is reached, else 0 (``reward.goal = 'dense'``: minus the task's "
                   "goal distance in [0, 1)); recomputed by ``compute_reward`` for relabelled goals.")
        else:
            doc = " ".join(inspect.getdoc(getattr(task, f"term_{name}")).split())
        weight = f" [{weights[name]}]" if name in weights else ""
        lines.append(f"* ``{name}``{weight}: {doc}")
    return lines


def _start_lines(task: type[Task], config) -> list[str]:
    lines = [f"``reset(options={{'phase': ...}})`` picks the start phase (default ``{task.PHASES[0]!r}``):"]
    for phase in task.PHASES:
        lines.append(f"* ``{phase}``: {task.PHASE_DOCS.get(phase, 'see the task class')}.")
    if len(task.PHASES) > 1:
        lines.append("A phase past the first is simulated once per process on the nominal parameters (seconds to "
                     "minutes) and then reused: a copy for the nominal physics, else carried over to the episode's "
                     f"tissue and settled for {PHASE_SETTLE_STEPS} env steps; the needle's start offsets act only on "
                     "the approach.")
    lines.append("Domain randomisation (``randomization``) samples the tissue stiffness, puncture force, wound gap "
                 "and the needle's start pose at every reset, from the env's seed; ``randomization.enabled: false`` "
                 "gives the nominal episode.")
    return lines


def _end_lines(task: type[Task], config) -> list[str]:
    seconds = task.MAX_EPISODE_STEPS * config.solver.dt * config.solver.substeps
    return [
        "``terminated`` on success; on failure: the tip leaves the workspace (the tissue's box grown by "
        f"``termination.workspace_margin = {config.termination.workspace_margin}`` m), a tear (a row holding the "
        f"needle or thread in the tissue at ``coupling.tear_force = {config.coupling.tear_force}`` N, with "
        "``termination.end_on_tear``), "
        "(flat ids of tasks that need every stitch on the plan, with ``termination.end_on_miss``) a stitch "
        "entered or exited off the plan, or a divergence of the simulation (a non-finite state, a speed above "
        f"``solver.max_speed = {config.solver.max_speed}`` m/s, or a non-finite observation or reward): "
        "``info['diverged'] = True``, the last finite observation, ``-w_failure`` and the banked progress handed "
        "back, every other term 0.",
        f"``truncated`` at the time limit, {task.MAX_EPISODE_STEPS} steps ({seconds:g} s with the default "
        "config).",
        "After ``terminated``, ``step`` raises RuntimeError until ``reset``.",
    ]


def _argument_lines(task: type[Task]) -> list[str]:
    return [
        "``gym.make(id, config=None, render_mode=None, action_mode=None)``:",
        "* ``config``: None (the task's defaults), an ``EnvConfig``, a nested mapping of overrides or the path of "
        "a YAML file of them, or the name of a shipped one (``suture_gym/configs/envs/<name>.yaml``); unknown "
        "keys and bad values raise ValueError naming the dotted key. The task's defaults: "
        f"``default_config({task.NAME!r})``.",
        "* ``render_mode``: None, ``'rgb_array'`` (images) or ``'human'`` (a live 3D view in the browser, viser; "
        "``render.viewer_host``/``viewer_port``).",
        "* ``action_mode``: ``'wrench'`` or ``'pose_delta'``, overriding ``action.mode``.",
    ]


def env_docstring(task: type[Task], goal_conditioned: bool) -> str:
    """The docstring of the env class of ``task`` (flat or goal-conditioned), from the task class and its
    default config."""
    from suture_gym.envs.config import default_config

    config = default_config(task.NAME)
    env_id = task.GOAL_ENV_ID if goal_conditioned else task.ENV_ID
    lines = [f"``{env_id}``: {inspect.getdoc(task)}"]
    lines += _section("Action Space", _action_lines(config))
    lines += _section("Observation Space", _observation_lines(task, config, goal_conditioned))
    lines += _section("Rewards", _reward_lines(task, config, goal_conditioned))
    lines += _section("Starting State", _start_lines(task, config))
    lines += _section("Episode End", _end_lines(task, config))
    lines += _section("Arguments", _argument_lines(task))
    lines += _section("Version History", [f"* {line}" for line in task.VERSION_HISTORY] or ["* the first version."])
    return "\n".join(lines) + "\n"


def env_class(task: type[Task], goal_conditioned: bool) -> type:
    """The env class of ``task``'s flat (or goal-conditioned) id: ``<Task>Env`` (``<Task>GoalEnv``), a subclass
    of :class:`~suture_gym.envs.base.SutureEnv` (:class:`~suture_gym.envs.base.SutureGoalEnv`) whose docstring
    is :func:`env_docstring` and whose default task is ``task``."""
    from suture_gym.envs.base import SutureEnv, SutureGoalEnv

    base = SutureGoalEnv if goal_conditioned else SutureEnv
    name = task.__name__ + ("GoalEnv" if goal_conditioned else "Env")
    namespace = {"__doc__": env_docstring(task, goal_conditioned), "__qualname__": name, "TASK": task.NAME}
    return type(name, (base,), namespace)
