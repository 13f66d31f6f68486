"""Needle/suture-tissue interaction checks (paper section 4) and the full-scene benchmark.

The scripted stitch (:class:`StitchController`, :func:`run_stitch`) drives the needle the way the scripted surgeon
(:mod:`suture_gym.tasks.surgeon`) does: a virtual coupling turns it about its own centre on the surgeon's
schedule through both wound edges of the two-bar scene, then it holds
the needle's orientation and pulls the thread with a constant force while the thread's tail is held. The
stitch checks measure residuals at the end of every substep of that run (after the solver's last projection,
which is the suture's direct solve); every parameter is recorded in ``settings``. The same stitch with a free
tail and a stopper knot instead (:func:`knotted_stitch`) measures how well the knot holds at the first entry.
The puncture and largest-wrench checks are in :mod:`suture_gym.measure.puncture`.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import asdict, dataclass, field, replace

import numpy as np

from suture_gym.measure.registry import CheckResult, benchmark, check
from suture_gym.sim.bvh import build_bvh
from suture_gym.sim.collision import TriangleSurface, signed_distance
from suture_gym.sim.coupling import NODE_IN, ROW_PATH, access_point
from suture_gym.sim.model import Control, State
from suture_gym.sim.needle import NeedleModel, VirtualCoupling
from suture_gym.sim.quat import (
    quat_to_matrix,
)
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.scenes import (
    PAPER_COUPLING,
    PAPER_SOLVER,
    WOUND_ARC_AXIS,
    WOUND_ARC_U,
    Scene,
    two_bar_suturing,
    wound_gap,
)
from suture_gym.sim.solver import PHASES, Solver
from suture_gym.tasks.surgeon import circle_grip_target, pull_wrench, turn_angles

DT = 1.0e-3  # s, substep of every run here
GAP_WINDOW = {"x_range": 0.005, "depth": 0.01}  # m, wound faces near the stitch where the gap is measured


def surface_at(surface: TriangleSurface, tissue_q: np.ndarray) -> TriangleSurface:
    """``surface`` with a BVH built for the tissue positions ``tissue_q`` (N, 3) m, for exact signed distances at
    the end of a substep (the model's BVH holds the rest shape; the solver's refitted copy holds the positions
    of the last detection, before the projection moved them)."""
    return replace(surface, bvh=build_bvh(surface.tri_vertices, tissue_q))


@dataclass
class StitchController:
    """Scripted surgeon for :func:`~suture_gym.sim.scenes.two_bar_suturing` scenes, on a bare scene (no env):
    the turn and the pull of :mod:`suture_gym.tasks.surgeon`, one target per substep of ``dt`` s.

    Turn phase (``t < turn_time``): a :class:`~suture_gym.sim.needle.VirtualCoupling` pulls the needle towards
    the pose of :func:`~suture_gym.tasks.surgeon.circle_grip_target` at the tip angle the surgeon's schedule
    (:func:`~suture_gym.tasks.surgeon.turn_angles`) gives from ``start_angle`` to ``start_angle + turn_angle``
    at ``turn_rate``, on the needle's circle (``arc_center`` (3,) m, normal ``axis``, angle origin ``u``).
    Pull phase: the needle's orientation is held at the last turn pose by the coupling's angular spring-damper
    and a constant force ``pull_force`` N along ``pull_direction`` acts at the grip, with linear damping
    ``pull_damping`` N s/m (:func:`~suture_gym.tasks.surgeon.pull_wrench`).
    """

    needle: NeedleModel
    arc_center: np.ndarray
    start_angle: float  # rad, tip angle of the needle's rest pose on its circle
    axis: tuple = WOUND_ARC_AXIS
    u: tuple = WOUND_ARC_U
    turn_rate: float = 1.0  # rad/s
    turn_angle: float = 6.1  # rad: the swage leaves bar B at about 2 pi - 0.24 for the default scene
    pull_force: float = 0.05  # N
    pull_direction: tuple = (0.0, -1.0, 0.5)
    pull_damping: float = 2.0  # N s/m
    dt: float = DT  # s, the substep: one turn target per substep
    coupling: VirtualCoupling = field(default_factory=VirtualCoupling)
    angles: list = field(init=False, repr=False)

    def __post_init__(self) -> None:
        self.angles = turn_angles(self.start_angle, self.start_angle + self.turn_angle, self.dt, self.turn_rate)

    @classmethod
    def for_scene(cls, scene: Scene, **kwargs) -> StitchController:
        """The controller for a :func:`~suture_gym.sim.scenes.two_bar_suturing` ``scene``, turning its needle
        from its rest pose on the circle the scene's settings record; ``kwargs`` set the other fields."""
        s = scene.settings
        return cls(scene.model.needle, np.array(s["arc_center_m"]), s["tip_angle_rad"], tuple(s["arc_axis"]),
                   tuple(s["arc_u"]), **kwargs)

    @property
    def turn_time(self) -> float:
        """Duration of the turn phase, s."""
        return len(self.angles) * self.dt

    def target(self, tip_angle: float) -> tuple[np.ndarray, np.ndarray]:
        """Grip pose ``(position (3,) m, orientation (4,))`` of the needle on its circle, tip at ``tip_angle``."""
        return circle_grip_target(self.needle, self.arc_center, self.axis, self.u, tip_angle)

    def wrench(self, t: float, state: State) -> np.ndarray:
        """Grip-point wrench (6,) ``[force N, torque N m]`` over the substep starting at ``t`` s for the needle
        ``state.needle``."""
        needle = self.needle
        k = int(round(t / self.dt))
        if k < len(self.angles):
            return self.coupling.wrench(needle, state.needle, *self.target(self.angles[k]))
        _, hold = self.target(self.angles[-1])
        direction = np.asarray(self.pull_direction, dtype=np.float64)
        direction = direction / np.linalg.norm(direction)
        return pull_wrench(needle, state.needle, hold, self.pull_force * direction, self.pull_damping, self.coupling)

    def settings(self) -> dict:
        return {
            "arc_axis": list(self.axis),
            "arc_u": list(self.u),
            "start_tip_angle_rad": self.start_angle,
            "turn_rate_rad_s": self.turn_rate,
            "turn_angle_rad": self.turn_angle,
            "pull_force_n": self.pull_force,
            "pull_direction": list(self.pull_direction),
            "pull_damping_n_s_m": self.pull_damping,
            "virtual_coupling": asdict(self.coupling),
        }


