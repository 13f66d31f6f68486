"""Tasks without physics: planned-arc geometry, reward terms on hand-made observables (exact sums, events,
potential shaping, costs, goals), configs, domain randomisation and the observation layout."""

import math
from dataclasses import fields as dataclass_fields
from dataclasses import replace

import numpy as np
import pytest
import yaml

from suture_gym.configs import AGENT_DIR, ENV_DIR
from suture_gym.envs import ENV_IDS, TASK_CLASSES
from suture_gym.envs.config import (
    EnvConfig,
    RewardConfig,
    apply_overrides,
    config_to_dict,
    default_config,
    load_config,
    save_config,
)
from suture_gym.envs.randomization import EpisodeParams, nominal_params, sample_params
from suture_gym.envs.spaces import observation_layout, observation_size, observation_table
from suture_gym.sim.coupling import CouplingParams
from suture_gym.sim.model import TissueMaterial
from suture_gym.sim.needle import NeedleShape
from suture_gym.sim.rod import SutureParams
from suture_gym.sim.solver import Solver
from suture_gym.tasks import NeedleInsert, Observables, PlannedArc, SutureThrow, WoundClosure
from suture_gym.tasks.geometry import plan_stitches

R = 0.026 / math.pi  # m, default needle curvature radius
CONFIGS = ENV_DIR
RNG = np.random.default_rng(3)
#: The package's own tasks (test modules may register more).
TASKS = ("needle_insert", "suture_throw", "wound_closure")


# --- geometry -----------------------------------------------------------------------------------------------


def test_pad_arc_meets_the_top_surface_at_entry_and_exit():
    (arc,) = plan_stitches("pad", (0.012, 0.024, 0.008), 0.004, R, 0.5, 1)
    assert arc.entry[2] == pytest.approx(0.008, abs=1e-15) and arc.exit[2] == pytest.approx(0.008, abs=1e-15)
    chord = 2 * math.sqrt(R * R - (0.5 * R) ** 2)
    assert np.linalg.norm(arc.exit - arc.entry) == pytest.approx(chord, rel=1e-12)
    assert arc.center[1] == pytest.approx(0.012) and arc.center[2] == pytest.approx(0.008 + 0.5 * R)
    bottom = arc.point(-0.5 * math.pi)
    assert bottom[2] == pytest.approx(0.008 - 0.5 * R, abs=1e-15)  # bite depth R - h
    assert arc.progress(arc.entry) == pytest.approx(0.0, abs=1e-12)
    assert arc.progress(arc.exit) == pytest.approx(1.0, abs=1e-12)
    assert arc.progress(bottom) == pytest.approx(0.5, abs=1e-12)


def test_wound_arc_crosses_both_wound_faces_below_the_surface():
    gap, width = 0.004, 0.012
    (arc,) = plan_stitches("wound", (0.016, width, 0.008), gap, R, 0.5, 1)
    p = arc.access_points
    assert p.shape == (4, 3)
    assert p[1, 1] == pytest.approx(width, abs=1e-15) and p[2, 1] == pytest.approx(width + gap, abs=1e-15)
    assert p[1, 2] < 0.008 and p[2, 2] < 0.008 and p[1, 2] == pytest.approx(p[2, 2])
    assert np.all(np.diff(arc.access_angles) > 0)


def test_stitches_are_spread_along_the_wound():
    arcs = plan_stitches("wound", (0.036, 0.012, 0.008), 0.004, R, 0.5, 3)
    np.testing.assert_allclose([a.center[0] for a in arcs], [0.009, 0.018, 0.027])


@pytest.mark.parametrize(
    "kind, size, gap, match",
    [
        ("pad", (0.012, 0.010, 0.008), 0.004, "does not fit"),
        ("wound", (0.016, 0.012, 0.008), 0.02, "wider than the planned chord"),
        ("blob", (0.016, 0.012, 0.008), 0.004, "kind"),
    ],
)
def test_impossible_plans_raise(kind, size, gap, match):
    with pytest.raises(ValueError, match=match):
        plan_stitches(kind, size, gap, R, 0.5, 1)


