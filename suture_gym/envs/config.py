"""Typed configuration of the suturing environments; YAML files only override the typed defaults.

An :class:`EnvConfig` is a tree of frozen dataclasses. The physical sections are the simulator's own parameter
dataclasses (``tissue`` is a :class:`~suture_gym.sim.model.TissueMaterial`, ``needle`` a
:class:`~suture_gym.sim.needle.NeedleShape`, ``suture`` a :class:`~suture_gym.sim.rod.SutureParams`,
``coupling`` a :class:`~suture_gym.sim.coupling.CouplingParams`, ``solver`` a
:class:`~suture_gym.sim.solver.Solver`, subclassed with the few env-scale defaults that differ and the env-only
fields), so every simulator parameter is settable from YAML and has one default.

:func:`default_config` gives the defaults of a task (the
values the registered ids use); :func:`load_config` applies overrides from a YAML file, a mapping or another
config on top of them. Every key of an override must name a field: an unknown key raises ValueError naming its
dotted path (``reward.puncture_bonus``), so a typo never passes silently. :func:`config_to_dict` gives the
resolved config as plain data, to save with every run.

Units are SI throughout (m, kg, s, N, Pa, rad); each field's comment states its unit.
"""

from __future__ import annotations

import functools
import math
import os
import re
import types
import typing
import warnings
from dataclasses import dataclass, field, fields, is_dataclass, replace
from pathlib import Path
from typing import Any, ClassVar

from suture_gym.configs import env_config_path
from suture_gym.envs.registry import task_class
from suture_gym.sim.anatomy import ANATOMY_KINDS, HAND_VOLUME
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.mesh import BYTES_PER_TET_IMPLICIT, BYTES_PER_TET_XPBD, check_tet_budget
from suture_gym.sim.model import VALIDATED_YOUNGS_MODULUS, TissueMaterial
from suture_gym.sim.needle import NeedleShape, VirtualCoupling
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.solver import Solver

#: Action modes: a wrench on the needle holder, or a pose change of the holder through the virtual coupling.
ACTION_MODES: tuple[str, ...] = ("wrench", "pose_delta")
#: Scene kinds: one tissue pad; two bars with a wound gap between them; the seed paper's abdominal wall and hand
#: (:mod:`suture_gym.sim.anatomy`); a user's mesh file with an incision (:class:`SceneConfig`).
SCENE_KINDS: tuple[str, ...] = ("pad", "wound", *ANATOMY_KINDS)
#: Tets per hexahedral cell (the five-tet scheme of the grids and the voxel backend).
_VOXEL_TETS_PER_CELL = 5
#: Observation modes: the flat state vector, or a Dict with images or a point cloud (:class:`ObservationConfig`).
OBSERVATION_MODES: tuple[str, ...] = ("state", "rgb", "depth", "rgbd", "point_cloud")
#: Goal rewards of the goal-conditioned variants.
GOAL_REWARDS: tuple[str, ...] = ("sparse", "dense")
#: Largest ``solver.dt``, s: ten times the 1 ms the environments are validated at (the physics checks use
#: 0.25-1 ms); at larger substeps contacts and punctures are no longer resolved.
MAX_DT = 0.01


def _fail(path: str, message: str) -> None:
    raise ValueError(f"{path} {message}")


