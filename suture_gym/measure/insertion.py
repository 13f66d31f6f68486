"""Needle insertion force checks: the force a position-controlled holder feels while it drives a
semicircle needle through a realistic pad along its own arc, and how the force before puncture depends on the
mesh.

The pad models a platinum-cure silicone suture-training pad of the Dragon Skin 10 class: E = 150 kPa (the
order of the 152 kPa "100 % modulus" of Smooth-On's Dragon Skin 10 technical bulletin; a secant modulus at
100 % strain, so a lower bound of the small-strain modulus), nu = 0.45, 3 x 3 x 1 cm on a rigid base, in 2 mm
cells. Everything runs at the environments' control rate: 1 ms substeps, the drive updated every
:data:`SUBSTEPS` substeps (one env step), with the implicit tissue integrator (``quasi_newton``, 2 sweeps).

The drive is kinematic in effect: the holder is a 1000 kg, 10 kg m^2 body (:data:`HOLDER`: a robot's
position-controlled stage, whose motion the tissue's forces do not change) pulled onto the needle's circle
at :data:`OMEGA` by a spring-damper of 100 rad/s with velocity feed-forward, so the needle turns at constant
angular speed whatever the tissue does. The force is the tissue's reaction along the arc: the constraint
moment on the needle about the circle's axis through its centre divided by the radius (positive when it
resists the turn), the force a sensor at the holder reads along the needle's path.
"""

from __future__ import annotations

import math
from dataclasses import asdict, replace

import numpy as np

from suture_gym.measure.registry import CheckResult, check
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.model import Control, TissueMaterial
from suture_gym.sim.needle import NeedleModel, NeedleShape, VirtualCoupling
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.scenes import Scene, add_strands, needle_circle_pose, suturing_pad
from suture_gym.sim.solver import Solver
from suture_gym.tasks.surgeon import TURN_RATE, circle_grip_target

DT = 1.0e-3  # s, the environments' substep
SUBSTEPS = 5  # substeps per env step: the drive's target is updated once per env step
SOLVER = Solver(tissue_integrator="quasi_newton", iterations=2, max_speed=50.0)
PAD_MATERIAL = TissueMaterial(youngs_modulus=1.5e5, poisson_ratio=0.45)
PAD_SIZE = (0.03, 0.03, 0.01)  # m
CELL = 2.0e-3  # m
#: The needle's circle: in the plane x = ARC_X (between the grid planes of 2 mm and 1 mm cells), normal +x,
#: its centre ARC_HEIGHT above the middle of the top face, so the arc dips 4.8 mm into the pad and enters and
#: leaves through the top face 15 mm apart; it starts 0.08 rad before the tip touches.
ARC_X = 0.0155
ARC_HEIGHT = 3.5e-3
ARC_AXIS = (1.0, 0.0, 0.0)
ARC_U = (0.0, 1.0, 0.0)
START_GAP = 0.08  # rad
OMEGA = TURN_RATE  # rad/s, the scripted surgeon's turn rate
#: The holder: so heavy that the tissue cannot change its motion (a position-controlled robot).
HOLDER = NeedleShape(holder_mass=1.0e3, holder_inertia=10.0)
DRIVE_RATE = 100.0  # rad/s, natural frequency of the drive's spring-damper (critically damped)
#: The force model at the scale of a silicone pad: a 1 N puncture, the exit at half of it (Frick et al. 2001
#: measure the exit peak at about half the entry's), a cutting force of a fifth of the puncture force (Okamura
#: et al. 2004 model it as constant per tip and tissue; not measured for this pad), a needle friction of
#: 10 N/m and the tip-contact patch (an effective radius of 1 mm for the tissue the tapered tip loads), chosen
#: by ``pre_puncture_stiffness_vs_mesh``: with the rows on the implicit tissue's exact compliance, the point tip's
#: slope is the mesh's (a point load on a coarser mesh is stiffer), the patch's is the tip's.
TIP_CONTACT_RADIUS = 1.0e-3
COUPLING = CouplingParams(
    puncture_force=1.0, exit_puncture_force=0.5, cutting_force=0.2, tip_contact_radius=TIP_CONTACT_RADIUS,
    tear_force=4.0, needle_axial_friction=10.0
)
#: A window after the puncture over which the force is not judged, s: the dent left by the entry springs back.
SETTLE = 0.02
#: Force window of the pre-puncture slope, as fractions of the puncture force.
SLOPE_WINDOW = (0.2, 0.8)


