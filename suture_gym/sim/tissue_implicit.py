"""Implicit-Euler tissue integrators for the stable neo-Hookean energy: the alternatives to the XPBD split.

One substep of implicit Euler with lumped masses ``M``, substep ``h`` and elastic energy ``E`` is the
minimisation (the "optimisation form", e.g. Martin et al. 2011, Liu et al. 2017, Chen et al. 2024)::

    x_new = argmin_x  Phi(x) = 1 / (2 h^2) (x - y)^T M (x - y) + E(x),     y = x_prev + h v + h^2 g,

over the free degrees of freedom (pinned particles and the constrained axis of an axis-aligned roller
support are held). ``y`` is what :func:`~suture_gym.sim.solver.predict_particles` writes into the positions
(velocity damped, gravity added). ``E = sum_t V0_t Psi(F_t)`` with the stable neo-Hookean density ``Psi`` of
:mod:`suture_gym.sim.tissue` (Macklin & Muller 2021's form of Smith et al. 2018); its stress, tangent and the
kernels that evaluate ``Phi`` are in :mod:`~suture_gym.sim.tissue_energy`, the rest system ``A0`` below and its
factor in :mod:`~suture_gym.sim.rest_system`; this module holds the integrators and their coupling to the rows.

Two solvers of that minimisation, both warm-started from ``x_prev + h v`` (which is the exact answer of a
body at static equilibrium, so a resting body stays at rest for any ``h``):

* :class:`QuasiNewton` (``"quasi_newton"``): ``x <- x - A0^-1 grad Phi(x)`` with the constant matrix
  ``A0 = M / h^2 + K0``, ``K0`` the stiffness at the rest shape (the exact Hessian of ``E`` there),
  factorised once per model and substep (CHOLMOD). Exact in one iteration for linear elasticity;
  for large strains and rotations a fixed-point iteration that keeps converging over substeps (Liu et al.
  2017 use the same kind of constant matrix as their quasi-Newton initial Hessian). Optional iterations
  check ``Phi`` and halve a step that raised it.
* :class:`VertexBlockDescent` (``"vbd"``): Chen et al. 2024: Gauss-Seidel over vertices, each a 3x3
  Newton step on ``Phi`` with the vertex's own Hessian block ``m / h^2 I + sum_t V0 (mu |g_k|^2 I +
  lambda c c^T)`` (``c = cof F g_k``; the ``J - gamma`` term has a zero vertex block because ``det F``
  is affine in each node), which is always SPD; optional Chebyshev acceleration over the sweeps (Wang 2015).

Coupling rows (needle, suture) act after the elastic solve. They see the tissue through its substep compliance
``C = A0^-1 / h^2`` among the vertices they touch (:meth:`ImplicitTissue.begin_rows`, the compliance tuple of
:mod:`~suture_gym.sim.coupling.compliance`): a row's generalised inverse mass is ``n^T (sum_ab b_a b_b C_ab) n``
and its impulse moves every touched vertex by its exact linearised response, so the rows are Gauss-Seidel on the
Schur complement of the implicit step. :meth:`ImplicitTissue.propagate_rows` then spreads their summed impulses
over the whole tissue (``A0^-1`` times them, from the cached columns of the touched vertices; there it reproduces
the rows' moves exactly) and adds their forces to the next sweep's solve: the tissue takes exactly the impulses the
needle and thread gave it. The wound's faces touch each other the same way
(:meth:`ImplicitTissue.project_face_contacts`).
Two sweeps per substep (``Solver.iterations = 2``) let the elastic solve carry the rows' load; with one, a tip
pushed 1 N into 100 kPa tissue falls through it (docs/tissue_integrator.md).
"""

from __future__ import annotations

import math
import warnings

import numpy as np
import scipy.sparse as sp
from numba import njit

from suture_gym.sim.rest_system import SparseCholesky, assemble_rest_system, rest_pattern
from suture_gym.sim.tissue import face_contact, project_face_contacts
from suture_gym.sim.tissue_energy import potential_kernel, potential_scratch, tet_columns, vbd_sweep

#: Integrator names accepted by :class:`~suture_gym.sim.solver.Solver` besides ``"xpbd"``.
IMPLICIT_INTEGRATORS = ("quasi_newton", "vbd")

#: Range of Young's modulus (Pa) and Poisson's ratio the implicit integrators are validated in
#: (``scripts/validate_physics.py``: tissue_rest_stiff, tissue_sag_vs_fem, uniaxial_*, cantilever_period).
VALIDATED_YOUNGS_PA = (1.0e3, 1.0e6)
VALIDATED_POISSON = (0.3, 0.49)

#: Step halvings tried when a quasi-Newton step raised ``Phi``.
MAX_HALVINGS = 4
#: Relative rise of ``Phi`` a step may show and still count as not raising it: the round-off of summing ``Phi``
#: (near equilibrium the true change is below it, and rejecting those steps would cost halvings for nothing).
ROUNDOFF = 1e-10
#: A quasi-Newton step that moves a particle by more than this fraction of the tissue's shortest rest edge leaves
#: the range where the rest-shape matrix ``A0`` is a good model of the energy (large local strain): the substep's
#: last solve then tests whether it has converged (below), at the cost of one more gradient and solve. Smaller
#: steps are not tested (the scripted NeedleInsert expert's are below 0.33 of its 2 mm cells, the largest while its
#: tip dents the pad).
LARGE_STEP_FRACTION = 0.25
#: Convergence test of a quasi-Newton solve after a large step, m/s: it goes on while its next step would still
#: change some particle's velocity (the step over the substep ``h``) by more than this. Stopping the solve short
#: of it hands the coupling rows and the next substep a velocity error; under a dent of most of a cell that error
#: grew from substep to substep (a needle pressed 5 N into the pad's edge: a next step of 0.15 m/s, then 1-2 m/s,
#: then a particle thrown 17 mm in one substep).
CONVERGED_SPEED = 0.1
#: Next step (as a speed over ``h``, m/s) above which the energy's estimate of it (:func:`next_step_estimate`) says
#: a step the solve did not test may have left it unconverged: a first step of the substep (a sweep before the last,
#: :meth:`QuasiNewton.solve`) or the coupling rows' move since the last solve (:meth:`QuasiNewton.rows_linear`). A
#: fifth of :data:`CONVERGED_SPEED`, because the estimate reads the tangent's departure from ``A0`` along the step
#: only and under-read the true next step by 2-9x in one case in ten on the environments' random-action workloads
#: (docs/tissue_integrator.md).
ESTIMATED_STEP_LIMIT = CONVERGED_SPEED / 5.0
#: Largest first step, in :attr:`ImplicitTissue.large_step` (a quarter of the shortest rest edge), whose energy
#: estimate is trusted; a larger one always leaves the solve unconverged. On NeedleInsert-v3's random-action
#: workload at 300 kPa, first steps of 0.5-0.7 mm (2 mm cells) all ended within 0.1 mm of their solution, of
#: 0.7-1.0 mm 24% did not, of 1.0-1.5 mm 79% (docs/tissue_integrator.md); the estimate flagged those.
TRUSTED_FIRST_STEP = 2.0
#: Most iterations a quasi-Newton solve adds to its set ones to pass :data:`CONVERGED_SPEED`.
MAX_EXTRA_ITERATIONS = 8
#: Range of the factor a quasi-Newton step solved to a tolerance is scaled by (the secant root of ``Phi``'s slope
#: along it, :meth:`QuasiNewton._iterate_to_tolerance`), and the least change of it that is tried.
LINE_SEARCH_RANGE = (0.25, 4.0)
LINE_SEARCH_MIN_CHANGE = 0.1
#: Time schemes of the implicit integrators (``Solver.tissue_scheme``): ``"euler"`` (implicit Euler) and
#: ``"bdf2"`` (the second-order backward differentiation formula, its first substep on an extrapolated history).
TISSUE_SCHEMES = ("euler", "bdf2")


