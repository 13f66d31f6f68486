"""Tissue physics checks against analytic references, and the tissue-only benchmark.

Every check runs the default :class:`~suture_gym.sim.solver.Solver` (one Gauss-Seidel sweep per substep).
One sweep per substep reproduces the implicit-Euler statics only while ``(dt c / h_e)^2 << 1`` with ``c``
a constraint's wave speed and ``h_e`` the cell size (otherwise each sweep stops short of the substep's
solution and the equilibrium it settles to is biased, see :mod:`suture_gym.sim.solver`). The hanging bar
and the cantilever therefore take ``dt = courant * h_e / sqrt(E / rho)``; the volume check sweeps ``dt``
and reports the bias; the dt-independence check compares 1 ms with 0.25 ms on the default scene. Every
parameter is recorded in ``settings``. Statics are reached with mass-proportional damping ``2 omega_1``
(critical for the fundamental mode ``omega_1`` of the analytic model), which does not move the equilibrium;
a run stops when the measured quantity changes by less than ``SETTLE_RTOL`` over a time ``1 / omega_1``.
The checks of the implicit integrators at the environments' rate are in :mod:`suture_gym.measure.tissue_stiff`.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np

from suture_gym.measure.registry import CheckResult, benchmark, check
from suture_gym.sim.mesh import signed_volumes
from suture_gym.sim.model import Control, TissueMaterial
from suture_gym.sim.scenes import (
    PAPER_SOLVER,
    PAPER_TISSUE,
    Scene,
    cantilever,
    compression_block,
    hanging_bar,
    paper_cube,
)
from suture_gym.sim.solver import Solver

GRAVITY = 9.81  # m/s^2
SETTLE_RTOL = 1e-4
MAX_SETTLE_CHUNKS = 60


def _settle(scene: Scene, solver: Solver, dt: float, chunk_time: float, probe) -> dict:
    """Step ``scene`` in chunks of ``chunk_time`` s until ``probe(scene)`` changes by < SETTLE_RTOL per chunk.

    Returns ``{value, simulated_s, substeps, converged, last_relative_change}``.
    """
    control = Control()
    steps = max(1, int(math.ceil(chunk_time / dt)))
    previous = probe(scene)
    change = math.inf
    chunks = 0
    while chunks < MAX_SETTLE_CHUNKS and change >= SETTLE_RTOL and not scene.state.diverged:
        for _ in range(steps):
            solver.step(scene.model, scene.state, control, dt)
        chunks += 1
        value = probe(scene)
        change = abs(value - previous) / max(abs(value), 1e-300)
        previous = value
    return {
        "value": float(previous),
        "simulated_s": chunks * steps * dt,
        "substeps": chunks * steps,
        "converged": bool(change < SETTLE_RTOL and not scene.state.diverged),
        "last_relative_change": float(change),
        "diverged": bool(scene.state.diverged),
    }


def _hanging_bar_run(nu: float, length: float, width: float, cells: tuple, youngs: float, courant: float) -> dict:
    density = 1000.0
    c = math.sqrt(youngs / density)
    omega = 0.5 * math.pi * c / length  # fundamental axial mode of a fixed-free bar
    material = TissueMaterial(youngs_modulus=youngs, poisson_ratio=nu, density=density, damping=2.0 * omega)
    scene = hanging_bar(length, width, cells, material, gravity=GRAVITY)
    h_e = min(width / cells[0], width / cells[1], length / cells[2])
    dt = courant * h_e / c
    bottom = scene.regions["bottom"]
    rest_z = scene.model.tissue.particle_rest_q[bottom, 2].mean()

    def elongation(s: Scene) -> float:
        return float(rest_z - s.state.tissue.particle_q[bottom, 2].mean())

    run = _settle(scene, PAPER_SOLVER, dt, 1.0 / omega, elongation)
    return {**run, "dt_s": dt, "damping_per_s": 2.0 * omega, "scene": scene.settings}


@check("hanging_bar")
def check_hanging_bar() -> CheckResult:
    """Elongation of a bar hanging under its own weight vs ``rho g L^2 / (2 E)`` (1-D bar theory), within 5%.

    E = 100 kPa keeps the largest strain (``rho g L / E`` at the clamp) under 1%. Poisson's ratio 0.3: linear
    tets lock volumetrically near 0.5 and the clamped top face adds lateral restraint, so the same mesh with
    nu = 0.49 comes out stiffer; that run is reported in ``details`` for information.
    """
    length, width, cells, youngs, density, courant = 0.1, 0.01, (2, 2, 20), 1.0e5, 1000.0, 0.05
    reference = density * GRAVITY * length**2 / (2.0 * youngs)
    main = _hanging_bar_run(0.3, length, width, cells, youngs, courant)
    locked = _hanging_bar_run(0.49, length, width, cells, youngs, courant)
    return CheckResult(
        name="hanging_bar",
        measured=main["value"],
        reference=reference,
        tolerance=0.05,
        unit="m",
        comparison="rel",
        settings={
            "length_m": length,
            "width_m": width,
            "cells": list(cells),
            "scheme": "five",
            "youngs_modulus_pa": youngs,
            "poisson_ratio": 0.3,
            "density_kg_m3": density,
            "gravity_m_s2": GRAVITY,
            "courant": courant,
            "dt_s": main["dt_s"],
            "damping_per_s": main["damping_per_s"],
            "solver": {"iterations": PAPER_SOLVER.iterations},
            "settle_rtol": SETTLE_RTOL,
            "measured_quantity": "mean downward displacement of the free end face",
        },
        details={
            "relative_error": main["value"] / reference - 1.0,
            "max_strain": density * GRAVITY * length / youngs,
            "settle": {k: main[k] for k in ("simulated_s", "substeps", "converged", "last_relative_change")},
            "poisson_0.49_same_mesh": {
                "elongation_m": locked["value"],
                "relative_error": locked["value"] / reference - 1.0,
                "converged": locked["converged"],
            },
        },
    )


@check("cantilever")
def check_cantilever() -> CheckResult:
    """Tip deflection of a clamped beam under its own weight vs Euler-Bernoulli ``q L^4 / (8 E I)``, within 10%.

    Square 1 x 1 x 10 cm beam, E = 10 MPa (tip deflection 1.5% of the length), nu = 0.3 (linear tets lock in
    bending near nu = 0.5). Linear tets are too stiff in bending and converge as the mesh is refined through
    the thickness; the measurement is the finest mesh, the coarser ones are in ``details``.
    """
    length, thickness, youngs, nu, density, courant = 0.1, 0.01, 1.0e7, 0.3, 1000.0, 0.2
    width = thickness
    inertia = width * thickness**3 / 12.0
    load = density * GRAVITY * width * thickness
    reference = load * length**4 / (8.0 * youngs * inertia)
    c = math.sqrt(youngs / density)
    # Fundamental bending mode of a clamped-free Euler-Bernoulli beam: (1.8751)^2 sqrt(E I / (rho A L^4)).
    omega = 1.8751**2 * math.sqrt(youngs * inertia / (density * width * thickness * length**4))
    material = TissueMaterial(youngs_modulus=youngs, poisson_ratio=nu, density=density, damping=2.0 * omega)
    refinements = []
    for n in (2, 3, 4, 6):
        cells = (10 * n, 2, n)
        scene = cantilever(length, thickness, width, cells, material, gravity=GRAVITY)
        dt = courant * (thickness / n) / c
        tip = scene.regions["tip"]
        rest_z = scene.model.tissue.particle_rest_q[tip, 2].mean()

        def deflection(s: Scene, tip=tip, rest_z=rest_z) -> float:
            return float(rest_z - s.state.tissue.particle_q[tip, 2].mean())

        run = _settle(scene, PAPER_SOLVER, dt, 1.0 / omega, deflection)
        refinements.append(
            {
                "cells": list(cells),
                "tets": scene.model.tissue.tet_count,
                "dt_s": dt,
                "tip_deflection_m": run["value"],
                "relative_error": run["value"] / reference - 1.0,
                "converged": run["converged"],
                "simulated_s": run["simulated_s"],
            }
        )
    errors = [abs(r["relative_error"]) for r in refinements]
    return CheckResult(
        name="cantilever",
        measured=refinements[-1]["tip_deflection_m"],
        reference=reference,
        tolerance=0.10,
        unit="m",
        comparison="rel",
        settings={
            "length_m": length,
            "thickness_m": thickness,
            "width_m": width,
            "scheme": "five",
            "youngs_modulus_pa": youngs,
            "poisson_ratio": nu,
            "density_kg_m3": density,
            "gravity_m_s2": GRAVITY,
            "courant": courant,
            "damping_per_s": 2.0 * omega,
            "solver": {"iterations": PAPER_SOLVER.iterations},
            "settle_rtol": SETTLE_RTOL,
            "refinement_cells": [r["cells"] for r in refinements],
            "measured_quantity": "mean downward displacement of the tip face, finest mesh",
        },
        details={
            "relative_error": refinements[-1]["relative_error"],
            "deflection_over_length": reference / length,
            "refinements": refinements,
            "error_shrinks_with_refinement": all(b < a for a, b in zip(errors, errors[1:], strict=False)),
        },
    )


@check("volume_compression")
def check_volume_compression() -> CheckResult:
    """Volume change of a block compressed 20% between frictionless plates vs the stable-neo-Hookean value.

    Uniaxial compression ``F = diag(s, t, t)`` with free lateral faces: zero lateral stress
    ``mu t + lambda (J - gamma) s t = 0`` gives ``J = s t^2 = 1 + (mu / lambda)(1 - 1/s)`` with the
    model's constraint moduli ``mu`` and ``lambda`` (:class:`~suture_gym.sim.model.TissueMaterial`). The
    plates are roller supports, so the discrete state is homogeneous and exact for any mesh; the remaining
    error is the solver's. Tolerance: 1% of the volume change. ``details`` lists the result for larger
    substeps: a sweep per substep underestimates the hydrostatic stiffness unless ``(dt c / h_e)^2`` is small.
    """
    size, cells, stretch = 0.02, 4, 0.8
    material = PAPER_TISSUE  # E = 1 kPa, nu = 0.49
    c = math.sqrt(material.youngs_modulus / material.density)
    omega = math.pi * c / size
    reference = material.lame_mu / material.hydrostatic_modulus * (1.0 - 1.0 / stretch)
    h_e = size / cells
    runs = []
    for dt in (1e-3, 2.5e-4, 1e-4, 5e-5, 2.5e-5):
        scene = compression_block(size, cells, stretch, replace(material, damping=2.0 * omega))
        tets = scene.model.tissue.tet_indices
        rest_volume = scene.model.tissue.tet_rest_volume.sum()

        def volume_change(s: Scene, tets=tets, rest_volume=rest_volume) -> float:
            return float(signed_volumes(s.state.tissue.particle_q, tets).sum() / rest_volume - 1.0)

        run = _settle(scene, PAPER_SOLVER, dt, 1.0 / omega, volume_change)
        side = scene.state.tissue.particle_q[scene.regions["side_x"], 0].mean() / size
        runs.append(
            {
                "dt_s": dt,
                "courant": dt * c / h_e,
                "courant_hydrostatic": dt * math.sqrt(material.hydrostatic_modulus / material.density) / h_e,
                "volume_change": run["value"],
                "relative_error": run["value"] / reference - 1.0,
                "lateral_stretch": float(side),
                "converged": run["converged"],
            }
        )
    final = runs[-1]
    return CheckResult(
        name="volume_compression",
        measured=final["volume_change"],
        reference=reference,
        tolerance=0.01,
        unit="1",
        comparison="rel",
        settings={
            "size_m": size,
            "cells": cells,
            "scheme": "five",
            "stretch": stretch,
            "youngs_modulus_pa": material.youngs_modulus,
            "poisson_ratio": material.poisson_ratio,
            "density_kg_m3": material.density,
            "damping_per_s": 2.0 * omega,
            "dt_s": final["dt_s"],
            "courant": final["courant"],
            "solver": {"iterations": PAPER_SOLVER.iterations},
            "settle_rtol": SETTLE_RTOL,
            "plates": "frictionless (roller supports), symmetry rollers on x=0, y=0",
            "measured_quantity": "V / V0 - 1 after settling",
        },
        details={
            "relative_error": final["relative_error"],
            "lateral_stretch": final["lateral_stretch"],
            "lateral_stretch_reference": math.sqrt((1.0 + reference) / stretch),
            "substep_sweep": runs,
        },
    )


def _top_sag_run(dt: float) -> dict:
    material = PAPER_TISSUE
    # Fundamental mode of a layer of height H clamped at its base: quarter shear wave, (pi / 2) c_s / H.
    height = 0.03
    omega = 0.5 * math.pi * math.sqrt(material.lame_mu / material.density) / height
    scene = paper_cube(material=replace(material, damping=2.0 * omega))
    top = scene.regions["top"]
    rest_z = scene.model.tissue.particle_rest_q[top, 2].mean()

    def sag(s: Scene) -> float:
        return float(rest_z - s.state.tissue.particle_q[top, 2].mean())

    run = _settle(scene, PAPER_SOLVER, dt, 1.0 / omega, sag)
    return {
        "dt_s": dt,
        "top_sag_m": run["value"],
        "converged": run["converged"],
        "damping_per_s": 2.0 * omega,
        "simulated_s": run["simulated_s"],
        "scene": scene.settings,
    }


@check("dt_independence")
def check_dt_independence() -> CheckResult:
    """Static sag of the default tissue scene changes by under 2% when the substep shrinks 4x (1 ms -> 0.25 ms).

    Scene: :func:`~suture_gym.sim.scenes.paper_cube` (two 9.5 x 3 x 3 cm bars on a rigid base, ends pinned,
    default 1 kPa tissue) under gravity; quantity: mean sag of the top faces. ``details`` also lists 2 ms and
    0.5 ms.
    """
    runs = {dt: _top_sag_run(dt) for dt in (2e-3, 1e-3, 5e-4, 2.5e-4)}
    coarse, fine = runs[1e-3]["top_sag_m"], runs[2.5e-4]["top_sag_m"]
    change = abs(coarse - fine) / abs(fine)
    return CheckResult(
        name="dt_independence",
        measured=change,
        reference=0.0,
        tolerance=0.02,
        unit="1",
        comparison="<=",
        settings={
            "scene": runs[1e-3]["scene"],
            "dt_pair_s": [1e-3, 2.5e-4],
            "damping_per_s": runs[1e-3]["damping_per_s"],
            "solver": {"iterations": PAPER_SOLVER.iterations},
            "settle_rtol": SETTLE_RTOL,
            "measured_quantity": "|sag(1 ms) - sag(0.25 ms)| / sag(0.25 ms), sag = mean top-face drop",
        },
        details={
            "sag_m": {f"{dt * 1e3:g}ms": r["top_sag_m"] for dt, r in runs.items()},
            "change_vs_0.25ms": {f"{dt * 1e3:g}ms": abs(r["top_sag_m"] - fine) / abs(fine) for dt, r in runs.items()},
            "converged": all(r["converged"] for r in runs.values()),
        },
    )


@check("residual_decrease")
def check_residual_decrease() -> CheckResult:
    """The tissue XPBD residual ``||C + alpha~ lambda||`` falls over the Gauss-Seidel sweeps of one substep.

    Scene: :func:`~suture_gym.sim.scenes.paper_cube`, default tissue and substep 1 ms, 50 substeps into its
    sag under gravity (a moving, loaded state); then one substep with 20 sweeps. Measured: residual after
    the last sweep over residual after the first; required: at least a 100-fold reduction.
    """
    dt, warmup, sweeps = 1e-3, 50, 20
    scene = paper_cube()
    solver, control = PAPER_SOLVER, Control()
    for _ in range(warmup):
        solver.step(scene.model, scene.state, control, dt)
    residuals = np.zeros(sweeps)
    Solver(iterations=sweeps, max_speed=50.0, tissue_integrator="xpbd").step(scene.model, scene.state, control, dt,
                                                                             residuals=residuals)
    ratios = residuals[1:] / residuals[:-1]
    return CheckResult(
        name="residual_decrease",
        measured=float(residuals[-1] / residuals[0]),
        reference=0.0,
        tolerance=0.01,
        unit="1",
        comparison="<=",
        settings={
            "scene": scene.settings,
            "dt_s": dt,
            "warmup_substeps": warmup,
            "sweeps": sweeps,
            "measured_quantity": "residual after the last sweep / residual after the first",
        },
        details={
            "residuals": residuals.tolist(),
            "monotone": bool(np.all(ratios < 1.0)),
            "worst_sweep_ratio": float(ratios.max()),
        },
    )


def _bench_cube(material: TissueMaterial, solver: Solver) -> dict:
    """Median substep of :func:`~suture_gym.sim.scenes.paper_cube` of ``material`` under gravity, 1 ms substeps."""
    dt, warmup, samples = 1e-3, 50, 400
    scene = paper_cube(material=material)
    control = Control()
    for _ in range(warmup):
        solver.step(scene.model, scene.state, control, dt)
    step_times = np.empty(samples)
    project_times = np.empty(samples)
    for i in range(samples):
        t0 = time.perf_counter()
        solver.step(scene.model, scene.state, control, dt)
        step_times[i] = time.perf_counter() - t0
    for i in range(samples):  # the projection phase alone (extra sweeps on the same state cost the same)
        t0 = time.perf_counter()
        solver._project(scene.model, scene.state, dt)
        project_times[i] = time.perf_counter() - t0
    substep = float(np.median(step_times))
    tissue = scene.model.tissue
    return {
        "tets": tissue.tet_count,
        "particles": tissue.particle_count,
        "strand_nodes": 0,
        "substep_ms": substep * 1e3,
        "substeps_per_s": 1.0 / substep,
        "collision_fraction": 0.0,
        "solver_fraction": float(np.median(project_times)) / substep,
        "substep_ms_p90": float(np.percentile(step_times, 90)) * 1e3,
        "dt_s": dt,
        "iterations": solver.iterations,
        "tissue_integrator": solver.tissue_integrator,
        "tissue_iterations": solver.tissue_iterations,
        "colors": int(len(tissue.tet_color_offsets) - 1),
        "youngs_modulus_pa": material.youngs_modulus,
        "poisson_ratio": material.poisson_ratio,
        "diverged": bool(scene.state.diverged),
        "max_speed_m_s": float(np.linalg.norm(scene.state.tissue.particle_qd, axis=1).max()),
    }


@benchmark("paper_cube_tissue")
def bench_paper_cube_tissue() -> dict:
    """Tissue alone at the paper's Table 1 scale (6840 tets), default solver, 1 ms substeps, one thread."""
    return _bench_cube(PAPER_TISSUE, Solver(iterations=1, max_speed=50.0,
                                                                                        tissue_integrator="xpbd"))
