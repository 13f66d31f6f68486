"""Meshes: structured grids, boundary surfaces, rest shapes, masses, validation errors, constraint colouring."""

import numpy as np
import pytest

from suture_gym.sim.coloring import color_constraints
from suture_gym.sim.mesh import (
    TetLocator,
    TetMesh,
    box_tet_grid,
    lumped_masses,
    rest_shape,
    signed_volumes,
    surface_triangles,
    validate_tet_mesh,
    vertices_in_box,
    vertices_on_plane,
)

UNIT_TET = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])


def _triangle_normals(vertices, triangles):
    v = vertices[triangles]
    return np.cross(v[:, 1] - v[:, 0], v[:, 2] - v[:, 0])


@pytest.mark.parametrize("scheme, per_cell", [("five", 5), ("six", 6)])
def test_box_grid_counts_orientation_and_volume(scheme, per_cell):
    size, cells = (0.3, 0.2, 0.1), (3, 4, 2)
    mesh = box_tet_grid(size, cells, origin=(1.0, -2.0, 0.5), scheme=scheme)
    assert mesh.tets.dtype == np.int32 and mesh.vertices.dtype == np.float64
    assert mesh.tet_count == per_cell * 3 * 4 * 2
    assert mesh.vertex_count == 4 * 5 * 3
    volume = signed_volumes(mesh.vertices, mesh.tets)
    assert np.all(volume > 0)
    assert volume.sum() == pytest.approx(0.3 * 0.2 * 0.1, rel=1e-12)
    assert np.allclose(mesh.vertices.min(axis=0), (1.0, -2.0, 0.5))
    assert np.allclose(mesh.vertices.max(axis=0), (1.3, -1.8, 0.6))
    # Vertex (i, j, k) has index i + (nx + 1) (j + (ny + 1) k).
    assert np.allclose(mesh.vertices[1 + 4 * (2 + 5 * 1)], (1.0 + 0.1, -2.0 + 0.1, 0.5 + 0.05))


@pytest.mark.parametrize("scheme", ["five", "six"])
def test_box_grid_is_conforming(scheme):
    """A conforming grid has boundary triangles only on the box faces: two per cell face there."""
    cells = (3, 2, 4)
    mesh = box_tet_grid((3.0, 2.0, 4.0), cells, scheme=scheme)
    triangles = surface_triangles(mesh.tets)
    nx, ny, nz = cells
    assert len(triangles) == 4 * (nx * ny + ny * nz + nx * nz)
    v = mesh.vertices[triangles]
    on_box_face = np.zeros(len(triangles), dtype=bool)
    for axis, extent in enumerate((3.0, 2.0, 4.0)):
        for value in (0.0, extent):
            on_box_face |= np.all(np.abs(v[:, :, axis] - value) < 1e-12, axis=1)
    assert on_box_face.all()


def test_five_scheme_alternates_mirrored_cells():
    """Both cells' central tets join the globally even corners, so the shared face x = 1 is split alike."""
    mesh = box_tet_grid((2.0, 1.0, 1.0), (2, 1, 1), scheme="five")
    volume = signed_volumes(mesh.vertices, mesh.tets)
    assert np.allclose(np.sort(volume[:5]), [1 / 6] * 4 + [1 / 3])
    central = mesh.tets[np.abs(volume - 1 / 3) < 1e-12]
    assert len(central) == 2
    corner_sums = mesh.vertices[central].sum(axis=2).round().astype(int)
    assert np.all(corner_sums % 2 == 0)


@pytest.mark.parametrize("scheme", ["five", "six"])
def test_surface_is_closed_with_outward_normals(scheme):
    mesh = box_tet_grid((0.2, 0.1, 0.3), (2, 3, 2), scheme=scheme)
    triangles, owner = surface_triangles(mesh.tets, return_tet=True)
    assert triangles.dtype == np.int32 and owner.dtype == np.int32
    v = mesh.vertices
    normals = _triangle_normals(v, triangles)
    # Outward: away from the owning tet's centroid.
    centroid_offset = v[triangles].mean(axis=1) - v[mesh.tets[owner]].mean(axis=1)
    assert np.all(np.einsum("ij,ij->i", normals, centroid_offset) > 0)
    # Each triangle is a face of its owning tet.
    for tri, tet in zip(triangles, owner, strict=True):
        assert set(tri.tolist()) <= set(mesh.tets[tet].tolist())
    # Closed and outward: the divergence theorem gives the enclosed volume; normals sum to zero.
    enclosed = np.einsum("ij,ij->i", v[triangles[:, 0]], np.cross(v[triangles[:, 1]], v[triangles[:, 2]])).sum() / 6
    assert enclosed == pytest.approx(0.2 * 0.1 * 0.3, rel=1e-12)
    assert np.allclose(normals.sum(axis=0), 0.0, atol=1e-15)
    edges = np.sort(np.concatenate([triangles[:, [0, 1]], triangles[:, [1, 2]], triangles[:, [2, 0]]]), axis=1)
    _, counts = np.unique(edges, axis=0, return_counts=True)
    assert np.all(counts == 2)


