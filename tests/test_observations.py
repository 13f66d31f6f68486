"""Pixel and point-cloud observations (``observation.mode``, suture_gym/envs/sensors.py): check_env in every mode,
images that follow the needle, depth against the known distance to the pad's top face, point-cloud points on the
tissue's faces, the needle's circle and the thread, seeded determinism, the config errors, the vector env and SB3.
"""

import warnings

import gymnasium as gym
import numpy as np
import pytest

import suture_gym.envs  # noqa: F401  (registers the ids)
from suture_gym.envs import SutureEnv, SutureGoalEnv
from suture_gym.envs.config import load_config
from suture_gym.envs.spaces import point_cloud_size

MODES = ("rgb", "depth", "rgbd", "point_cloud")
KEYS = {"rgb": {"rgb"}, "depth": {"depth"}, "rgbd": {"rgb", "depth"}, "point_cloud": {"point_cloud"}}
SMALL_CAMERA = {"width": 24, "height": 20}
_ENVS: dict = {}


def _env(mode: str, **observation) -> SutureEnv:
    """One shared NeedleInsert env per (mode, observation overrides) with a small camera."""
    key = (mode, repr(sorted(observation.items())))
    if key not in _ENVS:
        _ENVS[key] = SutureEnv("needle_insert", {"observation": {"mode": mode, "camera": SMALL_CAMERA, **observation}})
    return _ENVS[key]


def _observe(env: SutureEnv) -> dict:
    """The sensor keys of the env's current state, without stepping it."""
    return env.sensors.observe(env.sim, env._markers())


@pytest.mark.parametrize("mode", MODES)
def test_gymnasium_check_env_in_every_mode(mode):
    from gymnasium.utils.env_checker import check_env

    env = _env(mode)
    assert isinstance(env.observation_space, gym.spaces.Dict)
    assert set(env.observation_space.spaces) == KEYS[mode] | {"state"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # clean: not even a warning
        check_env(env, skip_render_check=True)


@pytest.mark.parametrize("mode", MODES)
def test_sb3_check_env_in_every_mode(mode):
    env_checker = pytest.importorskip("stable_baselines3.common.env_checker")
    env_checker.check_env(_env(mode), warn=False)


def test_spaces_shapes_and_dtypes():
    obs, _ = _env("rgbd").reset(seed=0)
    assert obs["rgb"].shape == (20, 24, 3) and obs["rgb"].dtype == np.uint8
    assert obs["depth"].shape == (20, 24, 1) and obs["depth"].dtype == np.float32
    assert obs["state"].shape == _env("rgbd").state_space.shape
    env = _env("point_cloud", include_state=False)
    assert set(env.observation_space.spaces) == {"point_cloud"}
    obs, _ = env.reset(seed=0)
    assert set(obs) == {"point_cloud"} and obs["point_cloud"].shape == (480, 3) == (point_cloud_size(env.config), 3)
    default = load_config("needle_insert", {"observation": {"mode": "rgb"}})
    assert (default.observation.camera.width, default.observation.camera.height) == (84, 84)
    assert load_config("needle_insert").observation.mode == "state"


def test_images_follow_the_needle():
    """Lifting the needle by 3 mm changes exactly the pixels around its old and new centreline in the colour and
    depth images, and the depth there grows or shrinks as the needle leaves or arrives."""
    env = _env("rgbd", camera={**SMALL_CAMERA, "width": 64, "height": 64})
    env.reset(seed=0)
    before = _observe(env)
    cam = env.sensors.camera
    nodes_before = env.sim.render_frame(env._markers(), "").needle_q
    env.sim.state.needle.body_pos[2] += 0.003
    after = _observe(env)
    nodes_after = env.sim.render_frame(env._markers(), "").needle_q
    changed = np.any(before["rgb"] != after["rgb"], axis=2)
    assert changed.sum() > 20
    u, v = np.meshgrid(np.arange(64) + 0.5, np.arange(64) + 0.5)
    near = np.zeros((64, 64), dtype=bool)
    for nodes in (nodes_before, nodes_after):
        uv, _ = cam.project(nodes)
        for a, b in zip(uv[:-1], uv[1:], strict=True):
            t = np.clip(((u - a[0]) * (b[0] - a[0]) + (v - a[1]) * (b[1] - a[1])) / max(np.sum((b - a) ** 2), 1e-12),
                        0.0, 1.0)
            near |= np.hypot(u - a[0] - t * (b[0] - a[0]), v - a[1] - t * (b[1] - a[1])) < 3.0
    assert not changed[~near].any()  # nothing but the needle moved
    # The node of the lifted needle farthest on screen from the needle before: there the needle is new, in front.
    uv_before, _ = cam.project(nodes_before)
    uv_after, _ = cam.project(nodes_after)
    apart = np.linalg.norm(uv_after[:, None] - uv_before[None], axis=2).min(axis=1)
    assert apart.max() > 4.0
    col, row = np.floor(uv_after[np.argmax(apart)]).astype(int)
    assert after["depth"][row, col, 0] < before["depth"][row, col, 0]
    env.sim.state.needle.body_pos[2] -= 0.003
    np.testing.assert_array_equal(_observe(env)["rgb"], before["rgb"])


def test_images_change_as_the_env_steps():
    env = _env("rgb")
    first, _ = env.reset(seed=0)
    obs = first
    for _ in range(15):
        obs, *_ = env.step(np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0]))  # push the needle down
    assert np.any(obs["rgb"] != first["rgb"])
    np.testing.assert_array_equal(obs["rgb"], _observe(env)["rgb"])  # the step's image is the state's


