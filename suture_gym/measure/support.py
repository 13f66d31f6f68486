"""The rigid base as a contact: tissue crushed against its base by the needle stays above it.

A one-cell-thick pad of the environments' cells on its base, the needle tip pushed straight down into it with
5 N and a puncture threshold above that (so no puncture relieves the load), at the environments' substep, sweeps
and implicit integrator. Without the support half-space only the pinned bottom nodes hold, and the free nodes
above them are driven through the base plane (``details``).

Not modelled: the needle itself is not stopped by the base; with the tissue under it flattened onto the base, the
tip ends about 0.7 mm below the base plane (``dent_before_puncture_m`` in ``details``, from 2.3 mm above it).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from suture_gym.measure.puncture import needle_over, push_tip
from suture_gym.measure.registry import CheckResult, check
from suture_gym.measure.tissue_stiff import STIFF_ENV_SWEEPS, STIFF_INTEGRATOR, _env_rate
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.mesh import signed_volumes
from suture_gym.sim.model import TissueMaterial
from suture_gym.sim.needle import NeedleModel
from suture_gym.sim.scenes import suturing_pad
from suture_gym.sim.solver import Solver
from suture_gym.sim.tissue import project_supports

BASE_PUSH_FORCE = 5.0  # N
BASE_PAD_SIZE = (0.016, 0.016, 0.002)  # m: one cell thick, so the push reaches the base
BASE_YOUNGS = 3.0e5  # Pa: a silicone suturing pad (0.1-0.5 MPa)
BASE_RAMP = 0.3  # s
BASE_HOLD = 0.3  # s


def _crushed_pad(supports: bool) -> dict:
    """Push :data:`BASE_PUSH_FORCE` into the thin pad; ``supports`` False strips the base half-space (the
    comparison run). Returns the push's record plus the lowest free particle height and inverted tets."""
    rate = _env_rate()
    cells = tuple(max(1, round(s / rate["cell_m"])) for s in BASE_PAD_SIZE)
    material = TissueMaterial(youngs_modulus=BASE_YOUNGS, poisson_ratio=rate["poisson_ratio"],
                              density=rate["density_kg_m3"], damping=rate["damping_per_s"])  # fmt: skip
    pad = suturing_pad(size=BASE_PAD_SIZE, cells=cells, material=material)
    if not supports:
        tissue = replace(pad.model.tissue, support_normal=np.zeros((0, 3)), support_offset=np.zeros(0))
        pad.model = replace(pad.model, tissue=tissue)
    params = CouplingParams(puncture_force=10.0 * BASE_PUSH_FORCE, tear_force=10.0 * BASE_PUSH_FORCE,
                            exit_puncture_force=0.0, cutting_force=0.0, tip_contact_radius=0.0,
                            needle_axial_friction=10.0)
    sx, sy, sz = BASE_PAD_SIZE
    radius = NeedleModel.from_shape().shape.curvature_radius
    scene = needle_over(pad, np.array([0.5 * sx, 0.5 * sy + radius, sz + params.resistance_eps]), params)
    solver = Solver(iterations=STIFF_ENV_SWEEPS, tissue_integrator=STIFF_INTEGRATOR, max_speed=50.0)
    record = push_tip(scene, BASE_PUSH_FORCE, rate["dt_s"], BASE_RAMP, BASE_HOLD, solver=solver)
    tissue, q = scene.model.tissue, scene.state.tissue.particle_q
    free = tissue.particle_inv_mass > 0
    record["lowest_free_particle_z_m"] = float(q[free, 2].min())
    record["inverted_tets"] = int(np.sum(signed_volumes(q, tissue.tet_indices) <= 0.0))
    record["tip_force_n"] = float(scene.state.coupling.tip_force)
    return record


@check("base_contact")
def check_base_contact() -> CheckResult:
    """A 5 N push crushes a 2 mm pad against its base: no free tissue particle may end below the base plane.

    Measured: the lowest free particle height after the push (m), which must be >= 0 (the base plane) up to
    round-off; ``details`` repeats the run without the support half-space."""
    with_base = _crushed_pad(True)
    without = _crushed_pad(False)
    rate = _env_rate()
    return CheckResult(
        name="base_contact",
        measured=with_base["lowest_free_particle_z_m"],
        reference=0.0,
        tolerance=1e-9,
        unit="m",
        comparison=">=",
        settings={
            "integrator": STIFF_INTEGRATOR,
            "dt_s": rate["dt_s"],
            "substeps": rate["substeps"],
            "iterations": STIFF_ENV_SWEEPS,
            "mesh": {"cell_m": rate["cell_m"], "scheme": "five", "pad_size_m": list(BASE_PAD_SIZE)},
            "youngs_modulus_pa": BASE_YOUNGS,
            "push_force_n": BASE_PUSH_FORCE,
            "ramp_s": BASE_RAMP,
            "hold_s": BASE_HOLD,
            "support": project_supports.__name__,
        },
        details={"with_base_contact": with_base, "without_base_contact": without},
    )