def insertion_pad(
    cell: float = CELL, coupling: CouplingParams = COUPLING, size: tuple = PAD_SIZE, entry_centred: bool = False
) -> tuple[Scene, dict]:
    """The pad (:data:`PAD_MATERIAL`, ``size`` m, cubic cells of ``cell`` m) with the default half-circle
    needle on its circle (module docstring) held by :data:`HOLDER`, a free 2 cm suture straight up from the
    swage, and ``coupling``. The circle is centred over the middle of the top face, or, with ``entry_centred``,
    placed so that the tip enters there (for a pad too small for the whole bite). Returns the scene and the
    circle ``{center, axis, u, start_angle, radius}``."""
    cells = tuple(int(round(s / cell)) for s in size)
    base = suturing_pad(size=size, cells=cells, material=PAD_MATERIAL)
    radius = NeedleModel.from_shape(HOLDER).shape.curvature_radius
    shift = math.sqrt(radius**2 - ARC_HEIGHT**2) if entry_centred else 0.0
    center = np.array([ARC_X - 0.5 * PAD_SIZE[0] + 0.5 * size[0], 0.5 * size[1] + shift, size[2] + ARC_HEIGHT])
    start = math.pi + math.asin(ARC_HEIGHT / radius) - START_GAP
    needle = NeedleModel.from_shape(HOLDER)
    scene = add_strands(
        base,
        needle_circle_pose(needle, center, ARC_AXIS, ARC_U, start),
        needle_shape=HOLDER,
        suture_params=SutureParams(length=0.02, node_count=21),
        suture_direction=(0.0, 0.0, 1.0),
        coupling_params=coupling,
    )
    circle = {"center": center, "axis": np.array(ARC_AXIS), "u": np.array(ARC_U), "start_angle": start,
              "radius": radius}  # fmt: skip
    return scene, circle


def drive_insertion(scene: Scene, circle: dict, duration: float, stop_at_puncture: bool = False) -> dict:
    """Turn the needle of ``scene`` about ``circle``'s centre at :data:`OMEGA` for ``duration`` s (module
    docstring), or until the first puncture; returns the samples of every substep as arrays: ``time`` s,
    ``force`` N (the reaction along the arc), ``tip_force``, ``cut_force``, ``friction_force`` N, ``travel`` m
    (the tip's arc length turned since the start), ``embedded`` m (strand length behind the newest path's
    entry), ``open`` (a puncture is open), ``exit_anchor`` (the tip presses on an exit anchor), ``punctures``,
    ``exits`` (closed paths) and whether it diverged."""
    model, state = scene.model, scene.state
    needle = model.needle
    center, axis, u, start, radius = (circle[k] for k in ("center", "axis", "u", "start_angle", "radius"))
    v = np.cross(axis, u)
    mass, inertia = needle.body_mass, float(np.trace(needle.body_inertia)) / 3.0
    drive = VirtualCoupling(
        linear_stiffness=mass * DRIVE_RATE**2, linear_damping=2.0 * mass * DRIVE_RATE,
        angular_stiffness=inertia * DRIVE_RATE**2, angular_damping=2.0 * inertia * DRIVE_RATE,
    )  # fmt: skip
    control = Control()
    names = ("time", "force", "tip_force", "cut_force", "friction_force", "travel", "embedded", "open",
             "exit_anchor", "punctures", "exits")  # fmt: skip
    samples = {name: [] for name in names}
    steps = int(round(duration / DT))
    for k in range(steps):
        if k % SUBSTEPS == 0:
            target_pos, target_quat = circle_grip_target(needle, center, axis, u, start + OMEGA * k * DT)
            target_vel = OMEGA * np.cross(axis, target_pos - center)
            control.needle_wrench = drive.wrench(needle, state.needle, target_pos, target_quat, target_vel,
                                                 OMEGA * axis)  # fmt: skip
        SOLVER.step(model, state, control, DT)
        rotation = quat_to_matrix(state.needle.body_quat)
        grip = state.needle.body_pos + rotation @ needle.grip_pos_body
        tip = state.needle.body_pos + rotation @ needle.tip_pos_body - center
        reaction = state.needle_reaction
        moment = reaction[3:] + np.cross(grip - center, reaction[:3])
        c = state.coupling
        newest = c.path_count - 1
        samples["time"].append((k + 1) * DT)
        samples["force"].append(-float(moment @ axis) / radius)
        samples["tip_force"].append(c.tip_force)
        samples["cut_force"].append(c.cut_force)
        samples["friction_force"].append(c.friction_force)
        samples["travel"].append(radius * (math.atan2(tip @ v, tip @ u) % (2.0 * math.pi) - start % (2.0 * math.pi)))
        samples["embedded"].append(float(c.path_sigma_entry[newest]) if newest >= 0 else 0.0)
        samples["open"].append(c.punctured)
        samples["exit_anchor"].append(c.tip_anchor_inside)
        samples["punctures"].append(c.punctures)
        samples["exits"].append(int(np.count_nonzero(~c.path_open[: c.path_count])))
        if state.diverged or (stop_at_puncture and c.punctures > 0):
            break
    out = {name: np.asarray(values, dtype=np.float64) for name, values in samples.items()}
    out["diverged"] = bool(state.diverged)
    return out


