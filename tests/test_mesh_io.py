"""Mesh files and tetrahedralisation: meshio round trips, trimesh surfaces, bad files named in errors."""

import numpy as np
import pytest
import trimesh

from suture_gym.sim.mesh import box_tet_grid, signed_volumes, surface_triangles
from suture_gym.sim.mesh_io import load_surface_mesh, read_tet_mesh, tetrahedralize_surface, write_tet_mesh

meshio = pytest.importorskip("meshio")


def test_vtu_round_trip_is_exact(tmp_path):
    mesh = box_tet_grid(size=(0.03, 0.02, 0.01), cells=(3, 2, 1))
    path = tmp_path / "bar.vtu"
    write_tet_mesh(path, mesh, point_data={"displacement": np.ones((mesh.vertex_count, 3))})
    back = read_tet_mesh(path)
    np.testing.assert_array_equal(back.vertices, mesh.vertices)
    np.testing.assert_array_equal(back.tets, mesh.tets)


def test_read_drops_unused_points_and_reindexes(tmp_path):
    mesh = box_tet_grid(size=(0.01, 0.01, 0.01), cells=(1, 1, 1))
    extra = np.vstack([[[5.0, 5.0, 5.0]], mesh.vertices])  # a stray point first shifts every index by one
    meshio.write(tmp_path / "m.vtu", meshio.Mesh(extra, [("tetra", mesh.tets.astype(np.int64) + 1)]))
    back = read_tet_mesh(tmp_path / "m.vtu")
    assert back.vertex_count == mesh.vertex_count
    np.testing.assert_allclose(signed_volumes(back.vertices, back.tets), signed_volumes(mesh.vertices, mesh.tets))


def test_read_rejects_surface_only_file(tmp_path):
    tri = np.array([[0, 1, 2]])
    pts = np.eye(3)
    meshio.write(tmp_path / "tri.vtu", meshio.Mesh(pts, [("triangle", tri)]))
    with pytest.raises(ValueError, match="no 'tetra' cells"):
        read_tet_mesh(tmp_path / "tri.vtu")


def test_read_names_inverted_tet(tmp_path):
    mesh = box_tet_grid(size=(0.02, 0.01, 0.01), cells=(2, 1, 1))
    tets = mesh.tets.astype(np.int64).copy()
    tets[3, [1, 2]] = tets[3, [2, 1]]
    meshio.write(tmp_path / "bad.vtu", meshio.Mesh(mesh.vertices, [("tetra", tets)]))
    with pytest.raises(ValueError, match=r"\b3\b"):
        read_tet_mesh(tmp_path / "bad.vtu")


def test_missing_file_is_named(tmp_path):
    with pytest.raises(FileNotFoundError, match="nope.vtu"):
        read_tet_mesh(tmp_path / "nope.vtu")


def test_write_checks_point_data_length(tmp_path):
    mesh = box_tet_grid(size=(0.01, 0.01, 0.01), cells=(1, 1, 1))
    with pytest.raises(ValueError, match="temperature"):
        write_tet_mesh(tmp_path / "m.vtu", mesh, point_data={"temperature": np.zeros(3)})


def test_open_surface_is_rejected(tmp_path):
    box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    open_box = trimesh.Trimesh(box.vertices, box.faces[:-2], process=False)
    path = tmp_path / "open.stl"
    open_box.export(path)
    with pytest.raises(ValueError, match="not closed"):
        load_surface_mesh(path)


def test_non_finite_surface_vertex_is_named():
    box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    vertices = box.vertices.copy()
    vertices[5, 1] = np.nan
    with pytest.raises(ValueError, match="vertex 5"):
        load_surface_mesh(trimesh.Trimesh(vertices, box.faces, process=False))


@pytest.mark.parametrize("bad", [0.0, -1e-3, np.inf, np.nan])
def test_bad_edge_length_is_named(bad):
    with pytest.raises(ValueError, match="edge_length"):
        tetrahedralize_surface(trimesh.creation.icosphere(radius=0.01), edge_length=bad, backend="voxel")


def test_bad_backend_is_named():
    with pytest.raises(ValueError, match="tetgen"):
        tetrahedralize_surface(trimesh.creation.icosphere(radius=0.01), edge_length=1e-3, backend="tetgen")


def test_voxel_fill_of_obj_stays_within_the_staircase_bound(tmp_path):
    radius = 0.02
    path = tmp_path / "sphere.obj"
    trimesh.creation.icosphere(subdivisions=3, radius=radius * 1e3).export(path)  # file in millimetres
    sphere = trimesh.load(path, force="mesh")
    exact, area = sphere.volume * 1e-9, sphere.area * 1e-6
    for spacing in (radius / 2, radius / 4, radius / 8):
        mesh = tetrahedralize_surface(path, edge_length=spacing, backend="voxel", scale=1e-3)
        volumes = signed_volumes(mesh.vertices, mesh.tets)
        assert np.all(volumes > 0)
        assert np.all(np.linalg.norm(mesh.vertices, axis=1) <= radius + np.sqrt(3) * spacing)
        surface_triangles(mesh.tets)  # closed boundary (raises otherwise)
        # Cells are kept by their centre, so the staircase differs from the solid only within half a cell
        # diagonal of the surface: the volume error is bounded by area * (sqrt(3)/2) * spacing.
        assert abs(volumes.sum() - exact) <= area * np.sqrt(3) / 2 * spacing
    assert abs(volumes.sum() - exact) / exact < 0.1  # finest grid: within 10 % of the sphere


def test_tetwild_backend_follows_the_surface():
    pytest.importorskip("pytetwild")
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.02)
    mesh = tetrahedralize_surface(sphere, edge_length=0.004, backend="tetwild")
    assert np.all(signed_volumes(mesh.vertices, mesh.tets) > 0)
    volume = signed_volumes(mesh.vertices, mesh.tets).sum()
    assert abs(volume - sphere.volume) / sphere.volume < 0.03