def test_single_tet_surface_orientation():
    triangles = surface_triangles(np.array([[0, 1, 2, 3]]))
    normals = _triangle_normals(UNIT_TET, triangles)
    centres = UNIT_TET[triangles].mean(axis=1) - UNIT_TET.mean(axis=0)
    assert len(triangles) == 4
    assert np.all(np.einsum("ij,ij->i", normals, centres) > 0)


def test_rest_shape_and_lumped_masses():
    mesh = box_tet_grid((0.02, 0.03, 0.04), (2, 2, 3))
    dm_inv, volume = rest_shape(mesh.vertices, mesh.tets)
    x = mesh.vertices[mesh.tets]
    dm = np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2)
    assert np.allclose(np.einsum("tij,tjk->tik", dm, dm_inv), np.eye(3), atol=1e-12)
    assert np.allclose(volume, signed_volumes(mesh.vertices, mesh.tets))
    mass = lumped_masses(mesh.vertices, mesh.tets, 1000.0)
    assert mass.shape == (mesh.vertex_count,)
    assert mass.sum() == pytest.approx(1000.0 * 0.02 * 0.03 * 0.04, rel=1e-12)
    assert np.all(mass > 0)
    density = np.where(np.arange(mesh.tet_count) % 2 == 0, 1000.0, 3000.0)
    mixed = lumped_masses(mesh.vertices, mesh.tets, density)
    assert mixed.sum() == pytest.approx((density * volume).sum(), rel=1e-12)
    with pytest.raises(ValueError, match="density"):
        lumped_masses(mesh.vertices, mesh.tets, -1.0)


def test_vertex_selection_helpers():
    mesh = box_tet_grid((1.0, 1.0, 1.0), (2, 2, 2))
    top = vertices_on_plane(mesh.vertices, (0, 0, 1), (0, 0, 2))
    assert top.sum() == 9 and np.all(mesh.vertices[top, 2] == 1.0)
    corner = vertices_in_box(mesh.vertices, (-0.1, -0.1, -0.1), (0.6, 0.6, 0.6))
    assert corner.sum() == 8
    with pytest.raises(ValueError, match="normal"):
        vertices_on_plane(mesh.vertices, (0, 0, 0), (0, 0, 0))
    with pytest.raises(ValueError, match="lower <= upper"):
        vertices_in_box(mesh.vertices, (1, 1, 1), (0, 0, 0))


def test_tet_mesh_is_read_only_copy():
    vertices = UNIT_TET.copy()
    mesh = TetMesh(vertices=vertices, tets=[[0, 1, 2, 3]])
    vertices[0, 0] = 5.0
    assert mesh.vertices[0, 0] == 0.0
    with pytest.raises(ValueError):
        mesh.vertices[0, 0] = 1.0


# --- validation errors name the offending element -------------------------------------------------------


def _two_tets():
    """Two tets sharing face (1, 2, 3) from opposite sides."""
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    tets = np.array([[0, 1, 2, 3], [1, 2, 3, 4]])
    tets[1] = tets[1] if signed_volumes(vertices, tets[1:])[0] > 0 else tets[1][[0, 2, 1, 3]]
    return vertices, tets


def test_valid_two_tet_mesh_passes():
    validate_tet_mesh(*_two_tets())


def test_non_finite_vertex_is_named():
    vertices, tets = _two_tets()
    vertices[3, 1] = np.nan
    with pytest.raises(ValueError, match="vertex 3 has a non-finite coordinate"):
        validate_tet_mesh(vertices, tets)
    vertices[3, 1] = np.inf
    with pytest.raises(ValueError, match="vertex 3"):
        TetMesh(vertices=vertices, tets=tets)


def test_out_of_range_index_is_named():
    vertices, tets = _two_tets()
    tets[1, 2] = 7
    with pytest.raises(ValueError, match="tet 1 references a vertex outside 0..4"):
        validate_tet_mesh(vertices, tets)
    tets[1, 2] = -1
    with pytest.raises(ValueError, match="tet 1 references"):
        validate_tet_mesh(vertices, tets)