def _insertion_settings(scene: Scene, circle: dict, duration: float) -> dict:
    return {
        "scene": scene.settings,
        "tissue": "silicone suture-training pad, Dragon Skin 10 class (module docstring)",
        "circle": {
            "center_m": circle["center"].tolist(),
            "axis": list(ARC_AXIS),
            "u": list(ARC_U),
            "start_angle_rad": circle["start_angle"],
            "radius_m": circle["radius"],
        },
        "angular_speed_rad_s": OMEGA,
        "holder": asdict(HOLDER),
        "drive_rate_rad_s": DRIVE_RATE,
        "dt_s": DT,
        "substeps_per_env_step": SUBSTEPS,
        "solver": asdict(SOLVER),
        "duration_s": duration,
    }


def insertion_profile(run: dict, puncture_force: float) -> dict:
    """The features of an insertion's force curve (``run`` from :func:`drive_insertion`): the entry peak (the
    largest force up to 5 substeps after the puncture), the force inside (from :data:`SETTLE` after the
    puncture until the exit anchor first engages, or until the exit): its smallest value and its least-squares
    slope against the embedded length, and the exit peak (the largest force from the exit anchor's first
    engagement to 5 substeps after the exit). Times in s, forces in N; NaN where a phase did not happen."""
    t, force = run["time"], run["force"]
    nan = math.nan
    pierced = np.flatnonzero(run["punctures"] > 0)
    if pierced.size == 0:
        return {"entry_peak_n": nan, "exit_peak_n": nan, "inside_min_n": nan, "inside_slope_n_m": nan,
                "puncture_time_s": nan, "exit_time_s": nan, "exit_anchor_time_s": nan}  # fmt: skip
    i_p = int(pierced[0])
    entry = float(force[: i_p + 6].max())
    after = np.arange(t.size) > i_p
    exited = np.flatnonzero(after & (run["exits"] > 0))
    i_x = int(exited[0]) if exited.size else t.size
    anchored = np.flatnonzero(after & (run["exit_anchor"] > 0) & (np.arange(t.size) < i_x))
    i_a = int(anchored[0]) if anchored.size else i_x
    inside = after & (t >= t[i_p] + SETTLE) & (np.arange(t.size) < i_a)
    slope = nan
    if np.count_nonzero(inside) >= 2:
        slope = float(np.polyfit(run["embedded"][inside], force[inside], 1)[0])
    exit_peak = float(force[i_a : i_x + 6].max()) if exited.size else nan
    return {
        "entry_peak_n": entry,
        "exit_peak_n": exit_peak,
        "inside_min_n": float(force[inside].min()) if inside.any() else nan,
        "inside_slope_n_m": slope,
        "puncture_time_s": float(t[i_p]),
        "exit_time_s": float(t[i_x]) if exited.size else nan,
        "exit_anchor_time_s": float(t[i_a]) if anchored.size else nan,
        "puncture_force_n": puncture_force,
    }


INSERTION_DURATION = 3.0  # s: the tip leaves the pad about 2.4 s after the start


@check("insertion_force_profile")
def check_insertion_force_profile() -> CheckResult:
    """A semicircle needle driven through the silicone pad along its arc at constant angular speed (module
    docstring), with a 1 N puncture threshold, a 0.5 N exit threshold and a 0.2 N cutting force. The curve must
    show an entry peak within 5% of the threshold, a force after the entry that stays > 0 and rises with the
    embedded length (cutting + friction), and an exit peak between 0.3 and 0.8 times the entry peak.

    Measured: exit peak / entry peak, reference 0.55, tolerance 0.25; NaN (a fail) if any other criterion
    fails (``details.criteria`` says which). The full curve, one sample per env step, is in ``details.curve``."""
    scene, circle = insertion_pad()
    run = drive_insertion(scene, circle, INSERTION_DURATION)
    profile = insertion_profile(run, COUPLING.puncture_force)
    entry, exit_peak = profile["entry_peak_n"], profile["exit_peak_n"]
    ratio = exit_peak / entry if entry > 0.0 else math.nan
    criteria = {
        "entry_peak_within_5_percent": bool(abs(entry - COUPLING.puncture_force) <= 0.05 * COUPLING.puncture_force),
        "force_inside_positive": bool(profile["inside_min_n"] > 0.0),
        "force_rises_with_embedded_length": bool(profile["inside_slope_n_m"] > 0.0),
        "exit_peak_found": bool(math.isfinite(exit_peak)),
        "not_diverged": not run["diverged"],
    }
    every = slice(SUBSTEPS - 1, None, SUBSTEPS)
    curve = {name: run[name][every].tolist() for name in ("time", "force", "tip_force", "cut_force",
                                                          "friction_force", "embedded")}  # fmt: skip
    return CheckResult(
        name="insertion_force_profile",
        measured=ratio if all(criteria.values()) else math.nan,
        reference=0.55,
        tolerance=0.25,
        unit="exit peak / entry peak",
        settings=_insertion_settings(scene, circle, INSERTION_DURATION),
        details={"exit_to_entry_ratio": ratio, "criteria": criteria, **profile, "curve": curve},
    )