@njit(cache=True)
def _begin_substep(q, y, external, free, gravity, h2, roller_particle, roller_axis, roller_value) -> None:
    """``q[roller_particle, roller_axis] <- roller_value`` (m), then ``y <- q``, ``external <- 0``, ``q <- q - h2
    gravity`` on the free dofs (``free`` the float mask; ``gravity`` (3,) m/s^2, ``h2`` the substep squared,
    s^2)."""
    for r in range(roller_particle.shape[0]):
        q[roller_particle[r], roller_axis[r]] = roller_value[r]
    for p in range(q.shape[0]):
        for i in range(3):
            y[p, i] = q[p, i]
            external[p, i] = 0.0
            q[p, i] -= gravity[i] * h2 * free[p, i]


@njit(cache=True)
def _begin_bdf2(q, q_prev, qd, y, xhat, external, free, gravity, h, beta, decay, damping, history_x, history_v,
                valid, roller_particle, roller_axis, roller_value) -> None:
    """BDF2's substep start: rollers on their planes, then on the free dofs (``free`` the float mask) from ``x_n =
    q_prev`` and ``v_n``, recovered from the predicted velocity ``qd = decay v_n + g h`` (``decay`` (N,) the
    prediction's ``exp(-c h)``), and the history ``x_{n-1}, v_{n-1}`` (``history_x``, ``history_v``; if not
    ``valid``, the constant-velocity ``x_n - h v_n, v_n``): ``xhat = (4 x_n - x_{n-1}) / 3``, ``vhat = (4 v_n -
    v_{n-1}) / 3``, ``y = xhat + beta (vhat + beta g) / (1 + beta c)`` (``beta = 2 h / 3``, ``c`` = ``damping``
    (N,) 1/s, taken implicitly), the warm start ``q = xhat + beta vhat / (1 + beta c)``; ``history_*`` become
    ``x_n, v_n``, ``external`` 0. Held dofs: ``y = q``."""
    for r in range(roller_particle.shape[0]):
        q[roller_particle[r], roller_axis[r]] = roller_value[r]
    for p in range(q.shape[0]):
        scale = beta / (1.0 + beta * damping[p])
        for i in range(3):
            external[p, i] = 0.0
            if free[p, i] == 0.0:
                y[p, i] = q[p, i]
                xhat[p, i] = q_prev[p, i]
                continue
            x_n = q_prev[p, i]
            v_n = (qd[p, i] - gravity[i] * h) / decay[p]
            if valid:
                x_old, v_old = history_x[p, i], history_v[p, i]
            else:
                x_old, v_old = x_n - h * v_n, v_n
            hat = (4.0 * x_n - x_old) / 3.0
            vhat = (4.0 * v_n - v_old) / 3.0
            xhat[p, i] = hat
            q[p, i] = hat + scale * vhat
            y[p, i] = q[p, i] + scale * beta * gravity[i]
            history_x[p, i] = x_n
            history_v[p, i] = v_n


@njit(cache=True)
def _finish_bdf2(q, xhat, free, inv_beta, qd, last) -> None:
    """BDF2's velocity ``v_{n+1} = (x_{n+1} - xhat) / beta`` (``inv_beta`` 1/s) on the free dofs of ``qd`` (N, 3)
    m/s; ``last <- q`` (the positions the next substep's history must start from)."""
    for p in range(q.shape[0]):
        for i in range(3):
            last[p, i] = q[p, i]
            if free[p, i] != 0.0:
                qd[p, i] = (q[p, i] - xhat[p, i]) * inv_beta


@njit(cache=True)
def _gather(flat: np.ndarray, index: np.ndarray, out: np.ndarray) -> np.ndarray:
    """``out[k] = flat[index[k]]``; returns ``out`` (numpy's fancy indexing, without its per-call overhead)."""
    for k in range(index.shape[0]):
        out[k] = flat[index[k]]
    return out


@njit(cache=True)
def _add_at(flat: np.ndarray, index: np.ndarray, step: np.ndarray, sign: float) -> float:
    """``flat[index] += sign * step`` (``sign`` +1 or -1, so the sums are numpy's bit for bit); returns
    ``max |step|`` (0 for none)."""
    largest = 0.0
    for k in range(index.shape[0]):
        flat[index[k]] += sign * step[k]
        largest = max(largest, abs(step[k]))
    return largest


@njit(cache=True)
def _free_touched(touched: np.ndarray, free_particle: np.ndarray, previous: np.ndarray) -> tuple:
    """``(vertices, same)``: the particles both ``touched`` and ``free_particle`` ((N,) bool), ascending ``int32``,
    and whether they are ``previous`` ((m,) int32)."""
    vertices = np.flatnonzero(touched & free_particle).astype(np.int32)
    same = vertices.shape[0] == previous.shape[0]
    if same:
        for k in range(vertices.shape[0]):
            if vertices[k] != previous[k]:
                return vertices, False
    return vertices, same


