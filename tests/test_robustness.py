"""Robustness of the needle-tissue coupling under hard pushes (an RL agent pushes at full action all the time).

The realistic case is a silicone-like suturing pad (30 kPa, nu = 0.45, 3 x 3 x 1 cm of 5 mm cells on a rigid
base) with the measured 1 N puncture force, at the 0.25 ms substep that tissue needs under large loads (see
the stability notes of :mod:`suture_gym.sim.solver`); the other case is the paper's 1 kPa two-bar scene at the
default 1 ms, where pushes of 0.2 N and more used to end in divergence within a few hundred substeps.
"""

from pathlib import Path

import gymnasium as gym
import numpy as np
import pytest

import suture_gym  # noqa: F401  (registers the ids)
from suture_gym.measure.puncture import (
    PAD_DT,
    PAD_PUNCTURE_FORCE,
    SETTLED_ANGULAR_SPEED,
    SETTLED_SPEED,
    WRENCH_CASES,
    hold_wrench,
    pad_with_needle,
    push_tip,
)
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.model import Control
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.sim.scenes import PAPER_SOLVER, two_bar_suturing
from suture_gym.sim.solver import Solver

DT = 1.0e-3  # s, the default substep (1 kPa scene)


def _tip(scene) -> np.ndarray:
    state, needle = scene.state, scene.model.needle
    return state.needle.body_pos + quat_to_matrix(state.needle.body_quat) @ needle.tip_pos_body


@pytest.mark.parametrize("factor", [0.9, 1.1])
def test_pad_is_pierced_only_above_the_puncture_force(factor):
    """Below the threshold the tip force builds up to the push and the tissue carries it; above it the tip
    pierces when its force reaches the threshold, not before."""
    run = push_tip(pad_with_needle(), factor * PAD_PUNCTURE_FORCE, PAD_DT, ramp=0.3, hold=0.2)
    assert not run["diverged"]
    assert run["pierced"] == (factor > 1.0)
    if factor < 1.0:
        assert run["peak_tip_force_n"] == pytest.approx(factor * PAD_PUNCTURE_FORCE, rel=0.03)
    else:
        assert run["peak_tip_force_n"] == pytest.approx(PAD_PUNCTURE_FORCE, rel=0.01)
    assert 0.0 < run["dent_before_puncture_m"] < 0.005  # the 1 cm pad bears the load before the tip cuts in


def test_rigid_base_stops_a_needle_driven_through_the_pad():
    scene = pad_with_needle()
    run = push_tip(scene, 2.0 * PAD_PUNCTURE_FORCE, PAD_DT, ramp=0.2, hold=0.2)
    assert run["pierced"] and not run["diverged"]
    eps = scene.model.coupling.params.resistance_eps
    assert _tip(scene)[2] == pytest.approx(eps, abs=1e-4)  # held at the base, eps above it
    assert scene.state.coupling.punctured  # still inside its path: no exit through the base


@pytest.mark.parametrize("case", ["down_drive", "down_twist_z", "oblique_x"])
def test_largest_wrench_into_the_pad_held_for_two_seconds(case):
    """5 N and 0.05 N m towards a pose in or under the pad, held 2 s: no divergence, and the needle ends at
    rest, held by the tissue and the base: its mean velocity and angular velocity over the last 0.2 s are
    within 1 mm and 0.1 rad of net motion (driven at 5 N, a needle that got free would be flying at m/s; a
    wedged one may rattle, see :data:`~suture_gym.measure.interaction.SETTLED_SPEED`)."""
    _, direction, axis, angle = next(c for c in WRENCH_CASES if c[0] == case)
    scene = pad_with_needle()
    run = hold_wrench(scene, direction, axis, angle)
    assert not run["diverged"] and run["time_s"] == pytest.approx(2.0)
    state = scene.state
    for array in (state.tissue.particle_q, state.needle.body_pos, state.suture.node_pos):
        assert np.all(np.isfinite(array))
    assert run["needle_mean_speed_m_s"] < SETTLED_SPEED
    assert run["needle_mean_angular_speed_rad_s"] < SETTLED_ANGULAR_SPEED
    assert run["settled"]
    assert run["max_tissue_speed_m_s"] < Solver().max_speed