def test_arc_distance_and_angle_against_construction():
    (arc,) = plan_stitches("pad", (0.012, 0.024, 0.008), 0.004, R, 0.3, 1)
    for angle in RNG.uniform(-2.5, -0.5, 20):
        offset_in_plane, offset_out = RNG.uniform(-1e-3, 1e-3, 2)
        radial = (arc.point(angle) - arc.center) / R
        p = arc.point(angle) + offset_in_plane * radial + offset_out * arc.axis
        assert arc.distance(p) == pytest.approx(math.hypot(offset_in_plane, offset_out), rel=1e-9, abs=1e-15)
        assert arc.angle(p) == pytest.approx(angle, abs=1e-12)
        np.testing.assert_allclose(np.cross(arc.axis, radial), arc.tangent(angle), atol=1e-15)


def test_bad_arc_fields_are_named():
    with pytest.raises(ValueError, match="PlannedArc.axis"):
        PlannedArc((0, 0, 0), (0, 0, 0), (0, 1, 0), R, np.array([-2.0, -1.0]))
    with pytest.raises(ValueError, match="PlannedArc.access_angles"):
        PlannedArc((0, 0, 0), (1, 0, 0), (0, 1, 0), R, np.array([-1.0, -2.0]))


# --- tasks on hand-made observables -------------------------------------------------------------------------


def _obs(tip, *, entries=(), exits=(), force=0.0, gap=0.0, thread=0.0, punctured=False, damaged=False,
         overlap=0.0):
    z3 = np.zeros(3)
    return Observables(
        time=0.0, tip_pos=np.asarray(tip, dtype=float), tip_dir=z3, needle_normal=z3, needle_center=z3, grip_pos=z3,
        needle_vel=z3, needle_omega=z3, tip_sdist=1.0, punctured=punctured, path_count=0,
        new_entries=np.array(entries, dtype=float).reshape(-1, 3),
        new_exits=np.array(exits, dtype=float).reshape(-1, 3),
        tip_force=0.0, tissue_force=force, haptic_wrench=np.zeros(6), damaged=damaged, wound_gap=gap,
        wound_overlap=overlap, thread_through=thread, suture_samples=np.zeros((0, 3)), diverged=False,
    )


def _task(cls, kind="pad", stitches=1, reward=None, gap_rest=0.0, end_on_miss=False):
    size = (0.012, 0.024, 0.008) if kind == "pad" else (0.016 * stitches, 0.012, 0.008)
    arcs = plan_stitches(kind, size, 0.004, R, 0.5, stitches)
    workspace = np.array([[-0.02, -0.02, -0.01], [0.05, 0.05, 0.03]])
    return cls(arcs, reward or RewardConfig(), tear_force=3.0, thread_target=0.01, closure_target=0.5,
               workspace=workspace, gap_rest=gap_rest, end_on_miss=end_on_miss)


def _assert_exact_sum(task, outcome):
    assert tuple(outcome.terms) == task.TERMS
    assert math.fsum(outcome.terms.values()) == outcome.reward


def _walk(task, arc, angles, punctured=False):
    """Tip along the planned circle at ``angles`` (inside the tissue if ``punctured``); returns the outcomes."""
    return [task.step(_obs(arc.point(a), punctured=punctured), np.zeros(6)) for a in angles]


def test_needle_insert_perfect_bite_rewards_and_succeeds():
    w = RewardConfig()
    task = _task(NeedleInsert)
    arc = task.arc
    start = arc.entry_angle - 0.15
    task.reset(_obs(arc.point(start)))
    outcomes = _walk(task, arc, np.linspace(start, arc.entry_angle, 5))
    outcomes.append(task.step(_obs(arc.entry, entries=[arc.entry], punctured=True), np.zeros(6)))
    assert outcomes[-1].terms["entry"] == pytest.approx(w.entry) and outcomes[-1].terms["puncture"] == w.puncture
    outcomes += _walk(task, arc, np.linspace(arc.entry_angle, arc.exit_angle, 20)[1:], punctured=True)
    final = task.step(_obs(arc.exit, exits=[arc.exit]), np.zeros(6))
    outcomes.append(final)
    for o in outcomes:
        _assert_exact_sum(task, o)
        assert o.terms["path"] == pytest.approx(0.0, abs=1e-9)
    assert final.success and final.terms["exit"] == pytest.approx(w.exit) and final.terms["success"] == w.success
    # potential-based progress telescopes to w_progress * (Phi_end - Phi_start) = w_progress * 1
    assert math.fsum(o.terms["progress"] for o in outcomes) == pytest.approx(w.progress, rel=1e-12)
    again = task.step(_obs(arc.exit), np.zeros(6))
    assert again.success and again.terms["success"] == 0.0  # the bonus is paid once