@njit(cache=True)
def _row_compliance(store, free_position, column_of, vertices, inv_h2, slot) -> np.ndarray:
    """The ``(3m, 3m)`` compliance block (1/kg) among ``vertices`` (m,): ``A0^-1`` (``store``, particle ``v``'s
    columns as its rows ``3 column_of[v] ..``, entries by ``free_position`` of each dof, -1 held: a zero row of
    the block) times ``inv_h2``
    (1/s^2). Writes each vertex's index into ``slot`` (N,), -1 for the others (a vertex set changes in a
    fraction of substeps: 16-20 us through numpy's fancy indexing)."""
    slot[:] = -1
    m = vertices.shape[0]
    matrix = np.zeros((3 * m, 3 * m))
    for a in range(m):
        slot[vertices[a]] = a
        for i in range(3):
            row = free_position[3 * vertices[a] + i]
            if row < 0:
                continue
            for b in range(m):
                c = 3 * column_of[vertices[b]]
                for j in range(3):
                    matrix[3 * a + i, 3 * b + j] = store[c + j, row] * inv_h2
    return matrix


@njit(cache=True)
def _spread_impulses(q_before, q, impulse, external, inv_h2, free_index, store, column_of, vertices) -> float:
    """:meth:`ImplicitTissue.propagate_rows`'s arithmetic: if any of ``impulse`` (N, 3) kg m is nonzero, ``q``
    (N, 3) m becomes ``q_before`` plus ``A0^-1 P / h^2`` on the free dofs (``free_index``), summed from the cached
    columns of ``A0^-1`` (``store``, particle ``v``'s as its rows ``3 column_of[v] ..``) of ``vertices``, the only
    particles the rows give impulses to; ``external`` (N, 3) N gains ``P / h^2`` and ``impulse`` is zeroed.
    Returns the largest move of a dof, m (0 when every impulse is zero).

    The sum runs column by column over contiguous memory, each dof's terms added in the order of ``vertices``: a
    dof-by-dof loop over the acting columns reads the store with a stride (0.34 ms a call with 26 acting vertices
    on the abdominal wall's 2,202 free dofs, the coupled scenes' costliest kernel)."""
    moved = False
    for p in range(impulse.shape[0]):
        for i in range(3):
            if impulse[p, i] != 0.0:
                moved = True
    if not moved:
        return 0.0
    flat = q.reshape(-1)
    flat[:] = q_before.reshape(-1)
    acting = np.empty(vertices.shape[0], np.int64)  # the vertices with an impulse (the rows' own, not all of S)
    count = 0
    for v in vertices:
        if impulse[v, 0] != 0.0 or impulse[v, 1] != 0.0 or impulse[v, 2] != 0.0:
            acting[count] = v
            count += 1
    n = free_index.shape[0]
    total = np.zeros(n)
    for a in range(count):
        v = acting[a]
        c = 3 * column_of[v]
        p0, p1, p2 = impulse[v, 0], impulse[v, 1], impulse[v, 2]
        x, y, z = store[c], store[c + 1], store[c + 2]
        for k in range(n):
            total[k] += x[k] * p0 + y[k] * p1 + z[k] * p2
    largest = 0.0
    for k in range(n):
        move = total[k] * inv_h2
        flat[free_index[k]] += move
        largest = max(largest, abs(move))
    for p in range(impulse.shape[0]):
        for i in range(3):
            external[p, i] += impulse[p, i] * inv_h2
            impulse[p, i] = 0.0
    return largest


@njit(cache=True)
def _face_contact_vertices(tri_indices, contact_vertex, contact_face, reach, q, free_particle) -> np.ndarray:
    """The free particles (``free_particle`` (N,) bool) of the wound's pairs that touch at ``q`` (N, 3) m
    (:func:`~suture_gym.sim.tissue.face_contact`): each pair's particle and its triangle's corners, ascending
    ``int32``."""
    mark = np.zeros(q.shape[0], np.bool_)
    for k in range(contact_vertex.shape[0]):
        v, f = contact_vertex[k], contact_face[k]
        if face_contact(tri_indices, v, f, reach, q)[0]:
            mark[v] = True
            for j in range(3):
                mark[tri_indices[f, j]] = True
    return np.flatnonzero(mark & free_particle).astype(np.int32)


def next_step_estimate(change: float, model: float, size: float, scale: float) -> float:
    """The next quasi-Newton step's size (m) after a move of ``size`` m (its largest over the particles) that
    changed ``Phi`` by ``change`` (J) where the rest system's quadratic predicted ``model`` (J, the move's
    linear response: negative): if the tangent differs from ``A0`` by ``eps A0`` along the move, ``Phi`` differs
    from the prediction by ``eps`` times it and the next step is ``eps`` times the move. A difference within
    :data:`ROUNDOFF` of ``scale`` (J, the size of ``Phi``) reads as none (0: no move, or a linear one); any other
    with a prediction that is not a decrease as inf (the move was not a linear response)."""
    delta = change - model
    if abs(delta) <= ROUNDOFF * abs(scale):
        return 0.0
    if not model < 0.0:
        return math.inf
    return abs(delta / model) * size


def check_material_range(tissue) -> None:
    """Raise ValueError for tissue the implicit integrators cannot represent, warn outside the validated range.

    Incompressible tets (``lambda = inf``, ``nu = 0.5``) need the constraint formulation: ValueError naming
    ``poisson_ratio``. Young's modulus ``E`` outside :data:`VALIDATED_YOUNGS_PA` or ``nu`` outside
    :data:`VALIDATED_POISSON` (recovered per tet from ``mu`` and ``lambda``): a ``UserWarning`` naming the
    parameter and the range.
    """
    if not np.all(np.isfinite(tissue.tet_lambda)):
        raise ValueError(
            "TissueMaterial.poisson_ratio = 0.5 (incompressible) is not supported by the implicit tissue "
            "integrators; use poisson_ratio <= 0.49"
        )
    mu = tissue.tet_mu
    lame = tissue.tet_lambda - mu
    nu = lame / (2.0 * (lame + mu))
    youngs = 2.0 * mu * (1.0 + nu)
    low, high = VALIDATED_YOUNGS_PA
    if youngs.min() < low * (1 - 1e-9) or youngs.max() > high * (1 + 1e-9):
        warnings.warn(
            f"TissueMaterial.youngs_modulus spans {youngs.min():.4g}..{youngs.max():.4g} Pa, outside the range "
            f"{low:g}..{high:g} Pa the implicit tissue integrator is validated for",
            UserWarning,
            stacklevel=3,
        )
    low, high = VALIDATED_POISSON
    if nu.min() < low - 1e-9 or nu.max() > high + 1e-9:
        warnings.warn(
            f"TissueMaterial.poisson_ratio spans {nu.min():.4g}..{nu.max():.4g}, outside the range "
            f"{low:g}..{high:g} the implicit tissue integrator is validated for",
            UserWarning,
            stacklevel=3,
        )