def test_depth_is_the_distance_to_the_pads_top_face():
    """A camera 30 mm straight above the pad sees its top face (z = 8 mm at rest) at depth 30 mm everywhere: the
    depth is along the optical axis, not along the ray; off the pad the background is ``far``, and nothing is
    deeper than the face."""
    height = 0.03
    top = 0.008
    camera = {"width": 40, "height": 40, "fov_y": 60.0, "eye": [0.004, 0.012, top + height],
              "look_at": [0.004, 0.012, top], "up": [0.0, 1.0, 0.0], "far": 0.2}
    env = SutureEnv("needle_insert", {"observation": {"mode": "depth", "camera": camera},
                                      "randomization": {"enabled": False}})
    obs, _ = env.reset(seed=0)
    env.sim.state.needle.body_pos[:] = [0.5, 0.5, 0.5]  # out of the picture
    depth = _observe(env)["depth"][..., 0]
    cam = env.sensors.camera
    u, v = np.meshgrid(np.arange(40) + 0.5, np.arange(40) + 0.5)
    # Where each pixel's ray meets the plane z = top (the camera looks straight down).
    x = 0.004 + (u - 20.0) / cam.focal_px * height
    y = 0.012 - (v - 20.0) / cam.focal_px * height
    margin = 0.4 * height / cam.focal_px  # pixel centres within 0.4 px of the pad's outline are left out
    on_pad = (x > margin) & (x < 0.008 - margin) & (y > margin) & (y < 0.024 - margin)
    off_pad = (x < -margin) | (x > 0.008 + margin) | (y < -margin) | (y > 0.024 + margin)
    assert on_pad.sum() > 100 and off_pad.sum() > 100
    sag = env.sim.model.tissue.particle_rest_q[:, 2].max() - env.sim.state.tissue.particle_q[:, 2].max()
    assert abs(sag) < 1e-5
    np.testing.assert_allclose(depth[on_pad], height, atol=2e-5)
    assert np.all(depth[off_pad] == np.float32(0.2))
    env.close()


