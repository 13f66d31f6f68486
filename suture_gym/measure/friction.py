"""Friction of the thread along its path through the tissue.

The model (:class:`~suture_gym.sim.coupling.CouplingParams` ``suture_axial_friction`` ``f``, N/m): kinetic,
Coulomb-like friction per unit length of embedded thread, independent of speed and of the thread's tension
(no capstan term). Each suture node on a path has a friction cap ``f s_j`` (N, ``s_j`` its share of thread
length, m): a row of the rod's direct solve holds its slip along the path's tangent at 0 while the friction
it needs stays within the cap (stick) and at the cap otherwise (slide). Pulled at any constant speed, a thread
with ``L`` m inside the tissue therefore resists with ``F = f L``.

The check drives a thread through a block of the environments' default tissue along a straight path and reads
the force at the holder against the embedded length. Everything is the environments' own: the pad
(:class:`~suture_gym.envs.config.SceneConfig`: 8 x 24 x 8 mm, 2 mm cells; :class:`TissueConfig`: 300 kPa,
nu 0.45), the coupling (:class:`CouplingConfig`: puncture, cutting, needle friction, tear force), SutureThrow's
thread (31 nodes, 3 cm) and the solver (:class:`SolverConfig`: 1 ms substeps, 5 per env step, 2 sweeps,
quasi-Newton tissue). The needle is the environments' wire, 26 mm long, on a circle of :data:`NEEDLE_RADIUS`
(8.5e-5 m off straight over its length), so the path is straight and the pull lies along it; it is held by
a position-controlled holder (:data:`HOLDER`, as in :mod:`suture_gym.measure.insertion`) that moves at
:data:`SPEED` along the path through the middle of the pad: the needle pierces the side face ``y = 0``, leaves
through ``y = 24 mm`` and draws the thread after it until the thread's free end has left the tissue too.
"""

from __future__ import annotations

import functools
import math
from dataclasses import asdict, replace

import numpy as np

from suture_gym.envs.config import CouplingConfig, NeedleConfig, SceneConfig, SolverConfig, SutureConfig, TissueConfig
from suture_gym.measure.registry import CheckResult, check
from suture_gym.sim.model import Control
from suture_gym.sim.needle import NeedleModel, VirtualCoupling
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.sim.scenes import Scene, add_strands, needle_circle_pose, suturing_pad
from suture_gym.tasks.suture_throw import SutureThrow

FRICTION = 30.0  # N/m: 0.72 N over the pad's 24 mm (suture drag through tissue: 0.1-1 N over a stitch)
SPEED = 0.02  # m/s: the scripted surgeon's needle draws the thread at about 0.8 cm/s (SutureThrow-v3, seed 0)
NEEDLE_RADIUS = 1.0  # m: the needle's 26 mm arc is 8.5e-5 m off straight
#: The holder: so heavy that the tissue cannot change its motion (a position-controlled robot).
HOLDER = {"holder_mass": 1.0e3, "holder_inertia": 10.0}
DRIVE_RATE = 100.0  # rad/s, natural frequency of the drive's spring-damper (critically damped)
#: The path: along +y at this (x, z), m, inside cells of the 2 mm grid (off its planes).
PATH_XZ = (0.0045, 0.0045)
START_GAP = 1.0e-3  # m, the tip starts this far before the face y = 0
SETTLE = 0.05  # s after the needle has left the tissue before the force is read (the exit's dent springs back)
#: Tolerance on the slope, relative. The friction is that of the nodes inside, ``f`` times their shares, so it
#: steps by ``f s`` (one 1 mm segment) as nodes pass the access points, where ``f L`` is continuous: a least-
#: squares line through such a staircase over the 24 mm of the path can tilt by about one step over the
#: range, 1 / 24 = 4%; 5% allows for the tissue's own response.
SLOPE_TOLERANCE = 0.05
#: Bound on the mean force without friction, as a fraction of ``f L`` at the full path: a free thread drawn at
#: constant speed needs none (its weight, 1e-5 N, and inertia are below 1e-4 of it).
ZERO_FRICTION_TOLERANCE = 0.01


