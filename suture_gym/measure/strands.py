"""Needle and suture checks against analytic references, and the needle + suture benchmark.

Every check builds its models from the library defaults (:class:`~suture_gym.sim.needle.NeedleShape`,
:class:`~suture_gym.sim.rod.SutureParams`) unless its ``settings`` say otherwise, steps needle and suture on
their own (no tissue) with :meth:`~suture_gym.sim.solver.Solver.step` at the default rod solver settings
(``iterations``, ``tolerance``) and records every parameter it used in ``settings``.
"""

from __future__ import annotations

import functools
import math
import time
from dataclasses import asdict

import numpy as np
from scipy.integrate import solve_ivp

from suture_gym.measure.registry import CheckResult, benchmark, check
from suture_gym.sim.model import Control, Model, State
from suture_gym.sim.needle import (
    NeedleModel,
    NeedleShape,
    NeedleState,
    VirtualCoupling,
    needle_point_world,
    wrench_at_com,
)
from suture_gym.sim.quat import (
    quat_conj,
    quat_from_axis_angle,
    quat_from_two_vectors,
    quat_mul,
    quat_rotation_vector,
    quat_to_matrix,
)
from suture_gym.sim.rod import (
    RodModel,
    RodState,
    StaticObstacles,
    SutureMaterial,
    SutureParams,
    segment_strain,
)
from suture_gym.sim.solver import Solver

GRAVITY = 9.81  # m/s^2
DT = 1.0e-3  # s, default substep
ITERATIONS = 8  # default most direct solves per substep (Solver.rod_iterations' default)
TOLERANCE = 1.0e-6  # default solver tolerance (Solver.rod_tolerance's default)
#: m/s, the solver's divergence guard; the 45 degree pull of ``suture_stretch_pull`` whips the free end at
#: ~110 m/s in its first substep, above the 50 m/s default, which would freeze the state as diverged.
MAX_SPEED = 1.0e3
SOLVER = Solver(max_speed=MAX_SPEED, rod_iterations=ITERATIONS, rod_tolerance=TOLERANCE, iterations=1,
                tissue_integrator="xpbd")


def _solver_settings(dt: float) -> dict:
    return {"dt_s": dt, "iterations_max": ITERATIONS, "tolerance": TOLERANCE, "max_speed_m_s": MAX_SPEED}


def _strands(
    gravity: float = GRAVITY,
    needle: NeedleModel | None = None,
    needle_state: NeedleState | None = None,
    suture: RodModel | None = None,
    suture_state: RodState | None = None,
    obstacles: StaticObstacles | None = None,
) -> tuple[Model, State]:
    """Model of needle and/or suture on their own (no tissue), ``gravity`` m/s^2 along -z, and its initial
    State holding the given needle and suture states (advanced in place by :data:`SOLVER`)."""
    model = Model(needle=needle, suture=suture, gravity=(0.0, 0.0, -gravity), obstacles=obstacles)
    return model, State.initial(model, needle=needle_state, suture=suture_state)


def _step(model: Model, state: State, control: Control, dt: float, timings: dict | None = None) -> int:
    """One :data:`SOLVER` substep (phase times added to ``timings``); returns the number of direct rod solves it
    used. A diverged state (which the solver would leave frozen) raises instead of being measured."""
    SOLVER.step(model, state, control, dt, timings=timings)
    if state.diverged:
        raise RuntimeError(f"the simulation diverged near t = {state.time:.4f} s")
    return state.work.rod_solves


# ---------------------------------------------------------------------------------------------------------
# Needle free flight
# ---------------------------------------------------------------------------------------------------------