def _free_dofs(tissue) -> np.ndarray:
    """``(N, 3) bool``: free axes (not pinned, not the normal of an axis-aligned roller support)."""
    free = np.repeat((tissue.particle_inv_mass > 0)[:, None], 3, axis=1)
    for p, normal in zip(tissue.roller_particle, tissue.roller_normal, strict=True):
        axis = int(np.argmax(np.abs(normal)))
        if abs(abs(normal[axis]) - 1.0) > 1e-12:
            raise ValueError(
                f"roller support of particle {int(p)} has normal {normal.tolist()}: the implicit tissue "
                "integrators support only axis-aligned roller normals"
            )
        free[p, axis] = False
    return free


class ImplicitTissue:
    """Per-(tissue, dt) data of an implicit integrator: free dofs, the factorised ``A0 = M/h^2 + K0`` and
    the buffers of a substep. Built by :func:`implicit_tissue`; the solver keeps one per state in
    :attr:`~suture_gym.sim.model.Work.tissue_integrator` (static per model and ``dt``, never in the frozen Model).

    Attributes:
        tissue: the :class:`~suture_gym.sim.model.TissueModel` it was built for.
        free: ``(N, 3) bool`` free degrees of freedom.
        dt: substep, s.
    """

    def __init__(self, tissue, dt: float, scheme: str = "euler"):
        check_material_range(tissue)
        if scheme not in TISSUE_SCHEMES:
            raise ValueError(f"Solver.tissue_scheme must be one of {TISSUE_SCHEMES}, got {scheme!r}")
        self.tissue = tissue
        self.dt = float(dt)
        self.scheme = scheme
        self.inv_h2 = 1.0 / (self.dt * self.dt)
        #: ``(N,)`` kg: the masses of the inertia term ``1 / (2 h^2) (x - y)^T M (x - y)``: the particles' own with
        #: implicit Euler; with BDF2 ``m (1 + beta c) (h / beta)^2`` (``beta = 2 h / 3``, ``c`` the material
        #: damping, 1/s), which makes the term BDF2's ``(1 + beta c) / (2 beta^2) (x - y)^T M (x - y)`` while the
        #: coupling rows' impulses keep turning into forces over ``h^2`` (their momentum is the needle's). Implicit
        #: Euler's in a substep of a BDF2 integrator that coupling rows touch (:meth:`begin_rows`).
        self.mass = np.array(tissue.particle_mass, dtype=np.float64)
        self._euler_mass = self.mass
        self.beta = self.dt
        if scheme == "bdf2":
            self.beta = 2.0 * self.dt / 3.0
            self._bdf2_mass = self.mass * (1.0 + self.beta * tissue.particle_damping) * (self.dt / self.beta) ** 2
        #: The scheme of the current substep: :attr:`scheme`, except ``"euler"`` in a substep of a BDF2 integrator
        #: that coupling rows touch.
        self.substep_scheme = scheme
        self._predicted = np.zeros((tissue.particle_count, 3))
        self._gravity = np.zeros(3)
        self._q = self._predicted
        self._decay = np.exp(-np.asarray(tissue.particle_damping, dtype=np.float64) * self.dt)
        self._xhat = np.zeros((tissue.particle_count, 3))
        self._history_x = np.zeros((tissue.particle_count, 3))
        self._history_v = np.zeros((tissue.particle_count, 3))
        #: The positions the last substep ended on (BDF2: its history is valid for a substep that starts there).
        self._last_q = np.full((tissue.particle_count, 3), np.nan)
        #: Largest gradient entry of ``Phi`` (N) at which a solve stops (``Solver.tissue_tolerance``; None: off).
        self.tolerance: float | None = None
        #: Quasi-Newton iterations (steps solved) in the current substep, and over all substeps: ``[substeps begun,
        #: iterations, most in one finished substep]``.
        self.substep_iterations = 0
        self.iteration_stats = [0, 0, 0]
        self.free = _free_dofs(tissue)
        #: Each roller's constrained axis and the coordinate that puts its particle on its plane (m).
        normal = tissue.roller_normal
        self.roller_axis = np.argmax(np.abs(normal), axis=1)
        self.roller_value = tissue.roller_offset / normal[np.arange(self.roller_axis.size), self.roller_axis]
        self.free_index = np.flatnonzero(self.free.ravel())
        pattern = rest_pattern(tissue, self.free_index)

        def factorise(mass: np.ndarray) -> SparseCholesky:
            data = np.zeros(pattern.indices.size)
            assemble_rest_system(
                tissue.tet_indices, tissue.tet_dm_inv, tissue.tet_rest_volume, tissue.tet_mu,
                tissue.tet_lambda, pattern.entry, pattern.diagonal,
                np.repeat(mass, 3)[self.free_index] * self.inv_h2, data,
            )  # fmt: skip
            n = self.free_index.size
            return SparseCholesky(sp.csc_matrix((data, pattern.indices, pattern.indptr), shape=(n, n)))

        #: The factorised implicit-Euler rest system ``A0 = M / h^2 + K0``: the solves of an Euler substep and the
        #: coupling rows' compliance (cached columns of its inverse), with either scheme.
        self.rest_factor = factorise(self._euler_mass)
        #: The factor the current substep solves with: :attr:`rest_factor`, or BDF2's ``M' / h^2 + K0`` (``M'`` the
        #: BDF2 masses above) in a BDF2 substep.
        self.factor = self.rest_factor
        #: Every factor this integrator holds.
        self.factors = (self.rest_factor,)
        if scheme == "bdf2":
            self._bdf2_factor = factorise(self._bdf2_mass)
            self.factors = (self.rest_factor, self._bdf2_factor)
        edges = tissue.particle_rest_q[tissue.tet_indices[:, [1, 2, 3, 2, 3, 3]]] - tissue.particle_rest_q[
            tissue.tet_indices[:, [0, 0, 0, 1, 1, 2]]]
        #: Step (m) above which :class:`QuasiNewton` tests its solve for convergence (:data:`LARGE_STEP_FRACTION`
        #: of the shortest rest edge).
        self.large_step = LARGE_STEP_FRACTION * float(np.sqrt(np.min(np.sum(edges * edges, axis=2))))
        #: ``(N, 3) float64`` 1.0 on free dofs (the mask
        #: :func:`~suture_gym.sim.tissue_energy.incremental_potential` takes).
        self.free_mask = self.free.astype(np.float64)
        #: Tets with a free node, ascending: the only ones whose energy changes.
        self.active_tets = np.flatnonzero(self.free[tissue.tet_indices].any(axis=(1, 2))).astype(np.int32)
        self._tet_columns = tet_columns(tissue.tet_indices, tissue.tet_dm_inv, tissue.tet_rest_volume, tissue.tet_mu,
                                        tissue.tet_lambda, self.active_tets)  # fmt: skip
        self._potential_scratch = potential_scratch(self.active_tets.size)
        self._free_particle = self.free.any(axis=1)
        self._free_grad = np.zeros(self.free_index.size)
        self.y = np.zeros((tissue.particle_count, 3))
        self.grad = np.zeros((tissue.particle_count, 3))
        self.external = np.zeros((tissue.particle_count, 3))
        #: m: how far the coupling rows' propagations moved the tissue since the substep's last elastic solve (a
        #: bound on any dof's move: the sum of each propagation's largest).
        self.rows_move = 0.0
        # The last solve's result, its rows' forces and Phi there (J), for :meth:`QuasiNewton.rows_linear`.
        self._solved_q = np.zeros((tissue.particle_count, 3))
        self._solved_external = np.zeros((tissue.particle_count, 3))
        self._solved_phi = 0.0
        #: Whether a sweep of this substep found nothing left for the later ones (set by the solver, see
        #: :meth:`~suture_gym.sim.solver.Solver._project`).
        self.sweeps_done = False
        #: Whether the substep's last solve (a :class:`QuasiNewton` solve with ``converge`` off) ended on a step that
        #: may have left it unconverged (:meth:`QuasiNewton.solve`): the substep's last sweep must solve again.
        self.unconverged = False
        #: Columns of ``A0^-1`` (over the free dofs) of particles' three dofs, solved for on first use, stored as
        #: rows (each contiguous): particle ``p``'s are rows ``3 c .. 3 c + 2``, ``c = _column_of[p]`` (-1: not yet).
        self._column_store = np.zeros((96, self.free_index.size))
        self._column_of = np.full(tissue.particle_count, -1)
        self._column_count = 0
        self._free_position = np.full(3 * tissue.particle_count, -1)
        self._free_position[self.free_index] = np.arange(self.free_index.size)
        self._slot = np.full(tissue.particle_count, -1, np.int32)
        self._impulse = np.zeros((tissue.particle_count, 3))
        self._contact_slot = np.full(tissue.particle_count, -1, np.int32)
        self._contact_impulse = np.zeros((tissue.particle_count, 3))
        self.compliance = (tissue.particle_inv_mass, self._slot, np.zeros(0, np.int32), np.zeros((0, 0)),
                           self._impulse)  # fmt: skip

    def begin(self, q: np.ndarray, gravity: np.ndarray, q_prev: np.ndarray | None = None,
              qd: np.ndarray | None = None) -> None:
        """Store the inertial target ``y`` and move ``q`` (the predicted positions) to the warm start on the free
        dofs; axis-aligned roller axes are set on their planes. Implicit Euler: ``y = q`` (``x_prev + h v + h^2
        g``), warm start ``y - h^2 g``. BDF2 (:func:`_begin_bdf2`) also needs the substep's start ``q_prev`` (m)
        and the predicted velocity ``qd`` (m/s); its history is the last substep's if ``q_prev`` is where that one
        ended, else extrapolated at constant velocity."""
        self.rows_move = 0.0
        self.unconverged = False
        self.sweeps_done = False
        stats = self.iteration_stats
        stats[0] += 1
        stats[2] = max(stats[2], self.substep_iterations)
        self.substep_iterations = 0
        t = self.tissue
        if self.scheme == "euler":
            _begin_substep(q, self.y, self.external, self.free_mask, gravity, self.dt * self.dt,
                           t.roller_particle, self.roller_axis, self.roller_value)  # fmt: skip
            return
        if q_prev is None or qd is None:
            raise ValueError("ImplicitTissue.begin with tissue_scheme 'bdf2' needs q_prev and qd")
        self.substep_scheme, self.factor, self.mass = "bdf2", self._bdf2_factor, self._bdf2_mass
        self._predicted[...] = q
        self._gravity[...] = gravity
        self._q = q
        valid = bool(np.array_equal(q_prev, self._last_q))
        _begin_bdf2(q, q_prev, qd, self.y, self._xhat, self.external, self.free_mask, gravity, self.dt, self.beta,
                    self._decay, t.particle_damping, self._history_x, self._history_v, valid, t.roller_particle,
                    self.roller_axis, self.roller_value)  # fmt: skip

    def _begin_euler(self) -> None:
        """Turn the BDF2 substep begun by :meth:`begin` into an implicit-Euler one: the predicted positions back,
        Euler's target and warm start, its masses and factor (the history is kept for the next BDF2 substep)."""
        self.substep_scheme, self.factor, self.mass = "euler", self.rest_factor, self._euler_mass
        q = self._q
        q[...] = self._predicted
        _begin_substep(q, self.y, self.external, self.free_mask, self._gravity, self.dt * self.dt,
                       self.tissue.roller_particle, self.roller_axis, self.roller_value)  # fmt: skip

    def finish(self, q: np.ndarray, qd: np.ndarray) -> None:
        """End of the substep, after the solver's velocities ``qd = (q - q_prev) / h`` (m/s): BDF2 replaces them on
        the free dofs by its own, ``(q - xhat) / beta`` (:func:`_finish_bdf2`), and remembers ``q`` (m); implicit
        Euler keeps them."""
        if self.substep_scheme == "bdf2":
            _finish_bdf2(q, self._xhat, self.free_mask, 1.0 / self.beta, qd, self._last_q)
        elif self.scheme == "bdf2":
            self._last_q[...] = q

    def iteration_summary(self) -> dict:
        """Quasi-Newton iterations per substep over the substeps begun so far (the current one included):
        ``{"substeps", "mean", "max"}``."""
        substeps, total, most = self.iteration_stats
        return {"substeps": substeps, "mean": total / substeps if substeps else 0.0,
                "max": max(most, self.substep_iterations)}  # fmt: skip

    def potential(self, q: np.ndarray, with_gradient: bool = True) -> float:
        """``Phi(q) - f_ext . q`` (J) of the current substep, ``f_ext`` the coupling rows' forces of the
        earlier sweeps of this substep (:attr:`external`, N); writes its gradient into ``self.grad`` (N) unless
        ``with_gradient`` is False."""
        return potential_kernel(
            q, self.y, self.mass, self.free_mask, self.inv_h2, self._tet_columns, self._potential_scratch,
            self.external, self.grad, with_gradient,
        )  # fmt: skip

    def begin_rows(self, touched: np.ndarray) -> tuple:
        """The coupling rows' compliance tuple for this substep (:mod:`~suture_gym.sim.coupling.compliance`):
        the substep compliance ``C = A0^-1 / h^2`` (1/kg) among the free particles of ``touched`` ((N,) bool,
        the vertices the rows act on), gathered from cached columns of ``A0^-1`` (``A0`` is constant, so each
        particle's columns are solved for once). Resets the impulse sum :meth:`propagate_rows` spreads.

        A BDF2 substep that rows touch becomes an implicit-Euler one (:meth:`_begin_euler`): with BDF2's target the
        rows' impulses reach the tissue's momentum over the following substeps, not in the one they act in, and
        under bang-bang needle forces the rigid rows then push against momentum still on its way and can diverge
        (docs/notes/tissue_integrator.md)."""
        self._impulse[...] = 0.0
        vertices, same = _free_touched(touched, self._free_particle, self.compliance[2])
        if self.substep_scheme == "bdf2" and vertices.size:
            self._begin_euler()
        if same:  # the same vertices as last substep: the same matrix
            return self.compliance
        self._solve_columns(vertices)
        matrix = _row_compliance(self._column_store, self._free_position, self._column_of, vertices, self.inv_h2,
                                 self._slot)  # fmt: skip
        self.compliance = (self.tissue.particle_inv_mass, self._slot, vertices, matrix, self._impulse)
        return self.compliance

    def _solve_columns(self, particles: np.ndarray) -> None:
        """Make sure the columns of ``A0^-1`` of each particle's x, y, z dofs (zero for a held dof) are in the
        column store (the store doubles when full).

        Each particle's three columns are solved on their own: a column solved in a batch with others rounds
        differently (by ~1e-16 relative) from the same column alone, so batching the missing particles of each
        substep would make the store, and every later trajectory, depend on the order the episodes before it first
        touched the particles (an env reset with the same seed would not replay the same episode)."""
        missing = particles[self._column_of[particles] < 0]
        if missing.size == 0:
            return
        start = self._column_count
        if 3 * (start + missing.size) > self._column_store.shape[0]:
            grown = np.zeros((max(2 * self._column_store.shape[0], 3 * (start + missing.size)), self.free_index.size))
            grown[: 3 * start] = self._column_store[: 3 * start]
            self._column_store = grown
        for k, particle in enumerate(missing):
            position = self._free_position[3 * particle : 3 * particle + 3]
            rhs = np.zeros((self.free_index.size, 3))
            free = np.flatnonzero(position >= 0)
            rhs[position[free], free] = 1.0
            solved = self.rest_factor.solve(rhs)
            solved[:, position < 0] = 0.0
            self._column_store[3 * (start + k) : 3 * (start + k + 1)] = solved.T
        self._column_of[missing] = np.arange(start, start + missing.size)
        self._column_count = start + missing.size

    def propagate_rows(self, q_before: np.ndarray, q: np.ndarray) -> None:
        """Spread the coupling rows' impulses of this sweep over the whole tissue.

        The rows moved the vertices they touch (the set ``S``) by ``C_{S,:} P`` (their exact linearised
        response, :mod:`~suture_gym.sim.coupling.compliance`) and summed the tissue's impulses ``P`` (kg m) in
        the compliance tuple. The whole tissue's response is ``Delta = A0^-1 P / h^2``; it equals the rows' moves
        at ``S``, so ``q = q_before + Delta`` keeps them and moves the rest of the tissue with them. ``P`` is zero
        outside ``S``, so ``Delta`` is a sum of ``S``'s columns of ``A0^-1``, which :meth:`begin_rows` cached: a
        product with ``3 |S|`` columns instead of a solve (``|S|`` is a few vertices; on the environments' pads
        the solve cost 30-140 us). :attr:`external` gains the rows' forces ``P / h^2`` (N), so the next sweep's
        elastic solve carries their load; the needle and thread took ``-P``, so momentum is exchanged exactly.
        """
        self.rows_move += _spread_impulses(
            q_before, q, self._impulse, self.external, self.inv_h2, self.free_index, self._column_store,
            self._column_of, self.compliance[2],
        )  # fmt: skip

    def rows_linear(self, q: np.ndarray) -> bool:
        """Whether the coupling rows' move of the tissue since the last solve (to ``q``, m) was its linear
        response, so that a later sweep's solve would only refine it; an integrator that cannot tell says
        False (:meth:`QuasiNewton.rows_linear` can)."""
        return False

    def project_face_contacts(self, q: np.ndarray) -> int:
        """One pass of the contact between the wound's faces (``TissueModel.contact_vertex``, ``contact_face``,
        :func:`~suture_gym.sim.tissue.face_contact`) through the substep compliance ``C = A0^-1 / h^2``, as the
        coupling rows act: each touching pair is pushed apart along its triangle's normal by the impulse that
        closes its gap with the tissue's linearised response among the touching pairs' vertices (their dense
        block, from the cached columns of ``A0^-1``), then the impulses are spread over the whole tissue and
        their forces join :attr:`external` (the next sweep's solve carries them).

        On the particles' inverse masses instead (:func:`~suture_gym.sim.tissue.project_face_contacts` with the
        diagonal compliance, the XPBD tissue's), a correction moves a face's vertex alone: under the fuzzer's
        bang-bang actions on the soft-fat abdominal wall a needle pressed one face millimetres into the other, each
        correction (2-5 mm) strained the vertex's cells by most of their size, the next solve threw it back through
        the face, and the tissue diverged within ten env steps. Through the compliance the face's neighbourhood
        moves with it.

        Args:
            q: ``(N, 3)`` positions, m; projected in place.

        Returns:
            The number of pairs corrected (0: nothing touched, ``q`` unchanged).
        """
        t = self.tissue
        vertices = _face_contact_vertices(t.tri_indices, t.contact_vertex, t.contact_face, t.contact_reach, q,
                                          self._free_particle)  # fmt: skip
        if vertices.size == 0:
            return 0
        self._solve_columns(vertices)
        matrix = _row_compliance(self._column_store, self._free_position, self._column_of, vertices, self.inv_h2,
                                 self._contact_slot)  # fmt: skip
        contact = (t.particle_inv_mass, self._contact_slot, vertices, matrix, self._contact_impulse)
        before = q.copy()
        corrected = project_face_contacts(t.tri_indices, t.contact_vertex, t.contact_face, t.contact_reach, q, contact)
        self.rows_move += _spread_impulses(
            before, q, self._contact_impulse, self.external, self.inv_h2, self.free_index, self._column_store,
            self._column_of, vertices,
        )  # fmt: skip
        return corrected


