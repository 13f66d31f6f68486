"""Model (static), State (time-varying) and Control (inputs) of the simulation, as dataclasses of NumPy arrays.

Field names follow ``<entity>_<quantity>``; every field states its shape, dtype and unit. A Model never
changes during a simulation (its arrays are read-only); the solver advances a State in place; a Control holds
what the agent commands during one step.

The needle, suture and coupling slots hold the objects of :mod:`suture_gym.sim.needle`,
:mod:`suture_gym.sim.rod` and :mod:`suture_gym.sim.coupling`. Every quantity that influences a later substep
lives in the State, so :meth:`State.snapshot` / :meth:`State.restore` replay bit for bit. The solver's
per-substep buffers (:class:`Work`, BVHs included) hang off the State they serve and carry nothing between
substeps.
"""

from __future__ import annotations

import math
import weakref
from dataclasses import dataclass, field, fields

import numpy as np

from suture_gym.sim.coloring import color_constraints
from suture_gym.sim.coupling import CouplingModel, CouplingState, CouplingWork
from suture_gym.sim.coupling.compliance import diagonal
from suture_gym.sim.mesh import TetMesh, lumped_masses, rest_shape, surface_triangles
from suture_gym.sim.needle import NeedleModel, NeedleState
from suture_gym.sim.rod import RodModel, RodState, RodWork, StaticObstacles
from suture_gym.sim.tissue import TetBlocks, tet_blocks
from suture_gym.sim.tissue_implicit import ImplicitTissue, implicit_tissue

#: Young's moduli (Pa) the simulator's checks cover (docs/tissue_integrator.md): 1 kPa to 1 MPa.
VALIDATED_YOUNGS_MODULUS = (1.0e3, 1.0e6)
#: Young's moduli (Pa) a :class:`TissueMaterial` accepts: generous bounds around the validated range. Below 1 Pa
#: a pad cannot carry its own weight; 100 MPa is stiff plastic, not tissue.
YOUNGS_MODULUS_LIMITS = (1.0, 1.0e8)

@dataclass(frozen=True)
class TissueMaterial:
    """Isotropic hyperelastic tissue material (stable neo-Hookean) with mass-proportional damping.

    Attributes:
        youngs_modulus: small-strain Young's modulus ``E``, Pa, within :data:`YOUNGS_MODULUS_LIMITS` (1 Pa to
            100 MPa: generous bounds around the 1 kPa-1 MPa the simulator is validated for). Default 300 kPa: a
            silicone suture-training pad (platinum-cure silicones of the pads' hardness, Shore 00-30 to 10A,
            have E of about 0.1-0.5 MPa; skin is reported from tens of kPa in indentation to about 1 MPa in
            tension). The seed paper's tissue is 1 kPa (:data:`suture_gym.sim.scenes.PAPER_TISSUE`).
        poisson_ratio: small-strain Poisson's ratio ``nu`` in ``[0, 0.5]``; 0.5 is incompressible. Default 0.45.
        density: mass density, kg/m^3 (> 0).
        damping: mass-proportional velocity damping rate ``c``, 1/s (>= 0): free particle velocities decay
            as ``exp(-c t)``, a mode of angular frequency ``omega`` has damping ratio ``c / (2 omega)``.
            Models the strong dissipation of soft tissue (paper section 5). The default 10/s damps the
            ~5 Hz fundamental wobble of a 3 cm block of default tissue on a rigid base at a ratio of about
            0.17: it stops visibly oscillating within a few tenths of a second.

    The stable neo-Hookean energy ``mu/2 (||F||^2 - 3) + lambda/2 (det F - 1 - mu/lambda)^2`` linearises to
    linear elasticity with Lame parameters ``(mu, lambda - mu)``, so to reproduce ``E`` and ``nu`` at small
    strain the constraint moduli are ``mu = E / (2 (1 + nu))`` and
    ``lambda = lame_lambda + mu = E nu / ((1 + nu)(1 - 2 nu)) + mu`` (``inf`` at ``nu = 0.5``).
    """

    youngs_modulus: float = 3.0e5
    poisson_ratio: float = 0.45
    density: float = 1000.0
    damping: float = 10.0

    def __post_init__(self) -> None:
        for name in ("youngs_modulus", "poisson_ratio", "density", "damping"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, (int, float, np.floating, np.integer)):
                raise ValueError(f"TissueMaterial.{name} must be a real number, got {value!r}")
            if not math.isfinite(float(value)):
                raise ValueError(f"TissueMaterial.{name} must be finite, got {value!r}")
            object.__setattr__(self, name, float(value))
        low, high = YOUNGS_MODULUS_LIMITS
        if not low <= self.youngs_modulus <= high:
            raise ValueError(
                f"TissueMaterial.youngs_modulus must lie in [{low:g}, {high:g}] Pa (the simulator is validated from "
                f"{VALIDATED_YOUNGS_MODULUS[0]:g} to {VALIDATED_YOUNGS_MODULUS[1]:g} Pa), got {self.youngs_modulus!r}"
            )
        if not 0.0 <= self.poisson_ratio <= 0.5:
            raise ValueError(f"TissueMaterial.poisson_ratio must lie in [0, 0.5], got {self.poisson_ratio!r}")
        if self.density <= 0:
            raise ValueError(f"TissueMaterial.density must be > 0 kg/m^3, got {self.density!r}")
        if self.damping < 0:
            raise ValueError(f"TissueMaterial.damping must be >= 0 1/s, got {self.damping!r}")

    @property
    def lame_mu(self) -> float:
        """Shear modulus ``mu = E / (2 (1 + nu))``, Pa; also the deviatoric constraint modulus."""
        return self.youngs_modulus / (2.0 * (1.0 + self.poisson_ratio))

    @property
    def lame_lambda(self) -> float:
        """Small-strain Lame parameter ``E nu / ((1 + nu)(1 - 2 nu))``, Pa (``inf`` at ``nu = 0.5``)."""
        if self.poisson_ratio == 0.5:
            return math.inf
        nu = self.poisson_ratio
        return self.youngs_modulus * nu / ((1.0 + nu) * (1.0 - 2.0 * nu))

    @property
    def hydrostatic_modulus(self) -> float:
        """Hydrostatic constraint modulus ``lame_lambda + mu``, Pa (``inf`` = incompressible)."""
        return self.lame_lambda + self.lame_mu