def _free_flight_reference(model: NeedleModel, state: NeedleState, wrench: np.ndarray, duration: float):
    """High-accuracy Newton-Euler solution (DOP853) for a constant world wrench at the grip point."""
    force = wrench[:3]
    torque_grip = wrench[3:]
    inertia_body = model.body_inertia

    def rhs(_t, y):
        q = y[6:10] / np.linalg.norm(y[6:10])
        w = y[10:13]
        r = quat_to_matrix(q)
        torque = torque_grip + np.cross(r @ model.grip_pos_body, force)
        inertia = r @ inertia_body @ r.T
        dw = np.linalg.solve(inertia, torque - np.cross(w, inertia @ w))
        wq = np.array([0.0, *w])
        dq = 0.5 * np.array(
            [
                wq[0] * q[0] - wq[1] * q[1] - wq[2] * q[2] - wq[3] * q[3],
                wq[0] * q[1] + wq[1] * q[0] + wq[2] * q[3] - wq[3] * q[2],
                wq[0] * q[2] - wq[1] * q[3] + wq[2] * q[0] + wq[3] * q[1],
                wq[0] * q[3] + wq[1] * q[2] - wq[2] * q[1] + wq[3] * q[0],
            ]
        )
        return np.concatenate([y[3:6], force / model.body_mass, dq, dw])

    y0 = np.concatenate([state.body_pos, state.body_vel, state.body_quat, state.body_omega])
    sol = solve_ivp(rhs, (0.0, duration), y0, method="DOP853", rtol=1e-11, atol=1e-14)
    y = sol.y[:, -1]
    return y[3:6], y[6:10] / np.linalg.norm(y[6:10]), y[10:13]


@check("needle_free_flight")
def check_needle_free_flight() -> CheckResult:
    """Constant grip wrench in free flight (no gravity, no damping): ``F = m a`` and ``tau = I alpha``, within 1%.

    The holder is a point mass at the grip (``holder_inertia = 0``) so the inertia about the centre of mass is
    the needle's own, strongly anisotropic and with products of inertia; the needle starts tilted and the
    torque about the centre of mass is split equally between the softest and the stiffest principal axes.
    Measured: the largest relative error among (a) the mean linear acceleration vs ``F/m``, (b) the
    first-substep angular acceleration vs ``I_world^-1 tau_com``, and (c) the angular velocity and (d) the
    rotation after ``T`` vs a DOP853 solution of Euler's equations (gyroscopic term included, torque
    ``tau_grip + r_grip x F`` following the body).
    """
    shape = NeedleShape(holder_inertia=0.0)
    model = NeedleModel.from_shape(shape)
    quat0 = quat_from_axis_angle(np.array([1.0, 2.0, 0.5]), 0.7)
    state = NeedleState.at_rest([0.0, 0.0, 0.1], quat0)
    # torque about the centre of mass split equally between the softest and stiffest principal axes (world)
    r0 = quat_to_matrix(quat0)
    eig, vec = np.linalg.eigh(model.body_inertia)
    force = np.array([1.0e-5, -2.0e-5, 0.5e-5])
    torque_target = 4.0e-9 * (r0 @ vec[:, 0] + r0 @ vec[:, 2])
    grip_offset = r0 @ model.grip_pos_body
    wrench = np.concatenate([force, torque_target - np.cross(grip_offset, force)])
    dt, duration = DT, 0.5
    steps = int(round(duration / dt))

    force, torque_com = wrench_at_com(model, state, wrench)
    alpha_ref = np.linalg.solve(r0 @ model.body_inertia @ r0.T, torque_com)
    system, full = _strands(gravity=0.0, needle=model, needle_state=state)
    control = Control(needle_wrench=wrench)
    _step(system, full, control, dt)
    alpha_first = state.body_omega / dt
    for _ in range(steps - 1):
        _step(system, full, control, dt)

    reference = NeedleState.at_rest([0.0, 0.0, 0.1], quat0)
    vel_ref, quat_ref, omega_ref = _free_flight_reference(model, reference, wrench, duration)
    accel_ref = force / model.body_mass
    err_lin = float(np.linalg.norm(state.body_vel / duration - accel_ref) / np.linalg.norm(accel_ref))
    err_alpha = float(np.linalg.norm(alpha_first - alpha_ref) / np.linalg.norm(alpha_ref))
    err_omega = float(np.linalg.norm(state.body_omega - omega_ref) / np.linalg.norm(omega_ref))
    rot_total = float(np.linalg.norm(quat_rotation_vector(quat_mul(quat_ref, quat_conj(quat0)))))
    rot_err = float(np.linalg.norm(quat_rotation_vector(quat_mul(state.body_quat, quat_conj(quat_ref)))))
    err_rot = rot_err / rot_total
    angle = math.degrees(
        math.acos(float(alpha_ref @ torque_com / (np.linalg.norm(alpha_ref) * np.linalg.norm(torque_com))))
    )
    measured = max(err_lin, err_alpha, err_omega, err_rot)
    return CheckResult(
        name="needle_free_flight",
        measured=measured,
        reference=0.0,
        tolerance=0.01,
        unit="rel",
        comparison="<=",
        settings={
            "needle_shape": asdict(shape),
            "initial_quat": quat0.tolist(),
            "wrench_grip": wrench.tolist(),
            "duration_s": duration,
            "dt_s": dt,
            "gravity": 0.0,
            "damping": 0.0,
            "reference_integrator": "scipy DOP853 rtol 1e-11",
        },
        details={
            "rel_err_linear_acceleration": err_lin,
            "rel_err_first_angular_acceleration": err_alpha,
            "rel_err_final_angular_velocity": err_omega,
            "rel_err_final_rotation": err_rot,
            "total_rotation_rad": rot_total,
            "final_omega_rad_s": state.body_omega.tolist(),
            "reference_omega_rad_s": omega_ref.tolist(),
            "body_mass_kg": model.body_mass,
            "inertia_eigenvalues_kg_m2": eig.tolist(),
            "inertia_offdiag_max_kg_m2": float(np.abs(model.body_inertia - np.diag(np.diag(model.body_inertia))).max()),
            "angle_alpha_vs_torque_deg": angle,
        },
    )