def test_puncture_away_from_the_plan_is_penalised():
    w = RewardConfig()
    task = _task(NeedleInsert)
    arc = task.arc
    task.reset(_obs(arc.point(arc.entry_angle - 0.1)))
    wrong = arc.entry + np.array([0.0, 2.0 * w.access_tolerance, 0.0])
    out = task.step(_obs(wrong, entries=[wrong]), np.zeros(6))
    assert out.terms["puncture"] == -w.puncture and out.terms["entry"] == 0.0
    partial = arc.entry + np.array([0.0, 0.5 * w.access_tolerance, 0.0])
    task.reset(_obs(arc.point(arc.entry_angle - 0.1)))
    out = task.step(_obs(partial, entries=[partial]), np.zeros(6))
    assert out.terms["entry"] == pytest.approx(0.5 * w.entry) and out.terms["puncture"] == w.puncture


def test_path_term_is_bounded_and_measures_distance():
    w = RewardConfig()
    task = _task(NeedleInsert)
    arc = task.arc
    task.reset(_obs(arc.point(-2.7)))
    d = 0.8e-3
    p = arc.center + (R + d) * (arc.point(-2.7) - arc.center) / R
    out = task.step(_obs(p), np.zeros(6))
    assert out.terms["path"] == pytest.approx(-w.path * d / (d + w.path_scale), rel=1e-12)
    far = task.step(_obs(arc.center + np.array([1.0, 0.0, 0.0])), np.zeros(6))
    assert -w.path < far.terms["path"] < 0.0


@pytest.mark.parametrize("force, cost", [(0.0, 0.0), (1.0, 0.0), (2.0, 0.5), (3.0, 1.0)])
def test_tissue_force_cost(force, cost):
    w = RewardConfig(safe_force=1.0)  # with the tear force 3 N of _task
    task = _task(NeedleInsert, reward=w)
    task.reset(_obs(task.arc.point(-2.7)))
    out = task.step(_obs(task.arc.point(-2.7), force=force), np.zeros(6))
    assert out.cost == pytest.approx(cost) and out.terms["tissue_force"] == pytest.approx(-w.tissue_force * cost)


def test_action_cost_and_exact_sum_for_random_steps():
    w = RewardConfig()
    task = _task(NeedleInsert)
    task.reset(_obs(task.arc.point(-2.7)))
    for _ in range(50):
        a = RNG.uniform(-1, 1, 6)
        tip = task.arc.center + RNG.normal(0, 0.005, 3)
        out = task.step(_obs(tip, force=RNG.uniform(0, 4)), a)
        assert out.terms["action"] == pytest.approx(-w.action * np.mean(a * a), rel=1e-12)
        _assert_exact_sum(task, out)


def test_leaving_the_workspace_hands_back_the_banked_progress():
    """The exploit a PPO run found: puncture, push the tip until the arc progress saturates, leave the workspace.
    With the failing end's potential at 0 the progress terms of the episode sum to -w * Phi(start) <= 0."""
    w = RewardConfig()
    task = _task(NeedleInsert)
    arc = task.arc
    task.reset(_obs(arc.entry))
    progress = [task.step(_obs(arc.entry, entries=[arc.entry], punctured=True), np.zeros(6))]
    progress += _walk(task, arc, np.linspace(arc.entry_angle, arc.exit_angle + 0.5, 10), punctured=True)
    banked = math.fsum(o.terms["progress"] for o in progress)
    assert banked == pytest.approx(w.progress, rel=1e-9)  # the whole arc's potential, as the exploit banked it
    away = task.step(_obs(task.workspace[1] + 0.01, punctured=True), np.zeros(6))
    assert away.out_of_workspace and not away.success
    _assert_exact_sum(task, away)
    assert banked + away.terms["progress"] == pytest.approx(0.0, abs=1e-12)