def test_repeated_vertex_is_named():
    vertices, tets = _two_tets()
    tets[1] = [1, 2, 2, 4]
    with pytest.raises(ValueError, match="tet 1 repeats a vertex"):
        validate_tet_mesh(vertices, tets)


def test_inverted_tet_is_named():
    vertices, tets = _two_tets()
    tets[0] = tets[0][[0, 2, 1, 3]]
    with pytest.raises(ValueError, match="tet 0 is inverted"):
        validate_tet_mesh(vertices, tets)


def test_zero_volume_tet_is_named():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])
    with pytest.raises(ValueError, match="tet 0 is degenerate"):
        validate_tet_mesh(vertices, [[0, 1, 2, 3]])


def test_unused_vertex_is_named():
    vertices = np.vstack([UNIT_TET, [[5.0, 5.0, 5.0]]])
    with pytest.raises(ValueError, match="vertex 4 is not used"):
        validate_tet_mesh(vertices, [[0, 1, 2, 3]])


def test_tets_sharing_only_an_edge_are_non_manifold():
    vertices = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1], [0, -1, 0], [0, 0, -1]])
    tets = np.array([[0, 1, 2, 3], [0, 1, 4, 5]])
    assert np.all(signed_volumes(vertices, tets) > 0)
    with pytest.raises(ValueError, match=r"non-manifold: edge \[0, 1\] is shared by 4"):
        validate_tet_mesh(vertices, tets)


def test_tets_sharing_only_a_vertex_are_non_manifold():
    vertices = np.vstack([UNIT_TET, -UNIT_TET[1:]])
    tets = np.array([[0, 1, 2, 3], [0, 4, 6, 5]])
    assert np.all(signed_volumes(vertices, tets) > 0)
    with pytest.raises(ValueError, match="non-manifold at vertex 0"):
        validate_tet_mesh(vertices, tets)


def test_overlapping_tets_on_one_side_of_a_face():
    vertices = np.vstack([UNIT_TET, [[0.2, 0.2, 2.0]]])
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4]])
    assert np.all(signed_volumes(vertices, tets) > 0)
    with pytest.raises(ValueError, match="tets 0 and 1 overlap"):
        validate_tet_mesh(vertices, tets)


def test_face_shared_by_three_tets():
    vertices = np.vstack([UNIT_TET, [[0.2, 0.2, 2.0]], [[0.2, 0.2, -1.0]]])
    tets = np.array([[0, 1, 2, 3], [0, 1, 2, 4], [0, 2, 1, 5]])
    assert np.all(signed_volumes(vertices, tets) > 0)
    with pytest.raises(ValueError, match=r"face \[0, 1, 2\] is shared by 3 tets \[0, 1, 2\]"):
        validate_tet_mesh(vertices, tets)


def test_a_validated_topology_still_has_its_geometry_checked():
    # The face and boundary checks of a tet array are remembered once passed (meshes are rebuilt every episode);
    # the geometric ones run again for every vertex set: the same grid with a vertex moved through a face fails.
    mesh = box_tet_grid((0.3, 0.2, 0.1), (3, 2, 2))
    moved = mesh.vertices.copy()
    moved[0] = mesh.vertices[mesh.tets[0]].mean(axis=0) + 2.0 * (mesh.vertices[mesh.tets[0]].mean(axis=0) - moved[0])
    with pytest.raises(ValueError, match="is inverted|is degenerate"):
        validate_tet_mesh(moved, mesh.tets)
    with pytest.raises(ValueError, match=f"vertex {mesh.vertex_count} is not used"):  # another vertex count
        validate_tet_mesh(np.vstack([mesh.vertices, [[5.0, 5.0, 5.0]]]), mesh.tets)


def test_a_failed_topology_is_not_remembered():
    vertices = np.vstack([UNIT_TET, -UNIT_TET[1:]])
    tets = np.array([[0, 1, 2, 3], [0, 4, 6, 5]])
    for _ in range(2):
        with pytest.raises(ValueError, match="non-manifold at vertex 0"):
            validate_tet_mesh(vertices, tets)


def test_surface_of_a_validated_mesh_equals_the_computed_one_and_is_the_callers():
    mesh = box_tet_grid((0.3, 0.2, 0.1), (3, 4, 2), scheme="six")
    triangles, tri_tet = surface_triangles(mesh.tets, return_tet=True)  # from the validation's record
    fresh, fresh_tet = surface_triangles(mesh.tets.astype(np.int64) + 0, return_tet=True)
    assert triangles.dtype == np.int32 and tri_tet.dtype == np.int32
    assert np.array_equal(triangles, fresh) and np.array_equal(tri_tet, fresh_tet)
    triangles[:] = 0  # the caller's own copy: the record is untouched
    assert np.array_equal(surface_triangles(mesh.tets), fresh)