def test_point_cloud_lies_on_the_scene():
    """Tissue rows on the pad's faces (none on its pinned bottom), needle rows on the needle's circle, thread rows
    on the thread's centreline, in that order."""
    env = SutureEnv("needle_insert", {"observation": {"mode": "point_cloud", "include_state": False},
                                      "suture": {"node_count": 11}, "randomization": {"enabled": False}})
    obs, _ = env.reset(seed=0)
    for _ in range(5):
        obs, *_ = env.step(env.action_space.sample())
    points = obs["point_cloud"].astype(np.float64)
    pc = env.config.observation.point_cloud
    assert points.shape == (pc.tissue + pc.needle + pc.suture, 3)
    tissue, needle, thread = np.split(points, [pc.tissue, pc.tissue + pc.needle])
    # Tissue: the deformed surface, linearly interpolated; at rest plus a few steps it stays within 0.2 mm of the
    # pad's box faces (x in [0, 8], y in [0, 24], z in [0, 8] mm) and on one of them.
    size = np.array(env.config.scene.size)
    to_face = np.minimum(np.abs(tissue), np.abs(tissue - size)).min(axis=1)
    assert np.all(to_face < 2e-4)
    inside = (tissue[:, 0] > 1e-3) & (tissue[:, 0] < size[0] - 1e-3) & (tissue[:, 1] > 1e-3) & (
        tissue[:, 1] < size[1] - 1e-3)
    assert not np.any(inside & (tissue[:, 2] < 1e-6))  # the pinned bottom face holds no point
    assert np.sum(inside & (tissue[:, 2] > size[2] - 2e-4)) > 50  # the top face holds points
    # Needle: in its plane, on its circle up to the chords' sagitta, from the tip to the swage.
    o = env.sim.observables()
    radius = env.config.needle.curvature_radius
    offset = needle - o.needle_center
    assert np.all(np.abs(offset @ o.needle_normal) < 1e-9)
    nodes = env.sim.model.needle.node_pos_body
    chord = np.linalg.norm(np.diff(nodes, axis=0), axis=1).max()
    np.testing.assert_allclose(np.linalg.norm(offset, axis=1), radius, atol=chord**2 / (8 * radius) + 1e-9)
    np.testing.assert_allclose(needle[0], o.tip_pos, atol=1e-6)
    # Thread: on the polyline of its nodes, from the swage to the tail.
    q = env.sim.state.suture.node_pos
    a, b = q[:-1], q[1:]
    t = np.clip(np.einsum("psk,sk->ps", thread[:, None] - a, b - a) / np.sum((b - a) ** 2, axis=1), 0.0, 1.0)
    gap = np.linalg.norm(thread[:, None] - (a + t[..., None] * (b - a)), axis=2).min(axis=1)
    assert np.all(gap < 1e-6)
    np.testing.assert_allclose(thread[[0, -1]], q[[0, -1]], atol=1e-6)
    env.close()


def test_point_cloud_rows_are_material_points():
    """A tissue row follows its material point: its barycentric weights on the deformed triangle stay put as the
    needle deforms the tissue (checked against the particles, not through the sampler)."""
    env = _env("point_cloud")
    env.reset(seed=0)
    sampler = env.sensors._sampler
    for _ in range(20):
        obs, *_ = env.step(np.array([0.0, 0.0, -1.0, 0.0, 0.0, 0.0]))
    q = env.sim.state.tissue.particle_q
    corners = q[sampler.tissue_vertices]
    expected = np.einsum("nk,nkj->nj", sampler.tissue_weights, corners)
    np.testing.assert_allclose(obs["point_cloud"][: len(expected)], expected, atol=1e-7)
    assert np.all(sampler.tissue_weights >= 0) and np.allclose(sampler.tissue_weights.sum(axis=1), 1.0)


