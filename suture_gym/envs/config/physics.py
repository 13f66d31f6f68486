"""The physical sections of the env config: tissue, scene, needle, thread, coupling and solver.

Each simulator section is the simulator's own parameter dataclass, subclassed with the env-only fields.
"""

from __future__ import annotations

import math
import warnings
from dataclasses import dataclass, field
from pathlib import Path
from typing import ClassVar

from suture_gym.envs.config.checks import _choice, _count, _fail, _real, _Section, sim_fields
from suture_gym.sim.anatomy import ANATOMY_KINDS, HAND_VOLUME
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.model import VALIDATED_YOUNGS_MODULUS, TissueMaterial
from suture_gym.sim.needle import NeedleShape
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.solver import Solver

#: Scene kinds: one tissue pad; two bars with a wound gap between them; the seed paper's abdominal wall and hand
#: (:mod:`suture_gym.sim.anatomy`); a user's mesh file with an incision (:class:`SceneConfig`).
SCENE_KINDS: tuple[str, ...] = ("pad", "wound", *ANATOMY_KINDS)
#: Tets per hexahedral cell (the five-tet scheme of the grids and the voxel backend).
_VOXEL_TETS_PER_CELL = 5
#: Largest ``solver.dt``, s: ten times the 1 ms the environments are validated at (the physics checks use
#: 0.25-1 ms); at larger substeps contacts and punctures are no longer resolved.
MAX_DT = 0.01
#: The environments' forces over the scale of the simulator's instrument defaults: the needle holder's mass and
#: inertia (:class:`~suture_gym.sim.needle.NeedleShape`) and the virtual coupling's gains
#: (:class:`~suture_gym.sim.needle.VirtualCoupling`) are the simulator's times this factor, so the holder has
#: the same response time and damping ratio under the environments' hundredfold forces.
FORCE_SCALE = 100.0


@dataclass(frozen=True)
class TissueConfig(TissueMaterial):
    """Tissue material: the simulator's :class:`~suture_gym.sim.model.TissueMaterial` itself (its fields, units,
    defaults and checks), warning outside the range the simulator is validated for.

    The default 300 kPa silicone pad is what every force default of the environments is scaled to
    (:class:`CouplingConfig`, :class:`ActionConfig`, :class:`NeedleConfig`; the ``*_paper.yaml`` configs are the
    seed paper's 1 kPa). The implicit tissue integrator (``solver.tissue_integrator``) keeps it true to its
    material at the default substep (docs/notes/tissue_integrator.md).
    """

    def __post_init__(self) -> None:
        super().__post_init__()
        low, high = VALIDATED_YOUNGS_MODULUS
        if not low <= self.youngs_modulus <= high:
            warnings.warn(
                f"tissue.youngs_modulus = {self.youngs_modulus:g} Pa is outside the range the simulator is validated "
                f"for ({low:g}-{high:g} Pa)",
                stacklevel=2,
            )


@dataclass(frozen=True)
class IncisionConfig(_Section):
    """The incision of a ``mesh`` scene, and the depth of the anatomical scenes' own (module
    :mod:`suture_gym.sim.incision`; its gap is ``scene.gap``)."""

    SECTION: ClassVar[str] = "scene.incision"

    points: tuple[tuple[float, float, float], ...] = ()  # m, the polyline on the surface, along +x (mesh scenes)
    depth: float = 0.0  # m; 0: the scene's own (abdominal_wall: skin and fat, hand: two cells)

    def validate(self, path: str) -> None:
        for k, point in enumerate(self.points):
            for j, v in enumerate(point):
                _real(f"{path}.points[{k}][{j}]", v)
        if len(self.points) == 1:
            _fail(f"{path}.points", "must hold at least two points (a polyline), got one")
        _real(f"{path}.depth", self.depth, low=0.0)