def _real(path: str, value: Any, *, low: float | None = None, high: float | None = None, strict_low: bool = False,
          strict_high: bool = False) -> None:
    """Check that ``value`` is a finite real number in the given bounds; ValueError naming ``path`` otherwise."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        _fail(path, f"must be a finite number, got {value!r}")
    if low is not None and (value <= low if strict_low else value < low):
        _fail(path, f"must be {'>' if strict_low else '>='} {low}, got {value!r}")
    if high is not None and (value >= high if strict_high else value > high):
        _fail(path, f"must be {'<' if strict_high else '<='} {high}, got {value!r}")


def _count(path: str, value: Any, low: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < low:
        _fail(path, f"must be an integer >= {low}, got {value!r}")


def _choice(path: str, value: Any, choices: tuple[str, ...]) -> None:
    if value not in choices:
        _fail(path, f"must be one of {list(choices)}, got {value!r}")


def _range(path: str, value: tuple[float, float], *, low: float, strict_low: bool = True) -> None:
    """A ``(lo, hi)`` sampling range with ``low < lo <= hi`` (or ``low <= lo`` when not strict)."""
    for k, v in enumerate(value):
        _real(f"{path}[{k}]", v, low=low, strict_low=strict_low)
    if value[0] > value[1]:
        _fail(path, f"must satisfy lo <= hi, got {list(value)}")


class _Section:
    """Base of the config sections: validated on construction, errors named ``<section>.<field>``."""

    SECTION: ClassVar[str] = ""

    def __post_init__(self) -> None:
        self.validate(self.SECTION)

    def validate(self, path: str) -> None:
        """Raise ValueError naming ``<path>.<field>`` for the first invalid field; every section defines it."""


def sim_fields(section: Any, sim_cls: type) -> dict:
    """The values of ``section`` for the fields of the simulator dataclass ``sim_cls`` (its base class), as
    keyword arguments of ``sim_cls``."""
    return {f.name: getattr(section, f.name) for f in fields(sim_cls) if f.init}


@dataclass(frozen=True)
class TissueConfig(TissueMaterial):
    """Tissue material: the simulator's :class:`~suture_gym.sim.model.TissueMaterial` itself (its fields, units
    and checks), with the environments' defaults for the fields below; the others keep the simulator's.

    Default 300 kPa: a silicone suture-training pad (platinum-cure silicones of the pads' hardness, Shore 00-30
    to 10A, have E of about 0.1-0.5 MPa; skin is reported from tens of kPa in indentation to about 1 MPa in
    tension), with nu = 0.45. The implicit tissue integrator (``solver.tissue_integrator``) keeps it true to its
    material at the default substep (docs/tissue_integrator.md). Every force default of the environments is
    scaled with it (:class:`CouplingConfig`, :class:`ActionConfig`, :class:`NeedleConfig`; the ``*_paper.yaml``
    configs are the seed paper's 1 kPa).
    """

    youngs_modulus: float = 3.0e5  # Pa
    poisson_ratio: float = 0.45  # dimensionless, [0, 0.5]

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
    (its fields, units, defaults and checks; the holder's mass and inertia scaled with the forces, see
    :class:`ActionConfig`) plus the body's damping and gravity compensation of
    :meth:`~suture_gym.sim.needle.NeedleModel.from_shape`."""

    holder_mass: float = 2.0  # kg, the needle driver and the hand (the arm's endpoint mass is 1-3 kg)
    holder_inertia: float = 1.0e-4  # kg m^2
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
    and checks) with the environments' defaults below, where ``node_count = 0`` means no thread, plus a
    stopper knot."""

    length: float = 0.03  # m
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
    itself (all its fields, units and checks), with the environments' defaults for the six below.

    Forces scale with the tissue's stiffness (the dent a force makes goes as ``F / E``). The thresholds were
    tuned on 3 kPa tissue, where the scripted surgeon's needle needs 3-11 mN while it cuts along the plan: a
    5 mN puncture threshold lands within about 1 mm of the planned entry (at 10 mN the tip slides 1.3 mm, at
    20 mN it slips in without puncturing), and the tear force is ten times the working forces. On the 300 kPa
    default tissue these are 0.5 N to puncture (measured suture-needle punctures: 0.5-2 N) and 10 N to tear.
    The insertion force model is on (docs/design.md, section 5.1): an exit peak of half the entry's (Frick et
    al. 2001), a cutting force of a fifth of the puncture force while the tip advances (the cutting term of
    Okamura et al. 2004) and a 1 mm tip patch, so the force before puncture rises with the tip's stiffness, not
    the mesh's.
    """

    puncture_force: float = 0.5  # N, tip force that pierces the surface
    exit_puncture_force: float = 0.25  # N, force on the surface from inside that lets the tip out
    cutting_force: float = 0.1  # N, resistance to the tip's advance while a puncture is open
    tip_contact_radius: float = 1.0e-3  # m, radius of the surface patch the tip loads before puncture
    tear_force: float = 10.0  # N, force of a row holding a strand in the tissue that tears it (ends the episode)
    needle_axial_friction: float = 150.0  # N/m of needle inside the tissue

    def params(self, puncture_force: float | None = None) -> CouplingParams:
        """The :class:`~suture_gym.sim.coupling.CouplingParams` of these fields, with ``puncture_force`` (N)
        replaced when given (a randomised episode's)."""
        values = sim_fields(self, CouplingParams)
        if puncture_force is not None:
            values["puncture_force"] = puncture_force
        return CouplingParams(**values)


@dataclass(frozen=True)
class SolverConfig(Solver):
    """Time stepping: the simulator's :class:`~suture_gym.sim.solver.Solver` itself (its fields, units and
    checks; ``max_speed`` tighter here), plus the substep ``dt``: one env step is ``substeps`` solver substeps
    of ``dt``."""

    iterations: int = 2  # sweeps per substep: the implicit tissue solve and the coupling rows alternate twice
    tissue_integrator: str = "quasi_newton"  # implicit Euler: true to the material at 1 ms
    max_speed: float = 20.0  # m/s, divergence threshold
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