def test_backing_out_through_the_entry_banks_no_progress():
    """Another shortcut a PPO run found: puncture at the entry, back out at once; the exit used to set the
    potential to that of a finished stitch. Now the potential after the final exit is the exit point's."""
    w = RewardConfig()
    task = _task(NeedleInsert)
    arc = task.arc
    task.reset(_obs(arc.point(arc.entry_angle - 0.1)))
    outcomes = [task.step(_obs(arc.entry, entries=[arc.entry], punctured=True), np.zeros(6))]
    outcomes += _walk(task, arc, np.linspace(arc.entry_angle, arc.entry_angle + 0.6, 6), punctured=True)
    assert math.fsum(o.terms["progress"] for o in outcomes) > 0.0
    out = task.step(_obs(arc.entry, exits=[arc.entry]), np.zeros(6))
    outcomes.append(out)
    assert task.state.exited and not out.success and out.terms["exit"] == 0.0
    assert math.fsum(o.terms["progress"] for o in outcomes) == pytest.approx(0.0, abs=1e-12)
    again = task.step(_obs(arc.entry, entries=[arc.entry], punctured=True), np.zeros(6))
    assert again.terms["puncture"] == -w.puncture  # a hole after the stitch is over


def test_progress_counts_only_through_the_tissue():
    """Out of the tissue before any exit, carrying the tip round the circle (above the surface) banks nothing."""
    task = _task(NeedleInsert)
    arc = task.arc
    task.reset(_obs(arc.point(arc.entry_angle - 0.1)))
    outcomes = [task.step(_obs(arc.entry, entries=[arc.entry], punctured=True), np.zeros(6))]
    outcomes += _walk(task, arc, np.linspace(arc.entry_angle, arc.exit_angle, 8), punctured=False)
    assert all(o.terms["progress"] == 0.0 for o in outcomes)


def test_wound_gap_crossing_is_capped_at_the_far_face_and_holes_pay_once():
    w = RewardConfig()
    task = _task(SutureThrow, kind="wound")
    arc = task.arc
    p = arc.access_points
    far_face = arc.access_progress[2]
    assert 0.0 < arc.access_progress[1] < far_face < 1.0
    task.reset(_obs(arc.point(arc.entry_angle - 0.1)))
    first = task.step(_obs(p[0], entries=[p[0]], punctured=True), np.zeros(6))
    task.step(_obs(p[1], exits=[p[1]]), np.zeros(6))
    assert task.state.potential == pytest.approx(arc.access_progress[1])
    task.step(_obs(arc.exit), np.zeros(6))  # the tip carried to the exit out of the tissue: capped at the far face
    assert task.state.potential == pytest.approx(far_face)
    second = task.step(_obs(p[2], entries=[p[2]], punctured=True), np.zeros(6))
    assert first.terms["puncture"] == w.puncture and second.terms["puncture"] == w.puncture
    third = task.step(_obs(p[2], entries=[p[2]], punctured=True), np.zeros(6))
    assert third.terms["puncture"] == 0.0  # re-entering a hole already made pays nothing


@pytest.mark.parametrize("where", ["entry", "exit"])
def test_a_stitch_off_the_plan_is_a_miss_that_ends_the_episode(where):
    w = RewardConfig()
    task = _task(NeedleInsert, end_on_miss=True)
    arc = task.arc
    off = np.array([0.0, 2.0 * w.access_tolerance, 0.0])
    task.reset(_obs(arc.point(arc.entry_angle - 0.1)))
    entry = arc.entry + (off if where == "entry" else 0.0)
    first = task.step(_obs(entry, entries=[entry], punctured=True), np.zeros(6))
    if where == "exit":
        assert not (first.missed or first.failed)
        _walk(task, arc, np.linspace(arc.entry_angle, arc.exit_angle, 10), punctured=True)
        first = task.step(_obs(arc.exit - off, exits=[arc.exit - off]), np.zeros(6))
    assert first.missed and first.failed and not first.success
    assert first.terms["failure"] == -w.failure
    assert task.state.potential == 0.0
    _assert_exact_sum(task, first)


def test_a_miss_without_end_on_miss_or_in_wound_closure_does_not_end_it():
    w = RewardConfig()
    for task in (_task(NeedleInsert), _task(WoundClosure, kind="wound", gap_rest=0.004, end_on_miss=True)):
        arc = task.arc
        task.reset(_obs(arc.point(arc.entry_angle - 0.1), gap=task.gap_rest))
        wrong = arc.entry + np.array([0.0, 2.0 * w.access_tolerance, 0.0])
        out = task.step(_obs(wrong, entries=[wrong], punctured=True, gap=task.gap_rest), np.zeros(6))
        assert out.missed == task.NEEDS_PLANNED_ACCESS and not out.failed and out.terms["failure"] == 0.0