@pytest.mark.parametrize("mode", MODES)
def test_seeded_determinism(mode):
    """The same seed and actions give identical observations (randomised needle start, so seeds differ)."""
    env = _env(mode, camera={"width": 48, "height": 48})
    rng = np.random.default_rng(3)
    actions = rng.uniform(-1, 1, (6, 6)).astype(np.float32)

    def rollout(seed):
        obs, _ = env.reset(seed=seed)
        trace = [obs]
        for a in actions:
            obs, *_ = env.step(a)
            trace.append(obs)
        return trace

    first, again, other = rollout(7), rollout(7), rollout(8)
    for a, b in zip(first, again, strict=True):
        for key in a:
            np.testing.assert_array_equal(a[key], b[key])
    for key in KEYS[mode]:
        assert any(not np.array_equal(a[key], b[key]) for a, b in zip(first, other, strict=True))


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"mode": "pixels"}, r"observation.mode must be one of \['state', 'rgb'"),
        ({"include_state": False}, "observation.include_state = false needs a pixel or point-cloud"),
        ({"mode": "rgb", "camera": {"width": 0}}, "observation.camera.width must be an integer >= 1, got 0"),
        ({"mode": "rgb", "camera": {"fov_y": 180}}, r"observation.camera.fov_y must be < 180.0, got 180"),
        ({"mode": "rgb", "camera": {"look_at": [0.0, 0.1]}}, "observation.camera.look_at must be empty or a list"),
        ({"mode": "rgb", "camera": {"eye": [0.0, 0.0, 0.1], "distance": 0.05}},
         "observation.camera.distance = 0.05 m is unused when observation.camera.eye is given"),
        ({"mode": "rgb", "camera": {"direction": [0.0, 0.0, 2.0]}},
         r"observation.camera.up = \[0.0, 0.0, 1.0\] is parallel to observation.camera.direction"),
        ({"mode": "rgb", "camera": {"far": 0.0005}}, "observation.camera.far must be > 0.001, got 0.0005"),
        ({"mode": "depth", "camera": {"distance": 1.5}}, "observation.camera.distance = 1.5 m must lie between"),
        ({"mode": "point_cloud", "point_cloud": {"tissue": 0}}, "observation.point_cloud.tissue must be an integer"),
    ],
)
def test_config_errors_name_the_bad_value(overrides, message):
    with pytest.raises(ValueError, match=message):
        load_config("needle_insert", {"observation": overrides})


def test_env_errors_name_the_camera():
    with pytest.raises(ValueError, match=r"observation.camera.far = 0.02 m must exceed 0.0\d+ m, the depth of"):
        SutureEnv("needle_insert", {"observation": {"mode": "rgb", "camera": {**SMALL_CAMERA, "far": 0.02}}})
    # The point looked at (4.2 cm from the eye) is in front of far = 5 cm, the box's farthest corner (5.5 cm) not.
    with pytest.raises(ValueError, match=r"observation.camera.far = 0.05 m must exceed 0.05\d+ m, the depth of"):
        SutureEnv("needle_insert", {"observation": {"mode": "rgb", "camera": {**SMALL_CAMERA, "far": 0.05}}})
    with pytest.raises(ValueError, match=r"observation.camera: up .* is parallel to the view direction"):
        SutureEnv("needle_insert", {"observation": {"mode": "rgb", "camera": {
            **SMALL_CAMERA, "eye": [0.004, 0.012, 0.05], "look_at": [0.004, 0.012, 0.0]}}})
    with pytest.raises(ValueError, match="include_state = false is not available in the goal-conditioned ids"):
        SutureGoalEnv("needle_insert", {"observation": {"mode": "rgb", "include_state": False}})


def test_camera_config_round_trips_through_yaml(tmp_path):
    from suture_gym.envs.config import save_config

    camera = {"eye": [0.05, -0.01, 0.04], "look_at": [0.004, 0.012, 0.008], "fov_y": 40.0, "width": 32}
    config = load_config("needle_insert", {"observation": {"mode": "rgbd", "include_state": False, "camera": camera,
                                                           "point_cloud": {"needle": 0}}})
    save_config(config, tmp_path / "config.yaml")
    assert load_config("needle_insert", tmp_path / "config.yaml") == config
    assert config.observation.camera.eye == (0.05, -0.01, 0.04) and config.observation.camera.distance == 0.0