@dataclass(frozen=True)
class SceneConfig(_Section):
    """Tissue geometry. Frame: gravity along -z, tissue resting on a rigid base at ``z = 0`` (bottom pinned).

    ``pad``: one block ``x in [0, size_x]``, ``y in [0, size_y]``, ``z in [0, size_z]``.
    ``wound``: two such blocks (bars) side by side along ``y`` with ``gap`` between their facing faces
    ``y = size_y`` and ``y = size_y + gap``; the wound runs along ``x``; both end faces ``x = 0`` and
    ``x = size_x`` of each bar are pinned (paper Fig. 5). Cells are as close to ``cell_size`` as the sizes allow;
    ``cell_size`` may not exceed any edge of the pad.
    ``abdominal_wall``: the slab ``size`` = (length, width, thickness) bent over a 15 cm cylinder, an incision
    along its crest over the middle two thirds of its length (:func:`~suture_gym.sim.anatomy.abdominal_wall`).
    ``hand``: the hand of :func:`~suture_gym.sim.anatomy.hand`, filled by the voxel backend at ``cell_size``, a
    wound along ``x`` on its back (``size`` unused).
    ``mesh``: the tet mesh or closed surface in the file ``path`` (m; a surface is tetrahedralised at
    ``cell_size`` by :func:`~suture_gym.sim.mesh_io.tetrahedralize_surface`, fTetWild if installed, else voxels),
    resting on a rigid base at its lowest point (the nodes within half a ``cell_size`` of it pinned), with the
    incision ``incision`` (its polyline along ``+x`` on the upper surface; the needle comes from above).
    In the wound scenes (all but ``pad``) the wound's faces part along ``y``; ``gap`` is the opening at the mouth
    of an incision. ``layer_thickness`` and ``layer_stiffness`` make any scene layered by depth below its upper
    surface (:mod:`suture_gym.sim.layers`): layer ``k`` has Young's modulus ``layer_stiffness[k] *
    tissue.youngs_modulus`` (so randomisation scales every layer), the last one filling the rest.
    ``wound_contact``: the wound's two faces are kept from passing through each other
    (:func:`~suture_gym.sim.incision.with_wound_contact`): a needle pushing one face (a soft layer tenting at the
    exit) pushes the other instead of crossing it.
    The scene's tets (five per cell, both bars of a wound; estimated for the hand; the file's for a mesh, counted
    when it is read) are refused above ``max_tets``, or when their estimated memory exceeds the machine's
    (:func:`~suture_gym.sim.mesh.check_tet_budget`), before anything is built.
    """

    SECTION: ClassVar[str] = "scene"

    kind: str = "pad"  # one of SCENE_KINDS
    size: tuple[float, float, float] = (0.008, 0.024, 0.008)  # m, (x, y, z) of the pad, of each bar, or the slab
    cell_size: float = 0.002  # m, target edge of the hexahedral cells (each split into five tets)
    grid: tuple[int, int, int] = (0, 0, 0)  # cells along (x, y, z) when non-zero, instead of size / cell_size
    gap: float = 0.004  # m, wound gap between the bars, or an incision's opening (wound scenes only)
    max_tets: int = 100_000  # most tets the scene may have (the defaults have 1-4k; 100k take ~0.8 GB implicit)
    path: str = ""  # tet mesh or closed surface file (mesh scenes only)
    incision: IncisionConfig = field(default_factory=IncisionConfig)
    layer_thickness: tuple[float, ...] = ()  # m, every layer's but the deepest, top first
    layer_stiffness: tuple[float, ...] = ()  # factors on tissue.youngs_modulus, one per layer (one more entry)
    wound_contact: bool = False  # the wound's faces cannot pass through each other (wound scenes only)

    def validate(self, path: str) -> None:
        _choice(f"{path}.kind", self.kind, SCENE_KINDS)
        if self.wound_contact and self.kind == "pad":
            _fail(f"{path}.wound_contact", "needs a wound: scene.kind 'pad' has none")
        for k, v in enumerate(self.size):
            _real(f"{path}.size[{k}]", v, low=0.0, strict_low=True)
        _real(f"{path}.cell_size", self.cell_size, low=0.0, strict_low=True)
        _real(f"{path}.gap", self.gap, low=0.0, strict_low=True)
        _count(f"{path}.max_tets", self.max_tets, 1)
        if self.grid != (0, 0, 0):
            for k, v in enumerate(self.grid):
                _count(f"{path}.grid[{k}]", v, 1)
        elif self.kind in ("pad", "wound", "abdominal_wall"):
            for k, v in enumerate(self.size):
                if self.cell_size > v:
                    _fail(f"{path}.cell_size", f"= {self.cell_size} m is larger than the pad: {path}.size[{k}] = {v} m")
        if self.kind == "mesh":
            if not self.path:
                _fail(f"{path}.path", "must name a tet mesh or closed surface file for scene.kind = 'mesh'")
            if not Path(self.path).is_file():
                _fail(f"{path}.path", f"= {self.path!r} is not a file")
            if len(self.incision.points) < 2 or self.incision.depth <= 0.0:
                _fail(f"{path}.incision", "needs points (two or more) and a depth > 0 for scene.kind = 'mesh'")
        else:
            if self.path:
                _fail(f"{path}.path", f"is read for scene.kind = 'mesh' only, got it with kind {self.kind!r}")
            if self.incision.points:
                _fail(f"{path}.incision.points", f"are read for scene.kind = 'mesh' only, got kind {self.kind!r}")
            if self.incision.depth and self.kind in ("pad", "wound"):
                _fail(f"{path}.incision.depth", f"is not read for scene.kind = {self.kind!r}")
        for k, v in enumerate(self.layer_thickness):
            _real(f"{path}.layer_thickness[{k}]", v, low=0.0, strict_low=True)
        for k, v in enumerate(self.layer_stiffness):
            _real(f"{path}.layer_stiffness[{k}]", v, low=0.0, strict_low=True)
        if (self.layer_thickness or self.layer_stiffness) and (
                len(self.layer_stiffness) != len(self.layer_thickness) + 1):
            _fail(f"{path}.layer_stiffness", f"must have one entry per layer, {len(self.layer_thickness) + 1} for "
                  f"{len(self.layer_thickness)} layer_thickness entries, got {len(self.layer_stiffness)}")

    @property
    def tets(self) -> int:
        """Tets of the scene: five per cell, times two bars for a wound; for the hand an estimate (its volume over
        the cell's, five tets each); 0 for a mesh (counted when its file is read)."""
        if self.kind == "hand":
            return int(_VOXEL_TETS_PER_CELL * HAND_VOLUME / self.cell_size**3)
        if self.kind == "mesh":
            return 0
        return _VOXEL_TETS_PER_CELL * math.prod(self.cells) * (2 if self.kind == "wound" else 1)

    @property
    def cells(self) -> tuple[int, int, int]:
        """Cell counts along (x, y, z): ``grid`` if set, else ``round(size / cell_size)``, at least 1."""
        if self.grid != (0, 0, 0):
            return self.grid
        return tuple(max(1, int(round(s / self.cell_size))) for s in self.size)


