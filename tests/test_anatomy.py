"""The anatomical scenes at coarse resolution: a curved layered abdominal wall and a hand, each with its wound."""


import numpy as np
import pytest

from suture_gym.configs import ENV_DIR
from suture_gym.envs.config import load_config, read_yaml
from suture_gym.measure.anatomy import SCENES
from suture_gym.measure.tissue_stiff import SCENE_SUBSTEP
from suture_gym.sim.anatomy import ABDOMINAL_LAYERS, abdominal_wall, curved_slab, hand, hand_surface
from suture_gym.sim.mesh import signed_volumes
from suture_gym.sim.scenes import wound_gap

CONFIGS = ENV_DIR


def test_curved_slab_wraps_the_box_onto_concentric_cylinders():
    size, radius = (0.06, 0.04, 0.01), 0.1
    mesh, box = curved_slab(size, (3, 4, 2), radius)
    assert np.all(signed_volumes(mesh.vertices, mesh.tets) > 0)
    centre = np.array([0.0, size[2] - radius])
    r = np.linalg.norm(mesh.vertices[:, 1:] - centre, axis=1)
    assert np.allclose(r[box[:, 2] == size[2]], radius) and np.allclose(r[box[:, 2] == 0.0], radius - size[2])
    assert mesh.vertices[:, 2].max() == pytest.approx(size[2])  # the crest, at y = 0
    with pytest.raises(ValueError, match="radius must exceed the slab's thickness"):
        curved_slab(size, (3, 4, 2), 0.005)


def test_abdominal_wall_layers_and_wound():
    gap = 0.002
    scene = abdominal_wall(cells=(6, 4, 3), incision_length=0.06, gap=gap)
    tissue = scene.model.tissue
    assert scene.settings["tets"] == 5 * 6 * 4 * 3
    # Layers by depth: 6.7 mm cells, centroids at 1/3 and 2/3 of a cell: skin (3 mm) holds some of the top row.
    skin, fat, muscle = (m for _, _, m in ABDOMINAL_LAYERS)
    counts = scene.settings["tet_layers"]
    assert sum(counts) == tissue.tet_count and all(c > 0 for c in counts)
    assert np.count_nonzero(np.isclose(tissue.tet_mu, skin.lame_mu)) == counts[0]
    assert np.count_nonzero(np.isclose(tissue.tet_mu, fat.lame_mu)) == counts[1]
    rest = tissue.particle_rest_q
    left, right = scene.regions["left_wound_face"], scene.regions["right_wound_face"]
    assert len(left) == len(right) > 0
    assert np.all(rest[left, 1] < 0) and np.all(rest[right, 1] > 0)
    assert np.all(np.abs(rest[left, 0] - 0.06) <= 0.03 + 1e-9)  # within the incision's length
    assert 0.0 < wound_gap(scene) < gap  # a V: the full gap at the mouth only
    assert np.all(tissue.particle_inv_mass[scene.regions["pinned"]] == 0.0)


def test_hand_surface_is_closed_and_hand_sized():
    surface = hand_surface(spacing=0.006)
    assert surface.is_watertight and surface.is_winding_consistent
    extent = surface.bounds[1] - surface.bounds[0]
    assert 250e-6 < surface.volume < 350e-6  # m^3: an adult hand is about 300-400 ml with the wrist
    assert 0.18 < extent[0] < 0.22 and 0.12 < extent[1] < 0.16 and 0.02 < extent[2] < 0.035


def test_hand_has_a_wound_on_its_back():
    scene = hand(edge_length=0.008)
    rest = scene.model.tissue.particle_rest_q
    left, right = scene.regions["left_wound_face"], scene.regions["right_wound_face"]
    assert len(left) == len(right) > 0
    assert np.ptp(rest[left, 1]) < 1e-9 and np.ptp(rest[right, 1]) < 1e-9  # flat: cut along a grid plane
    top = rest[:, 2].max()
    assert np.all(rest[np.concatenate([left, right]), 2] > top - 0.016 - 1e-9)  # on the back, two cells deep
    mouth = rest[left, 2].max()  # the top row: open by the full gap (a V below it)
    top_left, top_right = left[rest[left, 2] == mouth], right[rest[right, 2] == mouth]
    assert rest[top_right, 1].mean() - rest[top_left, 1].mean() == pytest.approx(0.0015)
    assert 0.0 < wound_gap(scene) < 0.0015


@pytest.mark.parametrize(
    ("benchmark", "config"),
    [("paper_abdominal_wall", "abdominal_wall_suture_throw.yaml"), ("paper_hand", "hand_suture_throw.yaml")],
)
def test_the_scene_benchmarks_time_the_shipped_configs_scene_and_substep(benchmark, config):
    shipped = load_config("suture_throw", CONFIGS / config)
    timed = load_config("suture_throw", SCENES[benchmark])
    assert timed.scene == shipped.scene and timed.solver == shipped.solver
    assert shipped.solver.dt * shipped.solver.substeps == pytest.approx(0.005)  # the default control period


def test_the_scene_substep_check_runs_at_the_largest_substep_of_the_shipped_configs():
    solvers = [read_yaml(path).get("solver", {}) for path in CONFIGS.glob("*.yaml")]
    largest = max(solvers, key=lambda solver: solver.get("dt", 0.0))
    assert (largest["dt"], largest["substeps"]) == SCENE_SUBSTEP
