"""The simulation facade of the environments: builds a task's scene, steps the coupled solver and hands out
read-only :class:`~suture_gym.tasks.Observables`.

Scene (all SI, gravity along -z, the tissue on a rigid base at ``z = 0``):

* tissue: a pad, or two bars with a wound gap (:class:`~suture_gym.envs.config.SceneConfig`), five-tet cells,
  bottom faces pinned (and, for the bars, both end faces, as in paper Fig. 5);
* the curved needle (:mod:`suture_gym.sim.needle`), its plane ``x = const`` across the pad or the wound, placed
  with its tip on the first planned circle ``plan.start_angle`` before the entry point;
* the suture (:mod:`suture_gym.sim.rod`) on the swage, if ``suture.node_count > 0``, laid out by the task's
  :meth:`~suture_gym.tasks.Task.initial_suture` hook; ``suture.knot_tail`` from its free end a stopper knot
  (wound_closure's running suture) stops the thread at the first entry, so pulling it draws the wound together;
* the coupling of needle and suture with the tissue (:mod:`suture_gym.sim.coupling`).

One env step is ``solver.substeps`` substeps of ``solver.dt``. Between substeps the facade records the events
the tasks need: each puncture (its entry point) and each exit of the tip (where it came out), as material points
(:mod:`suture_gym.envs.readout`, the one place that reads the simulator's state for the tasks).

Start phases (``reset(..., phase)``) past the task's first are reached by the task's
:meth:`~suture_gym.tasks.Task.start_phase` hook (by default the scripted surgeon of
:mod:`suture_gym.tasks.surgeon`), simulated from the approach state of the config's nominal parameters once per
process (:meth:`Simulation.simulate_phase`; tens of seconds to minutes) and cached for every simulation of the
same config (:data:`PHASE_STARTS`). A reset into a phase then costs:

* with the nominal physical parameters: one state copy, the simulated start bit for bit;
* with other ones (a randomised episode's tissue stiffness, puncture force or wound gap): the scene's build, the
  cached start carried over to it (the tissue moved with its rest shape where the wound gap differs) and
  :data:`PHASE_SETTLE_STEPS` env steps with the holder held still, in which the tissue settles to its own
  stiffness. The punctures are where the nominal approach made them (the puncture force only decides where the
  tip pierces, and that has happened).

Past the approach the episode's needle start offsets have no effect: the scripted approach drives the needle onto
the planned circle before it reaches the tissue.
"""

from __future__ import annotations

import math
from collections import OrderedDict
from dataclasses import dataclass, replace

import numpy as np

from suture_gym.envs.config import EnvConfig, sim_fields
from suture_gym.envs.randomization import EpisodeParams, nominal_params
from suture_gym.envs.readout import coupling_mark, mean_gap, observables, substep_events, thread_through
from suture_gym.envs.registry import task_class
from suture_gym.render.scene import RenderFrame
from suture_gym.sim.mesh import TetLocator
from suture_gym.sim.model import Control, Model, State, TissueMaterial
from suture_gym.sim.needle import (
    NeedleModel,
    NeedleState,
    VirtualCoupling,
    needle_point_world,
)
from suture_gym.sim.quat import (
    quat_from_rotation_vector,
    quat_mul,
    quat_normalize,
    quat_rotate,
    quat_to_matrix,
)
from suture_gym.sim.rod import RodModel
from suture_gym.sim.scenes import (
    Scene,
    assemble,
    needle_circle_pose,
)
from suture_gym.sim.tissue_scenes import TissueSpec, build_tissue
from suture_gym.tasks import Observables, PlannedArc, plan_across_incision, plan_stitches
from suture_gym.tasks.surgeon import circle_grip_target

#: Most built scenes kept per simulation.
CACHE_SIZE = 4
#: Env steps a start phase carried over to other physical parameters settles, the holder held still (0.05 s at
#: the defaults; after them the tissue of a carried-over SutureThrow start moves at about 1e-5 m/s).
PHASE_SETTLE_STEPS = 10
#: Most simulated start phases kept per process (:data:`PHASE_STARTS`).
PHASE_CACHE_SIZE = 16