# ---------------------------------------------------------------------------------------------------------
# Suture stretch
# ---------------------------------------------------------------------------------------------------------


@check("suture_stretch_hanging")
def check_suture_stretch_hanging() -> CheckResult:
    """Default suture clamped at one end, released horizontally, swings down and hangs: max stretch < 0.5%.

    Measured: the largest segment strain ``|x_{j+1} - x_j| / l - 1`` over all segments and all substeps of the
    swing and the hang (percent).
    """
    params = SutureParams()
    model = RodModel.from_params(params, pinned_nodes=[0])
    state = RodState.straight(model, [0.0, 0.0, 0.3], [1.0, 0.0, 0.0])
    system, full = _strands(suture=model, suture_state=state)
    control = Control()
    dt, duration = DT, 1.5
    steps = int(round(duration / dt))
    max_strain = 0.0
    solves = []
    for _ in range(steps):
        solves.append(_step(system, full, control, dt))
        max_strain = max(max_strain, float(np.abs(segment_strain(model, state)).max()))
    final_strain = float(np.abs(segment_strain(model, state)).max())
    tip = state.node_pos[-1] - state.node_pos[0]
    return CheckResult(
        name="suture_stretch_hanging",
        measured=100.0 * max_strain,
        reference=0.5,
        tolerance=0.0,
        unit="%",
        comparison="<=",
        settings={
            "suture": asdict(params),
            "clamp": "node 0 pinned at (0, 0, 0.3) m",
            "start": "straight along +x, at rest",
            "gravity_m_s2": GRAVITY,
            "duration_s": duration,
            **_solver_settings(dt),
        },
        details={
            "final_max_strain_percent": 100.0 * final_strain,
            "final_free_end_offset_m": tip.tolist(),
            "mean_solves_per_substep": float(np.mean(solves)),
            "max_solves_per_substep": int(np.max(solves)),
        },
    )


def _pull_node_force(direction: tuple, duration: float) -> dict:
    """Suture hanging at rest from its pinned node 0; a constant 1 N on the free end from t = 0."""
    params = SutureParams()
    model = RodModel.from_params(params, pinned_nodes=[0])
    state = RodState.straight(model, [0.0, 0.0, 0.3], [0.0, 0.0, -1.0])
    force = np.zeros((model.node_count, 3))
    d = np.asarray(direction, dtype=np.float64)
    force[-1] = d / np.linalg.norm(d)
    return _run_pull(*_strands(suture=model, suture_state=state), Control(suture_force=force), duration) | {
        "pull": f"1 N on the free end along {d.tolist()}"
    }