@dataclass(frozen=True)
class TissueModel:
    """Static description of the tetrahedral tissue. Build it with :meth:`from_mesh`.

    Attributes:
        particle_rest_q: ``(N, 3) float64`` rest positions, m.
        particle_mass: ``(N,) float64`` lumped masses, kg (pinned particles keep their mass).
        particle_inv_mass: ``(N,) float64`` inverse masses, 1/kg; 0 for pinned particles.
        particle_damping: ``(N,) float64`` velocity damping rate, 1/s (mass-weighted mean of the
            materials of the tets around the particle).
        tet_indices: ``(T, 4) int32`` particle indices of each positively oriented tet.
        tet_dm_inv: ``(T, 3, 3) float64`` inverse rest shape matrices ``Dm^-1``, 1/m.
        tet_rest_volume: ``(T,) float64`` rest volumes, m^3.
        tet_mu: ``(T,) float64`` deviatoric modulus ``mu``, Pa.
        tet_lambda: ``(T,) float64`` hydrostatic modulus ``lambda`` (= Lame lambda + mu, see
            :class:`TissueMaterial`), Pa; ``inf`` for incompressible tets.
        tet_color_order: ``(A,) int32`` the tets with at least one free node, sorted by colour: the
            Gauss-Seidel order (tets with four pinned nodes cannot move and are left out).
        tet_color_offsets: ``(K + 1,) int32`` colour ``k`` is ``tet_color_order[offsets[k]:offsets[k+1]]``.
        tri_indices: ``(F, 3) int32`` boundary triangles, counter-clockwise seen from outside.
        tri_tet: ``(F,) int32`` the tet each boundary triangle belongs to.
        roller_particle: ``(R,) int32`` particles held on a plane (frictionless sliding support).
        roller_normal: ``(R, 3) float64`` unit normals of those planes.
        roller_offset: ``(R,) float64`` plane offsets ``d`` in ``n . x = d``, m.
        support_normal: ``(S, 3) float64`` unit normals of rigid half-spaces the tissue rests on (the base of a
            pad): no free particle goes to ``n . x < d``; a one-sided, frictionless contact.
        support_offset: ``(S,) float64`` their offsets ``d``, m.
        contact_vertex: ``(P,) int32`` with ``contact_face``: pairs of a particle and a boundary triangle (index
            into ``tri_indices``) of the facing side of a wound, which the particle may not pass through
            (:func:`~suture_gym.sim.tissue.project_face_contacts`; pairs from
            :func:`~suture_gym.sim.incision.wound_contact_pairs`); empty (the default) for no contact between the
            tissue's own faces.
        contact_face: ``(P,) int32``, see ``contact_vertex``.
        contact_reach: m, how far behind its facing triangle a paired particle is still pushed out (farther: the
            pair is taken as not in contact, e.g. a face wrapped around the other).
    """

    particle_rest_q: np.ndarray
    particle_mass: np.ndarray
    particle_inv_mass: np.ndarray
    particle_damping: np.ndarray
    tet_indices: np.ndarray
    tet_dm_inv: np.ndarray
    tet_rest_volume: np.ndarray
    tet_mu: np.ndarray
    tet_lambda: np.ndarray
    tet_color_order: np.ndarray
    tet_color_offsets: np.ndarray
    tri_indices: np.ndarray
    tri_tet: np.ndarray
    roller_particle: np.ndarray
    roller_normal: np.ndarray
    roller_offset: np.ndarray
    support_normal: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    support_offset: np.ndarray = field(default_factory=lambda: np.zeros(0))
    contact_vertex: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    contact_face: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int32))
    contact_reach: float = 0.0

    def __post_init__(self) -> None:
        """Store read-only C-contiguous copies after checking dtypes, shapes and index ranges.

        The kernels index these arrays without bounds checks, so a model that passes here cannot make
        them read or write out of bounds.
        """
        sizes: dict[str, int] = {}
        for name, (dtype, shape) in _TISSUE_FIELDS.items():
            array = np.array(getattr(self, name), dtype=dtype, copy=True, order="C")
            if array.ndim != len(shape):
                raise ValueError(f"TissueModel.{name} must have shape {shape}, got {array.shape}")
            for symbol, actual in zip(shape, array.shape, strict=True):
                expected = sizes.setdefault(symbol, actual) if isinstance(symbol, str) else symbol
                if actual != expected:
                    raise ValueError(f"TissueModel.{name} must have shape {shape} with {sizes}, got {array.shape}")
            array.flags.writeable = False
            object.__setattr__(self, name, array)
        for name, bound in _TISSUE_INDEX_BOUNDS.items():
            array, limit = getattr(self, name), sizes[bound]
            if array.size and (array.min() < 0 or array.max() >= limit):
                raise ValueError(f"TissueModel.{name} holds indices outside 0..{limit - 1}")
        if not (math.isfinite(self.contact_reach) and self.contact_reach >= 0.0):
            raise ValueError(f"TissueModel.contact_reach must be finite and >= 0 m, got {self.contact_reach!r}")
        if self.contact_vertex.size and not self.contact_reach > 0.0:
            raise ValueError("TissueModel.contact_reach must be > 0 m when contact pairs are given")
        if not (np.all(np.isfinite(self.particle_inv_mass)) and np.all(self.particle_inv_mass >= 0)):
            raise ValueError("TissueModel.particle_inv_mass must be finite and >= 0")
        if not (np.all(self.tet_rest_volume > 0) and np.all(np.isfinite(self.tet_rest_volume))):
            raise ValueError("TissueModel.tet_rest_volume must be positive and finite")
        if not (np.all(self.tet_mu > 0) and np.all(np.isfinite(self.tet_mu)) and np.all(self.tet_lambda > 0)):
            raise ValueError("TissueModel.tet_mu must be positive and finite and tet_lambda positive (inf allowed)")
        offsets = self.tet_color_offsets
        if (
            len(offsets) == 0
            or offsets[0] != 0
            or offsets[-1] != len(self.tet_color_order)
            or np.any(np.diff(offsets) < 0)
        ):
            raise ValueError("TissueModel.tet_color_offsets must rise from 0 to len(tet_color_order)")

    @property
    def particle_count(self) -> int:
        """Number of particles ``N``."""
        return int(self.particle_rest_q.shape[0])

    @property
    def tet_count(self) -> int:
        """Number of tets ``T``."""
        return int(self.tet_indices.shape[0])

    @classmethod
    def from_mesh(
        cls,
        mesh: TetMesh,
        material: TissueMaterial | list[TissueMaterial] | tuple[TissueMaterial, ...],
        pinned: np.ndarray | None = None,
        tet_material: np.ndarray | None = None,
        rollers: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
        supports: tuple[np.ndarray, np.ndarray] | None = None,
    ) -> TissueModel:
        """Build the tissue model of a mesh.

        Args:
            mesh: a validated :class:`~suture_gym.sim.mesh.TetMesh` (its vertices are the rest positions).
            material: one :class:`TissueMaterial` for all tets, or a sequence indexed by ``tet_material``.
            pinned: ``(N,) bool`` mask of particles held fixed (inverse mass 0); default none.
            tet_material: ``(T,)`` integer index into ``material`` per tet; required iff ``material`` is a
                sequence.
            rollers: optional ``(particles (R,) int, normals (R, 3), offsets (R,) m)``: each listed particle
                is kept on the plane ``n . x = d`` and slides on it without friction (a roller support). A
                particle may appear on several planes with orthogonal normals; normals are normalised here.
            supports: optional ``(normals (S, 3), offsets (S,) m)``: rigid half-spaces ``n . x >= d`` no free
                particle may leave (the rigid base a pad is glued to: a contact, so the tissue cannot be pushed
                through it). Normals are normalised here.

        Returns:
            The frozen model. Tets are coloured for Gauss-Seidel order; boundary triangles are extracted.
        """
        if not isinstance(mesh, TetMesh):
            raise ValueError(f"mesh must be a TetMesh, got {type(mesh).__name__}")
        n, t = mesh.vertex_count, mesh.tet_count
        mu, lam, density, damping = _per_tet_material(material, tet_material, t)

        dm_inv, volume = rest_shape(mesh.vertices, mesh.tets)
        mass = lumped_masses(mesh.vertices, mesh.tets, density)
        weighted = np.zeros(n)
        np.add.at(weighted, mesh.tets.ravel(), np.repeat(0.25 * density * volume * damping, 4))
        particle_damping = weighted / mass

        if pinned is None:
            pinned = np.zeros(n, dtype=bool)
        pinned = np.asarray(pinned)
        if pinned.shape != (n,) or pinned.dtype != np.bool_:
            raise ValueError(f"pinned must be a ({n},) bool mask, got shape {pinned.shape} dtype {pinned.dtype}")
        inv_mass = np.where(pinned, 0.0, 1.0 / mass)

        roller_particle, roller_normal, roller_offset = _rollers(rollers, n)
        support_normal, support_offset = _supports(supports)
        # Tets whose four nodes are all pinned can never move: they are left out of the Gauss-Seidel order.
        active = np.flatnonzero(inv_mass[mesh.tets].sum(axis=1) > 0)
        active_order, offsets = color_constraints(mesh.tets[active], n)
        order = active[active_order]
        tri, tri_tet = surface_triangles(mesh.tets, return_tet=True)
        return cls(
            particle_rest_q=mesh.vertices,
            particle_mass=mass,
            particle_inv_mass=inv_mass,
            particle_damping=particle_damping,
            tet_indices=mesh.tets,
            tet_dm_inv=dm_inv,
            tet_rest_volume=volume,
            tet_mu=mu,
            tet_lambda=lam,
            tet_color_order=order,
            tet_color_offsets=offsets,
            tri_indices=tri,
            tri_tet=tri_tet,
            roller_particle=roller_particle,
            roller_normal=roller_normal,
            roller_offset=roller_offset,
            support_normal=support_normal,
            support_offset=support_offset,
        )