def run_stitch(
    scene: Scene,
    controller: StitchController,
    duration: float,
    solver: Solver | None = None,
    probe=None,
    dt: float = DT,
) -> dict:
    """Step ``scene`` under ``controller`` for ``duration`` s; ``probe(scene, t)`` is called after every substep.

    Returns the wound gap at rest, at the end of the turn and at the end (m, :data:`GAP_WINDOW`), the number
    of substeps, whether it diverged and the phase timings (s).
    """
    solver = solver or PAPER_SOLVER
    control = Control()
    timings: dict = {}
    gap_rest = wound_gap(scene, **GAP_WINDOW)
    gap_turn = math.nan
    steps = int(round(duration / dt))
    for k in range(steps):
        t = k * dt
        if math.isnan(gap_turn) and t >= controller.turn_time:
            gap_turn = wound_gap(scene, **GAP_WINDOW)
        control.needle_wrench = controller.wrench(t, scene.state)
        solver.step(scene.model, scene.state, control, dt, timings=timings)
        if probe is not None:
            probe(scene, (k + 1) * dt)
        if scene.state.diverged:
            break
    return {
        "gap_rest_m": gap_rest,
        "gap_after_turn_m": gap_turn,
        "gap_final_m": wound_gap(scene, **GAP_WINDOW),
        "substeps": k + 1,
        "diverged": bool(scene.state.diverged),
        "timings_s": timings,
    }


def strand_now(scene: Scene) -> np.ndarray:
    """Strand node positions (M, 3) m of the scene's current state (needle nodes, then suture nodes 1..)."""
    model, state = scene.model, scene.state
    needle = state.needle.body_pos + model.needle.node_pos_body @ quat_to_matrix(state.needle.body_quat).T
    if state.suture is None:
        return needle
    return np.vstack([needle, state.suture.node_pos[1:]])