@dataclass(frozen=True)
class ActionConfig(_Section):
    """How the 6 action components in [-1, 1] become a command.

    ``wrench``: ``[force (3) N, torque (3) N m]`` on the needle holder = action times ``(max_force x3,
    max_torque x3)``, world frame, torque about the grip point, held over the env step.
    ``pose_delta``: the holder's target pose moves by ``action[:3] * max_translation`` (m, world frame) and
    turns by the rotation vector ``action[3:] * max_rotation`` (rad, world frame, about the grip point) each
    env step; the virtual coupling (spring-damper with the stiffnesses below) pulls the needle towards it.
    Finite actions outside [-1, 1] are clipped to it, so these scales are the largest command.
    """

    SECTION: ClassVar[str] = "action"

    mode: str = "wrench"  # "wrench" or "pose_delta"
    max_force: float = 5.0  # N per component (half the tear force)
    max_torque: float = 0.02  # N m per component
    max_translation: float = 2.0e-4  # m per env step and component (pose_delta)
    max_rotation: float = 0.03  # rad per env step and component (pose_delta)
    # the virtual coupling (pose_delta, and the scripted surgeon): VirtualCoupling's defaults scaled, like the
    # holder's mass and inertia, by the forces' factor of 100 (the same response time and damping ratio)
    coupling_linear_stiffness: float = 100.0 * VirtualCoupling.linear_stiffness  # N/m
    coupling_linear_damping: float = 100.0 * VirtualCoupling.linear_damping  # N s/m
    coupling_angular_stiffness: float = 100.0 * VirtualCoupling.angular_stiffness  # N m/rad
    coupling_angular_damping: float = 100.0 * VirtualCoupling.angular_damping  # N m s/rad

    def validate(self, path: str) -> None:
        _choice(f"{path}.mode", self.mode, ACTION_MODES)
        for f in fields(self):
            if f.name != "mode":
                _real(f"{path}.{f.name}", getattr(self, f.name), low=0.0, strict_low=True)


@dataclass(frozen=True)
class PlanConfig(_Section):
    """The planned stitches: each is the needle's own circle turned about its centre (module tasks.geometry).

    The circle lies in a plane ``x = const`` (normal along the wound), its centre ``center_height`` (as a
    fraction of the needle's curvature radius) above the top surface; for a wound it is centred over the gap.
    Stitch ``i`` of ``stitches`` lies at ``x = size_x (i + 1) / (stitches + 1)``.
    """

    SECTION: ClassVar[str] = "plan"

    center_height: float = 0.5  # fraction of the curvature radius, in (0, 1)
    stitches: int = 1  # planned stitches along x
    start_angle: float = 0.15  # rad, the tip starts this far before the entry point along the circle
    thread_target: float = 0.01  # m, thread to pull through each stitch (tasks with a thread)
    closure_target: float = 0.6  # fraction of the initial wound gap to reach (wound_closure)

    def validate(self, path: str) -> None:
        _real(f"{path}.center_height", self.center_height, low=0.0, high=1.0, strict_low=True, strict_high=True)
        _count(f"{path}.stitches", self.stitches, 1)
        _real(f"{path}.start_angle", self.start_angle, low=0.0)
        _real(f"{path}.thread_target", self.thread_target, low=0.0, strict_low=True)
        _real(f"{path}.closure_target", self.closure_target, low=0.0, high=1.0, strict_low=True)


@dataclass(frozen=True)
class RandomizationConfig(_Section):
    """Seeded domain randomisation, sampled at every reset from the env's ``np_random`` in a fixed order.

    On by default (ids v2), like Gymnasium's ``reset_noise_scale``: every episode starts from a slightly
    different pose on slightly different tissue, so seeded evaluations are not one episode repeated.
    ``enabled: false`` gives the nominal episode at every reset (for debugging; the random stream is drawn
    the same). Scale ranges ``(lo, hi)`` multiply the nominal value by a log-uniform factor (``(1, 1)``
    disables one); noises are half-widths of uniform offsets per axis (0 disables). The sampled values are in
    ``info["params"]`` at reset and, with ``observation.privileged``, appended to the observation (whose size
    never depends on these settings).
    """

    SECTION: ClassVar[str] = "randomization"

    enabled: bool = True  # false: every episode has the nominal parameters
    youngs_modulus_scale: tuple[float, float] = (0.7, 1.3)  # factor on tissue.youngs_modulus
    puncture_force_scale: tuple[float, float] = (0.8, 1.25)  # factor on coupling.puncture_force
    gap_scale: tuple[float, float] = (0.9, 1.1)  # factor on scene.gap (wound scenes)
    needle_position_noise: float = 0.0005  # m, per axis, of the needle's start pose
    needle_rotation_noise: float = 0.05  # rad, per rotation-vector component of the start orientation

    def validate(self, path: str) -> None:
        if not isinstance(self.enabled, bool):
            _fail(f"{path}.enabled", f"must be true or false, got {self.enabled!r}")
        for name in ("youngs_modulus_scale", "puncture_force_scale", "gap_scale"):
            _range(f"{path}.{name}", getattr(self, name), low=0.0)
        _real(f"{path}.needle_position_noise", self.needle_position_noise, low=0.0)
        _real(f"{path}.needle_rotation_noise", self.needle_rotation_noise, low=0.0, high=math.pi)


