"""Scene builders: tissue geometry, material and supports, returned as a :class:`Scene`.

Every builder documents its geometry in metres in a right-handed frame with gravity along ``-z`` (unless
overridden) and returns the model, a state at rest, named particle regions and the parameters used.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass, field

import numpy as np

from suture_gym.sim.coupling import CouplingModel, CouplingParams
from suture_gym.sim.mesh import TetMesh, box_tet_grid
from suture_gym.sim.model import Model, State, TissueMaterial, TissueModel, TissueState
from suture_gym.sim.needle import NeedleModel, NeedleShape, NeedleState
from suture_gym.sim.quat import quat_from_two_vectors, quat_to_matrix
from suture_gym.sim.rod import RodModel, RodState, StaticObstacles, SutureParams
from suture_gym.sim.solver import Solver

STANDARD_GRAVITY = 9.81  # m/s^2
#: The seed paper's tissue (1 kPa, nearly incompressible): the default material of the builders below.
PAPER_TISSUE = TissueMaterial(youngs_modulus=1.0e3, poisson_ratio=0.49)
#: The seed paper's integrator: XPBD tissue, one sweep per small substep, 50 m/s before a state counts as diverged.
PAPER_SOLVER = Solver(tissue_integrator="xpbd", iterations=1, max_speed=50.0)
#: The strand-tissue interaction for the paper's 1 kPa tissue: 15 mN to puncture and 0.5 N/m of axial friction
#: (1 N would indent this tissue by centimetres before piercing it), 4 N to tear, and the point tip of the paper
#: (no tip patch, cutting or exit force): the default of :func:`two_bar_suturing`.
PAPER_COUPLING = CouplingParams(puncture_force=0.015, needle_axial_friction=0.5, tear_force=4.0,
                                exit_puncture_force=0.0, cutting_force=0.0, tip_contact_radius=0.0)


@dataclass
class Scene:
    """A built scene.

    Attributes:
        model: the static :class:`~suture_gym.sim.model.Model`.
        state: the initial :class:`~suture_gym.sim.model.State`: at rest, in the rest configuration unless
            the builder says otherwise.
        regions: named ``(k,) int32`` particle index arrays (documented per builder).
        settings: every parameter the builder used, JSON-serialisable.
    """

    model: Model
    state: State
    regions: dict[str, np.ndarray] = field(default_factory=dict)
    settings: dict = field(default_factory=dict)


def _material_settings(material: TissueMaterial | list[TissueMaterial]) -> dict | list[dict]:
    if isinstance(material, (list, tuple)):
        return [_material_settings(m) for m in material]
    return {
        "youngs_modulus_pa": material.youngs_modulus,
        "poisson_ratio": material.poisson_ratio,
        "density_kg_m3": material.density,
        "damping_per_s": material.damping,
    }


def _scene(
    mesh: TetMesh,
    material: TissueMaterial,
    pinned: np.ndarray,
    gravity,
    regions: dict[str, np.ndarray],
    settings: dict,
    rollers=None,
    supports=None,
    tet_material: np.ndarray | None = None,
) -> Scene:
    """Model, rest state, regions (boolean masks turned into index arrays) and settings of a scene; ``material``
    may be a list indexed by ``tet_material`` (T,) (layered tissue)."""
    tissue = TissueModel.from_mesh(mesh, material, pinned=pinned, tet_material=tet_material, rollers=rollers,
                                   supports=supports)
    model = Model(tissue=tissue, gravity=gravity)
    state = State(tissue=TissueState.at_rest(tissue))
    settings = {
        **settings,
        "material": _material_settings(material),
        "gravity_m_s2": model.gravity.tolist(),
        "tets": tissue.tet_count,
        "particles": tissue.particle_count,
    }
    indices = {name: np.flatnonzero(mask).astype(np.int32) for name, mask in regions.items()}
    return Scene(model=model, state=state, regions=indices, settings=settings)


#: The rigid base ``z >= 0`` a pad or the bars rest on (``TissueModel.from_mesh`` ``supports``): a contact, not
#: only the pinned bottom nodes, so a push cannot drive tissue through it.
_BASE = (np.array([[0.0, 0.0, 1.0]]), np.array([0.0]))


def _check_positive(name: str, value: float) -> float:
    value = float(value)
    if not (np.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite length in metres, got {value!r}")
    return value


def hanging_bar(
    length: float = 0.1,
    width: float = 0.01,
    cells: tuple[int, int, int] = (2, 2, 20),
    material: TissueMaterial | None = None,
    scheme: str = "five",
    gravity: float = STANDARD_GRAVITY,
) -> Scene:
    """A square bar hanging under gravity from its clamped top face.

    Geometry: ``x, y in [0, width]``, ``z in [-length, 0]``; the ``z = 0`` face is pinned; gravity
    ``(0, 0, -gravity)``. Analytic elongation for small strain: ``rho g L^2 / (2 E)``.

    Regions: ``top`` (pinned face), ``bottom`` (free end face ``z = -length``).
    """
    length, width = _check_positive("length", length), _check_positive("width", width)
    material = material or PAPER_TISSUE
    mesh = box_tet_grid((width, width, length), cells, origin=(0.0, 0.0, -length), scheme=scheme)
    z = mesh.vertices[:, 2]
    tol = 1e-9 * length
    top = np.abs(z) <= tol
    bottom = np.abs(z + length) <= tol
    settings = {
        "scene": "hanging_bar",
        "length_m": length,
        "width_m": width,
        "cells": [int(c) for c in cells],
        "scheme": scheme,
    }
    return _scene(mesh, material, top, (0.0, 0.0, -gravity), {"top": top, "bottom": bottom}, settings)


def cantilever(
    length: float = 0.1,
    thickness: float = 0.01,
    width: float = 0.01,
    cells: tuple[int, int, int] = (20, 2, 2),
    material: TissueMaterial | None = None,
    scheme: str = "five",
    gravity: float = STANDARD_GRAVITY,
) -> Scene:
    """A horizontal beam clamped at one end, bending under its own weight.

    Geometry: ``x in [0, length]`` (beam axis), ``y in [0, width]``, ``z in [0, thickness]``; the ``x = 0``
    face is pinned; gravity ``(0, 0, -gravity)``. Euler-Bernoulli tip deflection ``q L^4 / (8 E I)`` with
    ``q = rho g width thickness`` and ``I = width thickness^3 / 12``.

    Regions: ``clamped`` (pinned face), ``tip`` (free end face ``x = length``).
    """
    length = _check_positive("length", length)
    thickness, width = _check_positive("thickness", thickness), _check_positive("width", width)
    material = material or PAPER_TISSUE
    mesh = box_tet_grid((length, width, thickness), cells, scheme=scheme)
    x = mesh.vertices[:, 0]
    tol = 1e-9 * length
    clamped = np.abs(x) <= tol
    tip = np.abs(x - length) <= tol
    settings = {
        "scene": "cantilever",
        "length_m": length,
        "thickness_m": thickness,
        "width_m": width,
        "cells": [int(c) for c in cells],
        "scheme": scheme,
    }
    return _scene(mesh, material, clamped, (0.0, 0.0, -gravity), {"clamped": clamped, "tip": tip}, settings)


def compression_block(
    size: float = 0.02,
    cells: int = 4,
    stretch: float = 0.8,
    material: TissueMaterial | None = None,
    scheme: str = "five",
) -> Scene:
    """A cube squeezed between two frictionless plates, without gravity.

    Geometry: the rest cube is ``[0, size]^3``. Its bottom face slides on the plane ``z = 0`` and its top
    face on ``z = stretch * size`` (roller supports); the faces ``x = 0`` and ``y = 0`` slide on their
    planes too (symmetry planes that remove rigid motion without constraining the uniaxial state). The
    initial state is the rest shape scaled by ``stretch`` along ``z`` (no lateral expansion yet), at rest.

    Regions: ``bottom``, ``top`` (plate faces), ``side_x`` (the free face ``x = size``).
    """
    size = _check_positive("size", size)
    if not (np.isfinite(stretch) and 0.0 < stretch <= 1.0):
        raise ValueError(f"stretch must lie in (0, 1], got {stretch!r}")
    material = material or PAPER_TISSUE
    mesh = box_tet_grid((size, size, size), (cells, cells, cells), scheme=scheme)
    v = mesh.vertices
    tol = 1e-9 * size
    bottom = np.abs(v[:, 2]) <= tol
    top = np.abs(v[:, 2] - size) <= tol
    supports = [  # (face, plane normal, plane offset in m)
        (bottom, (0.0, 0.0, 1.0), 0.0),  # bottom plate
        (top, (0.0, 0.0, 1.0), stretch * size),  # top plate
        (np.abs(v[:, 0]) <= tol, (1.0, 0.0, 0.0), 0.0),  # symmetry plane x = 0
        (np.abs(v[:, 1]) <= tol, (0.0, 1.0, 0.0), 0.0),  # symmetry plane y = 0
    ]
    particle = np.concatenate([np.flatnonzero(face) for face, _, _ in supports])
    normal = np.concatenate([np.tile(n, (int(face.sum()), 1)) for face, n, _ in supports])
    offset = np.concatenate([np.full(int(face.sum()), d) for face, _, d in supports])
    settings = {"scene": "compression_block", "size_m": size, "cells": int(cells), "stretch": stretch, "scheme": scheme}
    scene = _scene(
        mesh,
        material,
        np.zeros(len(v), dtype=bool),
        (0.0, 0.0, 0.0),
        {"bottom": bottom, "top": top, "side_x": np.abs(v[:, 0] - size) <= tol},
        settings,
        rollers=(particle, normal, offset),
    )
    scene.state.tissue.particle_q[:, 2] *= stretch
    scene.state.tissue.particle_q_prev[...] = scene.state.tissue.particle_q
    return scene


def two_bar_wound(
    bar_size: tuple[float, float, float] = (0.095, 0.03, 0.03),
    cells: tuple[int, int, int] = (19, 6, 6),
    gap: float = 0.004,
    material: TissueMaterial | None = None,
    scheme: str = "five",
    base: bool = True,
    gravity: float = STANDARD_GRAVITY,
) -> Scene:
    """Two soft bars side by side with a wound gap between their long faces (paper Fig. 5).

    Geometry: bar ``length x width x height = bar_size`` along ``x``. The left bar occupies
    ``y in [0, width]``, the right bar ``y in [width + gap, 2 width + gap]``; both span ``x in [0, length]``
    and ``z in [0, height]``. The wound is the gap between the faces ``y = width`` and ``y = width + gap``.
    Both end faces (``x = 0`` and ``x = length``) of each bar are pinned, as in the paper; with ``base`` the
    bottom faces (``z = 0``) are pinned too and the base ``z >= 0`` is a contact (no free particle is pushed
    through it), i.e. the tissue rests on a rigid base (docs/design.md, "Departures
    from the brief": the default 1 kPa tissue would otherwise sag by about its own height).

    Regions: ``left_wound_face``, ``right_wound_face`` (the facing long faces), ``left_bar``, ``right_bar``
    (all particles of each bar), ``top`` (the ``z = height`` faces), ``pinned``.
    """
    if len(bar_size) != 3:
        raise ValueError(f"bar_size must be (length, width, height) in metres, got {bar_size!r}")
    length = _check_positive("bar length", bar_size[0])
    width = _check_positive("bar width", bar_size[1])
    height = _check_positive("bar height", bar_size[2])
    gap = _check_positive("gap", gap)
    material = material or PAPER_TISSUE
    left = box_tet_grid((length, width, height), cells, scheme=scheme)
    right = box_tet_grid((length, width, height), cells, origin=(0.0, width + gap, 0.0), scheme=scheme)
    vertices = np.concatenate([left.vertices, right.vertices])
    tets = np.concatenate([left.tets, right.tets + left.vertex_count])
    mesh = TetMesh(vertices=vertices, tets=tets)
    v = mesh.vertices
    tol = 1e-9 * max(bar_size)
    is_left = np.arange(len(v)) < left.vertex_count
    ends = (np.abs(v[:, 0]) <= tol) | (np.abs(v[:, 0] - length) <= tol)
    pinned = ends | ((np.abs(v[:, 2]) <= tol) if base else np.zeros(len(v), dtype=bool))
    regions = {
        "left_wound_face": is_left & (np.abs(v[:, 1] - width) <= tol),
        "right_wound_face": ~is_left & (np.abs(v[:, 1] - width - gap) <= tol),
        "left_bar": is_left,
        "right_bar": ~is_left,
        "top": np.abs(v[:, 2] - height) <= tol,
        "pinned": pinned,
    }
    settings = {
        "scene": "two_bar_wound",
        "bar_size_m": [length, width, height],
        "cells": [int(c) for c in cells],
        "gap_m": gap,
        "scheme": scheme,
        "base": base,
    }
    supports = _BASE if base else None
    return _scene(mesh, material, pinned, (0.0, 0.0, -gravity), regions, settings, supports=supports)


def paper_cube(
    material: TissueMaterial | None = None,
    gap: float = 0.004,
    base: bool = True,
    gravity: float = STANDARD_GRAVITY,
) -> Scene:
    """The paper's Table 1 row 1 scale: :func:`two_bar_wound` with two 19 x 6 x 6-cell bars (five-tet scheme).

    Two bars of 9.5 x 3 x 3 cm with 5 mm cells: 6840 tets and 1960 particles (paper: about 6.8k tets and 2k
    vertices). See :func:`two_bar_wound` for geometry and regions.
    """
    scene = two_bar_wound(
        bar_size=(0.095, 0.03, 0.03),
        cells=(19, 6, 6),
        gap=gap,
        material=material,
        scheme="five",
        base=base,
        gravity=gravity,
    )
    scene.settings["scene"] = "paper_cube"
    return scene


#: Silicone-like suturing practice pad: 30 times stiffer than the paper's 1 kPa tissue, nearly incompressible.
PAD_MATERIAL = TissueMaterial(youngs_modulus=3.0e4, poisson_ratio=0.45)


def suturing_pad(
    size: tuple[float, float, float] = (0.03, 0.03, 0.01),
    cells: tuple[int, int, int] = (6, 6, 2),
    material: TissueMaterial | None = None,
    scheme: str = "five",
    gravity: float = STANDARD_GRAVITY,
) -> Scene:
    """A block of tissue glued to a rigid base: a suturing practice pad.

    Geometry: ``x in [0, size_x]``, ``y in [0, size_y]``, ``z in [0, size_z]``; the bottom face ``z = 0`` is
    pinned and the base ``z >= 0`` is a contact no free particle is pushed through; gravity
    ``(0, 0, -gravity)``. Default material :data:`PAD_MATERIAL` (30 kPa, nu = 0.45) in 5 mm cells: it needs
    substeps of 0.5 ms to stay at rest and 0.25 ms under a needle pushed into it with several newtons (see the
    stability notes of :mod:`suture_gym.sim.solver`).

    Regions: ``top`` (the ``z = size_z`` face), ``pinned`` (the bottom face).
    """
    if len(size) != 3:
        raise ValueError(f"size must be (x, y, z) in metres, got {size!r}")
    sx, sy, sz = (_check_positive(f"size[{k}]", v) for k, v in enumerate(size))
    material = material or PAD_MATERIAL
    mesh = box_tet_grid((sx, sy, sz), cells, scheme=scheme)
    z = mesh.vertices[:, 2]
    tol = 1e-9 * max(sx, sy, sz)
    pinned = np.abs(z) <= tol
    settings = {"scene": "suturing_pad", "size_m": [sx, sy, sz], "cells": [int(c) for c in cells], "scheme": scheme}
    regions = {"top": np.abs(z - sz) <= tol, "pinned": pinned}
    return _scene(mesh, material, pinned, (0.0, 0.0, -gravity), regions, settings, supports=_BASE)


def _quat_from_matrix(r: np.ndarray) -> np.ndarray:
    """Unit quaternion (w, x, y, z) of the rotation matrix ``r`` (3, 3), with ``w >= 0``."""
    m = np.asarray(r, dtype=np.float64)
    trace = m[0, 0] + m[1, 1] + m[2, 2]
    if trace > 0.0:
        s = 2.0 * math.sqrt(1.0 + trace)
        q = np.array([0.25 * s, (m[2, 1] - m[1, 2]) / s, (m[0, 2] - m[2, 0]) / s, (m[1, 0] - m[0, 1]) / s])
    else:
        i = int(np.argmax([m[0, 0], m[1, 1], m[2, 2]]))
        j, k = (i + 1) % 3, (i + 2) % 3
        s = 2.0 * math.sqrt(1.0 + m[i, i] - m[j, j] - m[k, k])
        q = np.zeros(4)
        q[0] = (m[k, j] - m[j, k]) / s
        q[1 + i] = 0.25 * s
        q[1 + j] = (m[j, i] + m[i, j]) / s
        q[1 + k] = (m[k, i] + m[i, k]) / s
    q /= np.linalg.norm(q)
    return q if q[0] >= 0.0 else -q


def needle_circle_pose(
    needle: NeedleModel, center, axis, u, tip_angle: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pose ``(body_pos (3,) m, body_quat (4,))`` of ``needle`` lying on the circle of its own radius centred at
    ``center`` (3,) m in the plane of unit normal ``axis`` (3,), with its tip at angle ``tip_angle`` (rad) and
    its body trailing behind the tip: the one needle-on-circle poser of the package.

    Angles are measured from the unit in-plane direction ``u`` (3,) toward ``v = axis x u``; the tip advances
    counter-clockwise about ``axis`` (the :class:`~suture_gym.tasks.PlannedArc` convention). The needle's shape
    frame (circle in its x-y plane, normal +z, tip at polar angle ``tau``) maps to the circle: shape x ->
    ``cos(a) u + sin(a) v``, shape y -> ``sin(a) u - cos(a) v``, shape z -> ``-axis``, with
    ``a = tip_angle + tau``, so shape angle ``theta`` lands at angle ``a - theta``.
    """
    axis = np.asarray(axis, dtype=np.float64)
    u = np.asarray(u, dtype=np.float64)
    v = np.cross(axis, u)
    a = tip_angle + needle.shape.tip_angle
    e1 = math.cos(a) * u + math.sin(a) * v
    e2 = math.sin(a) * u - math.cos(a) * v
    quat = _quat_from_matrix(np.stack([e1, e2, -axis], axis=1))
    return np.asarray(center, dtype=np.float64) - quat_to_matrix(quat) @ needle.arc_center_body, quat


#: The circle of a needle across the wound of :func:`two_bar_wound` (for :func:`needle_circle_pose`): its plane
#: is the y-z plane, normal +x, angles measured from +y toward +z; turning the tip angle up drives the needle
#: tip first from bar A's side (-y) across the wound towards +y.
WOUND_ARC_AXIS = (1.0, 0.0, 0.0)
WOUND_ARC_U = (0.0, 1.0, 0.0)


def wound_tip_angle(needle: NeedleModel, angle: float = 0.0) -> float:
    """Tip angle (rad) on the wound circle (:data:`WOUND_ARC_AXIS`, :data:`WOUND_ARC_U`) of ``needle`` turned
    by ``angle`` rad from its rest pose across the wound: ``pi + angle - tau`` (``tau`` the shape's tip angle),
    so that at ``angle = 0`` the needle's shape x axis points along -y, its crown up (shape y -> +z, shape
    z -> -x) and, for the default needle (``tau = 0``), its tip is on bar A's side pointing down."""
    return math.pi + angle - needle.shape.tip_angle


def assemble(
    scene: Scene,
    needle: NeedleModel,
    needle_state: NeedleState,
    suture: RodModel | None = None,
    suture_state: RodState | None = None,
    coupling_params: CouplingParams | None = None,
    knot_tail: float = 0.0,
) -> Scene:
    """The tissue ``scene`` with a needle, an optional suture and their coupling with the tissue: the one scene
    assembler, used by :func:`add_strands` and the environments alike.

    The tissue's rigid supports (the base a pad or the bars rest on) are planes the suture cannot cross either
    (``Model.obstacles``, with :class:`~suture_gym.sim.rod.StaticObstacles`' Coulomb friction): without them
    the slack of a thread crossing a wound falls through the gap below the bars and hooks on their bottom
    edges.

    Args:
        scene: a tissue scene (its tissue state is copied as the initial tissue state; no tissue: no coupling).
        needle: the needle model; ``needle_state`` its state at rest.
        suture: the suture model, or None; ``suture_state`` its state (required with a suture).
        coupling_params: :class:`~suture_gym.sim.coupling.CouplingParams` (default parameters if None).
        knot_tail: m; a stopper knot this far from the suture's free end (0: none;
            :meth:`~suture_gym.sim.coupling.CouplingModel.build`).

    Returns:
        A new :class:`Scene` with the same regions and a copy of the settings.
    """
    tissue = scene.model.tissue
    coupling = obstacles = None
    if tissue is not None:
        coupling = CouplingModel.build(tissue, needle, suture, coupling_params or CouplingParams(), knot_tail=knot_tail)
        if suture is not None and tissue.support_offset.size:
            obstacles = StaticObstacles(plane_point=tissue.support_normal * tissue.support_offset[:, None],
                                        plane_normal=tissue.support_normal)
    model = Model(tissue=tissue, needle=needle, suture=suture, coupling=coupling, gravity=scene.model.gravity,
                  obstacles=obstacles)
    state = State.initial(model, needle=needle_state, suture=suture_state)
    if tissue is not None:
        state.tissue.assign(scene.state.tissue)
    return Scene(model=model, state=state, regions=scene.regions, settings=dict(scene.settings))


def add_strands(
    scene: Scene,
    needle_pose: tuple,
    *,
    needle_shape: NeedleShape | None = None,
    gravity_compensation: bool = True,
    suture_params: SutureParams | None = None,
    suture_direction=(0.0, -1.0, 0.0),
    suture_tail_pinned: bool = False,
    suture_knot_tail: float = 0.0,
    coupling_params: CouplingParams | None = None,
) -> Scene:
    """The tissue ``scene`` with a needle, an optional suture on its swage and their coupling with the tissue
    (:func:`assemble`).

    Args:
        scene: a tissue scene (its tissue state is copied as the initial tissue state).
        needle_pose: ``(body_pos (3,) m, body_quat (4,))`` of the needle at rest (see :func:`needle_circle_pose`).
        needle_shape: :class:`~suture_gym.sim.needle.NeedleShape` (default: 26 mm half circle, 30 nodes).
        gravity_compensation: the haptic device carries the needle's weight.
        suture_params: :class:`~suture_gym.sim.rod.SutureParams`, or None for a needle alone.
        suture_direction: (3,) the suture lies straight from the swage along this direction at rest.
        suture_tail_pinned: hold the suture's free end where it starts (an assistant's forceps).
        suture_knot_tail: m; a stopper knot this far from the suture's free end, which no hole lets through
            (0: none; :meth:`~suture_gym.sim.coupling.CouplingModel.build`).
        coupling_params: :class:`~suture_gym.sim.coupling.CouplingParams` (default parameters if None).

    Returns:
        A new :class:`Scene` (the same regions) whose settings add ``needle``, ``suture`` and ``coupling``.
    """
    needle = NeedleModel.from_shape(needle_shape, gravity_compensation=gravity_compensation)
    needle_state = NeedleState.at_rest(*needle_pose)
    suture = suture_state = None
    if suture_params is not None:
        suture = RodModel.from_params(suture_params)
        if suture_tail_pinned:
            suture = suture.with_pins([suture.node_count - 1])
        swage = needle_state.body_pos + quat_to_matrix(needle_state.body_quat) @ needle.swage_pos_body
        suture_state = RodState.straight(suture, swage, suture_direction)
    built = assemble(scene, needle, needle_state, suture, suture_state, coupling_params, suture_knot_tail)
    coupling = built.model.coupling
    built.settings.update({
        "needle": {**asdict(needle.shape), "gravity_compensation": gravity_compensation},
        "needle_pose": {"body_pos_m": needle_state.body_pos.tolist(), "body_quat": needle_state.body_quat.tolist()},
        "suture": None
        if suture_params is None
        else {
            "length_m": suture_params.length,
            "node_count": suture_params.node_count,
            "radius_m": suture_params.radius,
            "youngs_modulus_pa": suture_params.material.youngs_modulus,
            "inextensible": suture_params.inextensible,
            "direction": [float(v) for v in suture_direction],
            "tail_pinned": suture_tail_pinned,
            "knot_tail_m": suture_knot_tail,
        },
        "coupling": None if coupling is None else asdict(coupling.params),
    })
    return built


def tent_rod(model: RodModel, start: np.ndarray, end: np.ndarray, direction: np.ndarray) -> RodState:
    """A rod at rest from ``start`` (3,) to ``end`` (3,) m along two straight legs meeting at an apex beyond their
    midpoint along ``direction`` (3,), placed so the legs' total length is the rod's rest length (a tent); nodes
    at their rest arc lengths, segment frames along the legs."""
    length = float(model.seg_rest_length.sum())
    distance = float(np.linalg.norm(end - start))
    if not distance < length:
        raise ValueError(f"the thread ({length} m) is too short to reach its end point {distance:.4g} m away")
    mid = 0.5 * (start + end)
    d = direction / np.linalg.norm(direction)

    def legs(k: float) -> float:
        apex = mid + k * d
        return float(np.linalg.norm(apex - start) + np.linalg.norm(end - apex))

    lo, hi = 0.0, length
    for _ in range(100):  # bisection: the legs' length grows monotonically with k
        k = 0.5 * (lo + hi)
        lo, hi = (k, hi) if legs(k) < length else (lo, k)
    apex = mid + hi * d
    leg = float(np.linalg.norm(apex - start))
    s = np.concatenate([[0.0], np.cumsum(model.seg_rest_length)])
    first = s <= leg
    pos = np.empty((len(s), 3))
    pos[first] = start + s[first, None] / leg * (apex - start)
    rest = (s[~first] - leg) / max(length - leg, 1e-300)
    pos[~first] = apex + np.minimum(rest, 1.0)[:, None] * (end - apex)
    state = RodState.straight(model, start, end - start)
    state.node_pos[:] = pos
    state.node_pos_prev[:] = pos
    z = np.array([0.0, 0.0, 1.0])
    for j, e in enumerate(np.diff(pos, axis=0)):
        state.seg_quat[j] = quat_from_two_vectors(z, e / np.linalg.norm(e))
    return state


def two_bar_suturing(
    bar_size: tuple[float, float, float] = (0.03, 0.015, 0.015),
    cells: tuple[int, int, int] = (6, 3, 3),
    gap: float = 0.004,
    material: TissueMaterial | None = None,
    centre_height: float = 0.002,
    angle: float = 0.0,
    suture_params: SutureParams | None = None,
    suture_direction=(0.0, -1.0, 0.15),
    suture_tail_pinned: bool = True,
    suture_knot_tail: float = 0.0,
    coupling_params: CouplingParams | None = None,
) -> Scene:
    """:func:`two_bar_wound` (on its rigid base) ready to be sutured across the wound.

    The default needle (26 mm half circle, radius 8.3 mm) hangs over the middle of the wound in the plane
    ``x = length / 2`` with its circle centred ``centre_height`` above the top faces, over the middle of the
    gap, turned by ``angle`` (0: tip on bar A's side, 2 mm above it, pointing down; see
    :func:`wound_tip_angle`). Turning it about +x through about 2 pi takes the needle through bar A, across
    the gap, through bar B and out. The suture (default 8 cm, 81 nodes) starts straight from the swage along
    ``suture_direction`` with its tail held (``suture_tail_pinned``) and/or a stopper knot ``suture_knot_tail``
    m from its free end (:func:`add_strands`).

    Defaults for the 1 kPa paper tissue (:data:`PAPER_COUPLING`): ``puncture_force = 0.015 N`` and
    ``needle_axial_friction = 0.5 N/m`` (see :class:`CouplingParams`; at 0.05 N
    the second bite dents bar B's wound face by about 6 mm while the needle turns, the axial load stays
    below 0.02 N and the tip slides off). The threshold counts the axial load on the tip, see
    :func:`~suture_gym.sim.coupling.coupling_finish`.
    Settings add the needle's circle (``arc_center_m``, ``arc_axis``, ``arc_u`` and the start ``tip_angle_rad``
    for :func:`needle_circle_pose`), ``stitch_x_m`` and ``centre_height_m``.
    """
    base = two_bar_wound(bar_size=bar_size, cells=cells, gap=gap, material=material)
    length, width, height = (float(v) for v in bar_size)
    center = np.array([0.5 * length, width + 0.5 * gap, height + centre_height])
    needle = NeedleModel.from_shape()
    tip_angle = wound_tip_angle(needle, angle)
    scene = add_strands(
        base,
        needle_circle_pose(needle, center, WOUND_ARC_AXIS, WOUND_ARC_U, tip_angle),
        suture_params=suture_params or SutureParams(length=0.08, node_count=81),
        suture_direction=suture_direction,
        suture_tail_pinned=suture_tail_pinned,
        suture_knot_tail=suture_knot_tail,
        coupling_params=coupling_params or PAPER_COUPLING,
    )
    scene.settings["scene"] = "two_bar_suturing"
    scene.settings["arc_center_m"] = center.tolist()
    scene.settings["arc_axis"] = list(WOUND_ARC_AXIS)
    scene.settings["arc_u"] = list(WOUND_ARC_U)
    scene.settings["tip_angle_rad"] = tip_angle
    scene.settings["stitch_x_m"] = 0.5 * length
    scene.settings["centre_height_m"] = centre_height
    return scene


def wound_gap(
    scene: Scene, state: State | None = None, x_range: float | None = None, depth: float | None = None
) -> float:
    """Mean gap (m) between the facing wound faces of a :func:`two_bar_wound` scene: mean ``y`` of the right
    face's particles minus that of the left face's, over particles within ``x_range`` of the middle of the
    wound (all if None) and within ``depth`` of the top (all if None), in ``state`` (default the scene's)."""
    state = scene.state if state is None else state
    rest = scene.model.tissue.particle_rest_q
    q = state.tissue.particle_q
    length = float(rest[:, 0].max())
    top = float(rest[:, 2].max())
    means = []
    for name in ("left_wound_face", "right_wound_face"):
        idx = scene.regions[name]
        keep = np.ones(idx.size, dtype=bool)
        if x_range is not None:
            keep &= np.abs(rest[idx, 0] - 0.5 * length) <= x_range + 1e-12
        if depth is not None:
            keep &= rest[idx, 2] >= top - depth - 1e-12
        if not keep.any():
            raise ValueError(f"no {name} particle within x_range={x_range} m and depth={depth} m")
        means.append(float(q[idx[keep], 1].mean()))
    return means[1] - means[0]
