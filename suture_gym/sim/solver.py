"""The XPBD solver: one documented substep order (DESIGN.md section 3).

:meth:`Solver.step` advances a :class:`~suture_gym.sim.model.State` by one substep ``dt`` in place:

1. **Predict** (:meth:`Solver._predict`): store ``x_prev = x``; for every particle with inverse mass
   ``w > 0``: ``v <- v exp(-c dt) + g dt`` (mass-proportional damping ``c`` of its material, then gravity;
   semi-implicit Euler), ``x <- x + v dt``. Pinned particles keep ``v = 0``. Multipliers are reset to zero.
2. **Detect**: collision and coupling detection between needle, suture and tissue goes here, between
   prediction and projection (it needs the predicted positions and creates the constraints projected next).
3. **Project** (:meth:`Solver._project`): ``iterations`` Gauss-Seidel sweeps. Each sweep projects the tet
   constraints colour by colour (:func:`~suture_gym.sim.tissue.project_tets`), then the roller supports;
   coupling constraints (node-triangle, node-path, node-access, needle-suture attachment) and the suture's
   stretch/bend constraints join each sweep here.
4. **Velocities** (:meth:`Solver._update_velocities`): ``v = (x - x_prev) / dt``; a non-finite position or a
   speed above ``max_speed`` sets ``state.diverged``.
5. ``state.time += dt``.

The damping is applied to the old velocity before gravity is added so that a body at rest under gravity
predicts exactly ``x + g dt^2`` and the static equilibrium does not depend on the damping rate.

Accuracy: one sweep per substep is one Gauss-Seidel pass over the substep's implicit-Euler equations, with
multipliers starting from zero. Its equilibria match the material's only while ``(dt c / h)^2 << 1`` for
every constraint (``c`` the wave speed of that constraint's modulus, ``h`` the element size); otherwise the
material acts softer than specified. For near-incompressible tissue the hydrostatic constraint is the stiff
one: default tissue (E = 1 kPa, nu = 0.49) in 5 mm cells compressed by 20% loses 1.8% of its volume at
``dt`` = 1 ms, 0.58% at 0.25 ms, against 0.50% analytically (``volume_compression`` check), while bending
and sag under gravity are within about 1% at 1 ms (``dt_independence`` check). Smaller substeps or more
``iterations`` reduce the bias.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numba import njit

from suture_gym.sim.model import Control, Model, State
from suture_gym.sim.tissue import project_rollers, project_tets, tet_residual


@njit(cache=True)
def predict_particles(
    inv_mass: np.ndarray,
    damping: np.ndarray,
    gravity: np.ndarray,
    dt: float,
    q: np.ndarray,
    qd: np.ndarray,
    q_prev: np.ndarray,
) -> None:
    """Semi-implicit Euler prediction with mass-proportional damping.

    For particles with ``w > 0``: ``v <- v exp(-c dt) + g dt``, ``x <- x + v dt``; pinned particles get
    ``v = 0``. Every particle's position before the prediction is stored in ``q_prev``.

    Args:
        inv_mass: ``(N,)`` inverse masses, 1/kg.
        damping: ``(N,)`` damping rates ``c``, 1/s.
        gravity: ``(3,)`` acceleration, m/s^2.
        dt: substep, s.
        q: ``(N, 3)`` positions, m; advanced in place.
        qd: ``(N, 3)`` velocities, m/s; updated in place.
        q_prev: ``(N, 3)`` written with the positions before the prediction, m.
    """
    gx, gy, gz = gravity[0] * dt, gravity[1] * dt, gravity[2] * dt
    for i in range(q.shape[0]):
        q_prev[i, 0] = q[i, 0]
        q_prev[i, 1] = q[i, 1]
        q_prev[i, 2] = q[i, 2]
        if inv_mass[i] == 0.0:
            qd[i, 0] = 0.0
            qd[i, 1] = 0.0
            qd[i, 2] = 0.0
            continue
        decay = math.exp(-damping[i] * dt)
        qd[i, 0] = qd[i, 0] * decay + gx
        qd[i, 1] = qd[i, 1] * decay + gy
        qd[i, 2] = qd[i, 2] * decay + gz
        q[i, 0] += qd[i, 0] * dt
        q[i, 1] += qd[i, 1] * dt
        q[i, 2] += qd[i, 2] * dt


@njit(cache=True)
def update_particle_velocities(q: np.ndarray, q_prev: np.ndarray, dt: float, max_speed: float, qd: np.ndarray) -> bool:
    """``v = (x - x_prev) / dt``; returns True if any speed is non-finite or above ``max_speed`` (m/s).

    Args:
        q: ``(N, 3)`` positions after projection, m.
        q_prev: ``(N, 3)`` positions at the start of the substep, m.
        dt: substep, s.
        max_speed: divergence threshold, m/s.
        qd: ``(N, 3)`` written with the new velocities, m/s.
    """
    inv_dt = 1.0 / dt
    limit = max_speed * max_speed
    bad = False
    for i in range(q.shape[0]):
        vx = (q[i, 0] - q_prev[i, 0]) * inv_dt
        vy = (q[i, 1] - q_prev[i, 1]) * inv_dt
        vz = (q[i, 2] - q_prev[i, 2]) * inv_dt
        qd[i, 0] = vx
        qd[i, 1] = vy
        qd[i, 2] = vz
        if not (vx * vx + vy * vy + vz * vz <= limit):
            bad = True
    return bad


@dataclass(frozen=True)
class Solver:
    """XPBD substep integrator. Holds hyperparameters only; all data lives in Model and State.

    Attributes:
        iterations: Gauss-Seidel sweeps per substep (>= 1). One sweep per substep with small substeps is
            the XPBD "small steps" regime the defaults are validated in.
        max_speed: particle speed, m/s, above which the state is flagged as diverged (> 0).
    """

    iterations: int = 1
    max_speed: float = 50.0

    def __post_init__(self) -> None:
        if isinstance(self.iterations, bool) or not isinstance(self.iterations, (int, np.integer)):
            raise ValueError(f"Solver.iterations must be an integer, got {self.iterations!r}")
        if self.iterations < 1:
            raise ValueError(f"Solver.iterations must be >= 1, got {self.iterations}")
        if isinstance(self.max_speed, bool) or not isinstance(self.max_speed, (int, float, np.floating)):
            raise ValueError(f"Solver.max_speed must be a number in m/s, got {self.max_speed!r}")
        if not (math.isfinite(self.max_speed) and self.max_speed > 0):
            raise ValueError(f"Solver.max_speed must be a positive finite speed in m/s, got {self.max_speed!r}")
        object.__setattr__(self, "iterations", int(self.iterations))
        object.__setattr__(self, "max_speed", float(self.max_speed))

    def step(
        self,
        model: Model,
        state: State,
        control: Control,
        dt: float,
        residuals: np.ndarray | None = None,
    ) -> None:
        """Advance ``state`` by one substep of ``dt`` seconds, in place, in the order of the module docstring.

        Args:
            model: the static scene.
            state: the state to advance; left untouched if already ``diverged``.
            control: inputs held over the step (the needle wrench; unused by tissue-only scenes).
            dt: substep length, s; finite and positive.
            residuals: optional ``(iterations,) float64`` array written with the tissue XPBD residual
                (:func:`~suture_gym.sim.tissue.tet_residual`) after each sweep, for convergence studies.
        """
        dt = self._check_inputs(model, state, control, dt, residuals)
        if state.diverged:
            return
        self._predict(model, state, dt)
        for sweep in range(self.iterations):
            self._project(model, state, dt)
            if residuals is not None:
                residuals[sweep] = self.residual(model, state, dt)
        state.diverged = self._update_velocities(model, state, dt)
        state.time += dt

    def residual(self, model: Model, state: State, dt: float) -> float:
        """Tissue XPBD residual ``||C + alpha~ lambda||`` at the current positions and multipliers."""
        tissue, tissue_state = model.tissue, state.tissue
        if tissue is None:
            return 0.0
        return tet_residual(
            tissue.tet_indices,
            tissue.tet_dm_inv,
            tissue.tet_rest_volume,
            tissue.tet_mu,
            tissue.tet_lambda,
            tissue.tet_color_order,
            tissue_state.particle_q,
            tissue_state.tet_multiplier,
            dt,
        )

    def _check_inputs(self, model, state, control, dt, residuals) -> float:
        if isinstance(dt, bool) or not isinstance(dt, (int, float, np.floating)):
            raise ValueError(f"dt must be a number of seconds, got {dt!r}")
        dt = float(dt)
        if not (math.isfinite(dt) and dt > 0):
            raise ValueError(f"dt must be a finite positive number of seconds, got {dt!r}")
        if not isinstance(model, Model) or not isinstance(state, State) or not isinstance(control, Control):
            raise ValueError("step expects (Model, State, Control, dt)")
        if (model.tissue is None) != (state.tissue is None):
            raise ValueError("model.tissue and state.tissue must both be set or both be None")
        if model.tissue is not None:
            n, t = model.tissue.particle_count, model.tissue.tet_count
            if state.tissue.particle_q.shape != (n, 3) or state.tissue.tet_multiplier.shape != (t, 2):
                raise ValueError(
                    f"state.tissue does not match model.tissue: {state.tissue.particle_q.shape[0]} particles and "
                    f"{state.tissue.tet_multiplier.shape[0]} tets vs {n} and {t}"
                )
        if residuals is not None and (residuals.shape != (self.iterations,) or residuals.dtype != np.float64):
            raise ValueError(f"residuals must be a float64 array of shape ({self.iterations},), got {residuals.shape}")
        return dt

    def _predict(self, model: Model, state: State, dt: float) -> None:
        """Phase 1: predicted positions of every simulated body; multipliers reset."""
        tissue, tissue_state = model.tissue, state.tissue
        if tissue is not None:
            predict_particles(
                tissue.particle_inv_mass,
                tissue.particle_damping,
                model.gravity,
                dt,
                tissue_state.particle_q,
                tissue_state.particle_qd,
                tissue_state.particle_q_prev,
            )
            tissue_state.tet_multiplier[...] = 0.0

    def _project(self, model: Model, state: State, dt: float) -> None:
        """Phase 3, one Gauss-Seidel sweep over every constraint group."""
        tissue, tissue_state = model.tissue, state.tissue
        if tissue is not None:
            project_tets(
                tissue.particle_inv_mass,
                tissue.tet_indices,
                tissue.tet_dm_inv,
                tissue.tet_rest_volume,
                tissue.tet_mu,
                tissue.tet_lambda,
                tissue.tet_color_order,
                dt,
                tissue_state.particle_q,
                tissue_state.tet_multiplier,
            )
            project_rollers(
                tissue.particle_inv_mass,
                tissue.roller_particle,
                tissue.roller_normal,
                tissue.roller_offset,
                tissue_state.particle_q,
            )

    def _update_velocities(self, model: Model, state: State, dt: float) -> bool:
        """Phase 4: velocities from the position change; returns whether the state diverged."""
        tissue, tissue_state = model.tissue, state.tissue
        diverged = False
        if tissue is not None:
            diverged |= update_particle_velocities(
                tissue_state.particle_q, tissue_state.particle_q_prev, dt, self.max_speed, tissue_state.particle_qd
            )
        return diverged