@dataclass(frozen=True)
class RewardConfig(_Section):
    """Weights (dimensionless reward per unit of each term's measure) and tolerances of the reward terms.

    See :mod:`suture_gym.tasks` for each term's formula; a term whose weight is 0 is reported as 0.
    """

    SECTION: ClassVar[str] = "reward"

    path: float = 0.05  # per step at full deviation: -w d / (d + path_scale)
    path_scale: float = 1.0e-3  # m
    progress: float = 5.0  # per unit of arc progress (potential-based)
    entry: float = 2.0  # once, at the first puncture of a stitch: w max(0, 1 - e / tolerance)
    exit: float = 2.0  # once, when the tip comes out: w max(0, 1 - e / tolerance)
    puncture: float = 1.0  # once per puncture: +w at a planned access point, -w elsewhere
    thread: float = 2.0  # per target length of thread pulled through
    closure: float = 5.0  # per initial wound gap closed
    success: float = 5.0  # once, when the task succeeds
    # once, when the episode ends in failure; must exceed path / (1 - gamma) of the agent (tasks set their own)
    failure: float = 10.0
    tissue_force: float = 0.5  # per step at cost 1
    action: float = 0.01  # per step: -w mean(a^2)
    access_tolerance: float = 1.5e-3  # m, how close a puncture or exit must be to its planned point
    safe_force: float = 2.0  # N, coupling force below which the tissue-force cost is 0
    goal: str = "sparse"  # goal-conditioned variants: "sparse" (-1 until the goal is met, else 0) or "dense"

    def validate(self, path: str) -> None:
        for f in fields(self):
            if f.name in ("goal",):
                continue
            strict = f.name in ("path_scale", "access_tolerance", "safe_force")
            _real(f"{path}.{f.name}", getattr(self, f.name), low=0.0, strict_low=strict)
        _choice(f"{path}.goal", self.goal, GOAL_REWARDS)


@dataclass(frozen=True)
class TerminationConfig(_Section):
    """Episode ends besides success and the time limit (which registration sets)."""

    SECTION: ClassVar[str] = "termination"

    workspace_margin: float = 0.015  # m, the tip must stay within the tissue's box grown by this margin
    end_on_tear: bool = True  # terminate when the tissue tears (a strand's row at coupling.tear_force)
    # terminate once the task cannot succeed: a stitch entered or exited farther than reward.access_tolerance from
    # the plan, in tasks that need every stitch on it (NeedleInsert, SutureThrow); never in the goal-conditioned ids
    end_on_miss: bool = True

    def validate(self, path: str) -> None:
        _real(f"{path}.workspace_margin", self.workspace_margin, low=0.0, strict_low=True)
        for name in ("end_on_tear", "end_on_miss"):
            if not isinstance(getattr(self, name), bool):
                _fail(f"{path}.{name}", f"must be true or false, got {getattr(self, name)!r}")


def _point(path: str, value: tuple[float, ...], *, optional: bool) -> None:
    """A point or vector: three finite numbers (or, when ``optional``, none: the empty tuple)."""
    if optional and not value:
        return
    if len(value) != 3:
        _fail(path, f"must be {'empty or ' if optional else ''}a list of 3 numbers (x, y, z), got {list(value)}")
    for k, v in enumerate(value):
        _real(f"{path}[{k}]", v)