#: dtype and shape of every TissueModel field; named dimensions must agree across fields.
_TISSUE_FIELDS: dict[str, tuple[type, tuple]] = {
    "particle_rest_q": (np.float64, ("N", 3)),
    "particle_mass": (np.float64, ("N",)),
    "particle_inv_mass": (np.float64, ("N",)),
    "particle_damping": (np.float64, ("N",)),
    "tet_indices": (np.int32, ("T", 4)),
    "tet_dm_inv": (np.float64, ("T", 3, 3)),
    "tet_rest_volume": (np.float64, ("T",)),
    "tet_mu": (np.float64, ("T",)),
    "tet_lambda": (np.float64, ("T",)),
    "tet_color_order": (np.int32, ("A",)),
    "tet_color_offsets": (np.int32, ("K+1",)),
    "tri_indices": (np.int32, ("F", 3)),
    "tri_tet": (np.int32, ("F",)),
    "roller_particle": (np.int32, ("R",)),
    "roller_normal": (np.float64, ("R", 3)),
    "roller_offset": (np.float64, ("R",)),
    "support_normal": (np.float64, ("S", 3)),
    "support_offset": (np.float64, ("S",)),
    "contact_vertex": (np.int32, ("P",)),
    "contact_face": (np.int32, ("P",)),
}

