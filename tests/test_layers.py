"""Layered tissue: depths and layers of tets, tags from mesh files, and both integrators on a stiffness contrast."""

import math

import meshio
import numpy as np
import pytest

from suture_gym.measure.tissue import _settle
from suture_gym.sim.layers import depth_below_surface, layer_index
from suture_gym.sim.mesh import box_tet_grid
from suture_gym.sim.mesh_io import read_tet_regions, write_tet_mesh
from suture_gym.sim.model import Model, State, TissueMaterial, TissueModel, TissueState
from suture_gym.sim.scenes import Scene
from suture_gym.sim.solver import Solver


def test_layer_index_by_thickness():
    depth = np.array([-1e-4, 0.0, 0.0019, 0.002, 0.0069, 0.007, 0.05])
    assert layer_index(depth, [0.002, 0.005]).tolist() == [0, 0, 0, 1, 1, 2, 2]
    with pytest.raises(ValueError, match="layer thicknesses must be positive"):
        layer_index(depth, [0.002, 0.0])


def test_depth_below_a_flat_and_a_tilted_top():
    mesh = box_tet_grid((0.02, 0.02, 0.01), (2, 2, 4))
    centre = mesh.vertices[mesh.tets].mean(axis=1)
    assert depth_below_surface(mesh.vertices, mesh.tets) == pytest.approx(0.01 - centre[:, 2])
    # The same box turned 30 deg about x: depth is measured across the tilted top, not along z.
    a = math.radians(30)
    rot = np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])
    up = rot @ [0.0, 0.0, 1.0]
    depth = depth_below_surface(mesh.vertices @ rot.T, mesh.tets, up=up)
    assert depth == pytest.approx(0.01 - centre[:, 2])
    with pytest.raises(ValueError, match="no boundary triangle faces up"):
        depth_below_surface(mesh.vertices, mesh.tets, up=up, max_angle=math.radians(10))


def test_tags_round_trip_through_vtu_and_a_gmsh_file(tmp_path):
    mesh = box_tet_grid((1.0, 1.0, 1.0), (2, 1, 1))
    tags = np.arange(mesh.tet_count) % 3 + 5
    write_tet_mesh(tmp_path / "layers.vtu", mesh, cell_data={"tissue": tags})
    read, got = read_tet_regions(tmp_path / "layers.vtu")
    assert np.array_equal(got, tags) and np.array_equal(read.tets, mesh.tets)
    # A Gmsh file with physical groups per element (as Gmsh writes them), read by default.
    cells = [("tetra", mesh.tets.astype(np.int64))]
    meshio.write(tmp_path / "layers.msh", meshio.Mesh(mesh.vertices, cells, cell_data={
        "gmsh:physical": [tags], "gmsh:geometrical": [tags + 10]}), file_format="gmsh22", binary=False)
    assert np.array_equal(read_tet_regions(tmp_path / "layers.msh")[1], tags)
    with pytest.raises(ValueError, match=r"has no cell data 'skin'; it has \['tissue'\]"):
        read_tet_regions(tmp_path / "layers.vtu", name="skin")
    write_tet_mesh(tmp_path / "two.vtu", mesh, cell_data={"a": tags, "b": tags})
    with pytest.raises(ValueError, match=r"name the tet tags to read, one of the integer cell data \['a', 'b'\]"):
        read_tet_regions(tmp_path / "two.vtu")
    write_tet_mesh(tmp_path / "none.vtu", mesh)
    with pytest.raises(ValueError, match="no integer cell data"):
        read_tet_regions(tmp_path / "none.vtu")


@pytest.mark.parametrize("integrator", ["quasi_newton", "xpbd"])
def test_layered_hanging_bar_matches_bar_theory(integrator):
    """A 10 cm bar hanging from its top, its upper half 10 times stiffer than its lower half, settles to the 1-D
    elongation ``rho g (h_l^2 / (2 E_l) + (h_u h_l + h_u^2 / 2) / E_u)`` within 5% (the uniform bar's check), a
    third of what the soft bar alone would stretch."""
    length, width, cells, soft, stiff, rho, g = 0.1, 0.01, (2, 2, 20), 1.0e5, 1.0e6, 1000.0, 9.81
    omega = 0.5 * math.pi * math.sqrt(soft / rho) / length
    materials = [TissueMaterial(stiff, 0.3, rho, 2 * omega), TissueMaterial(soft, 0.3, rho, 2 * omega)]
    mesh = box_tet_grid((width, width, length), cells, origin=(0.0, 0.0, -length))
    layer = layer_index(depth_below_surface(mesh.vertices, mesh.tets), [0.5 * length])
    assert np.bincount(layer).tolist() == [mesh.tet_count // 2] * 2
    z = mesh.vertices[:, 2]
    tissue = TissueModel.from_mesh(mesh, materials, pinned=np.abs(z) < 1e-12, tet_material=layer)
    scene = Scene(Model(tissue=tissue, gravity=(0.0, 0.0, -g)), State(tissue=TissueState.at_rest(tissue)))
    bottom = np.abs(z + length) < 1e-12
    half = 0.5 * length
    reference = rho * g * (half**2 / (2 * soft) + (half * half + half**2 / 2) / stiff)
    if integrator == "xpbd":
        solver, dt = Solver(), 0.05 * (width / cells[0]) / math.sqrt(stiff / rho)
    else:
        solver, dt = Solver(tissue_integrator=integrator), 1e-3
    run = _settle(scene, solver, dt, 1.0 / omega, lambda s: float(z[bottom].mean() - s.state.tissue.particle_q[
        bottom, 2].mean()))
    assert run["converged"]
    assert run["value"] == pytest.approx(reference, rel=0.05)
