"""The live viewer (viser): ``render_mode="human"``, the viewer application, teleoperation and its recording as a
Minari dataset. Skipped where viser (the ``viewer`` extra) is not installed; the recording test also needs Minari
(the ``data`` extra)."""

from __future__ import annotations

import importlib.util
import sys
import time

import gymnasium as gym
import numpy as np
import pytest

from suture_gym.envs import ENV_IDS, GOAL_ENV_IDS
from suture_gym.envs.config import load_config
from suture_gym.render.live import EpisodeStatus, require_viser

NEEDLE = "SutureGym/NeedleInsert-v3"
needs_viser = pytest.mark.skipif(importlib.util.find_spec("viser") is None,
                                 reason="the live viewer needs viser: pip install 'suture_gym[viewer]'")


def test_missing_viser_names_the_viewer_extra(monkeypatch):
    monkeypatch.setitem(sys.modules, "viser", None)
    with pytest.raises(ImportError, match=r"suture_gym\[viewer\]"):
        require_viser()
    with pytest.raises(ImportError, match=r"suture_gym\[viewer\]"):
        gym.make(NEEDLE, render_mode="human")


@pytest.mark.parametrize(("key", "value"), [("viewer_port", 70000), ("viewer_port", -1), ("viewer_fps", 0.0),
                                            ("viewer_host", "")])
def test_viewer_config_refuses_bad_values(key, value):
    with pytest.raises(ValueError, match=f"render.{key}"):
        load_config("needle_insert", {"render": {key: value}})


def test_vector_env_refuses_human_render_mode():
    from suture_gym.envs import make_vector_env

    with pytest.raises(ValueError, match="render_mode='human'"):
        make_vector_env(NEEDLE, 2, workers=0, render_mode="human")


def test_teleop_keys_move_the_proxy_and_bad_input_is_named():
    from suture_gym.viewer.teleop import Teleop

    env = gym.make(NEEDLE)
    env.reset(seed=0)
    teleop = Teleop(env, translation_step=1e-3, rotation_step=0.1)
    teleop.sync()
    start = teleop.position.copy()
    for key in ("d", "W", "W", "Q"):
        teleop.press(key)
    np.testing.assert_allclose(teleop.position - start, [1e-3, 2e-3, -1e-3], atol=1e-12)
    teleop.press("R")
    np.testing.assert_allclose(teleop.position, env.unwrapped.sim.grip_pose()[0])
    assert np.all(np.abs(teleop.action()) <= 1.0)
    with pytest.raises(ValueError, match="unknown teleoperation key 'Z'"):
        teleop.press("Z")
    with pytest.raises(ValueError, match="translation_step"):
        teleop.set_steps(0.0, 0.1)
    with pytest.raises(ValueError, match="rotation_step"):
        teleop.set_steps(1e-3, float("nan"))
    env.close()


@needs_viser
def test_human_render_mode_streams_vertex_updates(monkeypatch):
    """``render_mode="human"`` serves the scene from the first reset; stepping updates the vertices of the meshes
    made at the first frame instead of sending new ones."""
    import viser

    made = []
    add_mesh = viser.SceneApi.add_mesh_simple

    def counting_add_mesh(self, name, *args, **kwargs):
        made.append(name)
        return add_mesh(self, name, *args, **kwargs)

    monkeypatch.setattr(viser.SceneApi, "add_mesh_simple", counting_add_mesh)
    env = gym.make(NEEDLE, render_mode="human", config={"render": {"viewer_port": 0, "viewer_fps": 1000.0},
                                                         "randomization": {"enabled": False}})
    env.reset(seed=0)
    view = env.unwrapped._live
    assert view is not None and view.port > 0
    mesh = view.scene.nodes["tissue"]
    push = np.zeros(6, dtype=np.float32)
    push[2] = -0.3  # press the needle down into the tissue (1.5 N; at 5 N it tears within 30 steps): it deforms
    for _ in range(40):
        _, _, terminated, _, info = env.step(push)
        assert not terminated
    assert env.render() is None
    sim = env.unwrapped.sim
    q = sim.state.tissue.particle_q
    assert made == ["/tissue"]  # the mesh was made once ...
    assert view.scene.nodes["tissue"] is mesh
    np.testing.assert_allclose(mesh.vertices, q.astype(np.float32))  # ... and follows the tissue
    assert np.max(np.abs(q - sim.model.tissue.particle_rest_q)) > 1e-5  # which moved
    needle = env.unwrapped.view_frame().needle_q
    np.testing.assert_allclose(view.scene.nodes["needle"].points[:, 0], needle[:-1], atol=1e-6)
    assert view.pushes >= 2
    assert f"{info['tip_force']:.3f} N" in view.panel.text["tip"]
    env.close()
    assert env.unwrapped._live is None