#: Index fields and the dimension they index into.
_TISSUE_INDEX_BOUNDS = {
    "tet_indices": "N",
    "tet_color_order": "T",
    "tri_indices": "N",
    "tri_tet": "T",
    "roller_particle": "N",
    "contact_vertex": "N",
    "contact_face": "F",
}


def _per_tet_material(material, tet_material, tet_count: int):
    """Per-tet ``(mu, lambda, density, damping)`` arrays from one material or a material table."""
    if isinstance(material, TissueMaterial):
        if tet_material is not None:
            raise ValueError("tet_material is only meaningful with a sequence of materials")
        table = [material]
        index = np.zeros(tet_count, dtype=np.int64)
    else:
        table = list(material)
        if not table or not all(isinstance(m, TissueMaterial) for m in table):
            raise ValueError("material must be a TissueMaterial or a non-empty sequence of TissueMaterial")
        if tet_material is None:
            raise ValueError("tet_material (T,) is required when material is a sequence")
        index = np.asarray(tet_material)
        if index.shape != (tet_count,) or not np.issubdtype(index.dtype, np.integer):
            raise ValueError(f"tet_material must be a ({tet_count},) integer array, got {index.shape} {index.dtype}")
        if index.min() < 0 or index.max() >= len(table):
            bad = int(np.flatnonzero((index < 0) | (index >= len(table)))[0])
            raise ValueError(f"tet_material[{bad}] = {int(index[bad])} is outside 0..{len(table) - 1}")
    props = np.array([[m.lame_mu, m.hydrostatic_modulus, m.density, m.damping] for m in table])
    per_tet = props[index]
    return per_tet[:, 0], per_tet[:, 1], per_tet[:, 2], per_tet[:, 3]