def test_ending_an_episode_early_costs_more_than_any_stay():
    """The per-step path penalty made leaving the workspace the best move of a policy that is off the plan: the
    failure term must outweigh the discounted path penalty of staying for ever, at the worst deviation."""
    checked = 0
    for f in sorted(AGENT_DIR.glob("*.yml")):
        for env_id, entry in yaml.safe_load(f.read_text()).items():
            task = ENV_IDS.get(env_id)
            if task is not None:
                reward = default_config(task).reward
                assert reward.failure > reward.path / (1.0 - entry["gamma"]), (f.name, env_id)
                checked += 1
    assert checked >= 6  # PPO and SAC for the three flat ids
    w = RewardConfig()
    task = _task(NeedleInsert)
    task.reset(_obs(task.arc.point(-2.7)))
    stay = task.step(_obs(task.arc.point(-2.7) + 0.005), np.zeros(6))
    assert stay.terms["failure"] == 0.0 and not stay.out_of_workspace
    away = task.step(_obs(task.workspace[1] + 0.01), np.zeros(6))
    assert away.out_of_workspace and away.terms["failure"] == -w.failure
    _assert_exact_sum(task, away)


def test_a_tear_that_ends_the_episode_is_a_failure():
    w = RewardConfig()
    task = _task(NeedleInsert)
    task.reset(_obs(task.arc.point(-2.7)))
    assert task.step(_obs(task.arc.point(-2.7), damaged=True), np.zeros(6)).terms["failure"] == -w.failure


def test_leaving_the_workspace_is_flagged():
    task = _task(NeedleInsert)
    task.reset(_obs(task.arc.point(-2.7)))
    assert task.step(_obs(np.array([0.2, 0.0, 0.0])), np.zeros(6)).out_of_workspace


def test_suture_throw_needs_both_exits_and_the_thread():
    w = RewardConfig()
    task = _task(SutureThrow, kind="wound")
    arc = task.arc
    task.reset(_obs(arc.point(arc.entry_angle - 0.1)))
    p = arc.access_points
    task.step(_obs(p[0], entries=[p[0]]), np.zeros(6))
    first_exit = task.step(_obs(p[1], exits=[p[1]]), np.zeros(6))
    assert first_exit.terms["exit"] == 0.0 and not task.state.exited  # left wound face: not the final exit
    far_edge = task.step(_obs(p[2], entries=[p[2]]), np.zeros(6))
    assert far_edge.terms["puncture"] == w.puncture and far_edge.terms["entry"] == 0.0
    out = task.step(_obs(p[3], exits=[p[3]]), np.zeros(6))
    assert out.terms["exit"] == pytest.approx(w.exit) and not out.success
    outcomes = [task.step(_obs(p[3], thread=t), np.zeros(6)) for t in np.linspace(0.0, 0.015, 16)]
    assert math.fsum(o.terms["thread"] for o in outcomes) == pytest.approx(w.thread, rel=1e-12)
    assert outcomes[-1].success and not outcomes[0].success
    assert sum(o.terms["success"] for o in outcomes) == w.success


def test_wound_closure_advances_stitches_and_rewards_gap_reduction():
    w = RewardConfig()
    gap0 = 0.004
    task = _task(WoundClosure, kind="wound", stitches=2, gap_rest=gap0)
    task.reset(_obs(task.arc.point(-2.7), gap=gap0))
    p = task.arc.access_points
    for k, point in enumerate(p):
        task.step(_obs(point, gap=gap0, **({"entries": [point]} if k % 2 == 0 else {"exits": [point]})), np.zeros(6))
    assert task.state.exited and task.state.stitch == 0
    out = task.step(_obs(p[3], gap=0.003, thread=0.02), np.zeros(6))
    assert task.state.stitch == 1 and not task.state.exited
    assert out.terms["closure"] == pytest.approx(w.closure * 0.25)
    gaps = np.linspace(0.003, 0.0015, 10)
    outcomes = [task.step(_obs(task.arc.point(-2.7), gap=g), np.zeros(6)) for g in gaps]
    assert math.fsum(o.terms["closure"] for o in outcomes) == pytest.approx(w.closure * 0.0015 / gap0, rel=1e-12)
    assert not any(o.success for o in outcomes)  # the gap closed (closure_target 0.5), the last stitch not made
    for o in outcomes:
        _assert_exact_sum(task, o)
    p = task.arc.access_points
    for k, point in enumerate(p):
        out = task.step(_obs(point, gap=0.0015, **({"entries": [point]} if k % 2 == 0 else {"exits": [point]})),
                        np.zeros(6))  # fmt: skip
        assert out.success == (k == len(p) - 1)  # the last stitch's final exit, the gap closed: success
    assert out.terms["success"] == w.success