@dataclass(frozen=True)
class CameraConfig(_Section):
    """The camera of the pixel observations (``observation.mode`` rgb, depth, rgbd): a pinhole camera
    (:class:`~suture_gym.render.Camera`) fixed in the world for the whole episode, square pixels, rendered straight
    at ``width x height`` (no supersampling).

    Pose: it looks at ``look_at`` (default: the centre of the box spanned by the tissue at rest and the needle's
    start) from ``eye``, or, when ``eye`` is empty, from ``look_at + distance * direction / |direction|``, where
    ``distance = 0`` picks the nearest distance at which that whole box is in view
    (:func:`~suture_gym.render.frame_box`). ``up`` fixes the roll. Depth is the distance along the optical axis;
    only ``near <= depth <= far`` is drawn, and a pixel that sees nothing has depth ``far``, which must lie beyond
    the scene's box (checked when the env is built; the default fits every shipped scene, the hand's reaching
    0.48 m).
    """

    SECTION: ClassVar[str] = "observation.camera"

    width: int = 84  # px
    height: int = 84  # px
    fov_y: float = 35.0  # degrees, vertical field of view, in (0, 180)
    look_at: tuple[float, ...] = ()  # m, world point at the image centre (empty: the scene box's centre)
    eye: tuple[float, ...] = ()  # m, world position of the camera (empty: from direction and distance)
    direction: tuple[float, float, float] = (1.0, -0.35, 0.9)  # from look_at towards the eye, any length
    distance: float = 0.0  # m, eye to look_at (0: the nearest that frames the scene box); needs an empty eye
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)  # world direction shown upwards in the image
    near: float = 0.001  # m, nearest depth drawn
    far: float = 1.0  # m, farthest depth drawn (beyond the scene's box), and the depth of the background

    def validate(self, path: str) -> None:
        _count(f"{path}.width", self.width, 1)
        _count(f"{path}.height", self.height, 1)
        _real(f"{path}.fov_y", self.fov_y, low=0.0, high=180.0, strict_low=True, strict_high=True)
        _point(f"{path}.look_at", self.look_at, optional=True)
        _point(f"{path}.eye", self.eye, optional=True)
        _point(f"{path}.direction", self.direction, optional=False)
        _point(f"{path}.up", self.up, optional=False)
        _real(f"{path}.distance", self.distance, low=0.0)
        _real(f"{path}.near", self.near, low=0.0, strict_low=True)
        _real(f"{path}.far", self.far, low=self.near, strict_low=True)
        if not any(self.up):
            _fail(f"{path}.up", f"must be a non-zero vector, got {list(self.up)}")
        if self.eye:
            if self.distance:
                _fail(f"{path}.distance", f"= {self.distance} m is unused when {path}.eye is given; leave it 0")
            if self.look_at and tuple(self.eye) == tuple(self.look_at):
                _fail(f"{path}.eye", f"= {list(self.eye)} m must differ from {path}.look_at")
        else:
            if not any(self.direction):
                _fail(f"{path}.direction", f"must be a non-zero vector, got {list(self.direction)}")
            cross = math.dist((0.0, 0.0, 0.0), (
                self.direction[1] * self.up[2] - self.direction[2] * self.up[1],
                self.direction[2] * self.up[0] - self.direction[0] * self.up[2],
                self.direction[0] * self.up[1] - self.direction[1] * self.up[0]))
            if cross <= 1e-9 * math.hypot(*self.direction) * math.hypot(*self.up):
                _fail(f"{path}.up", f"= {list(self.up)} is parallel to {path}.direction = {list(self.direction)}")
            if self.distance and not self.near < self.distance < self.far:
                _fail(f"{path}.distance", f"= {self.distance} m must lie between near = {self.near} m and far = "
                      f"{self.far} m, or the point looked at is not drawn")


@dataclass(frozen=True)
class PointCloudConfig(_Section):
    """Points of the ``point_cloud`` observation, per entity (:mod:`suture_gym.envs.sensors`): a fixed count on
    the tissue's surface, the needle's centreline and the thread's centreline (the last only in scenes with a
    thread, ``suture.node_count > 0``)."""

    SECTION: ClassVar[str] = "observation.point_cloud"

    tissue: int = 448  # points on the tissue's surface triangles that can move
    needle: int = 32  # points evenly spaced along the needle's centreline, tip to swage
    suture: int = 32  # points along the thread's centreline, swage to tail (scenes with a thread)

    def validate(self, path: str) -> None:
        _count(f"{path}.tissue", self.tissue, 1)
        _count(f"{path}.needle", self.needle, 0)
        _count(f"{path}.suture", self.suture, 0)