@pytest.mark.parametrize("push", [0.2, 1.0, 10.0])
@pytest.mark.parametrize("puncture_force", [1.0e3, 0.015])
def test_straight_push_on_the_default_tissue_does_not_diverge(push, puncture_force):
    """The pushes that diverged within 11-227 substeps: a force straight down at the tip of the free needle of
    the 1 kPa two-bar scene, with a threshold it cannot reach (the tissue is crushed against its base) and
    with the scene's (the needle goes through), held for 0.6 s."""
    scene = two_bar_suturing(coupling_params=CouplingParams(
        puncture_force=puncture_force, exit_puncture_force=0.0, cutting_force=0.0, tip_contact_radius=0.0,
        tear_force=4.0, needle_axial_friction=10.0))
    model, state = scene.model, scene.state
    needle = model.needle
    solver, control = PAPER_SOLVER, Control()
    force = np.array([0.0, 0.0, -push])
    for _ in range(600):
        r = quat_to_matrix(state.needle.body_quat)
        control.needle_wrench = np.concatenate(
            [force, np.cross(r @ (needle.tip_pos_body - needle.grip_pos_body), force)]
        )
        solver.step(model, state, control, DT)
        assert not state.diverged, f"diverged at t = {state.time:.3f} s"
    assert np.all(np.isfinite(state.tissue.particle_q))
    assert np.abs(state.tissue.particle_qd).max() < solver.max_speed


#: The corner actions (bit i set: component i at +1, else -1) of the fuzzer's episode that diverged on
#: NeedleInsert-v1 with the randomised config (env seed 627113664, wrench mode; issue 19; v2's default draws the
#: same episode): the needle, spun and pushed at full action, dents the pad's top edge by most of a cell, and the
#: tissue's one quasi-Newton iteration per solve left an error that grew from substep to substep until a
#: particle jumped 17 mm at step 39.
EDGE_DENT_CORNERS = (0, 12, 4, 19, 26, 16, 47, 38, 8, 51, 9, 16, 18, 50, 37, 15, 52, 35, 27, 18, 3, 44, 61, 53, 43,
                     60, 58, 23, 52, 49, 0, 59, 23, 49, 30, 2, 17, 42, 50)


def test_a_full_action_dent_at_the_pad_edge_does_not_diverge():
    env = gym.make("SutureGym/NeedleInsert-v3")
    env.reset(seed=627113664)
    sim = env.unwrapped.sim
    speeds = []
    for bits in EDGE_DENT_CORNERS:
        action = np.array([1.0 if bits >> i & 1 else -1.0 for i in range(6)], np.float32)
        *_, terminated, truncated, info = env.step(action)
        assert not info["diverged"]
        speeds.append(float(np.abs(sim.state.tissue.particle_qd).max()))
        if terminated or truncated:
            break
    assert len(speeds) == len(EDGE_DENT_CORNERS) and max(speeds) < 2.0, speeds  # was 15.4 m/s, flagged at 20


def test_a_tip_anchored_after_its_taper_pressed_the_wound_does_not_diverge(monkeypatch):
    """The fuzzer's WoundClosure-v3 episode (``scripts/fuzz.py --seed 2``: wrench mode, random in-box actions,
    episode seed 210341279) that diverged at step 156: the taper's contact rows read 49 N on the wound's face, the
    tip was anchored there in the next substep and that force was taken for the deflection of the anchor's spring,
    which put the anchor 4 cm out of the surface; its row pulled the patch 9 mm in one substep and inverted the
    tets under it."""
    speeds = _fuzz_episode_speeds(monkeypatch, "SutureGym/WoundClosure-v3", "wound_closure.yaml", "random",
                                  210341279, 160)
    assert len(speeds) == 160 and max(speeds) < 2.0, max(speeds)


