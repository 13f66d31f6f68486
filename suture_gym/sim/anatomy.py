"""The seed paper's anatomical scenes, built in code: a layered abdominal wall and a hand, each with an incision.

Both return a :class:`~suture_gym.sim.scenes.Scene` whose wound regions are named as
:func:`~suture_gym.sim.scenes.two_bar_wound`'s (``left_wound_face``, ``right_wound_face``), with the incision
along ``+x`` and its faces apart along ``y`` (left at the lower ``y``), so that code reading a wound (the
wound gap along ``y``, :func:`~suture_gym.sim.scenes.wound_gap`) reads these too.

Paper (Yu et al. 2020, Table 1): abdominal wall 4,333 tets and 1,261 vertices (TetWild), hand 8,656 tets and
2,357 vertices (TetGen); both are homogeneous 1 kPa there. Here the wall is layered by default (skin over fat
over muscle) and the hand is one material.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np

from suture_gym.sim.incision import Incision, incise
from suture_gym.sim.layers import depth_below_surface, layer_index
from suture_gym.sim.mesh import TetMesh, box_tet_grid, surface_triangles
from suture_gym.sim.model import TissueMaterial
from suture_gym.sim.scenes import STANDARD_GRAVITY, Scene, _scene

#: Scene kinds with an incision instead of two bars (this module's abdominal wall and hand, a user's mesh): their
#: stitches are planned on the built tissue (:func:`~suture_gym.tasks.geometry.plan_across_incision`).
ANATOMY_KINDS: tuple[str, ...] = ("abdominal_wall", "hand", "mesh")

#: Abdominal wall layers, top first: ``(name, thickness m, material)``; the last layer fills the rest. Skin is
#: the suture pad's 300 kPa (the environments' default; skin is reported from tens of kPa to about 1 MPa),
#: subcutaneous fat much softer, muscle in between: plausible contrasts, not measured values. With a needle they do
#: not work yet (one puncture threshold dents the fat by centimetres, and a softer fat under the skin tears the
#: scripted stitch; docs/design.md, section 4): the environments' wall gives skin and fat the same modulus.
ABDOMINAL_LAYERS: tuple[tuple[str, float, TissueMaterial], ...] = (
    ("skin", 0.003, TissueMaterial(youngs_modulus=3.0e5, poisson_ratio=0.45)),
    ("fat", 0.010, TissueMaterial(youngs_modulus=1.0e4, poisson_ratio=0.45)),
    ("muscle", math.inf, TissueMaterial(youngs_modulus=5.0e4, poisson_ratio=0.45)),
)


def curved_slab(size=(0.12, 0.08, 0.02), cells=(14, 10, 6), radius: float = 0.15) -> tuple[TetMesh, np.ndarray]:
    """A slab bent over a cylinder along ``x``: the abdominal wall's shape.

    The box ``x in [0, size_x]``, ``y in [-size_y/2, size_y/2]``, ``z in [0, size_z]`` (five-tet cells) is
    wrapped around the axis ``y = 0, z = size_z - radius`` so that its top becomes the cylinder of ``radius``
    (m) with its crest along ``y = 0, z = size_z``; the bottom is the concentric cylinder ``size_z`` below.
    The map preserves orientation (its Jacobian determinant is ``r / radius > 0``).

    Returns:
        ``(mesh, box_vertices (N, 3))``: the mesh and every vertex's position in the unbent box (for selecting
        faces of the box).
    """
    size = np.asarray(size, dtype=np.float64)
    if not (np.isfinite(radius) and radius > size[2]):
        raise ValueError(f"radius must exceed the slab's thickness {size[2]} m, got {radius!r}")
    box = box_tet_grid(size, cells, origin=(0.0, -0.5 * size[1], 0.0))
    x, y, z = box.vertices.T
    r = radius - size[2] + z
    theta = y / radius
    bent = np.stack([x, r * np.sin(theta), r * np.cos(theta) - (radius - size[2])], axis=1)
    return TetMesh(bent, box.tets), box.vertices


def abdominal_wall(
    layers: tuple[tuple[str, float, TissueMaterial], ...] = ABDOMINAL_LAYERS,
    size: tuple[float, float, float] = (0.12, 0.08, 0.02),
    cells: tuple[int, int, int] = (14, 10, 6),
    radius: float = 0.15,
    incision_length: float | None = None,
    incision_depth: float | None = None,
    gap: float = 0.002,
    gravity: float = STANDARD_GRAVITY,
) -> Scene:
    """A layered, curved abdominal-wall patch with an incision along its crest (paper Fig. 6).

    Geometry: :func:`curved_slab` of ``size`` (m) in ``cells``; by default 14 x 10 x 6 cells, 4,200 tets and
    1,155 vertices before the cut (paper: 4,333 and 1,261). The incision runs along ``+x`` on the crest
    (``y = 0``, ``z = size_z``) over ``incision_length`` centred on the patch (default two thirds of its length),
    ``incision_depth`` deep (default two thirds of its thickness: through skin and fat of the default layers),
    its mouth open by ``gap`` (:mod:`~suture_gym.sim.incision`). Tets take the
    material of their ``layers`` by depth below the outer surface. The patch's edges (its four side faces) and
    its inner surface are pinned: the rest of the body holds it.

    Regions: ``left_wound_face``, ``right_wound_face``, ``crack_front`` (the wound's bottom and ends),
    ``top`` (the outer surface), ``pinned``. Settings add the layers, the incision and ``tet_layers`` (tets
    per layer).
    """
    if len(layers) < 1 or not math.isinf(layers[-1][1]):
        raise ValueError("layers must end with a layer of thickness inf (it fills the rest)")
    mesh, box = curved_slab(size, cells, radius)
    layer = layer_index(depth_below_surface(mesh.vertices, mesh.tets), [t for _, t, _ in layers[:-1]])
    incision_length = 2.0 / 3.0 * size[0] if incision_length is None else incision_length
    incision_depth = 2.0 / 3.0 * size[2] if incision_depth is None else incision_depth
    start = 0.5 * (size[0] - incision_length)
    crest = (0.0, size[2])
    incision = Incision([[start, *crest], [start + incision_length, *crest]], depth=incision_depth, gap=gap)
    cut = incise(mesh, incision)
    source = box[cut.source_vertex]
    tol = 1e-9 * max(size)
    pinned = ((source[:, 0] <= tol) | (source[:, 0] >= size[0] - tol) | (np.abs(source[:, 1]) >= 0.5 * size[1] - tol)
              | (source[:, 2] <= tol))
    n = cut.mesh.vertex_count
    regions = {
        "left_wound_face": _mask(n, cut.left_face),
        "right_wound_face": _mask(n, cut.right_face),
        "crack_front": _mask(n, cut.crack_front),
        "top": source[:, 2] >= size[2] - tol,
        "pinned": pinned,
    }
    settings = {
        "scene": "abdominal_wall",
        "size_m": [float(s) for s in size],
        "cells": [int(c) for c in cells],
        "radius_m": float(radius),
        "layers": [{"name": name, "thickness_m": thickness} for name, thickness, _ in layers],
        "tet_layers": np.bincount(layer, minlength=len(layers)).tolist(),
        "incision": {"points_m": cut.points.tolist(), "depth_m": incision_depth, "gap_m": gap},
    }
    return _scene(cut.mesh, [m for _, _, m in layers], pinned, (0.0, 0.0, -gravity), regions, settings,
                  tet_material=layer)


def _mask(n: int, indices: np.ndarray) -> np.ndarray:
    mask = np.zeros(n, dtype=bool)
    mask[indices] = True
    return mask


def _capsule(p: np.ndarray, a, b, radius: float) -> np.ndarray:
    """Signed distance (m) of points ``p (M, 3)`` to the capsule of ``radius`` around the segment ``a``-``b``."""
    a, b = np.asarray(a, dtype=np.float64), np.asarray(b, dtype=np.float64)
    t = np.clip((p - a) @ (b - a) / ((b - a) @ (b - a)), 0.0, 1.0)
    return np.linalg.norm(p - a - t[:, None] * (b - a), axis=1) - radius


def _rounded_box(p: np.ndarray, centre, half, rounding: float) -> np.ndarray:
    """Signed distance (m) to the box of half extents ``half`` with edges rounded by ``rounding``."""
    q = np.abs(p - np.asarray(centre)) - (np.asarray(half) - rounding)
    return np.linalg.norm(np.maximum(q, 0.0), axis=1) + np.minimum(q.max(axis=1), 0.0) - rounding


def _smooth_union(a: np.ndarray, b: np.ndarray, k: float) -> np.ndarray:
    """Polynomial smooth minimum of two distances, blending over ``k`` m (a fillet between the shapes)."""
    h = np.clip(0.5 + 0.5 * (b - a) / k, 0.0, 1.0)
    return b + (a - b) * h - k * h * (1.0 - h)


#: Volume of :func:`hand_surface`, m^3 (303 ml at 4 mm, 299 ml at 6 mm spacing): the env config's tet estimate.
HAND_VOLUME = 3.0e-4


def hand_distance(p: np.ndarray) -> np.ndarray:
    """Signed distance (m, negative inside) of points ``p (M, 3)`` to an adult hand lying palm down, built from
    smooth primitives: a rounded-box palm 9 x 8.4 x 2.4 cm centred at the origin, a wrist stump toward ``-x``,
    four fingers along ``+x`` (capsules of radius 7.8-8.5 mm, 6.5-8 cm long, at least 4 mm apart) and a thumb
    angled toward ``+y``, blended with 1 cm fillets (5 mm at the fingers, whose webs would otherwise close).
    Palm, wrist, fingers and thumb all rest flat on the table ``z = -0.012`` (the shape is cut there); the back
    of the hand faces ``+z``; the hand spans about 20 x 15 x 2.4 cm."""
    p = np.asarray(p, dtype=np.float64)
    d = _rounded_box(p, (0.0, 0.0, 0.0), (0.045, 0.042, 0.012), 0.01)
    d = _smooth_union(d, _rounded_box(p, (-0.06, 0.0, 0.0), (0.02, 0.032, 0.012), 0.01), 0.01)
    for y, length, radius in ((-0.0315, 0.065, 0.0078), (-0.0105, 0.08, 0.0085), (0.0105, 0.078, 0.0085),
                              (0.0315, 0.07, 0.0082)):
        z = radius - 0.012  # resting on the table with the palm
        d = _smooth_union(d, _capsule(p, (0.035, y, z), (0.035 + length, y, z), radius), 0.005)
    d = _smooth_union(d, _capsule(p, (-0.015, 0.035, -0.0015), (0.03, 0.075, -0.0015), 0.0105), 0.01)
    return np.maximum(d, -0.012 - p[:, 2])  # flat on the table: the fillets may not bulge below it


#: ``(lower, upper)`` corners of a box around :func:`hand_distance`'s hand, m.
HAND_BOUNDS = (np.array([-0.09, -0.06, -0.025]), np.array([0.13, 0.095, 0.025]))


class _Implicit:
    """A shape given by a signed distance (m, negative inside), with what the voxel backend asks of a surface:
    ``bounds`` and ``contains``."""

    def __init__(self, distance, bounds) -> None:
        self.distance = distance
        self.bounds = bounds

    def contains(self, points: np.ndarray) -> np.ndarray:
        return self.distance(points) < 0.0


def hand_surface(spacing: float = 0.004):
    """The zero level set of :func:`hand_distance` as a closed triangle surface (``trimesh.Trimesh``, m).

    Marching tetrahedra on a five-tet grid of ``spacing`` (m): every tet whose corners' signed distances change
    sign contributes one triangle or two, through the points where the distance interpolates to zero on its
    edges (shared by the tets around an edge, so the surface is welded and closed; tets have no ambiguous
    cases, unlike marching cubes). No marching-cubes package is needed.
    """
    import trimesh

    lo, hi = HAND_BOUNDS
    cells = np.ceil((hi - lo) / spacing).astype(int)
    grid = box_tet_grid(tuple(cells * spacing), tuple(int(c) for c in cells), origin=tuple(lo))
    value = hand_distance(grid.vertices)
    # Keep the surface off the grid's corners, so that no triangle collapses to a point.
    near = np.abs(value) < 1e-3 * spacing
    value[near] = np.where(value[near] < 0.0, -1e-3, 1e-3) * spacing
    return trimesh.Trimesh(*_marching_tets(grid.vertices, grid.tets.astype(np.int64), value), process=False)


def _marching_tets(vertices: np.ndarray, tets: np.ndarray, value: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(points (P, 3), triangles (F, 3))`` of the zero level set of ``value (N,)`` over the tets, oriented
    with normals toward positive values (outward of a signed distance)."""
    inside = value[tets] < 0.0
    count = inside.sum(axis=1)
    triangles, outward = [], []
    # One corner on its own (1 inside, or 3 inside and 1 outside): a triangle across its three edges.
    for alone_inside in (True, False):
        sel = np.flatnonzero(count == (1 if alone_inside else 3))
        lone = np.argmax(inside[sel] == alone_inside, axis=1)
        others = (lone[:, None] + np.arange(1, 4)[None]) % 4
        a = tets[sel, lone]
        rest = np.take_along_axis(tets[sel], others, axis=1)  # (S, 3)
        triangles.append(np.stack([np.sort(np.stack([a, rest[:, k]], axis=1), axis=1) for k in range(3)], axis=1))
        direction = vertices[rest].mean(axis=1) - vertices[a]
        outward.append(direction if alone_inside else -direction)
    # Two inside (i, j), two outside (k, l): the quad ik, il, jl, jk as two triangles.
    sel = np.flatnonzero(count == 2)
    order = np.argsort(~inside[sel], axis=1, kind="stable")  # inside corners first
    i, j, k, m = np.take_along_axis(tets[sel], order, axis=1).T
    edge = {name: np.sort(np.stack(pair, axis=1), axis=1) for name, pair in
            (("ik", (i, k)), ("im", (i, m)), ("jm", (j, m)), ("jk", (j, k)))}
    direction = 0.5 * (vertices[k] + vertices[m] - vertices[i] - vertices[j])
    for a, b, c in (("ik", "im", "jm"), ("ik", "jm", "jk")):
        triangles.append(np.stack([edge[a], edge[b], edge[c]], axis=1))
        outward.append(direction)
    corner_edges = np.concatenate(triangles)  # (F, 3 corners, 2 grid vertices)
    keys, index = np.unique(corner_edges.reshape(-1, 2), axis=0, return_inverse=True)
    va, vb = value[keys[:, 0]], value[keys[:, 1]]
    t = va / (va - vb)
    points = vertices[keys[:, 0]] + t[:, None] * (vertices[keys[:, 1]] - vertices[keys[:, 0]])
    faces = index.reshape(-1, 3)
    mid = 0.5 * vertices[corner_edges].sum(axis=2)  # edge midpoints: a triangle that never degenerates
    flip = np.einsum("ij,ij->i", np.cross(mid[:, 1] - mid[:, 0], mid[:, 2] - mid[:, 0]), np.concatenate(outward)) < 0
    faces[flip] = faces[flip][:, ::-1]
    return points, faces


def hand(
    material: TissueMaterial | None = None,
    edge_length: float = 0.0058,
    incision_x: tuple[float, float] = (-0.02, 0.025),
    incision_depth: float = 0.01,
    gap: float = 0.0015,
    gravity: float = STANDARD_GRAVITY,
) -> Scene:
    """The hand of :func:`hand_distance` filled by the built-in voxel backend, a wound on its back (paper Fig. 7).

    Geometry: the cells of an ``edge_length`` (m) grid whose centres lie inside the hand (the voxel backend,
    :func:`~suture_gym.sim.mesh_io.voxel_fill`, asking the signed distance rather than a triangulated surface:
    exact and deterministic); the default 5.8 mm gives 8,555 tets (paper: 8,656). The incision runs along
    ``+x`` over the back of the palm, on the voxel grid's plane nearest ``y = 0`` (so its faces are flat), from
    ``incision_x[0]`` to ``incision_x[1]`` (m), following the surface, ``incision_depth`` deep (two cells), its
    mouth open by ``gap``. The hand lies flat on a table (:func:`resting_incised`; the nodes within one and a
    half edges of the table and of the wrist's cut end are pinned: the lowest cells of the fingers, whose round
    undersides leave them a cell above the palm's, included. Fingers left free as cantilevers flew off within
    0.1 s on the implicit integrator with one inner iteration per sweep, the environments' default; with four
    they sag by the 6 mm of beam theory).

    Regions: ``left_wound_face``, ``right_wound_face``, ``crack_front``, ``pinned``.
    """
    material = material or TissueMaterial(youngs_modulus=3.0e5, poisson_ratio=0.45)
    mesh = _hand_mesh(float(edge_length))
    lattice = np.unique(np.round(mesh.vertices[:, 1], 12))
    y = float(lattice[np.argmin(np.abs(lattice))])  # the grid plane nearest y = 0: flat wound faces
    x = np.linspace(incision_x[0], incision_x[1], 6)
    points = np.stack([x, np.full_like(x, y), surface_height(mesh, x, y)], axis=1)
    scene = resting_incised(mesh, Incision(points, depth=incision_depth, gap=gap), material, 1.5 * edge_length,
                            gravity, pin_low_x=True)
    scene.settings.update({"scene": "hand", "edge_length_m": edge_length, "backend": "voxel"})
    return scene


@lru_cache(maxsize=4)
def _hand_mesh(edge_length: float) -> TetMesh:
    """The hand's voxel mesh at ``edge_length`` (m), filled once per process and length: it depends on neither the
    material nor the gap an environment draws at each reset (a fill took 0.14 s of the hand's 0.36 s reset), and a
    :class:`~suture_gym.sim.mesh.TetMesh` is read-only, so every caller may share it."""
    from suture_gym.sim.mesh_io import voxel_fill

    return voxel_fill(_Implicit(hand_distance, HAND_BOUNDS), edge_length)


def resting_incised(mesh: TetMesh, incision: Incision, material: TissueMaterial, pin_height: float,
                    gravity: float = STANDARD_GRAVITY, pin_low_x: bool = False) -> Scene:
    """Any tet mesh with an incision, resting on a rigid table at its lowest point.

    The base ``z >= z_min`` is a contact, the nodes within ``pin_height`` (m) above it are pinned, and with
    ``pin_low_x`` those within ``pin_height`` of the lowest ``x`` too (a cut end, such as the hand's wrist);
    gravity ``-z``.

    Regions: ``left_wound_face``, ``right_wound_face``, ``crack_front``, ``pinned``. Settings add the incision.
    """
    cut = incise(mesh, incision)
    v = cut.mesh.vertices
    z_min = float(v[:, 2].min())
    pinned = v[:, 2] <= z_min + pin_height
    if pin_low_x:
        pinned |= v[:, 0] <= float(v[:, 0].min()) + pin_height
    n = cut.mesh.vertex_count
    regions = {
        "left_wound_face": _mask(n, cut.left_face),
        "right_wound_face": _mask(n, cut.right_face),
        "crack_front": _mask(n, cut.crack_front),
        "pinned": pinned,
    }
    settings = {
        "scene": "resting_incised",
        "pin_height_m": pin_height,
        "incision": {"points_m": cut.points.tolist(), "depth_m": incision.depth, "gap_m": incision.gap},
    }
    supports = (np.array([[0.0, 0.0, 1.0]]), np.array([z_min]))
    return _scene(cut.mesh, material, pinned, (0.0, 0.0, -gravity), regions, settings, supports=supports)


def surface_height(mesh: TetMesh, x: np.ndarray, y: float = 0.0) -> np.ndarray:
    """Height (m) of the mesh's upper boundary above the points ``(x (K,), y)``: the highest crossing of vertical
    rays just either side of ``y`` (1 um off, so that a ray along a voxel grid's plane does not slip between its
    faces); for laying an incision's polyline on the surface."""
    import trimesh

    surface = trimesh.Trimesh(mesh.vertices, surface_triangles(mesh.tets), process=False)
    top = float(mesh.vertices[:, 2].max()) + 1.0
    height = np.full(len(x), -np.inf)
    for offset in (-1e-6, 1e-6):
        origins = np.stack([x, np.full_like(x, y + offset), np.full_like(x, top)], axis=1)
        hits, ray, _ = surface.ray.intersects_location(origins, np.tile([0.0, 0.0, -1.0], (len(x), 1)))
        np.maximum.at(height, ray, hits[:, 2])
    if not np.all(np.isfinite(height)):
        bad = x[~np.isfinite(height)].tolist()
        raise ValueError(f"the incision at x = {bad} m, y = {y} m does not lie over the hand")
    return height
