"""The tissue of an environment's scene, built from a plain description (:class:`TissueSpec`).

Five kinds, all SI, gravity along -z, resting on a rigid base at ``z = 0``:

* ``pad``: a box of five-tet cells (:func:`~suture_gym.sim.scenes.suturing_pad`);
* ``wound``: two bars with a wound gap between them (:func:`~suture_gym.sim.scenes.two_bar_wound`);
* ``abdominal_wall``, ``hand``: the anatomical scenes with an incision (:mod:`suture_gym.sim.anatomy`);
* ``mesh``: a user's tet mesh or closed surface (tetrahedralised) with an incision along a polyline
  (:mod:`suture_gym.sim.incision`).

Optionally layered in depth (:func:`~suture_gym.sim.layers.layered`) and with contact between the wound's faces
(:func:`~suture_gym.sim.incision.with_wound_contact`). The env layer maps its config onto a :class:`TissueSpec`;
this module knows nothing of configs, tasks or envs.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np

from suture_gym.sim.anatomy import abdominal_wall, hand, resting_incised
from suture_gym.sim.incision import Incision, with_wound_contact
from suture_gym.sim.layers import layered
from suture_gym.sim.mesh import check_tet_budget
from suture_gym.sim.mesh_io import SURFACE_FORMATS, read_tet_mesh, tetrahedralize_surface
from suture_gym.sim.model import TissueMaterial
from suture_gym.sim.scenes import STANDARD_GRAVITY, Scene, suturing_pad, two_bar_wound


@dataclass(frozen=True)
class TissueSpec:
    """What tissue to build.

    Attributes:
        kind: ``pad``, ``wound``, ``abdominal_wall``, ``hand`` or ``mesh``.
        material: the tissue's material (the top layer's stiffness is ``layer_stiffness[0]`` times its modulus).
        size: ``(x, y, z)`` m of the pad, of each bar or of the wall's slab.
        cells: hexahedral cells along ``(x, y, z)`` (pad, wound, abdominal wall).
        cell_size: target cell edge, m (hand and mesh scenes; half of it is the resting mesh's settle offset).
        gap: the wound gap or the incision's opening, m (not the pad).
        layer_thickness: m, every layer's but the deepest, top first (empty: one layer).
        layer_stiffness: factors on ``material``'s modulus, one per layer (empty: one layer).
        wound_contact: the wound's faces cannot pass through each other.
        path: the mesh file of a ``mesh`` scene (a tet mesh, or a closed surface of
            :data:`~suture_gym.sim.mesh_io.SURFACE_FORMATS`).
        max_tets: most tets a ``mesh`` scene may have.
        incision_points: ``((x, y, z), ...)`` m, the incision's polyline on a ``mesh`` scene's surface.
        incision_depth: m; 0 for the anatomical scene's own depth.
    """

    kind: str
    material: TissueMaterial
    size: tuple[float, float, float]
    cells: tuple[int, int, int]
    cell_size: float
    gap: float
    layer_thickness: tuple[float, ...] = ()
    layer_stiffness: tuple[float, ...] = ()
    wound_contact: bool = False
    path: str = ""
    max_tets: int = 100_000
    incision_points: tuple[tuple[float, float, float], ...] = ()
    incision_depth: float = 0.0


def build_tissue(spec: TissueSpec) -> tuple[Scene, np.ndarray, np.ndarray]:
    """``(tissue Scene, left face (k,), right face (k,))``: the tissue of ``spec``; the faces are the wound
    faces' free particle indices in the upper half of the tissue, or of the incision's faces (the gap a surgeon
    sees; the bottom rows sit on the rigid base, an incision's faces meet at its bottom). Empty for a pad."""
    empty = np.zeros(0, dtype=np.int64)
    if spec.kind == "pad":
        built = suturing_pad(spec.size, spec.cells, spec.material, "five", STANDARD_GRAVITY)
    elif spec.kind == "wound":
        built = two_bar_wound(bar_size=spec.size, cells=spec.cells, gap=spec.gap, material=spec.material,
                              scheme="five", base=True, gravity=STANDARD_GRAVITY)
    else:
        built = _anatomy(spec)
    if spec.layer_stiffness:
        materials = [replace(spec.material, youngs_modulus=k * spec.material.youngs_modulus)
                     for k in spec.layer_stiffness]
        built = layered(built, materials, spec.layer_thickness)
    if spec.kind == "pad":
        return built, empty, empty
    if spec.wound_contact:
        built = with_wound_contact(built)
    tissue = built.model.tissue
    left = built.regions["left_wound_face"]
    right = built.regions["right_wound_face"]
    z = tissue.particle_rest_q[:, 2]
    if spec.kind == "wound":
        middle = 0.5 * spec.size[2]
    else:
        faces = np.concatenate([left, right])
        middle = 0.5 * (z[faces].min() + z[faces].max())
    upper = (tissue.particle_inv_mass > 0.0) & (z >= middle)
    return built, left[upper[left]], right[upper[right]]


def _anatomy(spec: TissueSpec) -> Scene:
    """The tissue of an ``abdominal_wall``, ``hand`` or ``mesh`` scene (one material; layered by the caller)."""
    depth = {"incision_depth": spec.incision_depth} if spec.incision_depth else {}
    if spec.kind == "abdominal_wall":
        return abdominal_wall(layers=(("tissue", math.inf, spec.material),), size=spec.size, cells=spec.cells,
                              gap=spec.gap, gravity=STANDARD_GRAVITY, **depth)
    if spec.kind == "hand":
        return hand(spec.material, edge_length=spec.cell_size, gap=spec.gap, gravity=STANDARD_GRAVITY, **depth)
    if spec.kind != "mesh":
        raise ValueError(f"kind must be pad, wound, abdominal_wall, hand or mesh, got {spec.kind!r}")
    path = spec.path
    if path.lower().endswith(SURFACE_FORMATS):
        mesh = tetrahedralize_surface(path, spec.cell_size, max_tets=spec.max_tets)
    else:
        mesh = read_tet_mesh(path)
        check_tet_budget(mesh.tet_count, f"scene.path = {path!r}", spec.max_tets, "scene.max_tets")
    incision = Incision(spec.incision_points, depth=spec.incision_depth, gap=spec.gap)
    return resting_incised(mesh, incision, spec.material, 0.5 * spec.cell_size, STANDARD_GRAVITY)