@dataclass(frozen=True)
class ObservationConfig(_Section):
    """What the observation holds, and its units (see :mod:`suture_gym.envs.spaces`).

    ``mode``: ``state`` is the flat vector (a ``Box``); ``rgb``, ``depth``, ``rgbd`` and ``point_cloud`` give a
    ``Dict`` observation with the keys ``rgb`` ``(H, W, 3) uint8``, ``depth`` ``(H, W, 1) float32`` m (``rgbd``:
    both), or ``point_cloud`` ``(N, 3) float32`` m in the world frame, plus ``state`` (the vector) unless
    ``include_state`` is false (:mod:`suture_gym.envs.sensors`).
    """

    SECTION: ClassVar[str] = "observation"

    suture_samples: int = 0  # thread nodes sampled evenly from the swage to the tail (0: none)
    privileged: bool = False  # append the randomised parameters
    scaled: bool = True  # each entry divided by its field's scale and clipped to its bound; false: raw SI values
    mode: str = "state"  # one of OBSERVATION_MODES
    include_state: bool = True  # the pixel and point-cloud modes also hold the vector, key "state"
    camera: CameraConfig = field(default_factory=CameraConfig)  # the rgb, depth and rgbd modes
    point_cloud: PointCloudConfig = field(default_factory=PointCloudConfig)  # the point_cloud mode

    def validate(self, path: str) -> None:
        _count(f"{path}.suture_samples", self.suture_samples, 0)
        for name in ("privileged", "scaled", "include_state"):
            if not isinstance(getattr(self, name), bool):
                _fail(f"{path}.{name}", f"must be true or false, got {getattr(self, name)!r}")
        _choice(f"{path}.mode", self.mode, OBSERVATION_MODES)
        if self.mode == "state" and not self.include_state:
            _fail(f"{path}.include_state", f"= false needs a pixel or point-cloud {path}.mode, got 'state'")


@dataclass(frozen=True)
class RenderConfig(_Section):
    """``render_mode="rgb_array"`` image size and supersampling; ``render_mode="human"`` live view's server and
    frame rate (:class:`suture_gym.render.live.LiveView`)."""

    SECTION: ClassVar[str] = "render"

    width: int = 320  # px (even, for video encoding)
    height: int = 240  # px (even)
    ssaa: int = 2  # supersampling factor
    viewer_host: str = "127.0.0.1"  # interface the live view serves on ("0.0.0.0": every interface)
    viewer_port: int = 8080  # TCP port (0: any free port; a taken one makes viser try the next)
    viewer_fps: float = 30.0  # most frames pushed to the browser per wall-clock second

    def validate(self, path: str) -> None:
        _count(f"{path}.width", self.width, 2)
        _count(f"{path}.height", self.height, 2)
        _count(f"{path}.ssaa", self.ssaa, 1)
        if not isinstance(self.viewer_host, str) or not self.viewer_host:
            _fail(f"{path}.viewer_host", f"must be a host name or address, got {self.viewer_host!r}")
        _count(f"{path}.viewer_port", self.viewer_port, 0)
        if self.viewer_port > 65535:
            _fail(f"{path}.viewer_port", f"must be a TCP port <= 65535, got {self.viewer_port!r}")
        _real(f"{path}.viewer_fps", self.viewer_fps, low=0.0, strict_low=True)


@dataclass(frozen=True)
class EnvConfig:
    """Everything an environment needs; see each section's class for its fields and units."""

    task: str = "needle_insert"
    tissue: TissueConfig = field(default_factory=TissueConfig)
    scene: SceneConfig = field(default_factory=SceneConfig)
    needle: NeedleConfig = field(default_factory=NeedleConfig)
    suture: SutureConfig = field(default_factory=SutureConfig)
    coupling: CouplingConfig = field(default_factory=CouplingConfig)
    solver: SolverConfig = field(default_factory=SolverConfig)
    action: ActionConfig = field(default_factory=ActionConfig)
    plan: PlanConfig = field(default_factory=PlanConfig)
    randomization: RandomizationConfig = field(default_factory=RandomizationConfig)
    reward: RewardConfig = field(default_factory=RewardConfig)
    termination: TerminationConfig = field(default_factory=TerminationConfig)
    observation: ObservationConfig = field(default_factory=ObservationConfig)
    render: RenderConfig = field(default_factory=RenderConfig)
    #: The task's own section (an instance of its class's ``PARAMS``; None: its defaults, or none).
    task_params: Any = None

    def __post_init__(self) -> None:
        cls = task_class(self.task)
        if cls.PARAMS is None:
            if self.task_params is not None:
                _fail("task_params", f"must be empty: task {self.task!r} has no parameters of its own")
        elif self.task_params is None:
            object.__setattr__(self, "task_params", cls.PARAMS())
        elif type(self.task_params) is not cls.PARAMS:
            _fail("task_params", f"must be a {cls.PARAMS.__name__}, got {type(self.task_params).__name__}")
        for f in fields(self):
            section = getattr(self, f.name)
            if f.name not in ("task", "task_params") and type(section) is not _field_types(EnvConfig)[f.name]:
                _fail(f.name, f"must be a {_field_types(EnvConfig)[f.name].__name__}, got {type(section).__name__}")
        scene = self.scene
        implicit = self.solver.tissue_integrator != "xpbd"
        check_tet_budget(scene.tets, f"scene.cell_size = {scene.cell_size:g} m over scene.size = {list(scene.size)} m",
                         scene.max_tets, "scene.max_tets", BYTES_PER_TET_IMPLICIT if implicit else BYTES_PER_TET_XPBD)
        noise, margin = self.randomization.needle_position_noise, self.termination.workspace_margin
        if noise >= margin:
            _fail("randomization.needle_position_noise", f"= {noise} m must be below termination.workspace_margin = "
                  f"{margin} m, or the needle can start outside the workspace")
        cls.check_config(self)