def _pull_via_needle(duration: float) -> dict:
    """Suture pinned at its top (last node), needle on its bottom end (node 0), 1 N down on the needle grip.

    The needle's weight is compensated (the device holds it) and it starts with the grip right below the
    swage, so the pull is in line with the thread from the start.
    """
    params = SutureParams()
    model = RodModel.from_params(params, pinned_nodes=[params.node_count - 1])
    needle = NeedleModel.from_shape(NeedleShape(), gravity_compensation=True)
    down = np.array([0.0, 0.0, -1.0])
    quat = quat_from_two_vectors(needle.grip_pos_body - needle.swage_pos_body, down)
    swage = np.array([0.0, 0.0, 0.1])
    needle_state = NeedleState.at_rest(swage - quat_to_matrix(quat) @ needle.swage_pos_body, quat)
    state = RodState.straight(model, swage, [0.0, 0.0, 1.0])
    control = Control(needle_wrench=np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0]))
    system, full = _strands(needle=needle, needle_state=needle_state, suture=model, suture_state=state)
    out = _run_pull(system, full, control, duration)
    swage_now = needle_point_world(needle, needle_state, needle.swage_pos_body)
    out["attachment_gap_m"] = float(np.linalg.norm(state.node_pos[0] - swage_now))
    return out | {"pull": "1 N down at the needle grip; needle weight compensated"}


def _run_pull(system: Model, full: State, control: Control, duration: float) -> dict:
    dt = DT
    model, state = system.suture, full.suture
    steps = int(round(duration / dt))
    settle_from = int(round(0.75 * steps))
    max_strain = 0.0
    late_strain, late_speed, solves = [], [], []
    for k in range(steps):
        solves.append(_step(system, full, control, dt))
        strain = float(np.abs(segment_strain(model, state)).max())
        max_strain = max(max_strain, strain)
        if k >= settle_from:
            late_strain.append(strain)
            late_speed.append(float(np.sqrt(np.mean(np.sum(state.node_vel**2, axis=1)))))
    return {
        "max_strain_percent": 100.0 * max_strain,
        "settled_max_strain_percent": 100.0 * max(late_strain),
        "settled_strain_std": float(np.std(late_strain)),
        "settled_rms_node_speed_m_s": float(np.mean(late_speed)),
        "settled_window_s": duration - settle_from * dt,
        "mean_solves_per_substep": float(np.mean(solves)),
        "max_solves_per_substep": int(np.max(solves)),
    }


@functools.lru_cache(maxsize=1)
def _pull_runs() -> dict:
    duration = 1.0
    return {
        "node_force_axial": _pull_node_force((0.0, 0.0, -1.0), duration),
        "node_force_oblique_45deg": _pull_node_force((1.0, 0.0, -1.0), duration),
        "needle_axial": _pull_via_needle(duration),
        "duration_s": duration,
    }


def _pull_settings() -> dict:
    return {
        "suture": asdict(SutureParams()),
        "needle_shape": asdict(NeedleShape()),
        "force_N": 1.0,
        "gravity_m_s2": GRAVITY,
        "duration_s": _pull_runs()["duration_s"],
        **_solver_settings(DT),
    }


@check("suture_stretch_pull")
def check_suture_stretch_pull() -> CheckResult:
    """Clamped suture pulled with 1 N at its free end: max stretch < 0.5% over the whole run (percent).

    Three runs, each a sudden 1 N load from rest on the default suture hanging from a clamp: on the free end
    node along the thread, on the free end node at 45 degrees (the thread swings into line), and through the
    needle attached to the free end (two-way swage attachment). Measured: the largest strain of any segment at
    any substep of the three runs, transients included.
    """
    runs = _pull_runs()
    cases = {k: v for k, v in runs.items() if isinstance(v, dict)}
    measured = max(c["max_strain_percent"] for c in cases.values())
    return CheckResult(
        name="suture_stretch_pull",
        measured=measured,
        reference=0.5,
        tolerance=0.0,
        unit="%",
        comparison="<=",
        settings=_pull_settings(),
        details=cases,
    )