@pytest.mark.parametrize(
    "vertices, tets, message",
    [
        (np.zeros((4, 2)), [[0, 1, 2, 3]], "vertices must have shape"),
        (UNIT_TET, [[0, 1, 2]], "tets must have shape"),
        (UNIT_TET, np.zeros((0, 4), dtype=int), "tets is empty"),
        (UNIT_TET, [[0.0, 1.0, 2.0, 3.0]], "integer"),
    ],
)
def test_bad_array_shapes(vertices, tets, message):
    with pytest.raises(ValueError, match=message):
        validate_tet_mesh(vertices, np.asarray(tets))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"size": (1, 1, 0)}, "size"),
        ({"size": (1, np.nan, 1)}, "size"),
        ({"cells": (1, 0, 1)}, "cells"),
        ({"cells": (1.5, 1, 1)}, "cells"),
        ({"origin": (0, 0)}, "origin"),
        ({"scheme": "seven"}, "scheme"),
    ],
)
def test_box_grid_bad_arguments(kwargs, message):
    args = {"size": (1, 1, 1), "cells": (1, 1, 1), **kwargs}
    with pytest.raises(ValueError, match=message):
        box_tet_grid(**args)


# --- colouring ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("scheme", ["five", "six"])
def test_coloring_is_valid_complete_and_deterministic(scheme):
    mesh = box_tet_grid((1.0, 1.0, 1.0), (4, 3, 3), scheme=scheme)
    order, offsets = color_constraints(mesh.tets, mesh.vertex_count)
    assert order.dtype == np.int32 and offsets.dtype == np.int32
    assert np.array_equal(np.sort(order), np.arange(mesh.tet_count))
    assert offsets[0] == 0 and offsets[-1] == mesh.tet_count and np.all(np.diff(offsets) > 0)
    for k in range(len(offsets) - 1):
        members = order[offsets[k] : offsets[k + 1]]
        particles = mesh.tets[members].ravel()
        assert len(np.unique(particles)) == len(particles), f"colour {k} has two tets sharing a particle"
        assert np.all(np.diff(members) > 0)
    again = color_constraints(mesh.tets, mesh.vertex_count)
    assert np.array_equal(order, again[0]) and np.array_equal(offsets, again[1])


def test_coloring_greedy_is_minimal_on_a_chain():
    """Constraints along a chain alternate between two colours."""
    chain = np.array([[i, i + 1] for i in range(6)])
    order, offsets = color_constraints(chain, 7)
    assert offsets.tolist() == [0, 3, 6]
    assert order.tolist() == [0, 2, 4, 1, 3, 5]


def test_coloring_rejects_bad_indices():
    with pytest.raises(ValueError, match="constraint 1 references a particle outside 0..2"):
        color_constraints(np.array([[0, 1], [1, 3]]), 3)


def test_tet_locator_matches_barycentric_coordinates_of_every_tet():
    """TetLocator.inside against each point's barycentric coordinates in every tet (brute force): random points
    in and around a grid, the grid's vertices, edge midpoints and face centres (closed tets: on the boundary is
    inside), and points just outside the box; repeated queries of one locator give the same answers."""
    mesh = box_tet_grid((0.03, 0.02, 0.01), (3, 2, 2))
    x = mesh.vertices[mesh.tets]
    dm_inv = np.linalg.inv(np.stack([x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]], axis=2))
    rng = np.random.default_rng(5)
    boundary = np.concatenate([mesh.vertices, 0.5 * (x[:, 0] + x[:, 1]), x[:, 1:].mean(axis=1)])
    outside = np.array([[-1e-6, 0.01, 0.005], [0.03 + 1e-6, 0.01, 0.005], [0.015, 0.01, 0.01 + 1e-6]])
    points = np.concatenate([rng.uniform((-0.005, -0.005, -0.005), (0.035, 0.025, 0.015), (300, 3)), boundary,
                             outside])  # fmt: skip
    b = np.einsum("tij,ptj->pti", dm_inv, points[:, None, :] - x[None, :, 0])
    expected = np.any((b >= -1e-12).all(axis=2) & (b.sum(axis=2) <= 1.0 + 1e-12), axis=1)
    locator = TetLocator(mesh.vertices, mesh.tets)
    found = locator.inside(points)
    assert np.array_equal(found, expected)
    assert found[300 : 300 + len(boundary)].all() and not found[-3:].any()
    assert expected[:300].any() and not expected[:300].all()
    assert np.array_equal(locator.inside(points[::-1]), expected[::-1])