def default_config(task: str) -> EnvConfig:
    """The defaults of the registered ``task``: the typed defaults overridden by the task class's ``CONFIG``
    (what the registered ids use)."""
    return apply_overrides(EnvConfig(), {"task": task, **task_class(task).CONFIG})


@functools.cache
def _field_types(cls) -> dict[str, Any]:
    """Resolved types of the dataclass fields of ``cls`` (class variables excluded)."""
    hints = typing.get_type_hints(cls)
    return {f.name: hints[f.name] for f in fields(cls)}


def _coerce(path: str, value: Any, kind: Any, current: Any) -> Any:
    """``value`` converted to the field type ``kind`` (nested dataclasses merge into ``current``)."""
    if is_dataclass(kind):
        if not isinstance(value, dict):
            _fail(path, f"must be a mapping of {kind.__name__} fields, got {type(value).__name__}")
        return _merge(path + ".", current, value)
    origin = typing.get_origin(kind)
    if origin in (typing.Union, types.UnionType):
        return _coerce_union(path, value, typing.get_args(kind))
    if origin is tuple:
        args = typing.get_args(kind)
        if len(args) == 2 and args[1] is Ellipsis:  # tuple[X, ...]: any length
            if not isinstance(value, (list, tuple)):
                _fail(path, f"must be a list, got {value!r}")
            return tuple(_coerce(f"{path}[{k}]", v, args[0], None) for k, v in enumerate(value))
        if not isinstance(value, (list, tuple)) or len(value) != len(args):
            _fail(path, f"must be a list of {len(args)} numbers, got {value!r}")
        return tuple(_coerce(f"{path}[{k}]", v, a, None) for k, (v, a) in enumerate(zip(value, args, strict=True)))
    if kind is float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            _fail(path, f"must be a number, got {value!r}")
        return float(value)
    if kind is int:
        if isinstance(value, bool) or not isinstance(value, int):
            _fail(path, f"must be an integer, got {value!r}")
        return value
    if kind is bool:
        if not isinstance(value, bool):
            _fail(path, f"must be true or false, got {value!r}")
        return value
    if kind is str:
        if not isinstance(value, str):
            _fail(path, f"must be a string, got {value!r}")
        return value
    raise TypeError(f"{path}: unsupported config field type {kind!r}")


def _coerce_union(path: str, value: Any, kinds: tuple) -> Any:
    """``value`` as the first of ``kinds`` it converts to (ValueError naming ``path`` if none)."""
    for kind in kinds:
        try:
            return _coerce(path, value, kind, None)
        except ValueError:
            continue
    _fail(path, f"must be one of {[getattr(k, '__name__', str(k)) for k in kinds]}, got {value!r}")


def _named(prefix: str, cls: type, error: ValueError, changed) -> ValueError:
    """``error`` raised by a section's own checks (a simulator dataclass's), renamed after its dotted key:
    ``<prefix><field>: <message>`` with the field the message names, the ``changed`` ones first."""
    message = str(error)
    if not prefix or message.startswith(prefix) or message.startswith("unknown config key"):
        return error
    candidates = [*changed, *(f.name for f in fields(cls) if f.name not in changed)]
    named = [name for name in candidates if re.search(rf"\b{name}\b", message)]
    key = prefix + named[0] if named else prefix.rstrip(".")
    return ValueError(f"{key}: {message}")


def _merge(prefix: str, base: Any, overrides: dict) -> Any:
    """A copy of dataclass ``base`` with ``overrides`` applied; unknown keys raise ValueError naming them."""
    types = _field_types(type(base))
    unknown = sorted(str(k) for k in overrides if k not in types)
    if unknown:
        names = ", ".join(f"'{prefix}{k}'" for k in unknown)
        raise ValueError(f"unknown config key(s) {names}; known keys here: {sorted(types)}")
    changes = {key: _coerce(prefix + key, value, types[key], getattr(base, key))
               for key, value in overrides.items() if key != "task_params"}
    if isinstance(base, EnvConfig):
        changes["task_params"] = _task_params(base, changes.get("task", base.task), overrides)
    try:
        return replace(base, **changes)
    except ValueError as error:
        raise _named(prefix, type(base), error, list(overrides)) from None