class QuasiNewton(ImplicitTissue):
    """Quasi-Newton implicit Euler with the prefactored rest-shape system (see the module docstring)."""

    name = "quasi_newton"

    def solve(self, q: np.ndarray, iterations: int, converge: bool = True) -> None:
        """``iterations`` steps ``x <- x - A0^-1 grad Phi(x)`` from the warm start in ``q`` (m, in place); with
        ``converge``, if the last one moved a particle by more than :data:`LARGE_STEP_FRACTION` of the shortest rest
        edge, up to :data:`MAX_EXTRA_ITERATIONS` more while the next step would still move one by more than
        :data:`CONVERGED_SPEED` times ``h``. Without ``converge`` (a sweep before the last, whose solve lacks the
        coupling rows' load: converging it would only move the tissue further into the needle) such a step sets
        :attr:`unconverged` instead.

        Each step is checked: if it raised ``Phi`` (by more than :data:`ROUNDOFF` relative) it is halved, up to
        :data:`MAX_HALVINGS` times, and undone if ``Phi`` still rose, so no solve increases ``Phi``. (Without the
        check a step under large local strain, where the tangent stiffness exceeds twice ``K0``, can overshoot and
        diverge.) The check's gradient is the next step's, so ``n`` small steps cost ``n`` solves and ``n + 1``
        evaluations of ``Phi`` (the last one without the gradient); a large last step costs a gradient and a
        solve more, the convergence test's, whose step is taken only if it fails.

        With :attr:`tolerance` set, a substep no coupling row touches (:meth:`begin_rows` found no vertex) solves to
        it instead (:meth:`_iterate_to_tolerance`); one that rows touch keeps the steps above with ``iterations`` 1.
        The rows' impulses move the tissue by the rest system's linear response, and the forces they read are
        ``A0`` times the move the solve made away from the warm start: exact for one step of ``x <- x - A0^-1 grad
        Phi`` (the rows then balance the true elastic force), but not for a converged solve under large local
        strain, where the supports would carry more than the load (docs/notes/tissue_integrator.md).
        """
        if self.tolerance is None or self.compliance[2].size:
            phi = self._iterate(q, iterations if self.tolerance is None else 1, converge)
        else:
            phi = self._iterate_to_tolerance(q, iterations, converge)
        self._solved_q[...] = q
        self._solved_external[...] = self.external
        self._solved_phi = phi

    def _iterate(self, q: np.ndarray, iterations: int, converge: bool) -> float:
        """The steps of :meth:`solve`; returns ``Phi`` at the final ``q`` (J)."""
        flat = q.reshape(-1)
        free = self.free_index
        phi = self.potential(q)
        converged = CONVERGED_SPEED * self.dt
        self.unconverged = False
        for iteration in range(iterations + MAX_EXTRA_ITERATIONS):
            step = self.factor.solve(_gather(self.grad.reshape(-1), free, self._free_grad))
            if iteration >= iterations and not np.max(np.abs(step), initial=0.0) > converged:
                return phi
            self.substep_iterations += 1
            self.iteration_stats[1] += 1
            size = _add_at(flat, free, step, -1.0)  # the step is -A0^-1 grad
            large = iteration == iterations - 1 and size > self.large_step
            test_next = iteration != iterations - 1 or (large and converge)
            trial = self.potential(q, test_next)
            bound = phi + ROUNDOFF * abs(phi)
            halvings = 0
            while not trial <= bound and halvings < MAX_HALVINGS:
                step *= 0.5
                _add_at(flat, free, step, 1.0)
                trial = self.potential(q, test_next)
                halvings += 1
            if not trial <= bound:
                _add_at(flat, free, step, 1.0)
                self.unconverged = large and not converge
                return phi
            if not converge and iteration == iterations - 1:
                # the step -A0^-1 g's linear response changes Phi by -g.A0^-1 g / 2
                estimate = next_step_estimate(trial - phi, -0.5 * float(self._free_grad @ step), size, phi)
                self.unconverged = (
                    halvings > 0
                    or size > TRUSTED_FIRST_STEP * self.large_step
                    or estimate > ESTIMATED_STEP_LIMIT * self.dt
                )
            phi = trial
            if not test_next:
                return phi
        return phi

    def _iterate_to_tolerance(self, q: np.ndarray, iterations: int, converge: bool) -> float:
        """The steps of :meth:`solve` with :attr:`tolerance` set: one, then more until the largest entry of ``grad
        Phi`` on the free dofs is at most :attr:`tolerance` (N), at most ``iterations`` in all. (The first is always
        taken: it is exact for linear elasticity, and a soft body's whole elastic force can be below a tolerance
        that suits a stiff one.) Each step ``p = -A0^-1 grad Phi`` is scaled by the secant root of ``Phi``'s slope
        along it (slopes ``g0.p`` and ``g1.p`` at ``x`` and ``x + p``, the latter from the gradient the step's check
        computes anyway; within :data:`LINE_SEARCH_RANGE`) unless the step met the tolerance, kept only if it
        lowers ``Phi`` further: ``A0`` is the rest stiffness, too stiff along a rotation and off along a large
        stretch, where the plain steps converge slowly (docs/notes/tissue_integrator.md); the scaling costs a
        potential pass where it moves. A step that raised ``Phi`` is halved as in :meth:`_iterate`. A solve that
        stops short of the tolerance without ``converge`` (a sweep before the last)
        sets :attr:`unconverged`. Returns ``Phi`` at the final ``q`` (J)."""
        flat = q.reshape(-1)
        free = self.free_index
        phi = self.potential(q)
        self.unconverged = False
        low, high = LINE_SEARCH_RANGE
        for iteration in range(iterations):
            gradient = _gather(self.grad.reshape(-1), free, self._free_grad)
            if iteration > 0 and not np.max(np.abs(gradient), initial=0.0) > self.tolerance:
                return phi
            step = self.factor.solve(gradient)
            self.substep_iterations += 1
            self.iteration_stats[1] += 1
            slope = -float(gradient @ step)  # along p = -step, at x
            _add_at(flat, free, step, -1.0)
            trial = self.potential(q)
            bound = phi + ROUNDOFF * abs(phi)
            end_gradient = _gather(self.grad.reshape(-1), free, self._free_grad)
            if trial <= bound and np.max(np.abs(end_gradient), initial=0.0) > self.tolerance:
                end_slope = -float(end_gradient @ step)
                scale = slope / (slope - end_slope) if slope != end_slope else 1.0
                scale = min(max(scale, low), high)
                if abs(scale - 1.0) > LINE_SEARCH_MIN_CHANGE:
                    extra = step * (scale - 1.0)
                    _add_at(flat, free, extra, -1.0)
                    scaled = self.potential(q)
                    if scaled <= trial:
                        trial = scaled
                    else:
                        _add_at(flat, free, extra, 1.0)
                        trial = self.potential(q)
            halvings = 0
            while not trial <= bound and halvings < MAX_HALVINGS:
                step *= 0.5
                _add_at(flat, free, step, 1.0)
                trial = self.potential(q)
                halvings += 1
            if not trial <= bound:
                _add_at(flat, free, step, 1.0)
                phi = self.potential(q)
                break
            phi = trial
        gradient = _gather(self.grad.reshape(-1), free, self._free_grad)
        self.unconverged = not converge and np.max(np.abs(gradient), initial=0.0) > self.tolerance
        return phi

    def rows_linear(self, q: np.ndarray) -> bool:
        """Whether the coupling rows' move of the tissue since the last solve (to ``q``, m) was its linear
        response: the rows' forces ``f`` added to :attr:`external` since then moved it by ``d = A0^-1 f``
        (:meth:`propagate_rows`), which the rest system's quadratic says lowers ``Phi`` by ``f.d / 2``; if ``Phi``
        at ``q`` (one energy pass) agrees so well that the estimated next step (:func:`next_step_estimate`) is
        below :data:`ESTIMATED_STEP_LIMIT` times ``h``, a solve would only refine it. (The last solve's own
        remainder is left out of the prediction: the solver asks only after a solve it did not leave
        unconverged.) On the abdominal wall's stitch every substep's rows moved the tissue back by just over
        ``large_step`` (the first solve relaxes the thread's dents, lacking its load) and a solve followed; the
        estimate reads 3-8 um."""
        f = self.external - self._solved_external
        d = q - self._solved_q
        model = -0.5 * float(np.vdot(f, d))
        now = self.potential(q, False)
        before = self._solved_phi - float(np.vdot(f, self._solved_q))  # Phi at the solve under the present forces
        return next_step_estimate(now - before, model, float(np.abs(d).max()), now) <= ESTIMATED_STEP_LIMIT * self.dt