def pre_puncture_slope(run: dict, puncture_force: float) -> float:
    """Least-squares slope (N/m) of the force against the tip's travel before the puncture, over the samples
    whose force lies in :data:`SLOPE_WINDOW` times ``puncture_force`` (NaN with fewer than two)."""
    before = run["punctures"] == 0
    lo, hi = SLOPE_WINDOW
    window = before & (run["force"] >= lo * puncture_force) & (run["force"] <= hi * puncture_force)
    if np.count_nonzero(window) < 2:
        return math.nan
    return float(np.polyfit(run["travel"][window], run["force"][window], 1)[0])


PRE_PUNCTURE_DURATION = 1.0  # s: at most; the runs stop at the puncture (about 0.4 s)
#: The pad of the mesh comparison, m: smaller than the insertion's (the 1 mm mesh of the full pad takes minutes
#: to factorise), the tip entering at the middle of its top face.
MESH_PAD_SIZE = (0.016, 0.016, 0.008)


@check("pre_puncture_stiffness_vs_mesh")
def check_pre_puncture_stiffness_vs_mesh() -> CheckResult:
    """The force-travel slope before puncture (over :data:`SLOPE_WINDOW` of the 1 N threshold) on a
    1.6 x 1.6 x 0.8 cm silicone pad (:data:`MESH_PAD_SIZE`) with cells of 2 mm and 1 mm, the needle driven
    along its arc as in ``insertion_force_profile``, with the tip-contact patch model (:data:`TIP_CONTACT_RADIUS`,
    the model :data:`COUPLING` uses, chosen by this comparison) and with the point tip (``tip_contact_radius`` 0:
    the tip is a point of its anchor triangle, and the needle nodes within ``tip_length`` share the load through
    their own contact rows once the dent is deeper than their spacing). Measured: |slope(1 mm) / slope(2 mm) - 1|
    of the patch model; reference 0, tolerance 0.2. The point tip's figure is in the details."""
    slopes = {}
    point = replace(COUPLING, tip_contact_radius=0.0)
    for label, coupling in (("tip_contact", COUPLING), ("point_tip", point)):
        for cell in (CELL, 0.5 * CELL):
            scene, circle = insertion_pad(cell, coupling, MESH_PAD_SIZE, entry_centred=True)
            run = drive_insertion(scene, circle, PRE_PUNCTURE_DURATION, stop_at_puncture=True)
            slopes[f"{label}_{cell * 1e3:g}mm_n_m"] = pre_puncture_slope(run, coupling.puncture_force)
    coarse, fine = (slopes[f"tip_contact_{c * 1e3:g}mm_n_m"] for c in (CELL, 0.5 * CELL))
    point_coarse, point_fine = (slopes[f"point_tip_{c * 1e3:g}mm_n_m"] for c in (CELL, 0.5 * CELL))
    scene, circle = insertion_pad(CELL, COUPLING, MESH_PAD_SIZE, entry_centred=True)
    return CheckResult(
        name="pre_puncture_stiffness_vs_mesh",
        measured=abs(fine / coarse - 1.0),
        reference=0.0,
        tolerance=0.2,
        unit="relative change of the slope",
        comparison="<=",
        settings={
            **_insertion_settings(scene, circle, PRE_PUNCTURE_DURATION),
            "cells_m": [CELL, 0.5 * CELL],
            "slope_window": list(SLOPE_WINDOW),
        },
        details={
            **slopes,
            "point_tip_relative_change": abs(point_fine / point_coarse - 1.0),
            "tip_contact_radius_m": TIP_CONTACT_RADIUS,
        },
    )