def _rollers(rollers, particle_count: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Validated roller arrays ``(particle (R,), unit normal (R, 3), offset (R,))``."""
    if rollers is None:
        return np.zeros(0, np.int32), np.zeros((0, 3)), np.zeros(0)
    if len(rollers) != 3:
        raise ValueError("rollers must be a tuple (particles, normals, offsets)")
    particle = np.asarray(rollers[0])
    normal = np.asarray(rollers[1], dtype=np.float64)
    offset = np.asarray(rollers[2], dtype=np.float64)
    r = len(particle)
    if particle.ndim != 1 or (r and not np.issubdtype(particle.dtype, np.integer)):
        raise ValueError(f"roller particles must be a 1-D integer array, got {particle.shape} {particle.dtype}")
    if normal.shape != (r, 3) or offset.shape != (r,):
        raise ValueError(f"roller normals must be ({r}, 3) and offsets ({r},), got {normal.shape}, {offset.shape}")
    if r and (particle.min() < 0 or particle.max() >= particle_count):
        bad = int(np.flatnonzero((particle < 0) | (particle >= particle_count))[0])
        raise ValueError(f"roller {bad} names particle {int(particle[bad])}, outside 0..{particle_count - 1}")
    length = np.linalg.norm(normal, axis=1)
    if not (np.all(np.isfinite(length)) and np.all(length > 0) and np.all(np.isfinite(offset))):
        raise ValueError("roller normals must be finite and non-zero and offsets finite")
    return particle.astype(np.int32), normal / length[:, None], offset


def _supports(supports) -> tuple[np.ndarray, np.ndarray]:
    """Validated support half-spaces ``(unit normal (S, 3), offset (S,))``."""
    if supports is None:
        return np.zeros((0, 3)), np.zeros(0)
    if len(supports) != 2:
        raise ValueError("supports must be a tuple (normals, offsets)")
    normal = np.asarray(supports[0], dtype=np.float64)
    offset = np.asarray(supports[1], dtype=np.float64)
    if normal.ndim != 2 or normal.shape[1:] != (3,) or offset.shape != normal.shape[:1]:
        raise ValueError(f"support normals must be (S, 3) and offsets (S,), got {normal.shape}, {offset.shape}")
    length = np.linalg.norm(normal, axis=1)
    if not (np.all(np.isfinite(length)) and np.all(length > 0) and np.all(np.isfinite(offset))):
        raise ValueError(f"support normals must be finite and non-zero and offsets finite, got {normal.tolist()}, "
                         f"{offset.tolist()}")
    return normal / length[:, None], offset


@dataclass
class TissueState:
    """Time-varying tissue arrays.

    Attributes:
        particle_q: ``(N, 3) float64`` positions, m.
        particle_qd: ``(N, 3) float64`` velocities, m/s.
        particle_q_prev: ``(N, 3) float64`` positions at the start of the latest substep, m (written by
            the solver's prediction).
        tet_multiplier: ``(T, 2) float64`` XPBD multipliers ``[lambda_D, lambda_H]`` accumulated in the
            latest substep, J s^2; the constraint force on node ``k`` is ``grad_k C lambda / dt^2``.
    """

    particle_q: np.ndarray
    particle_qd: np.ndarray
    particle_q_prev: np.ndarray
    tet_multiplier: np.ndarray

    @classmethod
    def at_rest(cls, model: TissueModel) -> TissueState:
        """State with every particle at its rest position, at rest, and zero multipliers."""
        q = np.array(model.particle_rest_q, dtype=np.float64, copy=True)
        return cls(
            particle_q=q,
            particle_qd=np.zeros_like(q),
            particle_q_prev=q.copy(),
            tet_multiplier=np.zeros((model.tet_count, 2)),
        )

    def copy(self) -> TissueState:
        """Deep copy."""
        return TissueState(**{f.name: getattr(self, f.name).copy() for f in fields(self)})

    def assign(self, other: TissueState) -> None:
        """Copy ``other``'s values into this state's arrays in place (shapes must match)."""
        for f in fields(self):
            mine, theirs = getattr(self, f.name), getattr(other, f.name)
            if mine.shape != theirs.shape:
                raise ValueError(f"TissueState.{f.name} has shape {mine.shape}, cannot assign {theirs.shape}")
            mine[...] = theirs


@dataclass(frozen=True)
class Model:
    """Everything static about a scene.

    Attributes:
        tissue: the :class:`TissueModel`, or None for a scene without tissue.
        needle: the :class:`~suture_gym.sim.needle.NeedleModel`, or None.
        suture: the suture :class:`~suture_gym.sim.rod.RodModel`, or None; with a needle, its node 0 is
            attached to the needle's swage.
        coupling: the :class:`~suture_gym.sim.coupling.CouplingModel` of needle + suture with the tissue, or
            None (needs tissue and needle, built for exactly this needle and suture).
        gravity: ``(3,) float64`` gravitational acceleration, m/s^2 (read-only).
        obstacles: :class:`~suture_gym.sim.rod.StaticObstacles` (planes, spheres) the suture cannot enter, with
            Coulomb friction, or None; needs a suture.
    """

    tissue: TissueModel | None = None
    needle: NeedleModel | None = None
    suture: RodModel | None = None
    coupling: CouplingModel | None = None
    gravity: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, -9.81]))
    obstacles: StaticObstacles | None = None

    def __post_init__(self) -> None:
        for name, kind in (
            ("tissue", TissueModel),
            ("needle", NeedleModel),
            ("suture", RodModel),
            ("coupling", CouplingModel),
            ("obstacles", StaticObstacles),
        ):
            value = getattr(self, name)
            if value is not None and not isinstance(value, kind):
                raise ValueError(f"Model.{name} must be a {kind.__name__} or None, got {type(value).__name__}")
        if self.coupling is not None:
            if self.tissue is None or self.needle is None:
                raise ValueError("Model.coupling needs Model.tissue and Model.needle")
            expected = self.needle.node_count + (0 if self.suture is None else self.suture.node_count - 1)
            if self.coupling.needle_node_count != self.needle.node_count or self.coupling.strand_node_count != expected:
                raise ValueError(
                    f"Model.coupling was built for a strand of {self.coupling.strand_node_count} nodes, but needle "
                    f"and suture make {expected}"
                )
        if self.obstacles is not None and self.suture is None:
            raise ValueError("Model.obstacles act on the suture: they need Model.suture")
        gravity = np.array(self.gravity, dtype=np.float64, copy=True)
        if gravity.shape != (3,) or not np.all(np.isfinite(gravity)):
            raise ValueError(f"Model.gravity must be three finite components in m/s^2, got {self.gravity!r}")
        gravity.flags.writeable = False
        object.__setattr__(self, "gravity", gravity)


class Work:
    """Buffers the solver reuses every substep for one model and one state (see :attr:`State.work`).

    They carry no information from one substep to the next: the detection refits the BVHs and rebuilds the
    coupling rows, and the solver loads the rod's warm start from the State before each substep's sweeps.

    Attributes:
        model: the :class:`Model` the buffers were sized for (compared by identity).
        rod_work: :class:`~suture_gym.sim.rod.RodWork` of the suture, or None.
        coupling_work: :class:`~suture_gym.sim.coupling.CouplingWork` (rows, refitted BVHs), or None.
        rod_solves: direct solves of the suture in the last substep's last sweep (iterations whose residual
            was above the solver's ``rod_tolerance``), a convergence reading.
        compliance: the tissue's side of the coupling rows this substep
            (:mod:`~suture_gym.sim.coupling.compliance`): :attr:`diagonal_compliance` (XPBD) or the implicit
            integrator's compliance among the rows' vertices (set by the solver each substep); None without
            tissue.
        diagonal_compliance: the particles' inverse masses as a compliance tuple, built once; None without
            tissue.
    """

    def __init__(self, model: Model):
        self.model = model
        self.rod_work = None if model.suture is None else RodWork(model.suture)
        self.coupling_work = None if model.coupling is None else CouplingWork(model.coupling)
        self.rod_solves = 0
        self.diagonal_compliance = None if model.tissue is None else diagonal(model.tissue.particle_inv_mass)
        self.compliance = self.diagonal_compliance
        self._tissue_integrator: ImplicitTissue | None = None
        self._tet_blocks: TetBlocks | None = None

    def tet_blocks(self) -> TetBlocks:
        """The tissue's tets in the XPBD sweep's blocks (:func:`~suture_gym.sim.tissue.tet_blocks` of its colour
        order), built on first use."""
        if self._tet_blocks is None:
            t = self.model.tissue
            self._tet_blocks = tet_blocks(t.particle_inv_mass, t.tet_indices, t.tet_dm_inv, t.tet_rest_volume, t.tet_mu,
                                          t.tet_lambda, t.tet_color_order)  # fmt: skip
        return self._tet_blocks

    def tissue_integrator(self, kind: str, dt: float, scheme: str = "euler") -> ImplicitTissue:
        """The implicit tissue integrator ``kind`` for substep ``dt`` (s) and time ``scheme`` of the model's tissue
        (:class:`~suture_gym.sim.tissue_implicit.ImplicitTissue`): built, with its factorised rest system, on first
        use and again only when ``kind``, ``dt`` or ``scheme`` changes."""
        current = self._tissue_integrator
        if current is None or current.name != kind or current.dt != float(dt) or current.scheme != scheme:
            current = implicit_tissue(self.model.tissue, kind, dt, scheme)
            for factor in current.factors:
                weakref.finalize(current, _drop_solve_buffer, factor).atexit = False
            self._tissue_integrator = current
        return current


def _drop_solve_buffer(factor) -> None:
    """Shrink the right-hand-side buffer of ``factor`` (a
    :class:`~suture_gym.sim.rest_system.SparseCholesky` about to be released) to no column.

    cholespy's CPU solver keeps the ``(n, k)`` buffer of its last solve and its destructor does not free it:
    8 n k bytes lost with every factorisation, i.e. with every randomised episode's new tissue (about 6 KB on the
    NeedleInsert pad). A solve with no column swaps that buffer for an empty one, so only the empty one is lost.
    """
    factor.release_buffer()


@dataclass
class State:
    """Everything that changes during a simulation.

    Attributes:
        tissue: the :class:`TissueState`, or None.
        needle: the :class:`~suture_gym.sim.needle.NeedleState`, or None.
        suture: the suture :class:`~suture_gym.sim.rod.RodState`, or None.
        coupling: the :class:`~suture_gym.sim.coupling.CouplingState`, or None.
        suture_tension: ``(S-1,) float64`` size of each suture segment's stretch multiplier in the last
            substep, kg m^2 (the rod solver's geometric-stiffness warm start), or None without a suture.
        suture_contact: ``(S,) bool`` the suture nodes whose contact row pushed at the end of the last substep
            (the rod solver's contact-set warm start: only these open a contact row in the next substep's first
            iteration, :meth:`~suture_gym.sim.solver.Solver._project_suture`); all True in a state that has not
            stepped; None without a suture.
        needle_reaction: ``(6,) float64`` wrench the constraints (tissue coupling, suture attachment) exerted on
            the needle in the last substep: force N, then torque about the grip point N m (the haptic
            reaction; the device feels its opposite), or None without a needle.
        time: simulated time, s.
        diverged: set by the solver when positions become non-finite or speeds absurd; the solver leaves a
            diverged state untouched from then on.
        work: the solver's :class:`Work` buffers for this state, made by the first step (None before). They
            carry no state, so :meth:`snapshot` leaves them out and :meth:`restore` keeps this state's own: no
            two states share buffers.
    """

    tissue: TissueState | None = None
    needle: NeedleState | None = None
    suture: RodState | None = None
    coupling: CouplingState | None = None
    suture_tension: np.ndarray | None = None
    suture_contact: np.ndarray | None = None
    needle_reaction: np.ndarray | None = None
    time: float = 0.0
    diverged: bool = False
    work: Work | None = field(default=None, repr=False, compare=False)

    @classmethod
    def initial(cls, model: Model, needle: NeedleState | None = None, suture: RodState | None = None) -> State:
        """A state at rest for ``model``: tissue in its rest shape, the given needle and suture states, an
        empty coupling state, a zero tension warm start and readings, and every suture node eligible for contact.
        A needle (suture) state is required iff the model has a needle (suture)."""
        if (model.needle is None) != (needle is None):
            raise ValueError("State.initial needs a needle state exactly when the model has a needle")
        if (model.suture is None) != (suture is None):
            raise ValueError("State.initial needs a suture state exactly when the model has a suture")
        return cls(
            tissue=None if model.tissue is None else TissueState.at_rest(model.tissue),
            needle=needle,
            suture=suture,
            coupling=None if model.coupling is None else CouplingState.empty(model.coupling),
            suture_tension=None if model.suture is None else np.zeros(model.suture.node_count - 1),
            suture_contact=None if model.suture is None else np.ones(model.suture.node_count, dtype=np.bool_),
            needle_reaction=None if model.needle is None else np.zeros(6),
        )

    def snapshot(self) -> State:
        """Deep copy of the whole state (restore it with :meth:`restore`), without the solver's :attr:`work`."""
        return State(
            tissue=None if self.tissue is None else self.tissue.copy(),
            needle=None if self.needle is None else self.needle.copy(),
            suture=None if self.suture is None else self.suture.copy(),
            coupling=None if self.coupling is None else self.coupling.copy(),
            suture_tension=None if self.suture_tension is None else self.suture_tension.copy(),
            suture_contact=None if self.suture_contact is None else self.suture_contact.copy(),
            needle_reaction=None if self.needle_reaction is None else self.needle_reaction.copy(),
            time=self.time,
            diverged=self.diverged,
        )

    def restore(self, snapshot: State) -> None:
        """Make this state equal to ``snapshot`` (deep copies; the snapshot stays reusable).

        The tissue arrays are overwritten in place, so references to them stay valid; the other parts are
        replaced by copies of the snapshot's. This state keeps its own :attr:`work`.
        """
        if (self.tissue is None) != (snapshot.tissue is None):
            raise ValueError("snapshot and state disagree on whether there is tissue")
        if self.tissue is not None:
            self.tissue.assign(snapshot.tissue)
        copy = snapshot.snapshot()
        self.needle = copy.needle
        self.suture = copy.suture
        self.coupling = copy.coupling
        self.suture_tension = copy.suture_tension
        self.suture_contact = copy.suture_contact
        self.needle_reaction = copy.needle_reaction
        self.time = snapshot.time
        self.diverged = snapshot.diverged


@dataclass
class Control:
    """Inputs held constant over a step.

    Attributes:
        needle_wrench: ``(6,) float64`` force (N, world frame) then torque (N m, world frame) applied to the
            needle holder's grip point.
        suture_force: ``(S, 3) float64`` external force on each suture node, N (world frame), or None for none;
            its row count must match the model's suture.
    """

    needle_wrench: np.ndarray = field(default_factory=lambda: np.zeros(6))
    suture_force: np.ndarray | None = None

    def __post_init__(self) -> None:
        wrench = np.array(self.needle_wrench, dtype=np.float64, copy=True)
        if wrench.shape != (6,):
            raise ValueError(f"Control.needle_wrench must have shape (6,), got {wrench.shape}")
        if not np.all(np.isfinite(wrench)):
            raise ValueError(f"Control.needle_wrench must be finite, got {wrench.tolist()}")
        self.needle_wrench = wrench
        if self.suture_force is not None:
            force = np.array(self.suture_force, dtype=np.float64, copy=True)
            if force.ndim != 2 or force.shape[1] != 3 or not np.all(np.isfinite(force)):
                raise ValueError(f"Control.suture_force must be a finite (S, 3) array in N, got shape {force.shape}")
            self.suture_force = force
