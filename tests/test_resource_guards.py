"""Resource guards and physical plausibility: meshes too large for the machine are refused before they are built
(with the tet count, the memory estimate, the cap and the parameter to change), and implausible settings are
refused naming their config key; the shipped configs pass untouched."""

import time
import warnings

import pytest
import trimesh
import yaml

import suture_gym.envs  # noqa: F401  (registers the ids)
import suture_gym.sim.mesh as mesh_module
from suture_gym.configs import ENV_DIR
from suture_gym.envs import SutureEnv, load_config
from suture_gym.sim.mesh import box_tet_grid
from suture_gym.sim.mesh_io import tetrahedralize_surface
from suture_gym.sim.model import TissueMaterial

CONFIGS = ENV_DIR


def test_a_fine_cell_size_is_refused_before_building_with_the_estimate_and_the_cap():
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"scene\.cell_size = 0\.0001 m .* 7,680,000 tets \(about 61\.4 GB.*"
                                         r"scene\.max_tets = 100,000"):
        load_config("needle_insert", {"scene": {"cell_size": 1e-4}})
    assert time.perf_counter() - start < 1.0


def test_the_tet_cap_is_a_config_key():
    with pytest.raises(ValueError, match=r"960 tets .* above scene\.max_tets = 500"):
        load_config("needle_insert", {"scene": {"max_tets": 500}})
    assert load_config("needle_insert", {"scene": {"cell_size": 1e-3, "max_tets": 8000}}).scene.tets == 7680


def test_the_memory_estimate_depends_on_the_integrator_and_is_checked_against_the_machine(monkeypatch):
    monkeypatch.setattr(mesh_module, "physical_memory", lambda: 5_000_000)
    # the default scene's 960 tets: about 1 MB with XPBD, 7.7 MB with the (default) implicit integrator
    mesh_module.check_tet_budget(960, "the default scene", 100_000, "scene.max_tets", mesh_module.BYTES_PER_TET_XPBD)
    with pytest.raises(ValueError, match=r"960 tets, about 0\.00768 GB .* more than this machine's 0\.005 GB"):
        load_config("needle_insert")


def test_tetrahedralising_at_a_tiny_edge_length_is_refused_before_it_starts():
    box = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    start = time.perf_counter()
    with pytest.raises(ValueError, match=r"edge_length = 1e-05 m .* 5,000,000,000 tets .* max_tets = 1,000,000"):
        tetrahedralize_surface(box, edge_length=1e-5, backend="voxel")
    with pytest.raises(ValueError, match=r"edge_length = 1e-05 m .*tetwild backend.* max_tets"):
        tetrahedralize_surface(box, edge_length=1e-5, backend="tetwild")
    assert time.perf_counter() - start < 1.0
    assert tetrahedralize_surface(box, edge_length=2.5e-3, backend="voxel", max_tets=320).tet_count == 320
    with pytest.raises(ValueError, match="max_tets = 319"):
        tetrahedralize_surface(box, edge_length=2.5e-3, backend="voxel", max_tets=319)


def test_the_voxel_fill_hands_its_cap_to_the_grid(monkeypatch):
    import suture_gym.sim.mesh_io as mesh_io

    seen = {}
    grid = mesh_io.box_tet_grid
    monkeypatch.setattr(mesh_io, "box_tet_grid", lambda *args, **kwargs: seen.update(kwargs) or grid(*args, **kwargs))
    box = trimesh.creation.box(extents=(0.01, 0.01, 0.01))
    tetrahedralize_surface(box, 2.5e-3, backend="voxel", max_tets=5_000_000)
    assert seen["max_tets"] == 5_000_000


def test_a_huge_grid_is_refused_before_it_is_allocated():
    with pytest.raises(ValueError, match=r"cells = \[1000, 1000, 1000\] gives 5,000,000,000 tets"):
        box_tet_grid(size=(0.01, 0.01, 0.01), cells=(1000, 1000, 1000))


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"solver": {"dt": 1.0}}, r"solver\.dt must be <= 0\.01 s"),
        ({"scene": {"cell_size": 0.01}}, r"scene\.cell_size = 0\.01 m is larger than the pad: scene\.size\[0\]"),
        ({"tissue": {"youngs_modulus": 1e12}}, r"tissue\.youngs_modulus: .* \[1, 1e\+08\] Pa"),
        ({"tissue": {"youngs_modulus": 0.1}}, r"tissue\.youngs_modulus"),
        ({"randomization": {"needle_position_noise": 0.05}}, r"randomization\.needle_position_noise = 0\.05 m must "
                                                             r"be below termination\.workspace_margin"),
    ],
)
def test_implausible_settings_are_named(overrides, match):
    with pytest.raises(ValueError, match=match):
        load_config("needle_insert", overrides)


def test_a_modulus_outside_the_validated_range_warns_and_the_simulator_refuses_absurd_ones():
    with pytest.warns(UserWarning, match=r"tissue\.youngs_modulus = 5e\+06 Pa is outside the range"):
        load_config("needle_insert", {"tissue": {"youngs_modulus": 5e6}})
    with pytest.raises(ValueError, match=r"TissueMaterial\.youngs_modulus must lie in"):
        TissueMaterial(youngs_modulus=1e12)


def test_a_needle_placed_far_outside_the_workspace_is_refused():
    env = SutureEnv("needle_insert")
    with pytest.raises(ValueError, match=r"tip starts at .* outside the workspace .* needle_position_offset = "
                                         r"\[1\.0, 0\.0, 0\.0\]"):
        env.reset(seed=0, options={"params": {"needle_position_offset": [1.0, 0.0, 0.0]}})


def test_every_shipped_config_passes_the_guards_without_a_warning():
    files = sorted(CONFIGS.glob("*.yaml"))
    assert files
    for path in files:
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            config = load_config(yaml.safe_load(path.read_text())["task"], path)
        assert config.scene.tets <= config.scene.max_tets