class VertexBlockDescent(ImplicitTissue):
    """Vertex Block Descent with Chebyshev acceleration (see the module docstring).

    Attributes:
        chebyshev_rho: spectral-radius estimate of the Chebyshev semi-iteration (Wang 2015); 0 = plain VBD, the
            default: with 0.9, two or three sweeps per substep diverged on the environments' pad (30 kPa to 1 MPa,
            1 ms; docs/tissue_integrator.md).
    """

    name = "vbd"
    chebyshev_rho = 0.0

    def __init__(self, tissue, dt: float, scheme: str = "euler"):
        super().__init__(tissue, dt, scheme)
        tissue = self.tissue
        active = np.flatnonzero(self.free.any(axis=1)).astype(np.int32)
        self.vertex_order = active
        incidence = tissue.tet_indices[tissue.tet_color_order]
        tet_of = np.repeat(tissue.tet_color_order, 4)
        corner = np.tile(np.arange(4), incidence.shape[0])
        vertex = incidence.ravel()
        order = np.argsort(vertex, kind="stable")
        self.adjacency_tet = tet_of[order].astype(np.int32)
        self.adjacency_corner = corner[order].astype(np.int32)
        counts = np.bincount(vertex, minlength=tissue.particle_count)
        self.adjacency_offsets = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)

    def solve(self, q: np.ndarray, iterations: int, converge: bool = True) -> None:
        """``iterations`` VBD sweeps with Chebyshev acceleration from the warm start in ``q`` (m, in place);
        ``converge`` is the common interface's (:meth:`QuasiNewton.solve`): VBD has no convergence test."""
        t = self.tissue
        rho2 = self.chebyshev_rho**2
        older = q.copy()
        old = q.copy()
        omega = 1.0
        for k in range(iterations):
            vbd_sweep(
                q, self.y, self.mass, self.free, self.inv_h2, t.tet_indices, t.tet_dm_inv, t.tet_rest_volume,
                t.tet_mu, t.tet_lambda, self.vertex_order, self.adjacency_offsets, self.adjacency_tet,
                self.adjacency_corner,
            )  # fmt: skip
            if k == 1:
                omega = 2.0 / (2.0 - rho2)
            elif k > 1:
                omega = 4.0 / (4.0 - rho2 * omega)
            if k >= 1:
                q[...] = older + omega * (q - older)
            older[...] = old
            old[...] = q


_KINDS = {"quasi_newton": QuasiNewton, "vbd": VertexBlockDescent}


def implicit_tissue(tissue, kind: str, dt: float, scheme: str = "euler") -> ImplicitTissue:
    """A new :class:`ImplicitTissue` of ``kind`` (:data:`IMPLICIT_INTEGRATORS`) for ``tissue``, ``dt`` (s) and
    time ``scheme`` (:data:`TISSUE_SCHEMES`):
    the rest system factorised once (the solver keeps it in ``State.work``, see
    :meth:`~suture_gym.sim.model.Work.tissue_integrator`)."""
    if kind not in _KINDS:
        raise ValueError(f"tissue_integrator must be one of {('xpbd', *IMPLICIT_INTEGRATORS)}, got {kind!r}")
    return _KINDS[kind](tissue, dt, scheme)