@check("suture_pull_jitter")
def check_suture_pull_jitter() -> CheckResult:
    """Jitter of the pulled suture once settled: RMS node speed over the last quarter of each run, < 1 mm/s.

    Same three runs as ``suture_stretch_pull``. 1 mm/s moves a node 17 um per 60 Hz frame, below what a
    rendered 0.2 mm thread shows; a converged inextensible solve at rest gives ~1e-11 m/s.
    """
    runs = _pull_runs()
    cases = {k: v for k, v in runs.items() if isinstance(v, dict)}
    measured = max(c["settled_rms_node_speed_m_s"] for c in cases.values())
    return CheckResult(
        name="suture_pull_jitter",
        measured=measured,
        reference=1.0e-3,
        tolerance=0.0,
        unit="m/s",
        comparison="<=",
        settings=_pull_settings(),
        details={
            k: {
                "settled_rms_node_speed_m_s": v["settled_rms_node_speed_m_s"],
                "settled_strain_std": v["settled_strain_std"],
            }
            for k, v in cases.items()
        },
    )


#: Extensible thread under an axial pull: 5 cm of the default material in 21 nodes, node 0 pinned, 2 N along the
#: thread on the free end, no gravity; node damping 20/s (the implicit step alone settles it within ~10 substeps).
THREAD_EXTENSION = {
    "length_m": 0.05,
    "node_count": 21,
    "damping_per_s": 20.0,
    "force_N": 2.0,
    "duration_s": 0.2,
    "sweeps": (1, 2, 4),
}


def _thread_extension_run(sweeps: int) -> dict:
    """The extensible thread of :data:`THREAD_EXTENSION` pulled from rest with ``sweeps`` solver sweeps per 1 ms
    substep; the strain of every segment at the end and how much it moved over the last quarter of the run."""
    c = THREAD_EXTENSION
    params = SutureParams(
        length=c["length_m"], node_count=c["node_count"], inextensible=False, damping=c["damping_per_s"]
    )
    model = RodModel.from_params(params, pinned_nodes=[0])
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    system, full = _strands(gravity=0.0, suture=model, suture_state=state)
    force = np.zeros((model.node_count, 3))
    force[-1, 0] = c["force_N"]
    control = Control(suture_force=force)
    solver = Solver(max_speed=MAX_SPEED, rod_iterations=ITERATIONS, rod_tolerance=TOLERANCE, iterations=sweeps,
                    tissue_integrator="xpbd")  # fmt: skip
    dt = DT
    steps = int(round(c["duration_s"] / dt))
    settle_from = int(round(0.75 * steps))
    settled = None
    for k in range(steps):
        solver.step(system, full, control, dt)
        if full.diverged:
            raise RuntimeError(f"the simulation diverged near t = {full.time:.4f} s")
        if k == settle_from:
            settled = segment_strain(model, state)
    strain = segment_strain(model, state)
    return {"strain": strain, "settled_change": float(np.abs(strain - settled).max())}