@dataclass(frozen=True)
class NeedleConfig(NeedleShape):
    """The curved needle and its holder: the simulator's :class:`~suture_gym.sim.needle.NeedleShape` itself
    (its fields, units, defaults and checks; the holder's mass and inertia :data:`FORCE_SCALE` times the
    simulator's, see :class:`ActionConfig`) plus the body's damping and gravity compensation of
    :meth:`~suture_gym.sim.needle.NeedleModel.from_shape`."""

    holder_mass: float = 2.0  # kg, FORCE_SCALE x the simulator's: the needle driver and the hand
    holder_inertia: float = 1.0e-4  # kg m^2, FORCE_SCALE x the simulator's
    linear_damping: float = 5.0  # 1/s, velocity damping of the needle body
    angular_damping: float = 5.0  # 1/s
    gravity_compensation: bool = True  # the haptic device carries the needle's weight

    def __post_init__(self) -> None:
        super().__post_init__()
        _real("needle.linear_damping", self.linear_damping, low=0.0)
        _real("needle.angular_damping", self.angular_damping, low=0.0)
        if not isinstance(self.gravity_compensation, bool):
            _fail("needle.gravity_compensation", f"must be true or false, got {self.gravity_compensation!r}")

    def shape(self) -> NeedleShape:
        """The :class:`~suture_gym.sim.needle.NeedleShape` of these fields."""
        return NeedleShape(**sim_fields(self, NeedleShape))


