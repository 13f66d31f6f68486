"""The XPBD solver: one documented substep order (docs/design.md section 3).

:meth:`Solver.step` advances a :class:`~suture_gym.sim.model.State` by one substep ``dt`` in place:

1. **Predict** (:meth:`Solver._predict`): tissue particles with inverse mass ``w > 0``: ``x_prev = x``,
   ``v <- v exp(-c dt) + g dt`` (mass-proportional damping ``c`` of their material, then gravity;
   semi-implicit Euler), ``x <- x + v dt``; pinned particles keep ``v = 0``; tet multipliers reset. The needle:
   Newton-Euler under the action wrench ``Control.needle_wrench`` at its grip point and gravity
   (:func:`~suture_gym.sim.needle.needle_predict`). The suture nodes under gravity and
   ``Control.suture_force`` (:func:`~suture_gym.sim.rod.rod_predict`). A non-finite prediction flags
   divergence and ends the substep.
2. **Detect** (:func:`~suture_gym.sim.coupling.coupling_detect`): strand node positions at the start of
   the substep and predicted, broad phase, signed distances, node states, the tip's anchor, puncture, path
   growth, exit, release and the coupling constraint rows with their contact frames (paper section 4), from
   the predicted positions; then how far each contact row may push its node out this substep
   (:func:`~suture_gym.sim.coupling.contact_floors`). Suture nodes held on a path or passing an access point
   get the inertia of the tissue point they are embedded in (:func:`~suture_gym.sim.coupling.embedded_inv_mass`)
   for this substep's projections.
3. **Project** (:meth:`Solver._project`): ``iterations`` sweeps. Each sweep projects the tet constraints
   colour by colour (:func:`~suture_gym.sim.tissue.project_tets`) and the roller supports; then, Gauss-Seidel,
   the needle's node-triangle and node-path rows with axial friction (rigid body, generalised inverse mass),
   the suture's node-path rows and the node-access rows, all two-way with the tissue
   (:mod:`suture_gym.sim.coupling`); last the suture's direct solve (inextensibility, bending, two-way swage
   attachment, its contacts with the static obstacles ``Model.obstacles`` and its node-triangle contacts with
   the tissue as one-sided rows; up to ``rod_iterations`` iterations, see :meth:`Solver._project_suture`), so a
   substep ends with the thread at its rest length. The suture's multipliers start from zero once per substep,
   after detection (:meth:`Solver._begin_suture`), and accumulate over its iterations in every sweep.
4. **Velocities** (:meth:`Solver._update_velocities`): ``v = (x - x_prev) / dt`` for tissue particles and
   suture nodes (then the obstacles' Coulomb friction on the suture nodes their contacts pushed,
   :func:`~suture_gym.sim.rod.friction_kernel`), the needle's linear and angular velocity from its pose
   change; a non-finite value or a speed
   above ``max_speed`` sets ``state.diverged``. Then the readings: the coupling forces (tip force for the
   next puncture test, friction, largest force, damage flag), the suture tensions (the rod's warm start for
   the next substep, kept in the State so that snapshots replay bit for bit) and the constraint wrench on the
   needle (:func:`~suture_gym.sim.needle.needle_constraint_wrench`, the haptic reaction).
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

Stability: the tissue projection is stable at rest only while ``dt sqrt(E / rho) / h`` stays below about
0.9 (``h`` the cell size): measured on a 3 x 3 x 1 cm pad of 5 mm cells (:func:`~suture_gym.sim.scenes.suturing_pad`)
at nu = 0.45, 20 kPa at 1 ms (0.89) stays at rest, 30 kPa at 1 ms (1.10) and 100 kPa at 0.5 ms (1.0) oscillate
by 0.6-2 m/s. The cause is in the constraint split of the stable neo-Hookean energy: ``C_D = ||F||`` and
``C_H = det F - gamma`` do not vanish at rest, so their multipliers carry an O(mu) stress there and the
curvature terms ``lambda grad^2 C`` that XPBD's linearisation drops (the whole shear stiffness) act
explicitly; more sweeps do not cure it (a 30 kPa pad of 2 mm cells at 1 ms still oscillates at 0.4 m/s
with 8 sweeps). Under the large local strains of a needle pressed into it the margin shrinks further: at
0.5 ms the 30 kPa pad keeps jittering at 0.2 m/s next to a needle held in it with 2 N, at 0.25 ms it
comes to rest, so tissue that stiff needs ``dt`` = 0.25 ms for 5 mm cells. Coupling rows cannot
transmit much more than ``m dt^-2`` times a cell size through a surface node of mass ``m`` in one sweep,
so a concentrated load also dents the tissue more at large ``dt`` (a 1 N tip on the 30 kPa pad: 3.7 mm at
0.25 ms, 5.3 mm at 0.5 ms). On a state's first step the solver computes that number
(:func:`~suture_gym.sim.tissue.xpbd_stability_number`) and warns, naming the parameters, above
:data:`~suture_gym.sim.tissue.XPBD_STABILITY_LIMIT`.

Implicit tissue (``tissue_integrator="quasi_newton"`` or ``"vbd"``, :mod:`suture_gym.sim.tissue_implicit`): the
tissue's phase-3 work is an implicit-Euler solve of its elastic energy in place of the tet projection, stable and
true to its material from 1 kPa to 1 MPa at 1 ms (docs/tissue_integrator.md); the coupling rows then solve
against the tissue's exact substep compliance among the vertices they touch (set up after detection,
:mod:`~suture_gym.sim.coupling.compliance`) and their impulses are spread through the tissue (``A0^-1`` times them).
Coupled scenes need ``iterations=2`` so the elastic solve and the rows alternate.

Robustness: every loop is bounded (fixed sweeps and rod iterations, path buffers of fixed size that flag
overflow instead of growing), and divergence is reported in ``state.diverged``, never raised. A state is
flagged when a position is non-finite or a speed exceeds ``max_speed``; during a large-strain snap-back
(a needle released from a deep dent, tissue cut through) tissue moves at up to its strain times its wave
speed (several m/s for 30 kPa tissue), so ``max_speed`` must stay well above that.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass

import numpy as np
from numba import njit

from suture_gym.sim.coupling import (
    apply_contact_reaction,
    apply_friction_reaction,
    contact_floors,
    coupling_detect,
    coupling_finish,
    embedded_inv_mass,
    project_access_rows,
    project_needle_rows,
    project_suture_path_rows,
    strand_positions_kernel,
    suture_contact_rows,
    suture_friction_rows,
)
from suture_gym.sim.coupling.compliance import row_vertices
from suture_gym.sim.model import Control, Model, State, Work
from suture_gym.sim.needle import needle_constraint_wrench, needle_predict, needle_update_velocities
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.sim.rod import (
    detect_contacts_kernel,
    friction_kernel,
    obstacle_arrays,
    rod_kernel_args,
    rod_predict,
)
from suture_gym.sim.rod_solver import rod_iteration_kernel, tension_from_multipliers
from suture_gym.sim.tissue import (
    XPBD_STABILITY_LIMIT,
    project_face_contacts,
    project_rollers,
    project_supports,
    project_tet_blocks,
    supports_violated,
    tet_residual,
    xpbd_stability_number,
)
from suture_gym.sim.tissue_implicit import IMPLICIT_INTEGRATORS, TISSUE_SCHEMES

#: Phases timed by :meth:`Solver.step` when given a ``timings`` dict (seconds accumulated per phase).
PHASES = ("predict", "detect", "project", "velocities")


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
    # the decay factor of the last damping rate seen: neighbouring particles share their material's, and an exp per
    # particle was half of this kernel's time
    rate, decay = math.nan, 1.0
    for i in range(q.shape[0]):
        q_prev[i, 0] = q[i, 0]
        q_prev[i, 1] = q[i, 1]
        q_prev[i, 2] = q[i, 2]
        if inv_mass[i] == 0.0:
            qd[i, 0] = 0.0
            qd[i, 1] = 0.0
            qd[i, 2] = 0.0
            continue
        if damping[i] != rate:
            rate = damping[i]
            decay = math.exp(-rate * dt)
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


@njit(cache=True)
def suture_contact_kernel(detect, node_pos, contacts, coupled, friction):
    """The contact rows of one iteration of the suture's direct solve (:meth:`Solver._project_suture`), made
    afresh at the current positions: every node's gap to the static obstacles
    (:func:`~suture_gym.sim.rod.detect_contacts_kernel`), then, with tissue, the node-triangle rows in place of an
    obstacle's where theirs is the smaller gap (:func:`~suture_gym.sim.coupling.suture_contact_rows`) and the thread's
    friction rows (:func:`~suture_gym.sim.coupling.suture_friction_rows`).

    Args:
        detect: ``(node_inv_mass (Ns,) 1/kg, radius m, plane_point, plane_normal, sphere_center, sphere_radius)``:
            the model's masses, the thread's radius and :func:`~suture_gym.sim.rod.obstacle_arrays`.
        node_pos: ``(Ns, 3)`` m. contacts: :class:`~suture_gym.sim.rod.RodWork`'s ``contacts`` group, written.
        coupled: ``None`` without tissue; else ``(needle_node_count, resistance_eps m, contact_rows,
            tri_vertices (T, 3), tissue_q (N, 3) m, tissue compliance, contact_w (Ns,) 1/kg, contact_tissue (Ns,)
            bool, row_lambda (M,) kg m)``.
        friction: ``None`` without thread friction; else ``(friction_rows, row_friction_lambda (M,))``
            (needs ``coupled``).
    """
    contact_gap, contact_normal, contact_cap = contacts[0], contacts[1], contacts[4]
    # every iteration, obstacles or not: the gaps are reset to this iteration's (the tissue rows compare against
    # them, and a gap kept from the last iteration would push a node out again)
    detect_contacts_kernel(node_pos, detect[0], detect[1], detect[2], detect[3], detect[4], detect[5], contact_gap,
                           contact_normal)  # fmt: skip
    if coupled is not None:
        nn, eps, contact_rows, tri_vertices, tissue_q, tissue, contact_w, contact_tissue, _ = coupled
        suture_contact_rows(nn, eps, contact_rows, tri_vertices, tissue_q, tissue, node_pos, contact_gap,
                            contact_normal, contact_w, contact_tissue)  # fmt: skip
        if friction is not None:
            suture_friction_rows(nn, friction[0], tissue_q, tissue, node_pos, contact_gap, contact_normal, contact_w,
                                 contact_cap)  # fmt: skip


@njit(cache=True)
def suture_reaction_kernel(contacts, z, coupled, friction):
    """The tissue's reaction to one solve of the suture's contact and friction rows (``z`` (Ns, 7), the solve's
    multiplier steps; :func:`~suture_gym.sim.coupling.apply_contact_reaction`,
    :func:`~suture_gym.sim.coupling.apply_friction_reaction`); arguments as :func:`suture_contact_kernel`'s."""
    contact_normal, contact_cap = contacts[1], contacts[4]
    nn, _, contact_rows, tri_vertices, tissue_q, tissue, _, contact_tissue, row_lambda = coupled
    apply_contact_reaction(nn, contact_rows, tri_vertices, contact_normal, z, contact_tissue, tissue, row_lambda,
                           tissue_q)  # fmt: skip
    if friction is not None:
        apply_friction_reaction(nn, friction[0], contact_cap, contact_normal, z, tissue, friction[1], tissue_q)