def _fuzz_episode_speeds(monkeypatch, env_id: str, config: str, strategy: str, seed: int, steps: int) -> list:
    """Replay up to ``steps`` steps of a fuzzer episode (wrench mode; ``scripts/fuzz.py``'s case of ``env_id`` and
    ``config``, ``strategy``, episode seed ``seed``), asserting at each step that it did not diverge; the tissue's
    largest particle speed (m/s) after each step, until the episode ends."""
    from conftest import import_script

    fuzz = import_script(monkeypatch, "fuzz")
    case = next(c for c in fuzz.cases() if c["id"] == env_id and c["action_mode"] == "wrench"
                and c["config"] == config)
    episode = fuzz.Episode(case, strategy, seed, 200)
    env = fuzz._make(case)
    env.reset(seed=episode.seed)
    actions = episode.actions(env)
    sim = env.unwrapped.sim
    speeds = []
    for _ in range(steps):
        *_, terminated, truncated, info = env.step(actions())
        assert not info["diverged"], len(speeds) + 1
        speeds.append(float(np.abs(sim.state.tissue.particle_qd).max()))
        if terminated or truncated:
            break
    env.close()
    return speeds


@pytest.mark.xfail(strict=True, reason="the pose_delta holder's spring force is not bounded: a target that runs "
                   "ahead of a needle blocked in the tissue presses it with k times the lead (10.5 N at step 600, "
                   "more after), crushing the tissue against the base until its tets invert")
def test_a_behaviour_cloned_throw_in_pose_delta_does_not_crush_the_tissue():
    """The deterministic actions of a behaviour-cloned PPO policy on SutureThrow-v3 in the needle frame (env seed
    100004, tests/data/suture_throw_bc_pose_delta_actions.npy, recorded once from the policy): every component in
    the box, the needle driven down through its two paths a few micrometres a step. The holder's target runs ahead
    of the blocked needle and its spring's force grows without bound; the tissue under the needle is compressed to
    J = 0.76 by step 400, jitters at 0.1-1 m/s from there as the solve stops converging, and its first tets invert at
    step 502 (the env flagged the divergence at step 630; with the anchor fix the episode ends in a tear at 611,
    the tissue already inverted and moving at 10 m/s)."""
    actions = np.load(Path(__file__).resolve().parent / "data" / "suture_throw_bc_pose_delta_actions.npy")
    env = gym.make("SutureGym/SutureThrow-v3", config="suture_throw_needle_frame")
    env.reset(seed=100004)
    sim = env.unwrapped.sim
    speeds = []
    for action in actions:
        *_, terminated, truncated, info = env.step(action)
        assert not info["diverged"], len(speeds) + 1
        speeds.append(float(np.abs(sim.state.tissue.particle_qd).max()))
        if terminated or truncated:
            break
    assert max(speeds) < 2.0, (len(speeds), max(speeds))


@pytest.mark.xfail(strict=True, reason="a needle spun up to 18 rad/s by the full torque, its tip whipping in and "
                   "out of the tissue, throws the tissue to 13.7 m/s in one env step (step 17)")
def test_a_needle_spun_by_bang_bang_torques_does_not_diverge(monkeypatch):
    """The fuzzer's NeedleInsertGoal-v3 episode (``scripts/fuzz.py --seed 1``: wrench mode, bang-bang in-box
    actions, episode seed 390309944) that diverged at step 25: one corner of the box held for 17 steps spins the
    needle up to 18 rad/s while its tip punctures and leaves the pad, then the opposite corner."""
    speeds = _fuzz_episode_speeds(monkeypatch, "SutureGym/NeedleInsertGoal-v3", "needle_insert.yaml", "bang_bang",
                                  390309944, 30)
    assert max(speeds) < 2.0, (len(speeds), max(speeds))