def test_wound_closure_gap_closed_by_pressing_is_no_success():
    """A gap closed before the last stitch is made (the needle pressing a wound edge) is not a success."""
    gap0 = 0.004
    task = _task(WoundClosure, kind="wound", stitches=1, gap_rest=gap0)
    task.reset(_obs(task.arc.point(-2.7), gap=gap0))
    out = task.step(_obs(task.arc.point(-2.7), gap=0.1 * gap0, force=1.0), np.zeros(6))
    assert not out.success and out.terms["success"] == 0.0


@pytest.mark.parametrize("cls", [NeedleInsert, WoundClosure])
def test_a_torn_tissue_is_no_success(cls):
    """The step that completes the task while the tissue tears ends in failure, not success."""
    gap0 = 0.004 if cls is WoundClosure else 0.0
    task = _task(cls, kind="wound" if cls is WoundClosure else "pad", gap_rest=gap0)
    task.reset(_obs(task.arc.point(-2.7), gap=gap0))
    p = task.arc.access_points
    for k, point in enumerate(p[:-1]):
        task.step(_obs(point, gap=gap0, **({"entries": [point]} if k % 2 == 0 else {"exits": [point]})), np.zeros(6))
    last = dict(exits=[p[-1]]) if len(p) % 2 == 0 else dict(entries=[p[-1]])
    out = task.step(_obs(p[-1], gap=0.1 * gap0, thread=0.02, force=5.0, damaged=True, **last), np.zeros(6))
    assert out.tear and not out.success and out.failed
    assert out.terms["success"] == 0.0 and out.terms["failure"] == -task.reward.failure


def test_task_state_round_trip():
    task = _task(NeedleInsert)
    arc = task.arc
    task.reset(_obs(arc.point(-2.7)))
    task.step(_obs(arc.entry, entries=[arc.entry]), np.zeros(6))
    saved = task.get_state()
    a = task.step(_obs(arc.point(-1.5)), np.zeros(6))
    task.set_state(saved)
    b = task.step(_obs(arc.point(-1.5)), np.zeros(6))
    assert a.terms == b.terms
    with pytest.raises(ValueError, match="TaskState"):
        task.set_state({"stitch": 0})


@pytest.mark.parametrize("cls, kind", [(NeedleInsert, "pad"), (SutureThrow, "wound"), (WoundClosure, "wound")])
@pytest.mark.parametrize("goal", ["sparse", "dense"])
def test_goal_terms_are_batched_and_consistent(cls, kind, goal):
    task = _task(cls, kind=kind, reward=RewardConfig(goal=goal), gap_rest=0.004)
    desired = task.desired_goal()
    assert desired.shape == (cls.GOAL_SIZE,) and len(cls.GOAL_LAYOUT) == cls.GOAL_SIZE
    batch = desired[None, :] + RNG.normal(0, 2e-3, (8, cls.GOAL_SIZE))
    batch[0] = desired
    terms = task.goal_term(batch, np.repeat(desired[None, :], 8, axis=0))
    single = [task.goal_term(batch[i : i + 1], desired[None, :])[0] for i in range(8)]
    np.testing.assert_array_equal(terms, single)
    assert terms[0] == 0.0
    if goal == "sparse":
        assert set(np.unique(terms)) <= {0.0, -1.0}
    else:
        assert np.all((terms <= 0.0) & (terms > -1.0))


# --- configs ----------------------------------------------------------------------------------------------


@pytest.mark.parametrize("task", TASKS)
def test_yaml_defaults_match_the_typed_defaults(task):
    assert load_config(task, CONFIGS / f"{task}.yaml") == default_config(task)