@njit(cache=True)
def _all_finite(a):
    for v in a.flat:
        if not math.isfinite(v):
            return False
    return True


@njit(cache=True)
def _equal(a: np.ndarray, b: np.ndarray) -> bool:
    """``np.array_equal`` of two float arrays of the same shape (no NaN is equal), without numpy's per-call cost."""
    x, y = a.reshape(-1), b.reshape(-1)
    for k in range(x.shape[0]):
        if x[k] != y[k]:
            return False
    return True


@dataclass(frozen=True)
class Solver:
    """XPBD substep integrator. Holds hyperparameters only; all data lives in Model and State (its per-substep
    buffers in ``State.work``, made on a state's first step).

    Attributes:
        iterations: sweeps per substep (>= 1): the tissue solve and the coupling rows alternate this often.
            Default 2, what the environments use with the implicit tissue; one sweep per small substep is
            the XPBD "small steps" regime.
        max_speed: speed, m/s, of any particle, suture node or needle point above which the state is flagged
            as diverged (> 0). Default 20 m/s: a hundred times the fastest motion a task asks for.
        rod_iterations: most direct-solver iterations of the suture per sweep (>= 1).
        rod_tolerance: the suture's solve stops once its residual (strain-like, dimensionless) is below this
            (>= 0).
        tissue_integrator: ``"quasi_newton"`` (implicit Euler, the default: true to the material at 1 ms
            substeps), ``"vbd"`` (the same step by vertex block descent; both in
            :mod:`suture_gym.sim.tissue_implicit`) or ``"xpbd"`` (the stable neo-Hookean XPBD split). With an implicit
            integrator each sweep solves the tissue (``tissue_iterations`` inner iterations) instead of projecting
            the tets, and the coupling rows see the tissue's substep compliance.
        tissue_iterations: inner iterations of an implicit tissue integrator per sweep (>= 1; unused by XPBD);
            with ``tissue_tolerance`` the most a solve may take.
        tissue_tolerance: N (>= 0): if positive, a quasi-Newton solve in a substep no coupling row touches takes
            one step, then more until the largest entry of the incremental potential's gradient (a force on a
            particle's axis) is at most this, up to ``tissue_iterations`` steps in all (a substep with rows keeps
            one step and the large-step test, :meth:`~suture_gym.sim.tissue_implicit.QuasiNewton.solve`); 0 (the
            default): ``tissue_iterations`` steps with the large-step convergence test there.
        tissue_scheme: time scheme of an implicit tissue integrator (:data:`~suture_gym.sim.tissue_implicit.
            TISSUE_SCHEMES`): ``"euler"`` (implicit Euler, the default; its numerical damping grows with
            ``omega dt``) or ``"bdf2"`` (second order, far less numerical damping; material damping taken
            implicitly).
    """

    iterations: int = 2
    max_speed: float = 20.0
    rod_iterations: int = 8
    rod_tolerance: float = 1.0e-6
    tissue_integrator: str = "quasi_newton"
    tissue_iterations: int = 1
    tissue_tolerance: float = 0.0
    tissue_scheme: str = "euler"

    def __post_init__(self) -> None:
        if self.tissue_scheme not in TISSUE_SCHEMES:
            raise ValueError(f"Solver.tissue_scheme must be one of {TISSUE_SCHEMES}, got {self.tissue_scheme!r}")
        value = self.tissue_tolerance
        if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)) or not (
            math.isfinite(value) and value >= 0
        ):
            raise ValueError(f"Solver.tissue_tolerance must be a finite number >= 0 (N; 0: off), got {value!r}")
        object.__setattr__(self, "tissue_tolerance", float(value))
        if self.tissue_integrator not in ("xpbd", *IMPLICIT_INTEGRATORS):
            raise ValueError(
                f"Solver.tissue_integrator must be one of {('xpbd', *IMPLICIT_INTEGRATORS)}, "
                f"got {self.tissue_integrator!r}"
            )
        for name in ("iterations", "rod_iterations", "tissue_iterations"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
                raise ValueError(f"Solver.{name} must be an integer, got {value!r}")
            if value < 1:
                raise ValueError(f"Solver.{name} must be >= 1, got {value}")
            object.__setattr__(self, name, int(value))
        for name, positive in (("max_speed", True), ("rod_tolerance", False)):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating)):
                raise ValueError(f"Solver.{name} must be a number, got {value!r}")
            if not (math.isfinite(value) and (value > 0 if positive else value >= 0)):
                raise ValueError(
                    f"Solver.{name} must be a finite number {'> 0' if positive else '>= 0'}, got {value!r}"
                )
            object.__setattr__(self, name, float(value))

    def step(
        self,
        model: Model,
        state: State,
        control: Control,
        dt: float,
        residuals: np.ndarray | None = None,
        timings: dict | None = None,
    ) -> None:
        """Advance ``state`` by one substep of ``dt`` seconds, in place, in the order of the module docstring.

        Args:
            model: the static scene.
            state: the state to advance; left untouched if already ``diverged``.
            control: inputs held over the step (the needle wrench at the grip point).
            dt: substep length, s; finite and positive.
            residuals: optional ``(iterations,) float64`` array written with the tissue XPBD residual
                (:func:`~suture_gym.sim.tissue.tet_residual`) after each sweep, for convergence studies.
            timings: optional dict; the wall-clock seconds of each phase in :data:`PHASES` are added to it.
        """
        dt = self._check_inputs(model, state, control, dt, residuals)
        if state.diverged:
            return
        if state.work is None or state.work.model is not model:
            state.work = Work(model)
            self._warn_if_unstable(model, dt)
        clock = _Clock(timings)
        self._predict(model, state, control, dt)
        clock.lap("predict")
        if not self._finite(state):
            state.diverged = True
            return
        self._detect(model, state, dt)
        self._begin_rows(model, state, dt)
        if model.suture is not None:
            self._begin_suture(state)
        clock.lap("detect")
        for sweep in range(self.iterations):
            self._project(model, state, dt, first_sweep=sweep == 0, last_sweep=sweep == self.iterations - 1)
            if residuals is not None:
                residuals[sweep] = self.residual(model, state, dt)
        clock.lap("project")
        state.diverged = self._update_velocities(model, state, dt)
        self._read_forces(model, state, dt)
        clock.lap("velocities")
        state.time += dt

    def _warn_if_unstable(self, model: Model, dt: float) -> None:
        """Warn, naming the parameters, when the XPBD tissue integrator runs outside its stability range
        (:func:`~suture_gym.sim.tissue.xpbd_stability_number`); checked once per model and state."""
        if model.tissue is None or self._implicit(model):
            return
        number = xpbd_stability_number(model.tissue, dt)
        if number > XPBD_STABILITY_LIMIT:
            warnings.warn(
                f"tissue_integrator 'xpbd' at dt = {dt:g} s is unstable for this tissue: dt sqrt(E / rho) / h = "
                f"{number:.3g} > {XPBD_STABILITY_LIMIT:g} (lower TissueMaterial.youngs_modulus or Solver dt, or use "
                "Solver(tissue_integrator='quasi_newton', iterations=2); docs/tissue_integrator.md)",
                UserWarning,
                stacklevel=3,
            )

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
        for name in ("tissue", "needle", "suture", "coupling"):
            if (getattr(model, name) is None) != (getattr(state, name) is None):
                raise ValueError(f"model.{name} and state.{name} must both be set or both be None")
        if model.tissue is not None:
            n, t = model.tissue.particle_count, model.tissue.tet_count
            if state.tissue.particle_q.shape != (n, 3) or state.tissue.tet_multiplier.shape != (t, 2):
                raise ValueError(
                    f"state.tissue does not match model.tissue: {state.tissue.particle_q.shape[0]} particles and "
                    f"{state.tissue.tet_multiplier.shape[0]} tets vs {n} and {t}"
                )
        if model.suture is not None:
            s = model.suture.node_count
            if (
                state.suture.node_pos.shape != (s, 3)
                or state.suture_tension is None
                or state.suture_tension.shape != (s - 1,)
                or state.suture_contact is None
                or state.suture_contact.shape != (s,)
            ):
                raise ValueError(
                    f"state.suture, state.suture_tension and state.suture_contact must match the model's {s} suture "
                    "nodes"
                )
        if control.suture_force is not None and (
            model.suture is None or control.suture_force.shape != (model.suture.node_count, 3)
        ):
            raise ValueError("control.suture_force must be an (S, 3) array for the model's S suture nodes")
        if model.needle is not None and (state.needle_reaction is None or state.needle_reaction.shape != (6,)):
            raise ValueError("state.needle_reaction must be a (6,) array when the model has a needle")
        if residuals is not None and (residuals.shape != (self.iterations,) or residuals.dtype != np.float64):
            raise ValueError(f"residuals must be a float64 array of shape ({self.iterations},), got {residuals.shape}")
        return dt

    def _predict(self, model: Model, state: State, control: Control, dt: float) -> None:
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
        if model.needle is not None:
            needle_predict(model.needle, state.needle, control.needle_wrench, dt, model.gravity)
        if model.suture is not None:
            rod_predict(model.suture, state.suture, dt, model.gravity, control.suture_force)

    @staticmethod
    def _finite(state: State) -> bool:
        """All predicted positions and orientations are finite."""
        arrays = []
        if state.tissue is not None:
            arrays.append(state.tissue.particle_q)
        if state.needle is not None:
            arrays += [state.needle.body_pos, state.needle.body_quat]
        if state.suture is not None:
            arrays.append(state.suture.node_pos)
        return all(_all_finite(a) for a in arrays)

    def _detect(self, model: Model, state: State, dt: float) -> None:
        """Phase 2: coupling detection and this substep's constraint rows."""
        coupling = model.coupling
        if coupling is None:
            return
        work = state.work.coupling_work
        suture_q = state.suture.node_pos if state.suture is not None else np.zeros((0, 3))
        suture_q_prev = state.suture.node_pos_prev if state.suture is not None else np.zeros((0, 3))
        strand_positions_kernel(
            state.needle.body_pos, state.needle.body_quat, model.needle.node_pos_body, suture_q, work.strand_q
        )
        strand_positions_kernel(
            state.needle.body_pos_prev, state.needle.body_quat_prev, model.needle.node_pos_body,
            suture_q_prev, work.strand_q_start,
        )  # fmt: skip
        coupling_detect(
            coupling, state.coupling, work, model.tissue, state.tissue.particle_q, work.strand_q, work.strand_q_start,
        )  # fmt: skip
        contact_floors(
            coupling.needle_node_count, coupling.params.resistance_eps, coupling.params.depenetration_speed * dt,
            work.contact_rows, coupling.surface.tri_vertices,
            (state.needle.body_pos_prev, state.needle.body_quat_prev, model.needle.node_pos_body), suture_q_prev,
            state.tissue.particle_q_prev,
        )  # fmt: skip

    def _integrator(self, state: State, dt: float):
        """The state's implicit tissue integrator of this solver's kind, scheme and tolerance for substep ``dt``."""
        integrator = state.work.tissue_integrator(self.tissue_integrator, dt, self.tissue_scheme)
        integrator.tolerance = self.tissue_tolerance if self.tissue_tolerance > 0 else None
        return integrator

    def _implicit(self, model: Model) -> bool:
        """Whether the tissue is stepped by an implicit integrator."""
        return model.tissue is not None and self.tissue_integrator != "xpbd"

    def _begin_rows(self, model: Model, state: State, dt: float) -> None:
        """After detection: start the implicit integrator's substep, choose the tissue side the coupling rows
        see this substep (``state.work.compliance``: the implicit compliance among the rows' vertices, else the
        particles' inverse masses; chosen every substep, so a state may change integrator between steps) and
        the suture nodes' embedded inverse masses."""
        work = state.work
        if self._implicit(model):
            integrator = self._integrator(state, dt)
            integrator.begin(state.tissue.particle_q, model.gravity, state.tissue.particle_q_prev,
                             state.tissue.particle_qd)
            if model.coupling is not None:
                work.compliance = integrator.begin_rows(self._row_vertices(model, state))
        elif model.tissue is not None:
            work.compliance = work.diagonal_compliance
        if model.coupling is not None and model.suture is not None:
            rows = work.coupling_work
            embedded_inv_mass(
                model.coupling.needle_node_count, rows.node_rows, rows.access_rows, rows.access_count,
                model.coupling.surface.tri_vertices, work.compliance, model.suture.node_inv_mass, rows.strand_q,
                rows.suture_mass,
            )  # fmt: skip

    @staticmethod
    def _row_vertices(model: Model, state: State) -> np.ndarray:
        """``(N,) bool``: the tissue vertices this substep's coupling rows touch
        (:func:`~suture_gym.sim.coupling.compliance.row_vertices`)."""
        work = state.work.coupling_work
        touched = np.zeros(model.tissue.particle_count, dtype=bool)
        row_vertices(
            work.row_kind, work.row_tri, work.row_tissue, work.row_weight, model.coupling.surface.tri_vertices,
            work.access_tri, work.access_count, work.tip_patch, work.cut_rows, touched,
        )  # fmt: skip
        return touched

    def _project(
        self, model: Model, state: State, dt: float, first_sweep: bool = True, last_sweep: bool = True
    ) -> None:
        """Phase 3, one sweep over every constraint group.

        With an implicit tissue integrator a later sweep re-solves the tissue only if the coupling rows moved it
        since the last solve by more than a quasi-Newton step is trusted without a convergence test
        (:attr:`~suture_gym.sim.tissue_implicit.ImplicitTissue.rows_move` over ``large_step``, a quarter of the
        shortest rest edge): a smaller move is the rows' linear response through the rest system ``A0``, which
        :meth:`~suture_gym.sim.tissue_implicit.ImplicitTissue.propagate_rows` has already spread over the whole
        tissue, and a solve would only refine it (by 2 um where the rows moved it 0.2 mm on the hand; no move at
        all leaves nothing to refine), and neither would it after a larger move that the energy reads as linear
        (:meth:`~suture_gym.sim.tissue_implicit.ImplicitTissue.rows_linear`); or if the previous solve may have
        ended unconverged (:attr:`~suture_gym.sim.tissue_implicit.ImplicitTissue.unconverged`): only the last
        sweep's solve, which carries the rows' load of the earlier ones, iterates until converged
        (:meth:`~suture_gym.sim.tissue_implicit.QuasiNewton.solve`). The earlier sweeps exist to let the tissue
        carry the rows' load, so the suture's direct solve, which converges on its own over its iterations,
        runs in the last sweep only (measured on WoundClosure at 100 kPa: 1.3x the env steps/s, no divergence).

        A sweep whose coupling rows moved nothing (tissue, needle and suture where they were, no support
        violated, the solve not left unconverged) would be repeated unchanged by every later sweep but for the
        suture's solve: it does that solve itself and the later sweeps of the substep are skipped
        (:attr:`~suture_gym.sim.tissue_implicit.ImplicitTissue.sweeps_done`), with the same result bit for bit
        (in NeedleInsert's random-action benchmark about two substeps in three have no row in contact).

        Every sweep ends with the tissue's rigid supports (:func:`~suture_gym.sim.tissue.project_supports`): the
        base is a contact the rows and the elastic solve cannot push particles through; then, where the model has
        them, the contacts of a wound's faces with each other (:func:`~suture_gym.sim.tissue.project_face_contacts`
        on the particles' inverse masses with XPBD, through the substep compliance with an implicit integrator:
        :meth:`~suture_gym.sim.tissue_implicit.ImplicitTissue.project_face_contacts`)."""
        tissue, tissue_state = model.tissue, state.tissue
        if self._implicit(model):
            if self._integrator(state, dt).sweeps_done:
                return
            self._project_implicit(model, state, dt, first_sweep, last_sweep)
        else:
            if tissue is not None:
                project_tet_blocks(*state.work.tet_blocks(), dt, tissue_state.particle_q, tissue_state.tet_multiplier)
                project_rollers(
                    tissue.particle_inv_mass,
                    tissue.roller_particle,
                    tissue.roller_normal,
                    tissue.roller_offset,
                    tissue_state.particle_q,
                )
            if model.coupling is not None:
                self._project_coupling(model, state, dt)
            if model.suture is not None:
                self._project_suture(model, state, dt)
        if tissue is not None and tissue.support_offset.size:
            project_supports(tissue.particle_inv_mass, tissue.support_normal, tissue.support_offset,
                             tissue_state.particle_q)  # fmt: skip
        if tissue is not None and tissue.contact_vertex.size:
            if self._implicit(model):
                self._integrator(state, dt).project_face_contacts(tissue_state.particle_q)
            else:
                project_face_contacts(tissue.tri_indices, tissue.contact_vertex, tissue.contact_face,
                                      tissue.contact_reach, tissue_state.particle_q,
                                      state.work.diagonal_compliance)  # fmt: skip

    def _project_implicit(self, model: Model, state: State, dt: float, first_sweep: bool, last_sweep: bool) -> None:
        """:meth:`_project` with an implicit tissue integrator (see there): the elastic solve, the coupling rows
        and the suture, then the rows' load spread over the tissue."""
        tissue_q = state.tissue.particle_q
        integrator = self._integrator(state, dt)
        if (
            first_sweep
            or integrator.unconverged
            or (integrator.rows_move > integrator.large_step and not integrator.rows_linear(tissue_q))
        ):
            integrator.solve(tissue_q, self.tissue_iterations, converge=last_sweep)
            integrator.rows_move = 0.0
        if model.coupling is not None:
            before = tissue_q.copy()
            bodies = None if last_sweep else self._row_bodies(state)
            self._project_coupling(model, state, dt)
            if bodies is not None and self._rows_idle(model, state, integrator, before, bodies):
                integrator.sweeps_done = last_sweep = True
            if model.suture is not None and last_sweep:
                self._project_suture(model, state, dt)
            integrator.propagate_rows(before, tissue_q)
        elif model.suture is not None:
            self._project_suture(model, state, dt)

    @staticmethod
    def _row_bodies(state: State) -> tuple:
        """Copies of what the coupling rows move besides the tissue: the needle's pose and the suture's nodes."""
        suture = None if state.suture is None else state.suture.node_pos.copy()
        return state.needle.body_pos.copy(), state.needle.body_quat.copy(), suture

    @staticmethod
    def _rows_idle(model: Model, state: State, integrator, tissue_before: np.ndarray, bodies: tuple) -> bool:
        """Whether this sweep's coupling rows moved nothing (tissue, needle, suture as before them), no particle
        violates a support and the elastic solve is not waiting for a later sweep to converge it: then a later
        sweep's solve would be skipped, its rows and supports would change nothing, and only the suture's solve
        remains."""
        tissue = model.tissue
        position, quaternion, suture = bodies
        return (
            not integrator.unconverged
            and _equal(state.tissue.particle_q, tissue_before)
            and _equal(state.needle.body_pos, position)
            and _equal(state.needle.body_quat, quaternion)
            and (suture is None or _equal(state.suture.node_pos, suture))
            and not supports_violated(tissue.particle_inv_mass, tissue.support_normal, tissue.support_offset,
                                      state.tissue.particle_q)  # fmt: skip
        )

    def _project_coupling(self, model: Model, state: State, dt: float) -> None:
        """The Gauss-Seidel coupling rows of needle and suture with the tissue."""
        coupling, work = model.coupling, state.work.coupling_work
        needle, needle_state = model.needle, state.needle
        compliance = state.work.compliance
        tissue_q = state.tissue.particle_q
        tri_vertices = coupling.surface.tri_vertices
        eps = coupling.params.resistance_eps
        project_needle_rows(
            (coupling.needle_node_count, needle.body_inv_mass, needle.body_inv_inertia, needle.node_pos_body,
             needle_state.body_pos_prev, needle_state.body_quat_prev),
            (compliance, state.tissue.particle_q_prev, tri_vertices),
            (coupling.strand_friction, eps, dt, coupling.params.tip_friction, coupling.params.tear_force),
            work.needle_rows, work.tip_friction, needle_state.body_pos, needle_state.body_quat, tissue_q,
        )  # fmt: skip
        suture_q = state.suture.node_pos if state.suture is not None else np.zeros((0, 3))
        if state.suture is not None:
            project_suture_path_rows(
                coupling.needle_node_count,
                work.row_kind,
                work.row_tissue,
                work.row_weight,
                work.row_tangent,
                work.suture_mass,
                compliance,
                coupling.params.tear_force * dt * dt,
                work.row_lambda,
                suture_q,
                tissue_q,
            )
        project_access_rows(
            work.access_rows, work.access_count,
            (coupling.needle_node_count, needle.body_inv_mass, needle.body_inv_inertia, needle.node_pos_body),
            work.suture_mass, compliance, tri_vertices, coupling.params.tear_force * dt * dt,
            work.access_lambda, needle_state.body_pos, needle_state.body_quat, suture_q, tissue_q,
        )  # fmt: skip

    @staticmethod
    def _begin_suture(state: State) -> None:
        """Start the suture's substep, once before the sweeps: its multipliers (``RodWork.lam``) start from zero
        here and accumulate over every iteration of every sweep's solve (:meth:`_project_suture`), so each
        iteration's XPBD step ``(J W J^T + alpha~) dlambda = -C - alpha~ lambda`` sees the substep's whole
        multiplier and a compliant (extensible) thread has its material's compliance for any number of sweeps.
        Also the geometric-stiffness warm start (``state.suture_tension``, loaded as the stretch multipliers that
        the rod's ``begin`` reads it from), the frames' start orientations, the obstacles' pushes (their Coulomb
        friction after the substep) and the friction rows' caps (a friction row, once made, stays for the
        substep)."""
        work = state.work.rod_work
        work.lam[:] = 0.0
        work.lam[1:, 0] = state.suture_tension
        work.begin(state.suture)
        work.contact_cap[:] = 0.0

    def _project_suture(self, model: Model, state: State, dt: float) -> None:
        """The suture's direct solve in one sweep (iterations of :func:`~suture_gym.sim.rod.rod_solve_iteration`'s
        kernel, its contact rows made two-way with the tissue: :func:`suture_contact_kernel`,
        :func:`suture_reaction_kernel`), up to ``rod_iterations`` iterations until its residual is below
        ``rod_tolerance``, continuing from the multipliers of the substep's earlier sweeps (:meth:`_begin_suture`).

        Before each iteration every node's contact row is reset to the static obstacles' (``model.obstacles``;
        none: no row) at the current positions (as :func:`~suture_gym.sim.rod.rod_detect_contacts`). With coupling,
        nodes held on a path or passing an access point use their embedded inverse masses
        (:func:`~suture_gym.sim.coupling.embedded_inv_mass`), and the suture's node-triangle rows enter the solve
        as one-sided contact rows, in place of an obstacle's where theirs is the smaller gap
        (:func:`~suture_gym.sim.coupling.suture_contact_rows`); after each iteration the tissue takes their
        reaction (:func:`~suture_gym.sim.coupling.apply_contact_reaction`). The contact set is warm-started: in
        the solve's first iteration only the nodes of ``state.suture_contact`` (those that pushed at the end of the
        last solve) and those that push already open a contact row where they penetrate, the others from the
        second on (with ``rod_iterations`` 1, all of them in the one iteration); on the hand's scene this
        took the thread's iterations from 5.2 to 4.0 a substep (its tail peeling off the ground had been released
        by the active-set passes one node at a time in every substep, docs/design.md). The number of solves goes
        to ``state.work.rod_solves``; the nodes that push at the end, to ``state.suture_contact``.
        """
        suture, rod_state, work = model.suture, state.suture, state.work.rod_work
        coupling, cwork = model.coupling, state.work.coupling_work
        coupled = friction = None
        if coupling is None:
            rod, needle, needle_pos, needle_quat = rod_kernel_args(suture, work, model.needle, state.needle)
        else:
            inv_mass, axis_inv_mass, axis = cwork.suture_mass
            rod, needle, needle_pos, needle_quat = rod_kernel_args(
                suture, work, model.needle, state.needle, inv_mass, cwork.suture_contact_w, axis_inv_mass, axis
            )
            tissue_q, tissue_w = state.tissue.particle_q, state.work.compliance
            coupled = (
                coupling.needle_node_count, coupling.params.resistance_eps, cwork.contact_rows,
                coupling.surface.tri_vertices, tissue_q, tissue_w, cwork.suture_contact_w, cwork.suture_contact_tissue,
                cwork.row_lambda,
            )  # fmt: skip
            # thread friction rows only when the thread has friction (the default has none)
            if coupling.params.suture_axial_friction > 0.0:
                friction_rows = (
                    coupling.strand_friction, cwork.row_kind, cwork.row_tissue, cwork.row_weight, cwork.row_tangent,
                    rod_state.node_pos_prev, state.tissue.particle_q_prev, dt,
                )  # fmt: skip
                friction = (friction_rows, cwork.row_friction_lambda)
        detect = (suture.node_inv_mass, suture.radius, *obstacle_arrays(model.obstacles))
        # the rod's iteration is called from here, not from a compiled loop around it: such a loop saved about 20 us
        # of the paper cube's 1 ms substep and cost about 8 s more compilation on a cold cache
        iteration = (rod, needle, work.start, work.frames, work.contacts, work.system, work.lam, rod_state.node_pos,
                     rod_state.seg_quat, needle_pos, needle_quat, float(dt), float(self.rod_tolerance))  # fmt: skip
        state.work.rod_solves = 0
        # the contact-set warm start: in the first iteration only the nodes that pushed at the end of the last
        # substep open a contact row where the prediction put them inside an obstacle; the others (a thread
        # peeling off the ground: its prediction falls back in) open one in a later iteration if the solve leaves
        # them inside. A solve of one iteration has no later one: there every node may open its row at once.
        work.contact_eligible[:] = state.suture_contact if self.rod_iterations > 1 else True
        for it in range(self.rod_iterations):
            suture_contact_kernel(detect, rod_state.node_pos, work.contacts, coupled, friction)
            residual = rod_iteration_kernel(*iteration, it > 0)
            if it == 0:
                work.contact_eligible[:] = True
            if residual <= self.rod_tolerance:
                break
            state.work.rod_solves += 1
            if coupled is not None:
                suture_reaction_kernel(work.contacts, work.z, coupled, friction)
        np.greater(work.lam[:, 6], 0.0, out=state.suture_contact)

    def _update_velocities(self, model: Model, state: State, dt: float) -> bool:
        """Phase 4: velocities from the position change; returns whether the state diverged."""
        tissue, tissue_state = model.tissue, state.tissue
        diverged = False
        if tissue is not None:
            diverged |= update_particle_velocities(
                tissue_state.particle_q, tissue_state.particle_q_prev, dt, self.max_speed, tissue_state.particle_qd
            )
            if self._implicit(model):
                self._integrator(state, dt).finish(tissue_state.particle_q, tissue_state.particle_qd)
        if model.suture is not None:
            rod = state.suture
            diverged |= update_particle_velocities(rod.node_pos, rod.node_pos_prev, dt, self.max_speed, rod.node_vel)
            if model.obstacles is not None and model.obstacles.friction > 0.0:
                friction_kernel(state.work.rod_work.contact_push, model.obstacles.friction, dt, rod.node_vel)
        if model.needle is not None:
            needle_update_velocities(state.needle, dt)
            vel, omega = state.needle.body_vel, state.needle.body_omega
            speed = math.sqrt(float(vel @ vel)) + model.needle.node_reach * math.sqrt(float(omega @ omega))
            diverged |= not speed <= self.max_speed
        return diverged

    def _read_forces(self, model: Model, state: State, dt: float) -> None:
        """Readings after the projection: coupling forces, suture tensions (warm start), needle reaction."""
        if model.coupling is not None:
            tip_direction = quat_to_matrix(state.needle.body_quat) @ model.needle.tip_dir_body
            coupling_finish(model.coupling, state.coupling, state.work.coupling_work, dt, tip_direction)
        if model.suture is not None:
            tension_from_multipliers(state.work.rod_work.lam, state.suture_tension)
        if model.needle is not None:
            needle_constraint_wrench(model.needle, state.needle, dt, out=state.needle_reaction)


class _Clock:
    """Adds the wall time since the previous lap to ``timings[phase]`` (does nothing without a dict)."""

    def __init__(self, timings: dict | None):
        self.timings = timings
        self.last = time.perf_counter() if timings is not None else 0.0

    def lap(self, phase: str) -> None:
        if self.timings is None:
            return
        now = time.perf_counter()
        self.timings[phase] = self.timings.get(phase, 0.0) + now - self.last
        self.last = now
