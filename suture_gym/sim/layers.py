"""Layered tissue: per-tet material regions by depth below the surface (skin over fat over muscle).

:meth:`~suture_gym.sim.model.TissueModel.from_mesh` takes a list of materials and a ``(T,)`` index into it per tet,
and both tissue integrators (XPBD and implicit) use the per-tet moduli; this module computes that index from
geometry. Regions from a mesh file's cell tags come from :func:`~suture_gym.sim.mesh_io.read_tet_regions`.
"""

from __future__ import annotations

import math

import numpy as np
from scipy.spatial import cKDTree

from suture_gym.sim.mesh import surface_triangles


def depth_below_surface(vertices: np.ndarray, tets: np.ndarray, up=(0.0, 0.0, 1.0),
                        max_angle: float = math.pi / 3) -> np.ndarray:
    """Depth of every tet's centroid below the mesh's upper surface.

    The upper surface is the boundary triangles whose outward normal lies within ``max_angle`` of ``up``; the
    depth is the distance from the centroid to the plane of the upper triangle with the nearest centroid, so it
    follows a curved surface (a slab bent over a cylinder) rather than a fixed height.

    Args:
        vertices: ``(N, 3)`` positions, m.
        tets: ``(T, 4)`` vertex indices of positively oriented tets.
        up: ``(3,)`` direction out of the upper surface (any length).
        max_angle: rad, in ``(0, pi/2]``.

    Returns:
        ``(T,) float64`` depths, m (>= 0 for a tet below its surface).
    """
    up = np.asarray(up, dtype=np.float64)
    if up.shape != (3,) or not np.all(np.isfinite(up)) or not np.linalg.norm(up) > 0:
        raise ValueError(f"up must be a finite non-zero (3,) direction, got {np.asarray(up).tolist()}")
    if not (0.0 < max_angle <= 0.5 * math.pi):
        raise ValueError(f"max_angle must lie in (0, pi/2] rad, got {max_angle!r}")
    vertices = np.asarray(vertices, dtype=np.float64)
    triangles = surface_triangles(tets)
    x = vertices[triangles]
    normal = np.cross(x[:, 1] - x[:, 0], x[:, 2] - x[:, 0])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    upper = normal @ (up / np.linalg.norm(up)) >= math.cos(max_angle)
    if not upper.any():
        raise ValueError(f"no boundary triangle faces up = {up.tolist()} within {math.degrees(max_angle):.0f} deg")
    centre = vertices[np.asarray(tets)].mean(axis=1)
    _, nearest = cKDTree(x[upper].mean(axis=1)).query(centre)
    return np.einsum("ij,ij->i", x[upper][nearest, 0] - centre, normal[upper][nearest])


def layer_index(depth: np.ndarray, thicknesses) -> np.ndarray:
    """Layer of each depth: 0 for ``depth < thicknesses[0]``, 1 for the next ``thicknesses[1]``, ...; everything
    below the listed layers (and any negative depth) goes to the neighbouring layer.

    Args:
        depth: ``(T,)`` depths below the surface, m (:func:`depth_below_surface`).
        thicknesses: ``(L - 1,)`` thicknesses of every layer but the deepest, m, each > 0.

    Returns:
        ``(T,) int64`` in ``0 .. L - 1``, the ``tet_material`` of
        :meth:`~suture_gym.sim.model.TissueModel.from_mesh` for a list of ``L`` materials, top first.
    """
    thicknesses = np.atleast_1d(np.asarray(thicknesses, dtype=np.float64))
    if thicknesses.ndim != 1 or not np.all(np.isfinite(thicknesses)) or not np.all(thicknesses > 0):
        raise ValueError(f"layer thicknesses must be positive lengths in metres, got {thicknesses.tolist()}")
    return np.searchsorted(np.cumsum(thicknesses), np.asarray(depth, dtype=np.float64), side="right").astype(np.int64)


def layered(scene, materials, thicknesses, up=(0.0, 0.0, 1.0)):
    """The tissue ``scene`` (a :class:`~suture_gym.sim.scenes.Scene` without strands) with its tets given
    ``materials`` (top first) by depth below its upper surface (:func:`depth_below_surface`, :func:`layer_index`);
    the same mesh, pinned particles, base supports, regions and state. Its settings add ``tet_layers`` (tets
    per layer) and the materials.

    Args:
        materials: ``L`` :class:`~suture_gym.sim.model.TissueMaterial`, top first.
        thicknesses: ``(L - 1,)`` m, every layer's but the deepest.
    """
    from suture_gym.sim.mesh import TetMesh
    from suture_gym.sim.model import Model, State, TissueModel, TissueState
    from suture_gym.sim.scenes import Scene, _material_settings

    tissue = scene.model.tissue
    if scene.model.needle is not None or tissue.roller_particle.size:
        raise ValueError("layered takes a tissue scene without strands or roller supports")
    if len(materials) != len(np.atleast_1d(thicknesses)) + 1:
        raise ValueError(f"layered needs one material per layer: {len(np.atleast_1d(thicknesses)) + 1}, got "
                         f"{len(materials)}")
    mesh = TetMesh(tissue.particle_rest_q, tissue.tet_indices)
    layer = layer_index(depth_below_surface(mesh.vertices, mesh.tets, up), thicknesses)
    rebuilt = TissueModel.from_mesh(mesh, list(materials), pinned=tissue.particle_inv_mass == 0.0, tet_material=layer,
                                    supports=(tissue.support_normal, tissue.support_offset))
    model = Model(tissue=rebuilt, gravity=scene.model.gravity)
    state = State(tissue=TissueState.at_rest(rebuilt))
    state.tissue.assign(scene.state.tissue)
    settings = {**scene.settings, "material": _material_settings(list(materials)),
                "layer_thickness_m": np.atleast_1d(thicknesses).tolist(),
                "tet_layers": np.bincount(layer, minlength=len(materials)).tolist()}
    return Scene(model=model, state=state, regions=scene.regions, settings=settings)