@check("thread_extension_sweeps")
def check_thread_extension_sweeps() -> CheckResult:
    """Steady axial strain of an extensible thread pulled with 2 N vs ``F / (E A)``, within 2% for 1, 2 and 4
    solver sweeps per substep.

    The thread's compliance must not depend on how many sweeps a substep takes: the rod's multipliers start
    from zero once per substep and accumulate over its sweeps. Measured: the largest relative strain error of
    any segment at the end of the run, over the three sweep counts (settings in :data:`THREAD_EXTENSION`,
    1 ms substeps, no gravity, node 0 pinned).
    """
    c = THREAD_EXTENSION
    params = SutureParams(length=c["length_m"], node_count=c["node_count"], inextensible=False)
    ea = params.material.youngs_modulus * math.pi * params.radius**2
    reference = c["force_N"] / ea
    runs = {sweeps: _thread_extension_run(sweeps) for sweeps in c["sweeps"]}
    errors = {sweeps: float(np.abs(run["strain"] / reference - 1.0).max()) for sweeps, run in runs.items()}
    return CheckResult(
        name="thread_extension_sweeps",
        measured=max(errors.values()),
        reference=0.0,
        tolerance=0.02,
        unit="rel",
        comparison="<=",
        settings={
            "suture_material": asdict(params.material),
            "radius_m": params.radius,
            **{k: list(v) if isinstance(v, tuple) else v for k, v in c.items()},
            "inextensible": False,
            "clamp": "node 0 pinned; force on the last node along the thread",
            "gravity_m_s2": 0.0,
            "tissue_integrator": "xpbd (no tissue)",
            **_solver_settings(DT),
        },
        details={
            "reference_strain": reference,
            "ea_N": ea,
            **{
                f"sweeps_{sweeps}": {
                    "rel_error": errors[sweeps],
                    "mean_strain": float(run["strain"].mean()),
                    "stiffness_ratio": reference / float(run["strain"].mean()),
                    "settled_strain_change": run["settled_change"],
                }
                for sweeps, run in runs.items()
            },
        },
    )


# ---------------------------------------------------------------------------------------------------------
# Rod statics
# ---------------------------------------------------------------------------------------------------------

#: Cantilever: 5 cm of the default suture material, 101 nodes; tip sag / length ~ 2.6%, well in the linear range.
CANTILEVER = {"length_m": 0.05, "node_count": 101, "damping_per_s": 20.0, "duration_s": 1.5}


def _cantilever_run(dt: float) -> tuple[np.ndarray, RodModel, dict]:
    c = CANTILEVER
    params = SutureParams(length=c["length_m"], node_count=c["node_count"], damping=c["damping_per_s"])
    model = RodModel.from_params(params, pinned_nodes=[0], clamped_segments=[0])
    state = RodState.straight(model, [0.0, 0.0, 0.0], [1.0, 0.0, 0.0])
    system, full = _strands(suture=model, suture_state=state)
    control = Control()
    steps = int(round(c["duration_s"] / dt))
    for _ in range(steps):
        _step(system, full, control, dt)
    info = {
        "final_max_node_speed_m_s": float(np.abs(state.node_vel).max()),
        "final_max_strain": float(np.abs(segment_strain(model, state)).max()),
    }
    return state.node_pos.copy(), model, info


@functools.lru_cache(maxsize=4)
def _cantilever_cached(dt: float):
    return _cantilever_run(dt)


def _cantilever_theory(model: RodModel) -> float:
    p = model.params
    ei = p.material.youngs_modulus * math.pi * p.radius**4 / 4.0
    q = p.material.density * math.pi * p.radius**2 * GRAVITY
    return q * p.length**4 / (8.0 * ei)


@check("rod_cantilever")
def check_rod_cantilever() -> CheckResult:
    """Tip deflection of a clamped suture-material rod under its own weight vs ``q L^4 / (8 E I)``, within 10%.

    Clamp: node 0 pinned and segment 0's frame fixed. Statics reached with node damping (does not move the
    equilibrium: damping acts on the old velocity only).
    """
    pos, model, info = _cantilever_cached(DT)
    sag = float(-pos[-1, 2])
    ref = _cantilever_theory(model)
    return CheckResult(
        name="rod_cantilever",
        measured=sag,
        reference=ref,
        tolerance=0.1,
        unit="m",
        comparison="rel",
        settings={
            "suture_material": asdict(SutureMaterial()),
            "radius_m": model.radius,
            **CANTILEVER,
            "clamp": "node 0 pinned, segment 0 clamped",
            "gravity_m_s2": GRAVITY,
            **_solver_settings(DT),
        },
        details={"relative_error": sag / ref - 1.0, "sag_over_length": sag / model.params.length, **info},
    )


