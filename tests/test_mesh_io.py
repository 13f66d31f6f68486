"""Mesh files and tetrahedralisation: meshio round trips, trimesh surfaces, bad files named in errors."""

import json
import os
from pathlib import Path

import numpy as np
import pytest
import trimesh

from suture_gym.sim.mesh import box_tet_grid, signed_volumes, surface_triangles
from suture_gym.sim.mesh_io import (
    load_surface_mesh,
    read_tet_mesh,
    tetrahedralize_surface,
    voxel_fill,
    write_tet_mesh,
)

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


def _gmsh_file(path):
    mesh = box_tet_grid(size=(0.02, 0.01, 0.01), cells=(2, 1, 1))
    write_tet_mesh(path, mesh)
    return path.read_bytes()


def test_msh_is_written_as_gmsh_and_read_back(tmp_path):
    data = _gmsh_file(tmp_path / "m.msh")
    assert data.startswith(b"$MeshFormat")
    assert read_tet_mesh(tmp_path / "m.msh").tet_count == 10


@pytest.mark.parametrize("fraction", [0.3, 0.6, 0.9])
def test_truncated_msh_names_the_file(tmp_path, fraction):
    data = _gmsh_file(tmp_path / "m.msh")
    (tmp_path / "cut.msh").write_bytes(data[: int(len(data) * fraction)])
    with pytest.raises(ValueError, match=r"cut\.msh.*could not be read"):
        read_tet_mesh(tmp_path / "cut.msh")


def test_non_gmsh_msh_is_refused_by_name(tmp_path):
    (tmp_path / "fluent.msh").write_text('(0 "ANSYS mesh")\n(10 (0 1 8 0 3))\n(10 (1 1 8 1 3)(\n0 0 0\n')
    with pytest.raises(ValueError, match=r"fluent\.msh.*not a Gmsh file"):
        read_tet_mesh(tmp_path / "fluent.msh")


@pytest.mark.parametrize("name", ["garbage.vtu", "garbage.vtk", "garbage.mesh", "empty.vtu", "empty.vtk"])
def test_unreadable_tet_file_raises_value_error_not_system_exit(tmp_path, name, capsys):
    (tmp_path / name).write_bytes(b"" if name.startswith("empty") else b"not a mesh \x00\xff\xfe\n" * 8)
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        read_tet_mesh(tmp_path / name)
    assert capsys.readouterr().out == ""  # meshio's complaints are in the message, not on stdout


def test_truncated_ply_is_refused_by_the_tet_reader(tmp_path):
    path = tmp_path / "cut.ply"
    trimesh.creation.box(extents=(0.02, 0.02, 0.02)).export(path)
    path.write_bytes(path.read_bytes()[:20])  # meshio's PLY reader loops forever on this
    with pytest.raises(ValueError, match=r"cut\.ply.*holds no tetrahedra"):
        read_tet_mesh(path)


def test_invalid_mesh_in_a_file_names_the_file(tmp_path):
    mesh = box_tet_grid(size=(0.02, 0.01, 0.01), cells=(2, 1, 1))
    tets = mesh.tets.astype(np.int64).copy()
    tets[3, [1, 2]] = tets[3, [2, 1]]
    meshio.write(tmp_path / "flipped.vtu", meshio.Mesh(mesh.vertices, [("tetra", tets)]))
    with pytest.raises(ValueError, match=r"flipped\.vtu.*tet 3"):
        read_tet_mesh(tmp_path / "flipped.vtu")


@pytest.mark.parametrize("name", ["garbage.obj", "garbage.stl", "garbage.off", "garbage.vtu", "cut.msh", "empty.ply"])
def test_unreadable_surface_file_names_the_file(tmp_path, name):
    if name == "cut.msh":
        data = _gmsh_file(tmp_path / "m.msh")[:300]
    elif name.startswith("empty"):
        data = b""
    else:
        data = b"not a mesh \x00\xff\xfe\n" * 8
    (tmp_path / name).write_bytes(data)
    with pytest.raises(ValueError, match=name.replace(".", r"\.")):
        load_surface_mesh(tmp_path / name)


