"""What a task reads (:class:`Observables`), and the machinery shared by the tasks: named reward terms that sum
exactly to the reward, events (punctures, exits), stitch bookkeeping, success, failure and goals.

During an episode a task never steps the physics: the simulation facade hands it an :class:`Observables`
snapshot (copies of plain arrays, SI units) after every env step, and it returns the reward terms and the episode
flags (only its ``start_phase`` hook drives the simulation, through :mod:`suture_gym.tasks.surgeon`). A task is
the unit of extension: one class declares its env id, time limit and config defaults (``ENV_ID``,
``MAX_EPISODE_STEPS``, ``CONFIG``, an optional section of its own, ``PARAMS``), its reward terms (one
``term_<name>(ctx)`` method per name in ``TERMS``, reading the :class:`StepContext` of the step), its config
check, episode initialisation (``initial_suture``, ``start_phase``) and termination (``success``, ``failure``); one
:func:`~suture_gym.envs.registry.register_task` line registers it.

Reward terms (each reported as ``info["reward_<name>"]``; a task uses a subset, in the order of its ``TERMS``;
``w_*`` are the :class:`~suture_gym.envs.config.RewardConfig` weights):

* ``path``: ``-w_path d / (d + path_scale)`` with ``d`` the tip's distance (m) to the current planned circle,
  until the stitch's final exit (bounded in ``(-w_path, 0]``).
* ``progress``: ``w_progress (Phi' - Phi)``, potential-based shaping with ``p`` the tip's fraction of the current
  planned arc (0 at the entry, 1 at the exit) and ``Phi = stitch + clip(p, 0, c)``: ``c = 1`` while the tip is in
  the tissue; after a non-final exit of the stitch (out of the near wound face) ``c`` is the planned fraction of
  the next entry (the far face); ``Phi = stitch`` before the stitch's first puncture or while the tip is out of
  the tissue before any exit, and ``stitch + clip(p_exit, 0, 1)`` after its final exit, ``p_exit`` the fraction
  at the exit point. Progress therefore counts only along a track through the tissue: backing out through the
  entry hole, or carrying the tip round above the surface, banks nothing.
* ``entry``: once per stitch, at its first puncture: ``w_entry max(0, 1 - e / access_tolerance)``, ``e`` the
  distance (m) from the puncture to the planned entry.
* ``exit``: once per stitch, when the tip comes out through the last planned surface: same form with the
  planned exit.
* ``puncture``: at every puncture, ``+w_puncture`` the first time it lies within ``access_tolerance`` of a
  planned entry into tissue (the top entry or, over a wound, the far wound face) of the current stitch, 0 when
  that entry was punctured before (re-entering a hole), ``-w_puncture`` otherwise (an unplanned hole, or any
  puncture after the stitch's final exit).
* ``thread``: ``w_thread (min(L', T) - min(L, T)) / T`` with ``L`` the thread pulled through the current
  stitch's exit (m) and ``T = plan.thread_target``, counted after the stitch's final exit.
* ``closure``: ``w_closure (min(g, g0) - min(g', g0)) / g0``: the reduction of the mean wound gap ``g`` (m,
  never negative) this step relative to the gap at rest ``g0``, counted below ``g0`` only, so an episode's
  closure pays at most ``w_closure``.
* ``success``: ``w_success`` once, on the step the task succeeds (never with the tissue torn).
* ``failure``: ``-w_failure`` once, on the step an episode ends in failure: the tip leaves the workspace, the
  tissue tears (with ``termination.end_on_tear``), the task can no longer succeed (``termination.end_on_miss``:
  a stitch of a task that needs every stitch on the plan was entered or exited farther than ``access_tolerance``
  from it), the wound's faces pass through each other by more than :data:`WOUND_OVERLAP_LIMIT` of the rest gap
  (a crushed wound, ``info["crushed"]``), or the simulation diverges (:meth:`Task.diverged`). Without it the
  per-step penalties (``path``, ``tissue_force``) make ending an episode early pay; it cannot pay once
  ``w_failure`` exceeds the discounted sum of those penalties, ``w_path / (1 - gamma)`` for the path term.
* ``forfeit``: on the step an episode ends in failure, minus what the event and increment terms (``entry``,
  ``exit``, ``puncture``, ``thread``, ``closure``) paid over the episode, if that is positive; 0 otherwise.
  With ``progress`` handing back its potential on a failing end, an episode that ends in failure returns at
  most the sum of its penalties (``path``, ``failure``, ``tissue_force``, ``action``, unplanned punctures):
  never more than 0, whatever the actions.
* ``tissue_force``: ``-w_tissue_force cost`` with ``cost = max(0, F - safe_force) / (tear_force - safe_force)``
  and ``F`` the largest coupling force (N) of the step; ``info["cost"] = cost`` (>= 0) for safe RL.
* ``action``: ``-w_action mean(a^2)`` of the action (clipped to the action box by the env).

The reward is ``math.fsum`` of the terms, so ``math.fsum(info["reward_<t>"] for t in TERMS) == reward`` holds
exactly (``fsum`` is correctly rounded, whatever the order of the terms).
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass, field, fields
from typing import ClassVar

import numpy as np

from suture_gym.sim.anatomy import ANATOMY_KINDS
from suture_gym.sim.rod import RodModel, RodState
from suture_gym.tasks.geometry import PlannedArc


@dataclass(frozen=True)
class Observables:
    """A read-only snapshot of everything a task may read, taken after an env step (all arrays are copies).

    Attributes:
        time: simulated time, s.
        tip_pos: ``(3,) float64`` needle tip, m.
        tip_dir: ``(3,) float64`` unit direction in which the tip advances.
        needle_normal: ``(3,) float64`` unit normal of the needle's plane (the tip advances clockwise about it).
        needle_center: ``(3,) float64`` centre of the needle's circle, m.
        grip_pos: ``(3,) float64`` grip point of the holder, m.
        needle_vel: ``(3,) float64`` velocity of the needle body's centre of mass, m/s.
        needle_omega: ``(3,) float64`` angular velocity of the needle, rad/s (world frame).
        tip_sdist: signed distance of the tip to the tissue surface, m (negative inside; ``inf`` far away).
        punctured: the tip is inside the tissue along an open path.
        path_count: paths (needle tracks) currently in the tissue.
        new_entries: ``(k, 3) float64`` entry points of the punctures since the previous snapshot, as material
            points (positions in the tissue's rest shape), m.
        new_exits: ``(k, 3) float64`` points where the tip came out since the previous snapshot (material points
            in the rest shape), m.
        tip_force: force the tip exerted on the surface before puncturing, N (0 once inside).
        tissue_force: largest coupling-constraint force in the last substep, N.
        haptic_wrench: ``(6,) float64`` wrench the constraints exert on the needle, ``[N, N m]`` about the grip.
        damaged: the tissue tore (a row holding a strand in it reached the tear force); sticky.
        wound_gap: mean gap between the facing wound faces over their free upper half, m (>= 0; 0 without a
            wound or with the faces in contact or through each other).
        wound_overlap: how far the facing wound faces have passed through each other, m (>= 0: minus the mean
            gap where it is negative, else 0): a state the physics should not reach.
        thread_through: thread beyond the needle that has come out of the newest exit point, m (0 before).
        suture_samples: ``(S, 3) float64`` thread nodes sampled from the swage to the tail, m.
        diverged: the simulation produced non-finite or absurd values.
    """

    time: float
    tip_pos: np.ndarray
    tip_dir: np.ndarray
    needle_normal: np.ndarray
    needle_center: np.ndarray
    grip_pos: np.ndarray
    needle_vel: np.ndarray
    needle_omega: np.ndarray
    tip_sdist: float
    punctured: bool
    path_count: int
    new_entries: np.ndarray
    new_exits: np.ndarray
    tip_force: float
    tissue_force: float
    haptic_wrench: np.ndarray
    damaged: bool
    wound_gap: float
    wound_overlap: float
    thread_through: float
    suture_samples: np.ndarray
    diverged: bool


@dataclass
class TaskState:
    """Bookkeeping of a task within an episode (copied by :meth:`Task.get_state`).

    Attributes:
        stitch: index of the current planned arc.
        punctured_stitch: the current stitch has had its first puncture.
        exits_in_stitch: times the tip came out during the current stitch.
        entries_hit: indices (into the planned access points) of the planned entries punctured so far in the
            current stitch.
        exited: the current stitch's final exit happened.
        entry_point: ``(3,)`` first puncture of the current stitch, m (nan before).
        exit_point: ``(3,)`` final exit of the current stitch, m (nan before).
        potential: ``Phi`` of the progress term at the last step.
        thread: thread pulled through the current stitch at the last step (capped at the target), m.
        gap: mean wound gap at the last step, m (0 without a wound).
        banked: what the ``entry``, ``exit``, ``puncture``, ``thread`` and ``closure`` terms paid so far in the
            episode (``forfeit`` hands it back on a failing end).
        succeeded: success has been reported.
    """

    stitch: int = 0
    punctured_stitch: bool = False
    exits_in_stitch: int = 0
    entries_hit: tuple = ()
    exited: bool = False
    entry_point: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    exit_point: np.ndarray = field(default_factory=lambda: np.full(3, np.nan))
    potential: float = 0.0
    thread: float = 0.0
    gap: float = 0.0
    banked: float = 0.0
    succeeded: bool = False

    def copy(self) -> TaskState:
        """Deep copy."""
        return TaskState(**{f.name: (v.copy() if isinstance(v := getattr(self, f.name), np.ndarray) else v)
                            for f in fields(self)})


@dataclass(frozen=True)
class TaskOutcome:
    """What a task returns for one env step.

    Attributes:
        terms: reward term name -> value, in the task's ``TERMS`` order.
        reward: ``math.fsum`` of the terms.
        cost: tissue-force cost (>= 0), ``info["cost"]``.
        success: the task succeeded this step (or earlier).
        tear: the tissue tore.
        out_of_workspace: the tip left the workspace box.
        missed: a stitch was entered or exited off the plan and the task needs every stitch on it
            (:attr:`Task.NEEDS_PLANNED_ACCESS`), so it can no longer succeed.
        crushed: the wound's faces passed through each other by more than :data:`WOUND_OVERLAP_LIMIT` of the
            rest gap.
        failed: the episode ends in failure: out of the workspace, a tear with ``end_on_tear``, a miss with
            ``end_on_miss``, or a crushed wound.
    """

    terms: dict
    reward: float
    cost: float
    success: bool
    tear: bool
    out_of_workspace: bool
    missed: bool
    crushed: bool
    failed: bool


@dataclass(frozen=True)
class StepContext:
    """What the reward terms of one step read (built by :meth:`Task._advance` after the bookkeeping).

    Attributes:
        obs: the observables after the step; ``action`` the raw ``(6,)`` action.
        exited_before: the current stitch had its final exit before this step.
        arc_before: the current planned stitch before this step.
        events: ``entry``, ``exit`` and ``puncture`` term values of this step's events.
        potential, previous_potential: ``Phi`` after and before the step.
        thread, previous_thread: thread through the stitch (capped at the target) after and before, m.
        previous_gap: mean wound gap before the step, m.
        success: the task is achieved; ``newly_succeeded``: for the first time this step.
        cost: tissue-force cost (>= 0).
        outside: the tip left the workspace; ``missed``, ``crushed``: see :class:`TaskOutcome`; ``failed``: the
            episode ends in failure.
    """

    obs: Observables
    action: np.ndarray
    exited_before: bool
    arc_before: PlannedArc
    events: dict
    potential: float
    previous_potential: float
    thread: float
    previous_thread: float
    previous_gap: float
    success: bool
    newly_succeeded: bool
    cost: float
    outside: bool
    missed: bool
    crushed: bool
    failed: bool


#: Terms whose episode total ``forfeit`` hands back on a failing end.
BANKED_TERMS: tuple[str, ...] = ("entry", "exit", "puncture", "thread", "closure")
#: Interpenetration of the wound's faces (mean, m) that ends an episode as a failure, as a fraction of the rest
#: gap: faces cannot pass through each other, so the simulation has left what it models (a crushed wound).
WOUND_OVERLAP_LIMIT = 0.25

#: Scene kinds with a wound to suture.
WOUND_KINDS: tuple[str, ...] = ("wound", *ANATOMY_KINDS)

#: The built-in tasks' version history (:attr:`Task.VERSION_HISTORY`): what they share.
BUILTIN_VERSION_HISTORY = (
    "v3: an episode that ends in failure returns at most its penalties (the ``forfeit`` term hands back what the "
    "event terms paid); the wound gap is never negative, faces pushed through each other end the episode "
    "(``info['crushed']``), and closure pays at most its weight; observations, actions, physics and success are "
    "v2's.",
    "v2: randomised by default (tissue stiffness x0.7-1.3, puncture force x0.8-1.25, wound gap x0.9-1.1, start "
    "pose +-0.5 mm and +-0.05 rad; ``randomization.enabled: false`` for the nominal episode) and the observation "
    "scaled to O(1) with finite bounds (``observation.scaled: false`` for raw SI values).",
    "v1: real-scale physics: 300 kPa tissue on the implicit integrator and forces in newtons (puncture 0.5 N, "
    "tear 10 N, actions up to 5 N and 0.02 N m), the insertion force model on; actions outside the box clipped, "
    "a divergence a failure, a step after the end refused.",
    "v0: 3 kPa XPBD tissue and millinewton forces (puncture 5 mN, actions up to 0.05 N and 2e-4 N m).",
)
#: The thread tasks' version history: :data:`BUILTIN_VERSION_HISTORY` with the thread's own changes added.
THREAD_VERSION_HISTORY = (
    BUILTIN_VERSION_HISTORY[0],
    BUILTIN_VERSION_HISTORY[1] + " The base under the wound is an obstacle of the thread (Coulomb friction 0.3).",
) + BUILTIN_VERSION_HISTORY[2:]


class Task(ABC):
    """Base of the suturing tasks. Subclasses set the class attributes and the goal methods.

    Args:
        arcs: the planned stitches, in the order they are to be made.
        reward: the :class:`~suture_gym.envs.config.RewardConfig`.
        tear_force: coupling force (N) at which the tissue tears (scales the tissue-force cost).
        thread_target: thread (m) to pull through each stitch.
        closure_target: fraction of the rest gap to reach (tasks with a wound).
        workspace: ``(2, 3)`` lower and upper corners of the box the tip must stay in, m.
        gap_rest: mean wound gap at rest, m (0 without a wound; only tasks with a wound use it).
        end_on_tear: a tear ends the episode as a failure.
        end_on_miss: a miss (see :class:`TaskOutcome`) ends the episode as a failure.
        params: the task's own config section (an instance of :attr:`PARAMS`; default its defaults).
    """

    #: Registered name (``EnvConfig.task``).
    NAME: ClassVar[str] = ""
    #: Gymnasium id of the flat env (:func:`~suture_gym.envs.registry.register_task`).
    ENV_ID: ClassVar[str] = ""
    #: Gymnasium id of the goal-conditioned variant, or None for none.
    GOAL_ENV_ID: ClassVar[str | None] = None
    #: Time limit, env steps.
    MAX_EPISODE_STEPS: ClassVar[int] = 0
    #: The ids' version history for the env docs, newest first: one short line per version, what changed for a user.
    #: Bump the ids' version (and add a line) whenever a change alters what an episode does.
    VERSION_HISTORY: ClassVar[tuple[str, ...]] = ()
    #: The task's config defaults: nested overrides of the typed defaults of
    #: :class:`~suture_gym.envs.config.EnvConfig` (what the registered ids use; YAML overrides them in turn).
    CONFIG: ClassVar[dict] = {}
    #: The task's own config section (YAML key ``task_params``): a frozen dataclass of its parameters, with
    #: defaults, validated in ``__post_init__``; None for none. :attr:`params` holds the episode's values.
    PARAMS: ClassVar[type | None] = None
    #: Scene kinds (``scene.kind``) the task can be played on.
    SCENE_KINDS: ClassVar[tuple[str, ...]] = ("pad", "wound")
    #: The task pulls a thread through, so the config needs one (``suture.node_count >= 2``).
    NEEDS_THREAD: ClassVar[bool] = False
    #: The scripted surgeon's tip-angle advance while turning (rad/s) and holder speed while pulling (m/s).
    SURGEON_TURN_RATE: ClassVar[float] = 1.0
    SURGEON_PULL_SPEED: ClassVar[float] = 0.02
    #: Reward terms, in the order reported.
    TERMS: ClassVar[tuple[str, ...]] = ()
    #: Start phases accepted by ``reset(options={"phase": ...})``, the first being the default (the scene as
    #: built); :meth:`start_phase` reaches the others.
    PHASES: ClassVar[tuple[str, ...]] = ("approach",)
    #: What each start phase is, for the env docs.
    PHASE_DOCS: ClassVar[dict[str, str]] = {
        "approach": "the needle at rest with its tip on the first planned circle, ``plan.start_angle`` rad before "
                    "the entry point",
        "inserted": "the needle driven along the plan until the tip is halfway along the first arc",
        "exited": "the needle driven along the plan until the tip is out at the far edge",
        "first_bite": "the first stitch made and its thread pulled through by ``plan.thread_target``",
    }
    #: Size of ``achieved_goal`` / ``desired_goal`` in the goal-conditioned variant.
    GOAL_SIZE: ClassVar[int] = 0
    #: Goal entries and their units, for the docs: (name, unit) per component.
    GOAL_LAYOUT: ClassVar[tuple[tuple[str, str], ...]] = ()
    #: Terms of the goal-conditioned variant: the goal term computed from the goals, then the terms read back
    #: from ``info``.
    GOAL_TERMS: ClassVar[tuple[str, ...]] = ("goal", "failure", "tissue_force", "action")
    #: Success needs each stitch's first puncture and final exit within ``access_tolerance`` of the plan.
    NEEDS_PLANNED_ACCESS: ClassVar[bool] = False

    def __init__(self, arcs, reward, tear_force: float, thread_target: float, closure_target: float,
                 workspace: np.ndarray, gap_rest: float, end_on_tear: bool = True, end_on_miss: bool = False,
                 params=None) -> None:
        if not arcs or not all(isinstance(a, PlannedArc) for a in arcs):
            raise ValueError("arcs must be a non-empty sequence of PlannedArc")
        if not (math.isfinite(tear_force) and tear_force > reward.safe_force):
            raise ValueError(f"tear_force ({tear_force} N) must exceed reward.safe_force ({reward.safe_force} N)")
        box = np.array(workspace, dtype=np.float64)
        if box.shape != (2, 3) or not np.all(box[0] < box[1]):
            raise ValueError(f"workspace must be (2, 3) [lower, upper] corners in m, got {workspace!r}")
        self.arcs = tuple(arcs)
        self.reward = reward
        self.tear_force = float(tear_force)
        self.thread_target = float(thread_target)
        self.closure_target = float(closure_target)
        self.workspace = box
        self.gap_rest = float(gap_rest)
        self.end_on_tear = bool(end_on_tear)
        self.end_on_miss = bool(end_on_miss)
        self.params = params if params is not None or self.PARAMS is None else self.PARAMS()
        self.state = TaskState()

    # ------------------------------------------------------------------------------------------------------
    # Hooks: config check and episode initialisation
    # ------------------------------------------------------------------------------------------------------

    @classmethod
    def check_config(cls, config) -> None:
        """Raise ValueError naming the key when the :class:`~suture_gym.envs.config.EnvConfig` ``config`` does
        not suit the task (by default: ``scene.kind`` in :attr:`SCENE_KINDS`, a thread if :attr:`NEEDS_THREAD`)."""
        if config.scene.kind not in cls.SCENE_KINDS:
            kinds = " or ".join(repr(k) for k in cls.SCENE_KINDS)
            raise ValueError(f"scene.kind must be {kinds} for task {cls.NAME!r}, got {config.scene.kind!r}")
        if cls.NEEDS_THREAD and config.suture.node_count == 0:
            raise ValueError(f"suture.node_count must be >= 2 for task {cls.NAME!r} (the thread is pulled through)")

    @classmethod
    def initial_suture(cls, suture: RodModel, swage: np.ndarray, arcs: tuple[PlannedArc, ...]) -> RodState:
        """Episode initialisation: the thread at rest on the swage (3,) m of the approach pose; by default
        straight along ``(0, -1, 1)`` (up and back, clear of the needle)."""
        return RodState.straight(suture, swage, (0.0, -1.0, 1.0))

    @classmethod
    def start_phase(cls, sim, phase: str) -> None:
        """Episode initialisation: drive the :class:`~suture_gym.envs.simulation.Simulation` ``sim`` from the
        approach state to the start of ``phase`` (one of :attr:`PHASES` past the first); by default the scripted
        surgeon's :func:`~suture_gym.tasks.surgeon.run_start_phase`."""
        from suture_gym.tasks.surgeon import run_start_phase

        run_start_phase(sim, phase)

    # ------------------------------------------------------------------------------------------------------
    # Episode
    # ------------------------------------------------------------------------------------------------------

    @property
    def arc(self) -> PlannedArc:
        """The current planned stitch."""
        return self.arcs[min(self.state.stitch, len(self.arcs) - 1)]

    def reset(self, obs: Observables) -> None:
        """Start an episode from ``obs``: forget the previous one, then take in the events of ``obs`` (a start
        phase past the approach arrives with its punctures and exits done) without rewarding them."""
        self.state = TaskState(gap=obs.wound_gap)
        self._consume_events(obs)
        self.state.thread = self._thread(obs)
        self._advance_stitch()
        self.state.potential = self._potential(obs)

    def get_state(self) -> TaskState:
        """A copy of the bookkeeping (for env snapshots)."""
        return self.state.copy()

    def set_state(self, state: TaskState) -> None:
        """Restore bookkeeping from :meth:`get_state`."""
        if not isinstance(state, TaskState):
            raise ValueError(f"state must be a TaskState, got {type(state).__name__}")
        self.state = state.copy()

    def step(self, obs: Observables, action: np.ndarray) -> TaskOutcome:
        """Reward terms and flags for the step that led to ``obs`` under ``action`` (6,): the bookkeeping
        (:meth:`_advance`) first, then each term of ``TERMS`` from its ``term_<name>`` method."""
        ctx = self._advance(obs, action)
        values = {name: getattr(self, f"term_{name}")(ctx) for name in self.TERMS}
        gained = math.fsum(values[name] for name in BANKED_TERMS if name in values)
        self.state.banked = 0.0 if ctx.failed else self.state.banked + gained
        return TaskOutcome(
            terms=values,
            reward=math.fsum(values.values()),
            cost=ctx.cost,
            success=ctx.success,
            tear=obs.damaged,
            out_of_workspace=ctx.outside,
            missed=ctx.missed,
            crushed=ctx.crushed,
            failed=ctx.failed,
        )

    def diverged(self) -> TaskOutcome:
        """The outcome of a step on which the simulation diverged (non-finite or absurd state): a failing end.

        Nothing can be measured on a diverged state, so every term is 0 except ``failure`` (``-w_failure``),
        ``progress`` (``-w_progress Phi``: the banked potential handed back, as on every failing end) and
        ``forfeit`` (what the event terms paid), for the tasks that have them; the cost is 0.
        """
        values = dict.fromkeys(self.TERMS, 0.0)
        if "failure" in values:
            values["failure"] = -self.reward.failure
        if "progress" in values:
            values["progress"] = -self.reward.progress * self.state.potential
        if "forfeit" in values:
            values["forfeit"] = -max(0.0, self.state.banked)
        self.state.potential = 0.0
        self.state.banked = 0.0
        return TaskOutcome(terms=values, reward=math.fsum(values.values()), cost=0.0, success=False, tear=False,
                           out_of_workspace=False, missed=False, crushed=False, failed=True)

    def _advance(self, obs: Observables, action: np.ndarray) -> StepContext:
        """Update the bookkeeping with ``obs`` (events, potential, thread, gap, stitch, success, end) and return
        what the reward terms read."""
        st = self.state
        w = self.reward
        exited_before, arc_before = st.exited, self.arc
        events = self._consume_events(obs)
        previous_potential = st.potential
        st.potential = self._potential(obs)
        thread = self._thread(obs)
        previous_thread, st.thread = st.thread, thread
        previous_gap, st.gap = st.gap, obs.wound_gap
        potential = st.potential
        self._advance_stitch()
        success = self.success(obs) and not obs.damaged  # a torn tissue is no success, whatever else was done
        newly_succeeded = success and not st.succeeded
        st.succeeded = st.succeeded or success
        outside = bool(np.any(obs.tip_pos < self.workspace[0]) or np.any(obs.tip_pos > self.workspace[1]))
        missed = self.missed()
        crushed = self.gap_rest > 0.0 and obs.wound_overlap > WOUND_OVERLAP_LIMIT * self.gap_rest
        failed = not success and (crushed or self.failure(obs, outside, missed))
        if failed:
            # A failing end is absorbing and its shaping potential is 0 (Ng et al. 1999): the progress banked on
            # the way is handed back (term_progress), so ending an episode early can never pay.
            st.potential = 0.0
        return StepContext(
            obs=obs, action=action, exited_before=exited_before, arc_before=arc_before, events=events,
            potential=potential, previous_potential=previous_potential, thread=thread,
            previous_thread=previous_thread, previous_gap=previous_gap, success=success,
            newly_succeeded=newly_succeeded,
            cost=max(0.0, obs.tissue_force - w.safe_force) / (self.tear_force - w.safe_force),
            outside=outside, missed=missed, crushed=crushed, failed=failed,
        )

    # ------------------------------------------------------------------------------------------------------
    # Reward terms: one method ``term_<name>(ctx) -> float`` per name in TERMS (formulas in the module doc)
    # ------------------------------------------------------------------------------------------------------

    def term_path(self, ctx: StepContext) -> float:
        """``-w_path d / (d + path_scale)``, ``d`` the tip's distance to the stitch's circle (m); 0 once exited."""
        if ctx.exited_before:
            return 0.0
        d = ctx.arc_before.distance(ctx.obs.tip_pos)
        return -self.reward.path * d / (d + self.reward.path_scale)

    def term_progress(self, ctx: StepContext) -> float:
        """``w_progress (Phi' - Phi)``; ``-w_progress Phi`` on a failing end (its potential is 0)."""
        if ctx.failed:
            return -self.reward.progress * ctx.previous_potential
        return self.reward.progress * (ctx.potential - ctx.previous_potential)

    def term_entry(self, ctx: StepContext) -> float:
        """``w_entry max(0, 1 - e / access_tolerance)`` at the stitch's first puncture, ``e`` its error (m)."""
        return ctx.events["entry"]

    def term_exit(self, ctx: StepContext) -> float:
        """``w_exit max(0, 1 - e / access_tolerance)`` at the stitch's final exit, ``e`` its error (m)."""
        return ctx.events["exit"]

    def term_puncture(self, ctx: StepContext) -> float:
        """``+w_puncture`` per new planned hole, ``-w_puncture`` per unplanned one, 0 for a re-entered hole."""
        return ctx.events["puncture"]

    def term_thread(self, ctx: StepContext) -> float:
        """``w_thread (min(L', T) - min(L, T)) / T``, ``L`` the thread (m) through the stitch's exit."""
        return self.reward.thread * (ctx.thread - ctx.previous_thread) / self.thread_target

    def term_closure(self, ctx: StepContext) -> float:
        """``w_closure (min(g, g0) - min(g', g0)) / g0``, ``g`` the mean wound gap (m), ``g0`` the gap at rest."""
        g0 = self.gap_rest
        return self.reward.closure * (min(ctx.previous_gap, g0) - min(ctx.obs.wound_gap, g0)) / g0

    def term_success(self, ctx: StepContext) -> float:
        """``w_success`` once, on the step the task succeeds."""
        return self.reward.success if ctx.newly_succeeded else 0.0

    def term_failure(self, ctx: StepContext) -> float:
        """``-w_failure`` once, on the step the episode ends in failure."""
        return -self.reward.failure if ctx.failed else 0.0

    def term_forfeit(self, ctx: StepContext) -> float:
        """On a failing end, minus what the :data:`BANKED_TERMS` paid over the episode (this step's included) if
        positive; else 0."""
        if not ctx.failed:
            return 0.0
        gained = math.fsum(getattr(self, f"term_{name}")(ctx) for name in BANKED_TERMS if name in self.TERMS)
        return -max(0.0, self.state.banked + gained)

    def term_tissue_force(self, ctx: StepContext) -> float:
        """``-w_tissue_force cost``, ``cost = max(0, F - safe_force) / (tear_force - safe_force)``, ``F`` in N."""
        return -self.reward.tissue_force * ctx.cost

    def term_action(self, ctx: StepContext) -> float:
        """``-w_action mean(a^2)`` of the action (clipped to the box)."""
        return -self.reward.action * float(np.mean(np.square(ctx.action)))

    def failure(self, obs: Observables, outside: bool, missed: bool) -> bool:
        """Termination hook: whether the step that led to ``obs`` ends the episode as a failure (asked only when
        it did not succeed). By default the tip left the workspace (``outside``), the tissue tore (with
        ``termination.end_on_tear``) or the task can no longer succeed (``missed``, with
        ``termination.end_on_miss``). A task with a failure of its own overrides this and calls ``super()``."""
        return outside or (obs.damaged and self.end_on_tear) or (missed and self.end_on_miss)

    def missed(self) -> bool:
        """Whether the current stitch was entered or exited farther than ``access_tolerance`` from the plan, in a
        task that needs every stitch on the plan (so it can no longer succeed); always False otherwise."""
        st = self.state
        if not self.NEEDS_PLANNED_ACCESS:
            return False
        tol = self.reward.access_tolerance
        entry_off = st.punctured_stitch and float(np.linalg.norm(st.entry_point - self.arc.entry)) > tol
        exit_off = st.exited and float(np.linalg.norm(st.exit_point - self.arc.exit)) > tol
        return bool(entry_off or exit_off)

    # ------------------------------------------------------------------------------------------------------
    # Events and potentials
    # ------------------------------------------------------------------------------------------------------

    def _consume_events(self, obs: Observables) -> dict:
        """Update the stitch bookkeeping with the punctures and exits in ``obs``; returns the event terms."""
        w = self.reward
        st = self.state
        tol = w.access_tolerance
        terms = {"entry": 0.0, "exit": 0.0, "puncture": 0.0}
        for point in obs.new_entries:
            arc = self.arc
            distances = np.linalg.norm(arc.access_points[0::2] - point, axis=1)
            nearest = 2 * int(np.argmin(distances))
            if st.exited or float(distances[nearest // 2]) > tol:
                terms["puncture"] -= w.puncture
            elif nearest not in st.entries_hit:
                terms["puncture"] += w.puncture
                st.entries_hit = (*st.entries_hit, nearest)
            if not st.punctured_stitch and not st.exited:
                st.punctured_stitch = True
                st.entry_point = np.array(point, dtype=np.float64)
                e = float(np.linalg.norm(point - arc.entry))
                terms["entry"] += w.entry * max(0.0, 1.0 - e / tol)
        for point in obs.new_exits:
            if not st.punctured_stitch or st.exited:
                continue
            st.exits_in_stitch += 1
            if st.exits_in_stitch == len(self.arc.access_angles) // 2:
                st.exited = True
                st.exit_point = np.array(point, dtype=np.float64)
                e = float(np.linalg.norm(point - self.arc.exit))
                terms["exit"] += w.exit * max(0.0, 1.0 - e / tol)
        return terms

    def _potential(self, obs: Observables) -> float:
        """``Phi`` of the progress term (see the module docstring)."""
        st = self.state
        arc = self.arc
        if st.exited:
            return st.stitch + min(max(arc.progress(st.exit_point), 0.0), 1.0)
        if not st.punctured_stitch:
            return float(st.stitch)
        if obs.punctured:
            cap = 1.0
        elif st.exits_in_stitch > 0:
            cap = arc.access_progress[min(2 * st.exits_in_stitch, len(arc.access_angles) - 1)]
        else:
            cap = 0.0
        return st.stitch + min(max(arc.progress(obs.tip_pos), 0.0), cap)

    def _thread(self, obs: Observables) -> float:
        """Thread pulled through the current stitch, capped at the target (0 before its final exit), m."""
        if not self.state.exited:
            return 0.0
        return min(max(obs.thread_through, 0.0), self.thread_target)

    def _advance_stitch(self) -> None:
        """Move to the next stitch once the current one is exited and its thread pulled through."""
        st = self.state
        if st.stitch + 1 >= len(self.arcs) or not st.exited or st.thread < self.thread_target:
            return
        st.stitch += 1
        st.punctured_stitch = False
        st.exits_in_stitch = 0
        st.entries_hit = ()
        st.exited = False
        st.entry_point = np.full(3, np.nan)
        st.exit_point = np.full(3, np.nan)
        st.potential = float(st.stitch)
        st.thread = 0.0

    # ------------------------------------------------------------------------------------------------------
    # Success and goals (per task)
    # ------------------------------------------------------------------------------------------------------

    def success(self, obs: Observables) -> bool:
        """Whether the task is achieved: the goal test on the achieved and desired goals (a task may ask more, and
        :meth:`_advance` never counts a step with the tissue torn)."""
        achieved = self.achieved_goal(obs)
        return bool(self.goal_reached(achieved[None, :], self.desired_goal()[None, :])[0])

    @abstractmethod
    def achieved_goal(self, obs: Observables) -> np.ndarray:
        """``(GOAL_SIZE,) float64`` goal achieved so far."""

    @abstractmethod
    def desired_goal(self) -> np.ndarray:
        """``(GOAL_SIZE,) float64`` goal of the episode."""

    @abstractmethod
    def goal_reached(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """``(B,) bool`` whether each row of ``achieved`` (B, G) meets the same row of ``desired`` (B, G)."""

    @abstractmethod
    def goal_distance(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """``(B,) float64`` in ``[0, 1)``: how far each achieved goal is from its desired goal (0 = met)."""

    def goal_term(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        """``(B,)`` goal term: sparse ``-1`` until reached, else 0; or dense ``-goal_distance``."""
        if self.reward.goal == "sparse":
            return np.where(self.goal_reached(achieved, desired), 0.0, -1.0)
        return -self.goal_distance(achieved, desired)

    def _position_goal(self, obs: Observables) -> np.ndarray:
        """``(8,)`` achieved ``[entry (3), exit (3), punctured, exited]``: the recorded points (the tip position
        before each happens) and whether the stitch's first puncture and final exit happened (0 or 1)."""
        st = self.state
        entry = st.entry_point if st.punctured_stitch else obs.tip_pos
        exit_ = st.exit_point if st.exited else obs.tip_pos
        return np.concatenate([entry, exit_, [float(st.punctured_stitch), float(st.exited)]])

    def _position_desired(self) -> np.ndarray:
        """``(8,)`` desired ``[planned entry (3), planned exit (3), 1, 1]``."""
        return np.concatenate([self.arc.entry, self.arc.exit, [1.0, 1.0]])

    def _positions_reached(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        tol = self.reward.access_tolerance
        entry = np.linalg.norm(achieved[:, 0:3] - desired[:, 0:3], axis=1)
        exit_ = np.linalg.norm(achieved[:, 3:6] - desired[:, 3:6], axis=1)
        events = np.all(achieved[:, 6:8] >= desired[:, 6:8], axis=1)
        return (entry <= tol) & (exit_ <= tol) & events

    def _positions_distance(self, achieved: np.ndarray, desired: np.ndarray) -> np.ndarray:
        tol = self.reward.access_tolerance
        entry = np.linalg.norm(achieved[:, 0:3] - desired[:, 0:3], axis=1)
        exit_ = np.linalg.norm(achieved[:, 3:6] - desired[:, 3:6], axis=1)
        missing = np.maximum(desired[:, 6:8] - achieved[:, 6:8], 0.0).sum(axis=1)
        return (entry / (entry + tol) + exit_ / (exit_ + tol) + missing) / 4.0