def friction_pad(friction: float) -> tuple[Scene, dict]:
    """The environments' default pad with the straight needle in front of its face ``y = 0`` (module
    docstring), SutureThrow's thread trailing behind it along ``-y``, and the environments' coupling with
    ``suture_axial_friction = friction`` N/m. Returns the scene and the configs it used, ``{"scene":
    SceneConfig, "tissue": TissueConfig, "solver": SolverConfig}``."""
    scene_cfg, tissue = SceneConfig(), TissueConfig()
    cells = tuple(int(round(s / scene_cfg.cell_size)) for s in scene_cfg.size)
    base = suturing_pad(size=scene_cfg.size, cells=cells, material=tissue)
    wire = NeedleConfig()
    arc_length = wire.shape().arc_angle * wire.curvature_radius
    shape = replace(wire.shape(), arc=arc_length / NEEDLE_RADIUS, curvature_radius=NEEDLE_RADIUS, **HOLDER)
    needle = NeedleModel.from_shape(shape)
    center = np.array([PATH_XZ[0], -START_GAP, PATH_XZ[1] + NEEDLE_RADIUS])
    pose = needle_circle_pose(needle, center, (1.0, 0.0, 0.0), (0.0, 1.0, 0.0), -0.5 * math.pi)
    thread = SutureConfig(**SutureThrow.CONFIG["suture"]).params()
    coupling = CouplingConfig(suture_axial_friction=friction).params()
    scene = add_strands(base, pose, needle_shape=shape, gravity_compensation=wire.gravity_compensation,
                        suture_params=thread, suture_direction=(0.0, -1.0, 0.0), coupling_params=coupling)  # fmt: skip
    return scene, {"scene": scene_cfg, "tissue": tissue, "solver": SolverConfig()}


def duration(scene: Scene) -> float:
    """Seconds of drive until the thread's free end is :data:`START_GAP` past the far face: the tip's travel
    of the gap, the pad, the needle and the thread, at :data:`SPEED`."""
    coupling = scene.model.coupling
    strand = float(coupling.strand_sigma[-1])
    return (2.0 * START_GAP + SceneConfig().size[1] + strand) / SPEED


def pull_through(friction: float) -> dict:
    """Drive the needle and thread of :func:`friction_pad` through the pad at :data:`SPEED`; returns per
    substep: ``time`` s, ``force`` N (the constraint force on the needle against its travel: while the needle
    is out of the tissue, the thread's pull at the swage), ``thread_in`` and ``needle_in`` m (the thread's and
    the needle's length between the entry and exit coordinates of the paths), ``friction_rows`` N (the sum of
    the thread's friction rows), the solver config, the scene and whether it diverged or tore."""
    scene, cfg = friction_pad(friction)
    model, state = scene.model, scene.state
    needle, coupling = model.needle, model.coupling
    solver_cfg = cfg["solver"]
    solver, dt = solver_cfg.solver(), solver_cfg.dt
    mass, inertia = needle.body_mass, float(np.trace(needle.body_inertia)) / 3.0
    drive = VirtualCoupling(
        linear_stiffness=mass * DRIVE_RATE**2, linear_damping=2.0 * mass * DRIVE_RATE,
        angular_stiffness=inertia * DRIVE_RATE**2, angular_damping=2.0 * inertia * DRIVE_RATE,
    )  # fmt: skip
    rotation = quat_to_matrix(state.needle.body_quat)
    grip0 = state.needle.body_pos + rotation @ needle.grip_pos_body
    quat0 = state.needle.body_quat.copy()
    velocity = np.array([0.0, SPEED, 0.0])
    nn = coupling.needle_node_count
    swage, end = float(coupling.strand_sigma[nn - 1]), float(coupling.strand_sigma[-1])
    control = Control()
    names = ("time", "force", "thread_in", "needle_in", "friction_rows")
    samples = {name: [] for name in names}
    for k in range(int(round(duration(scene) / dt))):
        if k % solver_cfg.substeps == 0:
            control.needle_wrench = drive.wrench(needle, state.needle, grip0 + velocity * k * dt, quat0, velocity)
        solver.step(model, state, control, dt)
        c = state.coupling
        thread_in = needle_in = 0.0
        for p in range(c.path_count):
            hi = float(c.path_sigma_entry[p])
            lo = 0.0 if c.path_open[p] else float(c.path_sigma_exit[p])
            thread_in += max(0.0, min(hi, end) - max(lo, swage))
            needle_in += max(0.0, min(hi, swage) - max(lo, 0.0))
        rows = state.work.coupling_work.row_friction_lambda[nn:]
        samples["time"].append((k + 1) * dt)
        samples["force"].append(-float(state.needle_reaction[:3] @ velocity) / SPEED)
        samples["thread_in"].append(thread_in)
        samples["needle_in"].append(needle_in)
        samples["friction_rows"].append(float(np.abs(rows).sum()) / dt**2 if friction > 0.0 else 0.0)
        if state.diverged:
            break
    out = {name: np.asarray(v) for name, v in samples.items()}
    out.update(diverged=bool(state.diverged), damaged=bool(state.coupling.damaged), scene=scene, config=cfg)
    return out