@needs_viser
@pytest.mark.parametrize("env_id", [i for i in (*ENV_IDS, *GOAL_ENV_IDS) if i.startswith("SutureGym/")])
def test_every_id_has_the_human_render_mode(env_id):
    env = gym.make(env_id, render_mode="human", config={"render": {"viewer_port": 0}})
    env.reset(seed=1)
    for _ in range(3):
        if env.step(env.action_space.sample())[2]:
            break
    nodes = env.unwrapped._live.scene.nodes
    thread = env.unwrapped.sim.state.suture is not None
    assert {"tissue", "needle", "markers", "planned_arcs", "reaction_force"} <= set(nodes)
    assert ("suture" in nodes) == thread
    env.close()


@needs_viser
def test_a_changed_layout_replaces_the_nodes_it_changes(recwarn):
    """A frame whose markers, strand or triangles differ in number replaces those nodes (a new episode layout);
    hidden layers stay hidden."""
    from suture_gym.render import RenderFrame
    from suture_gym.render.live import LiveView

    view = LiveView(port=0)
    try:
        tissue = np.array([[0, 0, 0], [0.01, 0, 0], [0, 0.01, 0], [0.01, 0.01, 0]], dtype=float)
        strand = np.array([[0, 0, 0.01], [0.005, 0, 0.012], [0.01, 0, 0.01]])
        arcs = [strand]
        frame = RenderFrame(tissue, np.array([[0, 1, 2]]), needle_q=strand, marker_q=tissue[:2])
        status = EpisodeStatus(0, 0, 0.0, 0.0, "running", "test")
        view.show(frame, arcs, strand[0], {}, status, force=True)
        first = dict(view.scene.nodes)
        view.scene.set_visible("markers", False)
        frame = RenderFrame(tissue, np.array([[0, 1, 2], [1, 3, 2]]), needle_q=strand[:2], marker_q=tissue)
        view.show(frame, arcs, strand[0], {}, status, force=True)
        nodes = view.scene.nodes
        for layer in ("tissue", "needle", "markers"):
            assert nodes[layer] is not first[layer]
            assert view.server.scene.get_handle_by_name(f"/{layer}") is not None
        assert nodes["planned_arcs"] is first["planned_arcs"] and nodes["reaction_force"] is first["reaction_force"]
        assert len(nodes["markers"].points) == 4 and not nodes["markers"].visible
        assert len(nodes["tissue"].faces) == 2 and len(nodes["needle"].points) == 1
        assert not [w for w in recwarn if "remove" in str(w.message)]
    finally:
        view.close()


def _app(**kwargs):
    from suture_gym.viewer.app import ViewerApp

    return ViewerApp(NEEDLE, port=0, speed=None, **kwargs)


@needs_viser
def test_viewer_plays_a_policy_and_pauses():
    app = _app(policy="expert")
    try:
        summary = app.run(max_steps=25)
        assert summary["steps"] == 25 and app.steps == 25
        assert 1 <= summary["frames"] <= 26
        # the panel's reward terms add up to the return over every step, not only over the frames pushed
        assert sum(app.view.panel.sums.values()) == pytest.approx(app.episode_return, abs=1e-9)
        assert app.episode_return != 0.0
        app.set_paused(True)
        assert app.tick() is False and app.steps == 25  # paused: the loop does not step ...
        app.step_once()
        assert app.steps == 26  # ... but single steps do
        app.reset(7)
        assert (app.seed, app.steps) == (7, 0)
        assert "paused" in app.view.panel.text["episode"] and "seed 7" in app.view.panel.text["episode"]
    finally:
        app.close()


@needs_viser
def test_the_page_controls_drive_the_viewer():
    """Each input of the page, set as a browser would set it, reaches the viewer."""
    app = _app(policy="expert")
    c = app.controls
    try:
        c["Paused"].value = True
        assert app.paused
        c["Step"].value = True
        assert app.steps == 1
        c["Seed"].value = 5
        c["Reset"].value = True
        assert (app.seed, app.steps) == (5, 0)
        c["As fast as possible"].value = False
        c["Speed (x real time)"].value = 0.5
        assert app.speed == 0.5
        c["Move step (mm)"].value = 1.0
        assert app.teleop.translation_step == pytest.approx(1e-3)
        z = app.env.unwrapped.sim.grip_pose()[0][2]
        c["Move z"].value = "+ (E)"  # a teleoperation button takes over from the policy
        c["Move z"].value = "− (Q)"
        c["Move z"].value = "− (Q)"
        assert app.driver == "teleop" and c["Driver"].value == "teleop"
        assert app.teleop.position[2] == pytest.approx(z - 1e-3)
        c["Show needle"].value = False
        assert not app.view.scene.nodes["needle"].visible
        c["Driver"].value = "policy: expert"
        assert app.driver == "policy"
    finally:
        app.close()


class FakeSpaceMouse:
    """A 3D mouse held at one deflection (pyspacemouse's device interface: ``read()``, ``close()``)."""

    def __init__(self, **deflection):
        self.state = type("State", (), {axis: deflection.get(axis, 0.0)
                                        for axis in ("x", "y", "z", "roll", "pitch", "yaw")})()
        self.closed = False

    def read(self):
        return self.state

    def close(self):
        self.closed = True