@check("rod_dt_independence")
def check_rod_dt_independence() -> CheckResult:
    """Static shape of the cantilever changes by under 2% when dt changes 4x (2 ms vs 0.5 ms).

    Measured: largest node position difference between the two settled shapes over the tip deflection.
    """
    dts = (2.0e-3, 0.5e-3)
    pos_a, model, info_a = _cantilever_cached(dts[0])
    pos_b, _, info_b = _cantilever_cached(dts[1])
    sag = float(-pos_b[-1, 2])
    diff = float(np.linalg.norm(pos_a - pos_b, axis=1).max())
    return CheckResult(
        name="rod_dt_independence",
        measured=diff / sag,
        reference=0.0,
        tolerance=0.02,
        unit="rel",
        comparison="<=",
        settings={
            "suture_material": asdict(SutureMaterial()),
            "radius_m": model.radius,
            **CANTILEVER,
            "dts_s": list(dts),
            "iterations_max": ITERATIONS,
            "tolerance": TOLERANCE,
            "max_speed_m_s": MAX_SPEED,
            "gravity_m_s2": GRAVITY,
        },
        details={
            "tip_sag_m": {str(dts[0]): float(-pos_a[-1, 2]), str(dts[1]): sag},
            "max_node_diff_m": diff,
            "runs": {str(dts[0]): info_a, str(dts[1]): info_b},
        },
    )


# ---------------------------------------------------------------------------------------------------------
# Benchmark
# ---------------------------------------------------------------------------------------------------------


@benchmark("strands")
def bench_strands() -> dict:
    """Needle (30 nodes) held 5 cm above a ground plane by the virtual coupling, 200-node suture hanging from
    it with about a quarter of its length lying on the ground (nylon 3-0 is stiff over a few cm), one 1 ms
    substep (coupling wrench + :meth:`~suture_gym.sim.solver.Solver.step`) at default settings (median of 500
    after a 1 s settle). Fractions from the solver's phase timings: ``collision_fraction`` its detect phase
    (tissue coupling only, nothing here: the ground contacts are detected before each rod iteration, inside
    the projection), ``solver_fraction`` projection (direct solve incl. ground contacts) and velocity update."""
    dt = DT
    needle = NeedleModel.from_shape()
    rod = RodModel.from_params()
    coupling = VirtualCoupling()
    grip_target = np.array([0.0, 0.0, 0.05])
    quat = np.array([1.0, 0.0, 0.0, 0.0])
    needle_state = NeedleState.from_grip_pose(needle, grip_target, quat)
    swage = needle_point_world(needle, needle_state, needle.swage_pos_body)
    ground = StaticObstacles.ground(0.0)
    system, full = _strands(
        needle=needle,
        needle_state=needle_state,
        suture=rod,
        suture_state=RodState.straight(rod, swage, [0.0, 0.3, -1.0]),
        obstacles=ground,
    )
    control = Control()

    def substep() -> tuple[float, float, float, int]:
        timings: dict = {}
        t0 = time.perf_counter()
        control.needle_wrench = coupling.wrench(needle, needle_state, grip_target, quat)
        solves = _step(system, full, control, dt, timings)
        total = time.perf_counter() - t0
        return total, timings["detect"], timings["project"] + timings["velocities"], solves

    for _ in range(1000):
        substep()
    samples = [substep() for _ in range(500)]
    total = np.array([s[0] for s in samples])
    detect = np.array([s[1] for s in samples])
    solve = np.array([s[2] for s in samples])
    median = float(np.median(total))
    return {
        "tets": 0,
        "particles": 0,
        "strand_nodes": needle.node_count + rod.node_count,
        "substep_ms": 1e3 * median,
        "substeps_per_s": 1.0 / median,
        "collision_fraction": float(detect.sum() / total.sum()),
        "solver_fraction": float(solve.sum() / total.sum()),
        "mean_solves_per_substep": float(np.mean([s[3] for s in samples])),
        "contact_nodes_at_end": int(np.count_nonzero(full.work.rod_work.contact_active)),
        "dt_s": dt,
        "iterations_max": ITERATIONS,
        "tolerance": TOLERANCE,
        "settings": {
            "needle_shape": asdict(needle.shape),
            "suture": asdict(rod.params),
            "coupling": asdict(coupling),
            "ground_friction": ground.friction,
        },
    }