def _task_params(base: EnvConfig, task: str, overrides: dict) -> Any:
    """The ``task_params`` section of ``task`` after ``overrides``: the task class's ``PARAMS`` (kept from
    ``base`` when the task does not change) with ``overrides["task_params"]`` merged in."""
    params_cls = task_class(task).PARAMS
    value = overrides.get("task_params")
    if params_cls is None:
        if value:
            _fail("task_params", f"must be empty: task {task!r} has no parameters of its own")
        return None
    current = base.task_params if task == base.task and base.task_params is not None else params_cls()
    if value is None:
        return current
    if not isinstance(value, dict):
        _fail("task_params", f"must be a mapping of {params_cls.__name__} fields, got {type(value).__name__}")
    try:
        return _merge("task_params.", current, value)
    except ValueError as error:
        raise ValueError(f"task_params ({task}): {error}") from None


def apply_overrides(config: EnvConfig, overrides: dict) -> EnvConfig:
    """``config`` with the nested mapping ``overrides`` applied (validated; unknown keys raise ValueError)."""
    if not isinstance(overrides, dict):
        raise ValueError(f"config overrides must be a mapping, got {type(overrides).__name__}")
    return _merge("", config, overrides)


def read_yaml(path: str | os.PathLike) -> dict:
    """The mapping stored in the YAML file ``path`` (an empty file is an empty mapping)."""
    import yaml

    with open(path, encoding="utf-8") as stream:
        data = yaml.safe_load(stream)
    if data is None:
        return {}
    if not isinstance(data, dict):
        raise ValueError(f"{path} must hold a mapping of config sections, got {type(data).__name__}")
    return data


def load_config(task: str, source: EnvConfig | dict | str | os.PathLike | None = None) -> EnvConfig:
    """The config of ``task``: its defaults, overridden by ``source``.

    Args:
        task: a registered task (:func:`~suture_gym.envs.registry.registered_tasks`).
        source: None (defaults), an :class:`EnvConfig` (used as is; its ``task`` must match), a nested mapping,
            the path of a YAML file holding one, or the name of a shipped one (:mod:`suture_gym.configs`). A ``task``
            key, if present, must name ``task``.

    Raises:
        ValueError: unknown keys (named by dotted path), wrong types, out-of-range values, or a task mismatch.
    """
    if isinstance(source, EnvConfig):
        config = source
    else:
        overrides = {}
        if isinstance(source, (str, os.PathLike)):
            overrides = read_yaml(env_config_path(source))
        elif isinstance(source, dict):
            overrides = source
        elif source is not None:
            kind = type(source).__name__
            raise ValueError(f"config must be None, an EnvConfig, a mapping or a YAML path, got {kind}")
        config = apply_overrides(default_config(task), overrides)
    if config.task != task:
        raise ValueError(f"config task is {config.task!r} but the environment is {task!r}")
    return config


def config_to_dict(config: Any) -> dict:
    """The config as plain nested dicts, lists and scalars (JSON/YAML-serialisable)."""

    def plain(value):
        if is_dataclass(value):
            return {f.name: plain(getattr(value, f.name)) for f in fields(value)}
        if isinstance(value, tuple):
            return [plain(v) for v in value]
        return value

    return plain(config)


def save_config(config: EnvConfig, path: str | os.PathLike) -> None:
    """Write the resolved ``config`` to ``path`` as YAML (load it back with :func:`load_config`)."""
    import yaml

    with open(path, "w", encoding="utf-8") as stream:
        yaml.safe_dump(config_to_dict(config), stream, sort_keys=False)


__all__ = [
    "ACTION_MODES",
    "OBSERVATION_MODES",
    "ActionConfig",
    "CameraConfig",
    "CouplingConfig",
    "EnvConfig",
    "IncisionConfig",
    "NeedleConfig",
    "ObservationConfig",
    "PlanConfig",
    "PointCloudConfig",
    "RandomizationConfig",
    "RenderConfig",
    "RewardConfig",
    "SceneConfig",
    "SolverConfig",
    "SutureConfig",
    "TerminationConfig",
    "TissueConfig",
    "apply_overrides",
    "config_to_dict",
    "default_config",
    "load_config",
    "read_yaml",
    "save_config",
    "sim_fields",
]