def thread_window(run: dict) -> np.ndarray:
    """``(T,) bool``: the samples with the needle out of the tissue for :data:`SETTLE` s and thread inside."""
    t = run["time"]
    out = run["needle_in"] == 0.0
    first_out = np.flatnonzero(out & (run["thread_in"] > 0.0))
    if first_out.size == 0:
        return np.zeros(t.size, bool)
    return out & (t >= t[first_out[0]] + SETTLE) & (run["thread_in"] > 0.0)


@functools.lru_cache(maxsize=1)
def _runs() -> tuple[dict, dict]:
    return pull_through(FRICTION), pull_through(0.0)


@check("suture_friction_slope")
def check_suture_friction_slope() -> CheckResult:
    """The thread drawn through the pad at constant speed (module docstring), with ``suture_axial_friction``
    :data:`FRICTION` and with 0. Over the samples where only thread is inside (:func:`thread_window`: the full
    path, then the free end's way through), the least-squares slope of the pull force against the embedded
    length must be the friction, and without friction the mean force must vanish.

    Measured: ``|slope / f - 1|``, bound :data:`SLOPE_TOLERANCE`; NaN (a fail) if the run without friction
    pulls with more than :data:`ZERO_FRICTION_TOLERANCE` of ``f`` times the path's length on average, or either
    run diverged or tore the tissue (``details.criteria``)."""
    run, free = _runs()
    window = thread_window(run)
    length, force = run["thread_in"][window], run["force"][window]
    slope, intercept = np.polyfit(length, force, 1) if window.sum() >= 2 else (math.nan, math.nan)
    full = float(length.max()) if window.any() else math.nan
    free_window = thread_window(free)
    free_mean = float(free["force"][free_window].mean()) if free_window.any() else math.nan
    criteria = {
        "no_friction_force_vanishes": bool(abs(free_mean) <= ZERO_FRICTION_TOLERANCE * FRICTION * full),
        "not_diverged": not (run["diverged"] or free["diverged"]),
        "not_torn": not (run["damaged"] or free["damaged"]),
    }
    error = float(abs(slope / FRICTION - 1.0))
    cfg = run["config"]
    every = slice(cfg["solver"].substeps - 1, None, cfg["solver"].substeps)
    return CheckResult(
        name="suture_friction_slope",
        measured=error if all(criteria.values()) else math.nan,
        reference=0.0,
        tolerance=SLOPE_TOLERANCE,
        unit="relative slope error",
        comparison="<=",
        settings={
            "dt_s": cfg["solver"].dt,
            "substeps_per_env_step": cfg["solver"].substeps,
            "solver": asdict(cfg["solver"]),
            "mesh": run["scene"].settings,
            "tissue": asdict(cfg["tissue"]),
            "suture_axial_friction_n_m": FRICTION,
            "model": "kinetic friction per unit length of thread in the paths: F = f L, N",
            "speed_m_s": SPEED,
            "path": {"direction": [0.0, 1.0, 0.0], "x_z_m": list(PATH_XZ), "start_gap_m": START_GAP},
            "needle_radius_m": NEEDLE_RADIUS,
            "holder": HOLDER,
            "drive_rate_rad_s": DRIVE_RATE,
            "settle_s": SETTLE,
        },
        details={
            "slope_n_m": float(slope),
            "intercept_n": float(intercept),
            "full_path_m": full,
            "force_at_full_path_n": float(force[length == full].mean()) if window.any() else math.nan,
            "friction_rows_slope_n_m": float(np.polyfit(length, run["friction_rows"][window], 1)[0])
            if window.sum() >= 2
            else math.nan,
            "no_friction_mean_force_n": free_mean,
            "no_friction_max_abs_force_n": float(np.abs(free["force"][free_window]).max())
            if free_window.any()
            else math.nan,
            "criteria": criteria,
            "curve": {
                "time_s": run["time"][every].tolist(),
                "force_n": run["force"][every].tolist(),
                "no_friction_force_n": free["force"][every].tolist(),
                "thread_in_m": run["thread_in"][every].tolist(),
                "needle_in_m": run["needle_in"][every].tolist(),
            },
        },
    )