@dataclass(frozen=True)
class PhaseStart:
    """A start phase simulated on a config's nominal parameters (:meth:`Simulation.simulate_phase`).

    Attributes:
        state: the physics state at the start of the phase (a snapshot: never stepped, only copied).
        entries: the ``(3,)`` material points (rest shape, m) of the punctures the approach made, in order.
        exits: the ``(3,)`` material points (rest shape, m) where the tip came out during the approach.
        rest_q: ``(N, 3)`` the tissue's rest positions in that scene, m.
    """

    state: State
    entries: tuple
    exits: tuple
    rest_q: np.ndarray


#: The simulated start phases of this process: ``(EnvConfig, phase) -> PhaseStart``, least recently used first,
#: at most :data:`PHASE_CACHE_SIZE`; shared by every simulation (so by every env of one config).
PHASE_STARTS: OrderedDict = OrderedDict()


@dataclass(frozen=True)
class _Build:
    """A built scene for one set of physical parameters (immutable; shared by snapshots)."""

    model: Model
    arcs: tuple[PlannedArc, ...]
    workspace: np.ndarray
    left_face: np.ndarray
    right_face: np.ndarray
    gap_rest: float
    initial: State


@dataclass(frozen=True)
class SimulationSnapshot:
    """Everything :meth:`Simulation.restore` needs (the physics state is a deep copy); ``task`` is the config's
    task name, since a snapshot restores only into a simulation of the same task."""

    task: str
    build: _Build
    params: EpisodeParams
    state: State
    entries: tuple
    exits: tuple