@needs_viser
def test_a_3d_mouse_takes_over_and_moves_the_proxy():
    app = _app(policy="expert")
    mouse = FakeSpaceMouse(z=-0.5, yaw=0.01)  # yaw inside the dead band
    try:
        app.attach_spacemouse(mouse)
        app.step_once()
        assert app.driver == "teleop"  # deflecting it took over from the policy
        z = app.teleop.position[2]
        quat = app.teleop.quat.copy()
        for _ in range(10):
            app.step_once()
        # 0.5 of full deflection at 2 cm/s for 10 env steps of 5 ms
        assert app.teleop.position[2] - z == pytest.approx(-0.5 * 0.02 * 10 * app.control_dt)
        np.testing.assert_array_equal(app.teleop.quat, quat)
    finally:
        app.close()
    assert mouse.closed


@needs_viser
def test_viewer_cli_runs_headless(capsys):
    from suture_gym.viewer.app import main

    assert main(["--env", NEEDLE, "--policy", "random", "--port", "0", "--steps", "5", "--speed", "0"]) == 0
    captured = capsys.readouterr()
    assert "5 env steps" in captured.err
    assert "viser" not in captured.out  # stdout stays the caller's (viser's address box goes to stderr)


@needs_viser
@pytest.mark.parametrize("action_mode", ["wrench", "pose_delta"])
def test_teleoperated_episode_is_recorded_and_cloned(tmp_path, action_mode):
    """Scripted key presses through the viewer's input path move the needle, are recorded as a Minari dataset
    and load back through the behaviour-cloning loader."""
    pytest.importorskip("minari", reason="recording needs Minari: pip install 'suture_gym[data]'")
    from suture_gym.baselines.imitation import load_minari_demos

    app = _app(action_mode=action_mode, seed=3, config={"randomization": {"enabled": False}})  # the nominal start
    try:
        grip0 = app.env.unwrapped.sim.grip_pose()[0]
        app.set_recording(True)
        for key in ("D", "D", "W", "E", "L", "R", "Q", "Q", "Q", "Q"):
            app.press(key)
            for _ in range(8):
                app.step_once()
        assert app.steps == 80 and app.teleop.presses == 10
        grip = app.env.unwrapped.sim.grip_pose()[0]
        # R dropped the proxy onto the grip after +2x, +y, +z; then -z four times (0.5 mm each): the needle went
        # down by about the proxy's 2 mm and moved along +x.
        assert grip[2] - grip0[2] < -1.0e-3
        assert grip[0] - grip0[0] > 2.0e-4
        summary = app.save_demonstrations("suture_gym/NeedleInsert-v3/teleop-test-v0", root=tmp_path)
        assert summary == {"episodes": 1, "steps": 80, "dataset_id": "suture_gym/NeedleInsert-v3/teleop-test-v0",
                           "root": str(tmp_path)}
    finally:
        app.close()
    demos = load_minari_demos("suture_gym/NeedleInsert-v3/teleop-test-v0", root=tmp_path)
    assert demos["actions"].shape == (80, 6) and demos["observations"].shape[0] == 80
    assert demos["episode_starts"].tolist() == [0] and demos["episode_lengths"].tolist() == [80]
    assert demos["truncated"][-1] and not demos["terminated"].any()  # stopped by the demonstrator
    assert np.abs(demos["actions"]).max() > 0.05  # the keys acted
    assert demos["tip_forces"].shape == (80,)


@needs_viser
def test_browser_shows_the_tissue_and_the_needle(tmp_path):
    """The page in headless Chromium draws the scene: hiding the tissue, then the needle, changes the picture by
    at least the area each covers (a blank or error page would not change)."""
    pytest.importorskip("selenium", reason="the browser test needs selenium: pip install 'suture_gym[dev]'")
    pytest.importorskip("PIL", reason="the browser test decodes screenshots with Pillow")
    from PIL import Image

    from suture_gym.viewer.browser import Browser, changed_pixels, find_chromium, scene_pixels

    try:
        find_chromium()
    except RuntimeError as err:
        pytest.skip(f"no browser for the viewer test: {err}")
    app = _app(policy="expert")
    try:
        app.run(max_steps=170)  # the needle is in the tissue
        app.set_paused(True)
        with Browser() as browser:
            browser.open(app.view.url)
            browser.wait_for(lambda im: scene_pixels(im) > 5000)
            time.sleep(1.0)
            full = browser.screenshot()
            Image.fromarray(full).save(tmp_path / "viewer.png")
            for layer, area in (("tissue", 5000), ("needle", 150)):
                app.view.scene.set_visible(layer, False)
                browser.wait_for(lambda im, area=area: changed_pixels(im, full) > area, timeout=30)
                app.view.scene.set_visible(layer, True)
                browser.wait_for(lambda im: changed_pixels(im, full) < 50, timeout=30)
    finally:
        app.close()