def test_every_yaml_config_loads():
    files = sorted(CONFIGS.glob("*.yaml"))
    assert files
    for path in files:
        import yaml

        task = yaml.safe_load(path.read_text())["task"]
        load_config(task, path)


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"reward": {"puncture_bonus": 1.0}}, "'reward.puncture_bonus'"),
        ({"rewards": {}}, "'rewards'"),
        ({"scene": {"size": [0.01, 0.02]}}, "scene.size"),
        ({"tissue": {"youngs_modulus": -1.0}}, "tissue.youngs_modulus"),
        ({"tissue": {"youngs_modulus": "soft"}}, "tissue.youngs_modulus"),
        ({"solver": {"substeps": 2.5}}, "solver.substeps"),
        ({"action": {"mode": "teleport"}}, "action.mode"),
        ({"randomization": {"youngs_modulus_scale": [2.0, 1.0]}}, "randomization.youngs_modulus_scale"),
        ({"tissue": 3}, "tissue"),
        ({"suture": {"knot_tail": -0.001}}, "suture.knot_tail"),
        ({"suture": {"length": 0.03, "knot_tail": 0.03}}, "suture.knot_tail"),
    ],
)
def test_bad_config_values_are_named(overrides, match):
    with pytest.raises(ValueError, match=match):
        load_config("needle_insert", overrides)


@pytest.mark.parametrize(
    "overrides, match",
    [
        ({"coupling": {"max_paths": 0}}, "coupling.max_paths"),
        ({"coupling": {"tip_friction": -0.1}}, "coupling.tip_friction"),
        ({"needle": {"density": -1.0}}, "needle.density"),
        ({"needle": {"wire_radius": 0.1}}, "needle.wire_radius"),
        ({"needle": {"arc": "half"}}, "needle.arc"),
        ({"suture": {"material": {"youngs_modulus": -1.0}}}, "suture.material.youngs_modulus"),
        ({"suture": {"node_count": 1}}, "suture.node_count"),
        ({"solver": {"rod_tolerance": -1.0}}, "solver.rod_tolerance"),
        ({"tissue": {"poisson_ratio": 0.7}}, "tissue.poisson_ratio"),
    ],
)
def test_bad_simulator_parameters_are_named_by_their_key(overrides, match):
    with pytest.raises(ValueError, match=match):
        load_config("needle_insert", overrides)


@pytest.mark.parametrize("section, sim_cls", [("tissue", TissueMaterial), ("needle", NeedleShape),
                                               ("suture", SutureParams), ("coupling", CouplingParams),
                                               ("solver", Solver)])
def test_every_simulator_parameter_is_a_config_key_with_one_default(section, sim_cls):
    """The env section is the simulator's dataclass: all its fields are keys, and a default the env does not
    set on purpose (env scale) is the simulator's own."""
    cfg = default_config("needle_insert")
    values = config_to_dict(getattr(cfg, section))
    env_scale = {"tissue": {"youngs_modulus", "poisson_ratio"}, "suture": {"length", "node_count"},
                 "needle": {"holder_mass", "holder_inertia"},
                 "coupling": {"puncture_force", "tear_force", "needle_axial_friction", "exit_puncture_force",
                              "cutting_force", "tip_contact_radius"},
                 "solver": {"max_speed", "iterations", "tissue_integrator"}}
    sim_default = sim_cls()
    for f in dataclass_fields(sim_cls):
        assert f.name in values
        if f.name not in env_scale.get(section, ()):
            assert getattr(getattr(cfg, section), f.name) == getattr(sim_default, f.name), f.name


def test_yaml_simulator_parameters_reach_the_simulation():
    from suture_gym.envs.simulation import Simulation

    cfg = load_config("suture_throw", {"coupling": {"tip_friction": 0.5, "max_paths": 8},
                                       "suture": {"damping": 2.0, "material": {"youngs_modulus": 1.0e9}},
                                       "solver": {"rod_iterations": 3}, "needle": {"density": 8000.0}})
    sim = Simulation(cfg)
    params = sim.model.coupling.params
    assert (params.tip_friction, params.max_paths) == (0.5, 8)
    assert sim.suture_params.damping == 2.0 and sim.suture_params.material.youngs_modulus == 1.0e9
    assert sim.solver.rod_iterations == 3 and sim.model.needle.shape.density == 8000.0


def test_config_task_mismatch_and_wound_requirements():
    with pytest.raises(ValueError, match="task"):
        load_config("needle_insert", {"task": "suture_throw"})
    with pytest.raises(ValueError, match="suture.node_count"):
        load_config("suture_throw", {"suture": {"node_count": 0}})
    with pytest.raises(ValueError, match="scene.kind"):
        load_config("wound_closure", {"scene": {"kind": "pad"}})


