"""The abdominal_wall, hand and mesh scene kinds in the env configs: validation, plans across an incision."""

import math

import numpy as np
import pytest

from suture_gym.envs.config import load_config
from suture_gym.envs.simulation import Simulation
from suture_gym.sim.mesh import box_tet_grid
from suture_gym.sim.mesh_io import write_tet_mesh

# A 3 x 2.4 x 1 cm block in 2 mm cells (its top at z = 1 cm) with a 2 cm incision along x in its middle.
BLOCK = box_tet_grid((0.03, 0.024, 0.01), (15, 12, 5))
INCISION = {"points": [[0.005, 0.012, 0.01], [0.025, 0.012, 0.01]], "depth": 0.007}


@pytest.fixture
def block_file(tmp_path):
    path = tmp_path / "block.vtu"
    write_tet_mesh(path, BLOCK)
    return str(path)


def test_mesh_scene_plans_its_stitches_on_the_tissue(block_file):
    gap = 0.002
    config = load_config("suture_throw", {"scene": {"kind": "mesh", "path": block_file, "cell_size": 0.002,
                                                    "gap": gap, "incision": INCISION}})
    sim = Simulation(config)
    assert sim.model.tissue.tet_count == BLOCK.tet_count
    (arc,) = sim.arcs
    # On a flat top the crossings are analytic (tasks.geometry.plan_stitches): the circle's centre is
    # h = center_height R above the top, the faces at +-gap/2 from the middle at the mouth (a V below it).
    radius, h = arc.radius, config.plan.center_height * arc.radius
    assert arc.center == pytest.approx([0.015, 0.012, 0.01 + h])
    assert arc.entry_angle == pytest.approx(-math.pi + math.asin(h / radius), abs=1e-8)
    assert arc.exit_angle == pytest.approx(-math.asin(h / radius), abs=1e-8)
    face = arc.access_points[1:3]
    assert np.all(np.abs(face[:, 1] - 0.012) < 0.5 * gap) and face[1, 1] > face[0, 1]
    assert sim.gap_rest > 0.0
    left, right = sim._build.left_face, sim._build.right_face
    assert len(left) == len(right) > 0


def test_layers_apply_to_any_scene_kind(block_file):
    config = load_config("suture_throw", {"scene": {
        "kind": "mesh", "path": block_file, "cell_size": 0.002, "incision": INCISION,
        "layer_thickness": [0.002], "layer_stiffness": [1.0, 0.5]}})
    tissue = Simulation(config).model.tissue
    mu = config.tissue.youngs_modulus / (2 * (1 + config.tissue.poisson_ratio))
    # 2 mm cells, five tets each: the top row of cells (centroids within 2 mm of the top) is the first layer.
    top_row = BLOCK.tet_count // 5
    assert np.count_nonzero(np.isclose(tissue.tet_mu, mu)) == top_row
    assert np.count_nonzero(np.isclose(tissue.tet_mu, 0.5 * mu)) == BLOCK.tet_count - top_row


def test_abdominal_wall_config_counts_its_grid():
    config = load_config("wound_closure", "configs/envs/abdominal_wall_wound_closure.yaml")
    assert config.scene.tets == 5 * 14 * 10 * 6


@pytest.mark.parametrize("scene, message", [
    ({"kind": "mesh"}, "scene.path must name a tet mesh"),
    ({"kind": "mesh", "path": "no/such/file.vtu", "incision": INCISION}, "scene.path = 'no/such/file.vtu' is not"),
    ({"kind": "pad", "path": "block.vtu"}, "scene.path is read for scene.kind = 'mesh' only"),
    ({"kind": "abdominal_wall", "incision": INCISION}, "scene.incision.points are read for scene.kind = 'mesh'"),
    ({"kind": "wound", "incision": {"depth": 0.004}}, "scene.incision.depth is not read for scene.kind = 'wound'"),
    ({"kind": "wound", "layer_thickness": [0.002], "layer_stiffness": [1.0]}, "scene.layer_stiffness must have one"),
    ({"kind": "wound", "grid": [4, 0, 2]}, r"scene.grid\[1\] must be an integer >= 1"),
    ({"kind": "mesh", "incision": {"points": [[0.0, 0.0, 0.0]]}}, "scene.incision.points must hold at least two"),
])
def test_bad_scene_settings_are_named(scene, message, block_file):
    if scene.get("path") == "block.vtu":
        scene = {**scene, "path": block_file}
    with pytest.raises(ValueError, match=message):
        load_config("suture_throw", {"scene": scene})


def test_the_documented_mesh_example_builds_on_a_surface_file(tmp_path):
    from suture_gym.envs.config import read_yaml
    from suture_gym.sim.anatomy import hand_surface

    hand_surface(spacing=0.008).export(tmp_path / "hand.obj")
    overrides = read_yaml("docs/examples/mesh_suture_throw.yaml")
    overrides["scene"]["path"] = str(tmp_path / "hand.obj")
    sim = Simulation(load_config("suture_throw", overrides))
    (arc,) = sim.arcs
    assert len(arc.access_angles) == 4 and sim.gap_rest > 0.0
    assert sim.model.tissue.tet_count > 5000  # the hand filled by the voxel backend at 5.8 mm