def test_goal_env_adds_the_sensor_keys():
    from gymnasium.utils.env_checker import check_env

    env = SutureGoalEnv("needle_insert", {"observation": {"mode": "depth", "camera": SMALL_CAMERA}})
    assert set(env.observation_space.spaces) == {"observation", "achieved_goal", "desired_goal", "depth"}
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        # The goal boxes are unbounded (as in the state-mode goal ids); the depth box is not.
        warnings.filterwarnings("ignore", message=".*Box observation space (minimum|maximum) value is.*infinity")
        check_env(env, skip_render_check=True)
    obs, _ = env.reset(seed=0)
    obs, reward, *_, info = env.step(env.action_space.sample())
    assert env.observation_space.contains(obs)
    assert reward == env.compute_reward(obs["achieved_goal"], obs["desired_goal"], info)
    env.close()


def test_vector_env_batches_dict_observations():
    from suture_gym.envs.vector import make_vector_env

    config = {"observation": {"mode": "rgbd", "camera": SMALL_CAMERA}}
    venv = make_vector_env("SutureGym/NeedleInsert-v3", 2, config=config, workers=0)
    obs, _ = venv.reset(seed=[1, 2])
    assert obs["rgb"].shape == (2, 20, 24, 3) and obs["depth"].shape == (2, 20, 24, 1)
    obs, *_ = venv.step(np.zeros((2, 6), dtype=np.float32))
    assert venv.observation_space.contains(obs)
    venv.close()


def test_sb3_multi_input_policy_and_vecnormalize_leave_the_images_alone():
    """PPO's MultiInputPolicy trains on the Dict observations of the SB3 vector env and of the agents' pipeline;
    VecNormalize there normalises the state and depth but not the uint8 image (NatureCNN needs >= 36 px)."""
    pytest.importorskip("stable_baselines3")
    from stable_baselines3 import PPO

    from suture_gym.baselines.imitation import behaviour_clone
    from suture_gym.baselines.training import make_train_envs
    from suture_gym.envs.sb3 import make_sb3_vec_env

    config = {"observation": {"mode": "rgbd", "camera": {"width": 36, "height": 36}}}
    venv = make_sb3_vec_env("SutureGym/NeedleInsert-v3", 1, config=config, workers=0)
    model = PPO("MultiInputPolicy", venv, n_steps=8, batch_size=8, n_epochs=1, device="cpu", seed=0)
    model.learn(8)
    venv.close()
    env, eval_env = make_train_envs("SutureGym/NeedleInsert-v3", 1, 0, {"config": config}, {"clip_obs": 10.0})
    assert sorted(env.norm_obs_keys) == ["depth", "state"]
    obs = env.reset()
    assert obs["rgb"].dtype == np.uint8 and env.observation_space["rgb"].dtype == np.uint8
    model = PPO("MultiInputPolicy", env, n_steps=8, batch_size=8, n_epochs=1, device="cpu", seed=0)
    model.learn(8)
    assert env.obs_rms["state"].count > 8  # the statistics were updated
    with pytest.raises(ValueError, match="behaviour cloning reads flat state observations"):
        behaviour_clone(model, {"observations": np.zeros((1, 40)), "actions": np.zeros((1, 6)),
                                "rewards": np.zeros(1), "episode_starts": np.zeros(1)})
    env.close()
    eval_env.close()


def test_culling_the_tissues_back_faces_leaves_the_image_unchanged():
    """The sensor renderer culls the tissue's back faces (its surface is closed and outward-oriented); on the
    wound scene, with the needle in the tissue, the image is the one drawn with every face."""
    from suture_gym.render import SceneRenderer

    env = SutureEnv("suture_throw", {"observation": {"mode": "rgb", "camera": {"width": 64, "height": 64}}})
    env.reset(seed=0, options={"phase": "inserted"})
    obs = _observe(env)["rgb"]
    every_face = SceneRenderer(64, 64, camera=env.sensors.camera)
    reference = every_face.render_sensor(env.sim.render_frame(env._markers(), ""), rgb=True, depth=False)[0]
    np.testing.assert_array_equal(obs, reference)
    nodes = env.sim.render_frame(env._markers(), "").needle_q
    assert np.any((nodes[:, 1] > 0.0) & (nodes[:, 1] < 0.012) & (nodes[:, 2] > 0.0) & (nodes[:, 2] < 0.008))
    env.close()
