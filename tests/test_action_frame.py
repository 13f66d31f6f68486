"""The needle action frame: actions read in the needle's own axes, turning about the centre of its circle."""

import gymnasium as gym
import numpy as np
import pytest

import suture_gym  # noqa: F401
from suture_gym.baselines.study import study
from suture_gym.envs import SutureEnv
from suture_gym.sim.quat import quat_mul, quat_rotation_vector, quat_to_matrix


def test_the_constant_drive_about_the_circle_centre_inserts_the_needle():
    """In pose_delta mode with the needle frame one component alone follows the planned arc, entry to exit."""
    result = study("SutureGym/NeedleInsert-v3", ["drive"], episodes=2, seed=123,
                   env_kwargs={"config": "needle_insert_needle_frame"})
    assert result["policies"]["drive"]["success_rate"] == 1.0
    assert result["policies"]["drive"]["mean_episode_length"] < 200


def test_a_pose_delta_action_in_the_needle_frame_turns_the_target_about_the_circle_centre():
    env = SutureEnv("needle_insert", config={"action": {"mode": "pose_delta", "frame": "needle"}})
    env.reset(seed=0)
    rot, centre = env._action_frame()
    pos, quat = env._target_pos.copy(), env._target_quat.copy()
    action = np.array([0.0, 0.0, 0.0, 0.0, 0.0, -0.5], dtype=np.float32)
    env.step(action)
    turn = quat_rotation_vector(quat_mul(env._target_quat, np.array([quat[0], *-quat[1:]])))
    np.testing.assert_allclose(turn, rot @ [0.0, 0.0, -0.5 * env.config.action.max_rotation], atol=1e-12)
    # the target kept its distance to the circle's centre and turned about the needle's normal through it
    assert np.linalg.norm(env._target_pos - centre) == pytest.approx(np.linalg.norm(pos - centre), rel=1e-12)
    assert np.dot(env._target_pos - pos, rot[:, 2]) == pytest.approx(0.0, abs=1e-12)


@pytest.mark.parametrize("mode", ["wrench", "pose_delta"])
def test_action_toward_inverts_the_needle_frame(mode):
    """The expert's actions (action_toward) are read back into the same command in either frame."""
    env = SutureEnv("needle_insert", config={"action": {"mode": mode, "frame": "needle"}})
    env.reset(seed=1)
    grip, quat = env.sim.grip_pose()
    target = grip + np.array([2e-5, -1e-5, 3e-5])
    if mode == "pose_delta":
        action = env.action_toward(target, quat)
        rot, centre = env._action_frame()
        np.testing.assert_allclose(rot @ (action[:3] * env.config.action.max_translation), target - grip, atol=1e-9)
    else:
        wrench = np.array([0.3, -0.2, 0.1, 0.002, -0.001, 0.003])
        action = env.action_for_wrench(wrench)
        np.testing.assert_allclose(env._world_wrench(action.astype(np.float64) * env._wrench_scale), wrench,
                                   rtol=1e-6, atol=1e-9)


def test_the_world_frame_is_the_default_and_a_bad_frame_is_named():
    env = gym.make("SutureGym/NeedleInsert-v3")
    assert env.unwrapped.config.action.frame == "world"
    rot, centre = env.unwrapped._action_frame()
    assert centre is None and np.array_equal(rot, np.eye(3))
    with pytest.raises(ValueError, match=r"action\.frame must be one of \['world', 'needle'\], got 'tool'"):
        gym.make("SutureGym/NeedleInsert-v3", config={"action": {"frame": "tool"}})


def test_the_study_names_a_bad_policy():
    with pytest.raises(ValueError, match="unknown policy 'hoover'"):
        study("SutureGym/NeedleInsert-v3", ["hoover"], episodes=1)
    with pytest.raises(ValueError, match="gauss<s> needs a standard deviation"):
        study("SutureGym/NeedleInsert-v3", ["gauss-1"], episodes=1)


def test_needle_frame_axes_are_the_needles_body_axes():
    env = SutureEnv("needle_insert", config={"action": {"mode": "pose_delta", "frame": "needle"}})
    env.reset(seed=2)
    rot, _ = env._action_frame()
    np.testing.assert_allclose(rot, quat_to_matrix(env.sim.state.needle.body_quat))