@dataclass(frozen=True)
class SutureConfig(SutureParams):
    """The suture thread: the simulator's :class:`~suture_gym.sim.rod.SutureParams` itself (its fields, units
    and defaults and checks), except that ``node_count = 0`` (the default) means no thread, plus a stopper
    knot."""

    node_count: int = 0  # nodes along the thread (0: needle only)
    knot_tail: float = 0.0  # m of thread beyond a stopper knot tied near its free end (0: no knot)

    def __post_init__(self) -> None:
        if self.node_count != 0:
            super().__post_init__()
        else:  # no thread: the other fields must still be valid for when one is added
            SutureParams(**{**sim_fields(self, SutureParams), "node_count": 2})
        _real("suture.knot_tail", self.knot_tail, low=0.0, high=self.length, strict_high=True)

    def params(self) -> SutureParams | None:
        """The :class:`~suture_gym.sim.rod.SutureParams` of these fields (None without a thread)."""
        return SutureParams(**sim_fields(self, SutureParams)) if self.node_count else None


@dataclass(frozen=True)
class CouplingConfig(CouplingParams):
    """Needle/suture-tissue interaction: the simulator's :class:`~suture_gym.sim.coupling.CouplingParams`
    itself (all its fields, units, defaults and checks).

    Forces scale with the tissue's stiffness (the dent a force makes goes as ``F / E``). The thresholds were
    tuned on 3 kPa tissue, where the scripted surgeon's needle needs 3-11 mN while it cuts along the plan: a
    5 mN puncture threshold lands within about 1 mm of the planned entry (at 10 mN the tip slides 1.3 mm, at
    20 mN it slips in without puncturing), and the tear force is ten times the working forces. On the 300 kPa
    default tissue these are 0.5 N to puncture and 10 N to tear. The insertion force model is on
    (docs/design.md, section 5.1): an exit peak of half the entry's (Frick et al. 2001), a cutting force of a
    fifth of the puncture force while the tip advances (the cutting term of Okamura et al. 2004) and a 1 mm tip
    patch, so the force before puncture rises with the tip's stiffness, not the mesh's.
    """

    def params(self, puncture_force: float | None = None) -> CouplingParams:
        """The :class:`~suture_gym.sim.coupling.CouplingParams` of these fields, with ``puncture_force`` (N)
        replaced when given (a randomised episode's)."""
        values = sim_fields(self, CouplingParams)
        if puncture_force is not None:
            values["puncture_force"] = puncture_force
        return CouplingParams(**values)


@dataclass(frozen=True)
class SolverConfig(Solver):
    """Time stepping: the simulator's :class:`~suture_gym.sim.solver.Solver` itself (its fields, units,
    defaults and checks), plus the substep ``dt``: one env step is ``substeps`` solver substeps of ``dt``."""

    dt: float = 1.0e-3  # s, substep
    substeps: int = 5  # substeps per env step

    def __post_init__(self) -> None:
        super().__post_init__()
        _real("solver.dt", self.dt, low=0.0, strict_low=True)
        if self.dt > MAX_DT:
            _fail("solver.dt", f"must be <= {MAX_DT} s (the environments are validated at 1 ms substeps, the paper's "
                  f"scenes at 5/3 and 2.5 ms), got {self.dt!r}")
        _count("solver.substeps", self.substeps, 1)

    def solver(self) -> Solver:
        """The :class:`~suture_gym.sim.solver.Solver` of these fields."""
        return Solver(**sim_fields(self, Solver))