def test_config_round_trip_through_yaml(tmp_path):
    overrides = {"tissue": {"youngs_modulus": 2500.0}, "plan": {"stitches": 2}}
    cfg = apply_overrides(default_config("suture_throw"), overrides)
    path = tmp_path / "resolved.yaml"
    save_config(cfg, path)
    assert load_config("suture_throw", path) == cfg
    assert config_to_dict(cfg)["plan"]["stitches"] == 2
    assert isinstance(cfg, EnvConfig) and load_config("suture_throw", cfg) is cfg


# --- randomisation ------------------------------------------------------------------------------------------


def _randomized():
    return apply_overrides(default_config("suture_throw"), {"randomization": {
        "youngs_modulus_scale": [0.5, 2.0], "puncture_force_scale": [0.8, 1.25], "gap_scale": [0.75, 1.25],
        "needle_position_noise": 1e-3, "needle_rotation_noise": 0.05}})


def test_sampling_is_seeded_and_within_ranges():
    cfg = _randomized()
    a = [sample_params(cfg, np.random.default_rng(11)) for _ in range(2)]
    assert a[0].to_dict() == a[1].to_dict()
    rng = np.random.default_rng(5)
    nominal = nominal_params(cfg)
    for _ in range(200):
        p = sample_params(cfg, rng)
        assert 0.5 * nominal.youngs_modulus <= p.youngs_modulus <= 2.0 * nominal.youngs_modulus
        assert 0.75 * nominal.gap <= p.gap <= 1.25 * nominal.gap
        assert np.all(np.abs(p.needle_position_offset) <= 1e-3) and np.all(np.abs(p.needle_rotation_offset) <= 0.05)


def test_disabled_randomisation_gives_the_nominal_values_exactly_and_draws_the_same_stream():
    on = default_config("needle_insert")
    off = apply_overrides(on, {"randomization": {"enabled": False}})
    rng_on, rng_off = np.random.default_rng(0), np.random.default_rng(0)
    p, q = sample_params(off, rng_off), sample_params(on, rng_on)
    n = nominal_params(off)
    assert p.physics_key() == n.physics_key() and q.physics_key() != n.physics_key()
    assert not p.needle_position_offset.any() and not p.needle_rotation_offset.any()
    assert rng_on.random() == rng_off.random()  # the same draws were made


def test_a_scene_without_a_wound_keeps_its_nominal_gap():
    cfg = default_config("needle_insert")
    assert cfg.scene.kind == "pad" and cfg.randomization.gap_scale != (1.0, 1.0)
    rng = np.random.default_rng(3)
    assert all(sample_params(cfg, rng).gap == cfg.scene.gap for _ in range(20))


def test_param_overrides_are_checked():
    p = nominal_params(default_config("needle_insert"))
    assert p.with_overrides({"youngs_modulus": 2000.0}).youngs_modulus == 2000.0
    with pytest.raises(ValueError, match="stiffness"):
        p.with_overrides({"stiffness": 1.0})
    with pytest.raises(ValueError, match="EpisodeParams.gap"):
        replace(p, gap=-1.0)
    assert p.as_array().shape == (len(EpisodeParams.LAYOUT),)


# --- observation layout -------------------------------------------------------------------------------------


@pytest.mark.parametrize("task", TASKS)
@pytest.mark.parametrize("extra", [{}, {"action": {"mode": "pose_delta"}, "observation": {"privileged": True}}])
def test_observation_table_covers_every_index_once(task, extra):
    layout = observation_layout(apply_overrides(default_config(task), extra))
    rows = observation_table(layout)
    assert [r[0] for r in rows] == list(range(observation_size(layout)))
    assert len({r[1] for r in rows}) == len(rows)
    assert all(r[2] for r in rows)
    names = {f.name for f in layout}
    assert ("params" in names) == bool(extra) and ("target_offset" in names) == bool(extra)


def test_task_classes_are_registered_by_name():
    assert set(TASKS) <= set(TASK_CLASSES)
    for name in TASKS:
        cls = TASK_CLASSES[name]
        assert cls.NAME == name and ENV_IDS[cls.ENV_ID] == name
        assert cls.TERMS[-2:] == ("tissue_force", "action") and "success" in cls.TERMS