class Simulation:
    """Physics of one environment (see the module docstring).

    Args:
        config: the resolved :class:`~suture_gym.envs.config.EnvConfig`.

    The scene of the nominal parameters is built here, so :attr:`arcs` and :attr:`workspace` exist before the
    first :meth:`reset`.
    """

    def __init__(self, config: EnvConfig) -> None:
        self.config = config
        self.task_cls = task_class(config.task)
        s = config.solver
        self.solver = s.solver()
        self.dt = s.dt
        self.substeps = s.substeps
        n = config.needle
        self.needle_shape = n.shape()
        self.needle_model = NeedleModel.from_shape(
            self.needle_shape,
            linear_damping=n.linear_damping,
            angular_damping=n.angular_damping,
            gravity_compensation=n.gravity_compensation,
        )
        self.suture_params = config.suture.params()
        a = config.action
        self.coupling_spring = VirtualCoupling(
            linear_stiffness=a.coupling_linear_stiffness,
            linear_damping=a.coupling_linear_damping,
            angular_stiffness=a.coupling_angular_stiffness,
            angular_damping=a.coupling_angular_damping,
        )
        self.control = Control()
        #: Set to a dict to accumulate the solver's phase times (s) into it (benchmarks); None: no timing.
        self.timings: dict | None = None
        self._builds: OrderedDict = OrderedDict()
        self.params: EpisodeParams | None = None
        self._build = self._get_build(nominal_params(config))
        self.state: State = self._build.initial.snapshot()
        self._entries: list[np.ndarray] = []
        self._exits: list[np.ndarray] = []

    # ------------------------------------------------------------------------------------------------------
    # Properties
    # ------------------------------------------------------------------------------------------------------

    @property
    def model(self) -> Model:
        """The current physical model."""
        return self._build.model

    @property
    def arcs(self) -> tuple[PlannedArc, ...]:
        """The planned stitches of the current scene."""
        return self._build.arcs

    @property
    def workspace(self) -> np.ndarray:
        """``(2, 3)`` box the needle tip must stay in (tissue box grown by the margin), m."""
        return self._build.workspace

    @property
    def gap_rest(self) -> float:
        """Mean wound gap of the scene at rest, m (0 without a wound)."""
        return self._build.gap_rest

    @property
    def control_dt(self) -> float:
        """Duration of one env step, s."""
        return self.dt * self.substeps

    @property
    def time(self) -> float:
        """Simulated time of the current state, s."""
        return self.state.time

    # ------------------------------------------------------------------------------------------------------
    # Building
    # ------------------------------------------------------------------------------------------------------

    def _get_build(self, params: EpisodeParams) -> _Build:
        """The scene of ``params`` (cached by :meth:`EpisodeParams.physics_key` and the start offsets)."""
        key = (params.physics_key(), params.needle_position_offset.tobytes(), params.needle_rotation_offset.tobytes())
        build = self._builds.get(key)
        if build is None:
            build = self._make_build(params)
            self._builds[key] = build
            if len(self._builds) > CACHE_SIZE:
                self._builds.popitem(last=False)
        else:
            self._builds.move_to_end(key)
        return build

    def _tissue_spec(self, params: EpisodeParams) -> TissueSpec:
        """The tissue of the config's scene with the episode's stiffness and wound gap."""
        cfg = self.config
        scene = cfg.scene
        material = TissueMaterial(**{**sim_fields(cfg.tissue, TissueMaterial),
                                     "youngs_modulus": params.youngs_modulus})
        return TissueSpec(kind=scene.kind, material=material, size=scene.size, cells=scene.cells,
                          cell_size=scene.cell_size, gap=params.gap, layer_thickness=scene.layer_thickness,
                          layer_stiffness=scene.layer_stiffness, wound_contact=scene.wound_contact,
                          path=scene.path, max_tets=scene.max_tets, incision_points=scene.incision.points,
                          incision_depth=scene.incision.depth)

    def _plan(self, tissue_scene: Scene, gap: float) -> tuple[PlannedArc, ...]:
        """The planned arcs: from the config's geometry for a pad or two bars, on the built tissue across its
        incision otherwise (:func:`~suture_gym.tasks.geometry.plan_across_incision`)."""
        cfg = self.config
        radius = self.needle_shape.curvature_radius
        if cfg.scene.kind in ("pad", "wound"):
            return plan_stitches(cfg.scene.kind, cfg.scene.size, gap, radius, cfg.plan.center_height,
                                 cfg.plan.stitches)
        tissue = tissue_scene.model.tissue
        inside = TetLocator(tissue.particle_rest_q, tissue.tet_indices).inside
        return plan_across_incision(np.array(tissue_scene.settings["incision"]["points_m"]), inside, radius,
                                    cfg.plan.center_height, cfg.plan.stitches)

    def _make_build(self, params: EpisodeParams) -> _Build:
        cfg = self.config
        tissue_scene, left, right = build_tissue(self._tissue_spec(params))
        arcs = self._plan(tissue_scene, params.gap)
        coupling_params = cfg.coupling.params(puncture_force=params.puncture_force)
        needle = self.needle_model
        pos, quat = needle_circle_pose(needle, arcs[0].center, arcs[0].axis, arcs[0].u,
                                       arcs[0].entry_angle - cfg.plan.start_angle)
        grip = pos + quat_rotate(quat, needle.grip_pos_body)
        quat = quat_normalize(quat_mul(quat_from_rotation_vector(params.needle_rotation_offset), quat))
        pos = grip - quat_rotate(quat, needle.grip_pos_body) + params.needle_position_offset
        needle_state = NeedleState.at_rest(pos, quat)
        suture = suture_state = None
        if self.suture_params is not None:
            suture = RodModel.from_params(self.suture_params)
            suture_state = self.task_cls.initial_suture(suture, pos + quat_rotate(quat, needle.swage_pos_body), arcs)
        scene = assemble(tissue_scene, needle, needle_state, suture, suture_state, coupling_params,
                         knot_tail=cfg.suture.knot_tail)
        rest = scene.model.tissue.particle_rest_q
        margin = cfg.termination.workspace_margin
        workspace = np.stack([rest.min(axis=0) - margin, rest.max(axis=0) + margin])
        tip = needle_point_world(needle, needle_state, needle.tip_pos_body)
        if np.any(tip < workspace[0]) or np.any(tip > workspace[1]):
            raise ValueError(
                f"the needle's tip starts at {tip.round(4).tolist()} m, outside the workspace "
                f"{workspace.round(4).tolist()} m (termination.workspace_margin = {margin} m around the tissue): check "
                f"plan.start_angle = {cfg.plan.start_angle} rad and the episode's needle_position_offset = "
                f"{params.needle_position_offset.tolist()} m"
            )
        gap_rest = mean_gap(rest, left, right)
        for array in (workspace, left, right):
            array.flags.writeable = False
        return _Build(scene.model, arcs, workspace, left, right, gap_rest, scene.state)

    # ------------------------------------------------------------------------------------------------------
    # Episode
    # ------------------------------------------------------------------------------------------------------

    def reset(self, params: EpisodeParams, phase: str = "approach") -> None:
        """Start from the scene of ``params`` at rest or, for a phase past the task's first, from the phase's start
        (see the module docstring: the nominal parameters' simulated start, carried over to ``params``).

        Clears the recorded events; the phase's own events (its punctures and exits) are recorded for the
        task to take in.
        """
        if not isinstance(params, EpisodeParams):
            raise ValueError(f"params must be EpisodeParams, got {type(params).__name__}")
        self._entries, self._exits = [], []
        if phase == self.task_cls.PHASES[0]:
            self._build = self._get_build(params)
            self.params = params
            self._load_state(self._build.initial)
            return
        start = self._phase_start(phase)
        self._build = self._get_build(replace(params, needle_position_offset=np.zeros(3),
                                              needle_rotation_offset=np.zeros(3)))
        self.params = params
        self._load_state(start.state)
        self._entries, self._exits = list(start.entries), list(start.exits)
        if params.physics_key() != nominal_params(self.config).physics_key():
            self._carry_over(start)

    def simulate_phase(self, params: EpisodeParams, phase: str) -> None:
        """Simulate the approach to ``phase`` (past the task's first) on the scene of ``params`` from its
        initial state, with the task's :meth:`~suture_gym.tasks.Task.start_phase` hook, recording its events:
        what :meth:`reset` does once per process for the nominal parameters (slow: tens of seconds to minutes)."""
        self._build = self._get_build(params)
        self.params = params
        self._load_state(self._build.initial)
        self._entries, self._exits = [], []
        self.task_cls.start_phase(self, phase)

    def _phase_start(self, phase: str) -> PhaseStart:
        """The :class:`PhaseStart` of ``phase`` on the config's nominal parameters, simulated on first use
        (:meth:`simulate_phase`) and kept in :data:`PHASE_STARTS`."""
        key = (self.config, phase)
        start = PHASE_STARTS.get(key)
        if start is not None:
            PHASE_STARTS.move_to_end(key)
            return start
        self.simulate_phase(nominal_params(self.config), phase)
        start = PhaseStart(self.state.snapshot(), tuple(e.copy() for e in self._entries),
                           tuple(e.copy() for e in self._exits), self.model.tissue.particle_rest_q)
        PHASE_STARTS[key] = start
        if len(PHASE_STARTS) > PHASE_CACHE_SIZE:
            PHASE_STARTS.popitem(last=False)
        return start

    def _carry_over(self, start: PhaseStart) -> None:
        """Fit the loaded ``start`` (another scene's) to the current scene: move the tissue and the recorded
        events with the rest shape's change (the wound gap's), then let the tissue settle to its own material for
        :data:`PHASE_SETTLE_STEPS` env steps with the holder held at its pose."""
        rest = self.model.tissue.particle_rest_q
        shift = rest - start.rest_q
        if np.any(shift):
            tissue = self.state.tissue
            tissue.particle_q += shift
            tissue.particle_q_prev += shift

            def moved(point: np.ndarray) -> np.ndarray:
                return point + shift[int(np.argmin(np.sum((start.rest_q - point) ** 2, axis=1)))]

            self._entries = [moved(e) for e in self._entries]
            self._exits = [moved(e) for e in self._exits]
        grip_pos, grip_quat = self.grip_pose()
        for _ in range(PHASE_SETTLE_STEPS):
            self.step_toward(grip_pos, grip_quat)

    def step(self, wrench: np.ndarray) -> None:
        """Advance one env step with the grip-point ``wrench`` (6,) ``[N, N m]`` held over every substep."""
        self.control.needle_wrench[:] = wrench
        for _ in range(self.substeps):
            self._substep()

    def step_toward(self, target_pos: np.ndarray, target_quat: np.ndarray) -> None:
        """Advance one env step with the virtual coupling pulling the grip toward the target pose (``(3,)`` m,
        ``(4,)`` quaternion), its wrench recomputed every substep."""
        for _ in range(self.substeps):
            self._pull_toward(target_pos, target_quat)
            self._substep()

    def _pull_toward(self, target_pos: np.ndarray, target_quat: np.ndarray) -> None:
        needle = self.state.needle
        if not (np.all(np.isfinite(needle.body_pos)) and np.all(np.isfinite(needle.body_quat))):
            self.control.needle_wrench[:] = 0.0
            return
        self.control.needle_wrench[:] = self.coupling_spring.wrench(self.model.needle, needle, target_pos, target_quat)

    def substep(self, wrench: np.ndarray) -> None:
        """Advance one solver substep with the grip-point ``wrench`` (6,) ``[N, N m]``."""
        self.control.needle_wrench[:] = wrench
        self._substep()

    def _substep(self) -> None:
        """One solver substep, recording punctures and exits (:func:`~suture_gym.envs.readout.substep_events`)."""
        mark = coupling_mark(self.state)
        self.solver.step(self.model, self.state, self.control, self.dt, timings=self.timings)
        if self.state.diverged:
            return
        entry, exit_ = substep_events(self.model, mark, self.state)
        if entry is not None:
            self._entries.append(entry)
        if exit_ is not None:
            self._exits.append(exit_)

    # ------------------------------------------------------------------------------------------------------
    # Poses (the scripted surgeon's, suture_gym.tasks.surgeon)
    # ------------------------------------------------------------------------------------------------------

    def grip_pose(self) -> tuple[np.ndarray, np.ndarray]:
        """``(grip position (3,) m, needle orientation (4,))`` of the current state (copies)."""
        needle = self.state.needle
        return needle.body_pos + quat_rotate(needle.body_quat, self.model.needle.grip_pos_body), needle.body_quat.copy()

    def tip_position(self) -> np.ndarray:
        """``(3,)`` position of the needle tip in the current state, m."""
        return needle_point_world(self.model.needle, self.state.needle, self.model.needle.tip_pos_body)

    def arc_grip_target(self, arc: PlannedArc, tip_angle: float) -> tuple[np.ndarray, np.ndarray]:
        """Grip pose ``(position (3,) m, orientation (4,))`` of the needle lying on ``arc`` with its tip at
        ``tip_angle`` (rad)."""
        return circle_grip_target(self.model.needle, arc.center, arc.axis, arc.u, tip_angle)

    # ------------------------------------------------------------------------------------------------------
    # Observables
    # ------------------------------------------------------------------------------------------------------

    def thread_through(self) -> float:
        """Thread beyond the needle that has come out of the newest exit point, m (0 before any exit)."""
        return thread_through(self.model, self.state)

    def wound_gap(self) -> float:
        """Mean gap between the wound faces, m, over their free particles in the upper half of the tissue (mean
        y of the far face minus mean y of the near face); 0 without a wound."""
        return mean_gap(self.state.tissue.particle_q, self._build.left_face, self._build.right_face)

    def observables(self) -> Observables:
        """Snapshot of what the tasks read (copies, :func:`~suture_gym.envs.readout.observables`); clears the
        recorded events."""
        faces = (self._build.left_face, self._build.right_face)
        obs = observables(self.model, self.state, self._entries, self._exits, faces,
                          self.config.observation.suture_samples)
        self._entries, self._exits = [], []
        return obs

    # ------------------------------------------------------------------------------------------------------
    # Snapshots and rendering
    # ------------------------------------------------------------------------------------------------------

    def snapshot(self) -> SimulationSnapshot:
        """Deep copy of the physics state, with the scene it belongs to and the pending events."""
        return SimulationSnapshot(
            task=self.config.task,
            build=self._build,
            params=self.params if self.params is not None else nominal_params(self.config),
            state=self.state.snapshot(),
            entries=tuple(e.copy() for e in self._entries),
            exits=tuple(e.copy() for e in self._exits),
        )

    def restore(self, snapshot: SimulationSnapshot) -> None:
        """Make the simulation equal to ``snapshot`` (which stays reusable)."""
        if not isinstance(snapshot, SimulationSnapshot):
            raise ValueError(f"snapshot must be a SimulationSnapshot, got {type(snapshot).__name__}")
        if snapshot.task != self.config.task:
            raise ValueError(f"the snapshot is of task {snapshot.task!r}; this simulation is of task "
                             f"{self.config.task!r}")
        if snapshot.build.model.tissue.particle_count != self.model.tissue.particle_count:
            raise ValueError(f"the snapshot's tissue has {snapshot.build.model.tissue.particle_count} particles, this "
                             f"simulation's {self.model.tissue.particle_count}: it comes from another scene")
        self._build = snapshot.build
        self.params = snapshot.params
        self._load_state(snapshot.state)
        self._entries = [e.copy() for e in snapshot.entries]
        self._exits = [e.copy() for e in snapshot.exits]

    def _load_state(self, state: State) -> None:
        """Make :attr:`state` a copy of ``state`` (which stays reusable). A state of the current scene's model is
        overwritten in place, so it keeps the solver's buffers (``State.work``: rows, refitted BVHs, an implicit
        tissue's factorised system) and a reset does not rebuild them."""
        work = self.state.work
        if work is not None and work.model is self._build.model:
            self.state.restore(state)
        else:
            self.state = state.snapshot()

    def view_points(self) -> np.ndarray:
        """``(N, 3)`` points a camera should frame: the tissue at rest and the needle's start nodes, m."""
        needle = self._build.initial.needle
        nodes = needle.body_pos + self.model.needle.node_pos_body @ quat_to_matrix(needle.body_quat).T
        return np.concatenate([self.model.tissue.particle_rest_q, nodes])

    def render_frame(self, markers: np.ndarray, caption: str) -> RenderFrame:
        """The current state as a :class:`~suture_gym.render.RenderFrame` with ``markers`` (P, 3) m."""
        state = self.state
        needle = state.needle
        nodes = needle.body_pos + self.model.needle.node_pos_body @ quat_to_matrix(needle.body_quat).T
        return RenderFrame(
            tissue_q=state.tissue.particle_q,
            tissue_triangles=self.model.tissue.tri_indices,
            needle_q=nodes,
            needle_radius=self.needle_shape.wire_radius,
            suture_q=None if state.suture is None else state.suture.node_pos,
            suture_radius=self.config.suture.radius,
            marker_q=markers,
            marker_radius=3.0e-4,
            tip_force=float(state.coupling.tip_force) if math.isfinite(state.coupling.tip_force) else 0.0,
            force_threshold=(self.params or nominal_params(self.config)).puncture_force,
            haptic_force=_finite_norm(state.needle_reaction[:3]),
            haptic_span=self.config.action.max_force,
            caption=caption,
        )


def _finite_norm(vector: np.ndarray) -> float:
    """Euclidean norm of ``vector``, or 0.0 when it is not finite (a diverged step's reaction)."""
    norm = float(np.linalg.norm(vector))
    return norm if math.isfinite(norm) else 0.0