class _StitchProbe:
    """End-of-substep residuals of the coupling constraints during a stitch."""

    def __init__(self):
        self.path_needle = 0.0
        self.path_suture = 0.0
        self.path_suture_samples: list[float] = []
        self.access = 0.0
        self.access_samples: list[float] = []
        self.outside_depth = 0.0
        self.inside_nodes = 0
        self.suture_in_nodes_max = 0

    def __call__(self, scene: Scene, t: float) -> None:
        model, state = scene.model, scene.state
        work = state.work.coupling_work
        nn = model.coupling.needle_node_count
        x = strand_now(scene)
        q = state.tissue.particle_q
        rows = np.flatnonzero(work.row_kind == ROW_PATH)
        if rows.size:
            p = np.einsum("ik,ikj->ij", work.row_weight[rows], q[work.row_tissue[rows]])
            residual = np.linalg.norm(np.cross(x[rows] - p, work.row_tangent[rows]), axis=1)
            needle_rows = rows < nn
            if needle_rows.any():
                self.path_needle = max(self.path_needle, float(residual[needle_rows].max()))
            if (~needle_rows).any():
                worst = float(residual[~needle_rows].max())
                self.path_suture = max(self.path_suture, worst)
                self.path_suture_samples.append(worst)
        for a in range(work.access_count):
            b = access_point(model.coupling, q, work.access_tri[a], work.access_bary[a])
            lo, hi = int(work.access_node[a, 0]), int(work.access_node[a, 3])
            seg_a, seg_b = x[lo:hi], x[lo + 1 : hi + 1]
            e = seg_b - seg_a
            u = np.clip(np.einsum("ij,ij->i", b - seg_a, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
            d = float(np.linalg.norm(seg_a + u[:, None] * e - b, axis=1).min())
            self.access = max(self.access, d)
            self.access_samples.append(d)
        suture_nodes = x[nn:]
        status = state.coupling.strand_status[nn:]
        self.suture_in_nodes_max = max(self.suture_in_nodes_max, int(np.count_nonzero(status == NODE_IN)))
        free = status != NODE_IN
        if free.any():
            sdist, _, _ = signed_distance(suture_nodes[free], surface_at(model.coupling.surface, q), q)
            self.outside_depth = max(self.outside_depth, float(max(0.0, -sdist.min())))
            self.inside_nodes += int(np.count_nonzero(sdist < 0.0))


def stitch_settings(scene: Scene, controller: StitchController, duration: float, solver: Solver) -> dict:
    return {
        "scene": scene.settings,
        "controller": controller.settings(),
        "duration_s": duration,
        "dt_s": DT,
        "solver": asdict(solver),
        "gap_window_m": GAP_WINDOW,
    }


STITCH_PULL_TIME = 3.0  # s of pulling after the turn


@functools.lru_cache(maxsize=1)
def _stitch_run() -> tuple[dict, dict, dict]:
    """The default stitch with residual probes (run once, shared by the stitch checks)."""
    scene = two_bar_suturing()
    controller = StitchController.for_scene(scene)
    solver = PAPER_SOLVER
    duration = controller.turn_time + STITCH_PULL_TIME
    probe = _StitchProbe()
    run = run_stitch(scene, controller, duration, solver, probe)
    state = scene.state.coupling
    result = {
        **run,
        "punctures": int(state.punctures),
        "paths": int(state.path_count),
        "damaged": bool(state.damaged),
        "overflow": bool(state.overflow),
        "path_residual_needle_max_m": probe.path_needle,
        "path_residual_suture_max_m": probe.path_suture,
        "path_residual_suture_p99_m": float(np.percentile(probe.path_suture_samples, 99))
        if probe.path_suture_samples
        else 0.0,
        "access_residual_max_m": probe.access,
        "access_residual_p99_m": float(np.percentile(probe.access_samples, 99)) if probe.access_samples else 0.0,
        "suture_outside_depth_max_m": probe.outside_depth,
        "suture_inside_node_samples": probe.inside_nodes,
        "suture_nodes_in_paths_max": probe.suture_in_nodes_max,
    }
    timings = run.pop("timings_s")
    result["timings_s"] = timings
    return result, stitch_settings(scene, controller, duration, solver), {"needle_nodes": scene.model.needle.node_count}


@check("node_path_residual")
def check_node_path_residual() -> CheckResult:
    """Largest distance of a strand node from its path line, ``|(p - q) x t|`` (eq. 1), at the end of any
    substep of the scripted stitch (both bites and the pull), for needle and suture nodes; bound 0.5 mm."""
    run, settings, _ = _stitch_run()
    measured = max(run["path_residual_needle_max_m"], run["path_residual_suture_max_m"])
    return CheckResult(
        name="node_path_residual",
        measured=measured,
        reference=0.0,
        tolerance=5e-4,
        unit="m",
        comparison="<=",
        settings=settings,
        details={k: v for k, v in run.items() if k != "timings_s"},
    )


@check("access_point_residual")
def check_access_point_residual() -> CheckResult:
    """Largest distance from an access point to the strand piece through it (eq. 3), at the end of any substep
    of the scripted stitch; bound 0.5 mm."""
    run, settings, _ = _stitch_run()
    return CheckResult(
        name="access_point_residual",
        measured=run["access_residual_max_m"],
        reference=0.0,
        tolerance=5e-4,
        unit="m",
        comparison="<=",
        settings=settings,
        details={k: v for k, v in run.items() if k != "timings_s"},
    )


@check("suture_outside_tissue")
def check_suture_outside_tissue() -> CheckResult:
    """Deepest a suture node not matched to a path is inside the tissue at the end of any substep of the
    scripted stitch (fresh signed distance to the deformed surface); bound 0.5 mm (the resistance layer is
    0.3 mm). The details say how many suture nodes were inside paths at most (the thread did go through)."""
    run, settings, _ = _stitch_run()
    return CheckResult(
        name="suture_outside_tissue",
        measured=run["suture_outside_depth_max_m"],
        reference=0.0,
        tolerance=5e-4,
        unit="m",
        comparison="<=",
        settings=settings,
        details={k: v for k, v in run.items() if k != "timings_s"},
    )


#: m: the stopper knot of :func:`knotted_stitch`, 14 mm behind the swage, so it reaches the first entry while
#: the needle is still turning and has the rest of the turn and the pull to hold against.
KNOT_TAIL = 0.066
#: m: the knot is at the entry once the entry's strand coordinate is this close to the knot's.
KNOT_ARRIVAL = 1.0e-4


@functools.lru_cache(maxsize=1)
def knotted_stitch() -> dict:
    """The default stitch (:func:`run_stitch`) with a free thread tail and a stopper knot :data:`KNOT_TAIL` from
    its end instead of a held tail; returns its run (gaps, m) and settings plus, per substep from the knot's
    arrival at the first entry on, the largest distance (m) between the knot's strand point and the entry
    access point, and: ``knot_sigma_m`` and the largest entry coordinate seen (m), the arrival time (s, nan if
    never), the swage's travel after it (m), the deepest point of the tail beyond the knot (m, > 0 inside the
    tissue), damage and divergence."""
    scene = two_bar_suturing(suture_tail_pinned=False, suture_knot_tail=KNOT_TAIL)
    controller = StitchController.for_scene(scene)
    solver = PAPER_SOLVER
    duration = controller.turn_time + STITCH_PULL_TIME
    coupling = scene.model.coupling
    knot = coupling.knot_sigma
    sigma = coupling.strand_sigma
    tail = sigma > knot + scene.model.suture.seg_rest_length.max()
    swage = coupling.needle_node_count - 1  # the strand node on the swage
    log = {"entry_max": -math.inf, "arrived": math.nan, "swage_at_arrival": None, "distance_max": 0.0,
           "tail_depth_max": -math.inf}

    def probe(sc: Scene, t: float) -> None:
        c = sc.state.coupling
        q = strand_now(sc)
        tissue_q = sc.state.tissue.particle_q
        depth, _, _ = signed_distance(q[tail], surface_at(coupling.surface, tissue_q), tissue_q)
        log["tail_depth_max"] = max(log["tail_depth_max"], float(-depth.min()))
        if c.path_count == 0:
            return
        log["entry_max"] = max(log["entry_max"], float(c.path_sigma_entry[0]))
        if log["swage_at_arrival"] is None and c.path_sigma_entry[0] >= knot - KNOT_ARRIVAL:
            log["arrived"], log["swage_at_arrival"] = t, q[swage].copy()
        if log["swage_at_arrival"] is not None:
            point = np.array([np.interp(knot, sigma, q[:, i]) for i in range(3)])
            entry = access_point(coupling, sc.state.tissue.particle_q, c.path_entry_tri[0], c.path_entry_bary[0])
            log["distance_max"] = max(log["distance_max"], float(np.linalg.norm(point - entry)))

    run = run_stitch(scene, controller, duration, solver, probe)
    run.pop("timings_s")
    arrived = log["swage_at_arrival"] is not None
    return {
        **run,
        "knot_sigma_m": knot,
        "entry_sigma_max_m": log["entry_max"],
        "arrival_s": log["arrived"],
        "duration_s": duration,
        "swage_travel_after_arrival_m": float(np.linalg.norm(strand_now(scene)[swage] - log["swage_at_arrival"]))
        if arrived
        else 0.0,
        "knot_entry_distance_max_m": log["distance_max"] if arrived else math.inf,
        "tail_depth_max_m": log["tail_depth_max"],
        "damaged": bool(scene.state.coupling.damaged),
        "settings": stitch_settings(scene, controller, duration, solver),
    }


@check("knot_hold")
def check_knot_hold() -> CheckResult:
    """Farthest the stopper knot of :func:`knotted_stitch` gets from the first entry once it has reached it,
    while the needle turns on and pulls the thread; bound 0.6 mm (node-access holds a strand piece one 1 mm
    segment long centred on the knot: half a segment, plus the constraint's residual)."""
    run = knotted_stitch()
    return CheckResult(
        name="knot_hold",
        measured=run["knot_entry_distance_max_m"],
        reference=0.0,
        tolerance=6e-4,
        unit="m",
        comparison="<=",
        settings=run["settings"],
        details={k: v for k, v in run.items() if k != "settings"},
    )


# ---------------------------------------------------------------------------------------------------------
# Tip force profile
# ---------------------------------------------------------------------------------------------------------


@check("tip_force_profile")
def check_tip_force_profile() -> CheckResult:
    """Forces over one bite of the scripted stitch (bar A): the tip's contact force rises to the puncture
    threshold and drops to zero at the puncture; then the axial friction grows with the inserted length.

    Measured: the slope of the total axial friction force against the inserted needle length while the tip is
    inside bar A (least squares), which should equal ``needle_axial_friction`` (N/m) when the needle slides:
    reference that parameter, tolerance 25%. The details give the peak tip force, the force after puncture and
    the friction at several depths."""
    scene = two_bar_suturing()
    params = scene.model.coupling.params
    controller = StitchController.for_scene(scene)
    samples: list[tuple] = []

    def probe(s: Scene, t: float) -> None:
        c = s.state.coupling
        inside = c.punctured
        depth = float(c.path_sigma_entry[c.path_count - 1]) if inside else 0.0
        samples.append((t, c.tip_force, c.friction_force, inside, depth, c.path_count))

    run_stitch(scene, controller, 2.0, probe=probe)
    data = np.array(samples, dtype=float)
    t, tip, friction, inside, depth, paths = data.T
    first_in = int(np.argmax(inside > 0))
    first_bite = (paths == 1) & (inside > 0)
    exit_index = first_in + int(np.argmax(~first_bite[first_in:]))
    peak_before = float(tip[:first_in].max())
    settle = first_bite & (depth > 2e-3)  # after the first 2 mm, the needle slides
    slope, intercept = np.polyfit(depth[settle], friction[settle], 1)
    quartiles = np.quantile(depth[settle], [0.25, 0.5, 0.75, 1.0])
    friction_at = {f"{d * 1e3:.1f}mm": float(np.interp(d, depth[settle], friction[settle])) for d in quartiles}
    return CheckResult(
        name="tip_force_profile",
        measured=float(slope),
        reference=params.needle_axial_friction,
        tolerance=0.25,
        unit="N/m",
        comparison="rel",
        settings={"scene": scene.settings, "controller": controller.settings(), "dt_s": DT, "duration_s": 2.0},
        details={
            "puncture_force_n": params.puncture_force,
            "peak_tip_force_before_puncture_n": peak_before,
            "tip_force_after_puncture_n": float(tip[first_in : first_in + 20].max()),
            "puncture_time_s": float(t[first_in]),
            "exit_time_s": float(t[exit_index]),
            "friction_fit_intercept_n": float(intercept),
            "friction_at_depth_n": friction_at,
            "max_inserted_length_m": float(depth[first_bite].max()),
        },
    )


# ---------------------------------------------------------------------------------------------------------
# Benchmark
# ---------------------------------------------------------------------------------------------------------


BENCH_PUNCTURE_FORCE = 0.008  # N: the 3 cm tall bar B of this scale gives way more than the small scene's


@benchmark("paper_cube")
def bench_paper_cube() -> dict:
    """The paper's Table 1 row 1 scale with strands: two 9.5 x 3 x 3 cm bars (6840 tets, 1960 particles), the
    30-node needle and a 200-node, 20 cm suture. The needle is first driven through both wound edges by the
    scripted stitch (turn rate 2 rad/s, puncture force 0.008 N), then, pulling the thread, substeps are
    timed: median wall time and the fractions spent in detection (broad phase, signed distances, paths, rows)
    and in projection. ``paths`` and ``suture_nodes_in_paths`` show that the thread is through both bites."""
    scene = two_bar_suturing(
        bar_size=(0.095, 0.03, 0.03),
        cells=(19, 6, 6),
        centre_height=0.002,
        suture_params=SutureParams(),
        suture_direction=(0.0, -1.0, 0.3),
        coupling_params=replace(PAPER_COUPLING, puncture_force=BENCH_PUNCTURE_FORCE),
    )
    controller = StitchController.for_scene(scene, turn_rate=2.0)
    solver = PAPER_SOLVER
    run_stitch(scene, controller, controller.turn_time)
    control = Control()
    samples = 300
    step_times = np.empty(samples)
    phase = {name: np.empty(samples) for name in PHASES}
    t0_sim = controller.turn_time
    for i in range(samples):
        timings: dict = {}
        control.needle_wrench = controller.wrench(t0_sim + i * DT, scene.state)
        start = time.perf_counter()
        solver.step(scene.model, scene.state, control, DT, timings=timings)
        step_times[i] = time.perf_counter() - start
        for name in PHASES:
            phase[name][i] = timings.get(name, 0.0)
    substep = float(np.median(step_times))
    total = step_times.sum()
    coupling = scene.state.coupling
    tissue = scene.model.tissue
    return {
        "tets": tissue.tet_count,
        "particles": tissue.particle_count,
        "strand_nodes": scene.model.coupling.strand_node_count,
        "substep_ms": substep * 1e3,
        "substeps_per_s": 1.0 / substep,
        "collision_fraction": float(phase["detect"].sum() / total),
        "solver_fraction": float(phase["project"].sum() / total),
        "substep_ms_p90": float(np.percentile(step_times, 90)) * 1e3,
        "phase_ms_median": {name: float(np.median(v)) * 1e3 for name, v in phase.items()},
        "paths": int(coupling.path_count),
        "suture_nodes_in_paths": int(
            np.count_nonzero(coupling.strand_status[scene.model.needle.node_count :] == NODE_IN)
        ),
        "diverged": bool(scene.state.diverged),
        "dt_s": DT,
        "solver": asdict(solver),
        "puncture_force_n": BENCH_PUNCTURE_FORCE,
    }