def test_an_obj_with_a_non_utf8_comment_loads(tmp_path):
    # trimesh decodes text that is not UTF-8 with charset_normalizer, which it does not require itself: without
    # it (a core dependency of ours for this) the file was refused as unreadable
    box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    (tmp_path / "latin1.obj").write_bytes(b"# Caf\xe9 exporter \xa9\n" + box.export(file_type="obj").encode())
    assert load_surface_mesh(tmp_path / "latin1.obj").volume == pytest.approx(8e-6)


def test_surface_from_a_meshio_format_loads(tmp_path):
    box = trimesh.creation.box(extents=(0.02, 0.02, 0.02))
    meshio.write(tmp_path / "box.vtu", meshio.Mesh(box.vertices, [("triangle", box.faces)]))
    surface = load_surface_mesh(tmp_path / "box.vtu")
    assert surface.is_watertight
    assert surface.volume == pytest.approx(8e-6)


FAKE_TETWILD = '''
import json
import os

import numpy as np


def tetrahedralize(vertices, faces, edge_length_abs, num_threads):
    """Stands in for fTetWild: writes its debug file into the working directory, records where and in which
    process it ran, and fills the surface's bounding box with one tet."""
    open("__tracked_surface.stl", "w").close()
    with open(os.environ["FAKE_TETWILD_LOG"], "w") as log:
        json.dump({"pid": os.getpid(), "cwd": os.getcwd()}, log)
    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    corners = np.array([lo, [hi[0], lo[1], lo[2]], [lo[0], hi[1], lo[2]], [lo[0], lo[1], hi[2]]])
    return corners, np.array([[0, 1, 2, 3]])
'''


def test_tetwild_runs_in_a_scratch_directory_of_another_process(tmp_path, monkeypatch):
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "pytetwild.py").write_text(FAKE_TETWILD)
    monkeypatch.syspath_prepend(str(fake))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(fake), os.environ.get("PYTHONPATH", "")]))
    monkeypatch.setenv("FAKE_TETWILD_LOG", str(tmp_path / "log.json"))
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    mesh = tetrahedralize_surface(trimesh.creation.box(extents=(0.02, 0.02, 0.02)), edge_length=0.01, backend="tetwild")
    assert mesh.tet_count == 1
    ran = json.loads((tmp_path / "log.json").read_text())
    assert ran["pid"] != os.getpid()  # os.chdir in this process would move every thread's working directory
    assert Path(ran["cwd"]).resolve() != work.resolve()
    assert os.getcwd() == str(work) and list(work.iterdir()) == []
    assert not Path(ran["cwd"]).exists()  # the scratch directory is removed


def test_a_failing_tetwild_raises_with_its_error_output(tmp_path, monkeypatch):
    fake = tmp_path / "fake"
    fake.mkdir()
    (fake / "pytetwild.py").write_text("def tetrahedralize(*args, **kwargs):\n    raise MemoryError('out of memory')\n")
    monkeypatch.syspath_prepend(str(fake))
    monkeypatch.setenv("PYTHONPATH", os.pathsep.join([str(fake), os.environ.get("PYTHONPATH", "")]))
    with pytest.raises(RuntimeError, match=r"(?s)fTetWild failed \(exit status 1\).*MemoryError: out of memory"):
        tetrahedralize_surface(trimesh.creation.box(extents=(0.02, 0.02, 0.02)), edge_length=0.01, backend="tetwild")


def test_voxel_fill_bridges_cells_that_touch_only_along_an_edge():
    """Two boxes meeting along an edge: a centre test keeps cells that share only that edge (a non-manifold
    boundary, which the mesh validation refuses); the fill bridges them with the cells between."""

    class TwoBoxes:
        bounds = (np.zeros(3), np.array([2.0, 2.0, 1.0]))

        @staticmethod
        def contains(p):
            first = np.all((p >= 0.0) & (p <= 1.0), axis=1)
            second = np.all((p >= [1.0, 1.0, 0.0]) & (p <= [2.0, 2.0, 1.0]), axis=1)
            return first | second

    mesh = voxel_fill(TwoBoxes(), 0.5)
    centres = mesh.vertices[mesh.tets].mean(axis=1)
    cells = {tuple(c) for c in np.floor(centres / 0.5).astype(int).tolist()}
    # 2 x 2 x 2 cells per box; the bridge is one cell on either side of the shared edge, in both layers.
    assert len(cells) == 8 + 8 + 4 and {(1, 2, 0), (2, 1, 0), (1, 2, 1), (2, 1, 1)} <= cells
    assert mesh.tet_count == 5 * len(cells)
