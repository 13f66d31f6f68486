"""End to end: the two-bar wound sutured by a scripted surgeon through the real solver.

The needle is turned about its own centre by a virtual coupling: it pierces bar A, exits into the wound gap,
pierces bar B and exits; the thread follows through both bites; then, with the thread's tail held, a constant
pull on the needle closes the wound. The gap is measured between the facing wound faces within 5 mm of the
stitch and 10 mm of the top.
"""

import numpy as np
import pytest

from suture_gym.measure.interaction import StitchController, run_stitch
from suture_gym.sim.coupling import NODE_IN, ROW_PATH, access_point
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.sim.rod import segment_strain
from suture_gym.sim.scenes import two_bar_suturing, wound_gap
from suture_gym.sim.solver import Solver

PULL_TIME = 3.0  # s


@pytest.fixture(scope="module")
def stitched():
    scene = two_bar_suturing()
    controller = StitchController(scene.model.needle, np.array(scene.settings["arc_center_m"]))
    events = []

    def probe(s, t):
        c = s.state.coupling
        events.append((t, c.punctures, c.path_count, bool(c.punctured)))

    run = run_stitch(scene, controller, controller.turn_time + PULL_TIME, Solver(), probe)
    print(
        f"\nwound gap: rest {run['gap_rest_m'] * 1e3:.2f} mm, needle through both edges "
        f"{run['gap_after_turn_m'] * 1e3:.2f} mm, after pulling {run['gap_final_m'] * 1e3:.2f} mm"
    )
    return scene, run, events


def test_needle_pierces_bar_a_exits_pierces_bar_b_and_exits(stitched):
    scene, run, events = stitched
    t, punctures, paths, open_ = (np.array(v) for v in zip(*events, strict=True))
    first = np.argmax(punctures >= 1)
    second = np.argmax(punctures >= 2)
    assert punctures[-1] == 2 and paths[-1] == 2
    assert 0 < first < second
    assert open_[first] and not open_[second - 1]  # bite A closed (tip in the gap) before bite B opened
    assert not open_[-1]  # and bite B closed too: the needle came out
    state = scene.state.coupling
    tissue = scene.model.tissue
    q = scene.state.tissue.particle_q
    for k, bar in ((0, "left_bar"), (1, "right_bar")):
        tets = state.pathnode_tet[state.path_first[k] : state.path_first[k] + state.path_len[k]]
        assert state.path_len[k] >= 5
        in_bar = np.isin(tissue.tet_indices[tets], scene.regions[bar]).all(axis=1)
        assert in_bar.all(), f"path {k} leaves {bar}"
        assert np.all(np.isfinite(q[tissue.tet_indices[tets]]))


def test_thread_follows_through_both_bites(stitched):
    scene, run, _ = stitched
    state = scene.state.coupling
    nn = scene.model.coupling.needle_node_count
    suture_paths = state.strand_path[nn:][state.strand_status[nn:] == NODE_IN]
    assert set(suture_paths.tolist()) == {0, 1}  # thread, not needle, lies in both paths at the end
    assert np.all(state.strand_path[:nn] == -1)  # the needle is out
    work = scene.model.scratch.coupling_work
    assert np.count_nonzero(work.row_kind[nn:] == ROW_PATH) >= 10


def test_pulling_the_thread_closes_the_wound(stitched):
    scene, run, _ = stitched
    assert not run["diverged"] and not scene.state.coupling.damaged and not scene.state.coupling.overflow
    assert run["gap_final_m"] < 0.5 * run["gap_rest_m"]
    assert run["gap_after_turn_m"] - run["gap_final_m"] > 3e-3
    assert wound_gap(scene, x_range=0.005, depth=0.01) == run["gap_final_m"]


def test_thread_stays_inextensible_and_attached(stitched):
    scene, _, _ = stitched
    model, state = scene.model, scene.state
    assert np.abs(segment_strain(model.suture, state.suture)).max() < 5e-3
    swage = state.needle.body_pos + quat_to_matrix(state.needle.body_quat) @ model.needle.swage_pos_body
    assert np.linalg.norm(state.suture.node_pos[0] - swage) < 1e-5


KNOT_TAIL = 0.066  # m: puts the knot 14 mm behind the swage, which reaches the first entry during the turn


@pytest.fixture(scope="module")
def knotted():
    """The same stitch with a free thread tail and a stopper knot instead of a held tail."""
    scene = two_bar_suturing(suture_tail_pinned=False, suture_knot_tail=KNOT_TAIL)
    controller = StitchController(scene.model.needle, np.array(scene.settings["arc_center_m"]))
    log = []

    def probe(s, t):
        c = s.state.coupling
        swage = s.state.needle.body_pos + quat_to_matrix(s.state.needle.body_quat) @ s.model.needle.swage_pos_body
        log.append((t, c.path_sigma_entry[0] if c.path_count else np.nan, swage.copy()))

    run = run_stitch(scene, controller, controller.turn_time + PULL_TIME, Solver(), probe)
    return scene, run, log


def test_a_stopper_knot_stops_the_thread_at_the_first_entry_and_the_pull_closes_the_wound(knotted):
    scene, run, log = knotted
    coupling, state = scene.model.coupling, scene.state.coupling
    knot = coupling.knot_sigma
    t, sigma_entry, swage = np.array([r[0] for r in log]), np.array([r[1] for r in log]), np.array([r[2] for r in log])
    assert np.nanmax(sigma_entry) <= knot + 1e-12  # the entry's coordinate never passes the knot
    arrived = int(np.argmax(sigma_entry >= knot - 1e-4))
    assert sigma_entry[arrived] >= knot - 1e-4 and t[arrived] < t[-1] - 2.0  # reached with 2 s of work left
    assert np.all(sigma_entry[arrived:] >= knot - 5e-4)  # and held there (within half a segment)
    assert np.linalg.norm(swage[-1] - swage[arrived]) > 5e-3  # while the needle went on pulling
    # the tail beyond the knot stayed outside the tissue, and the knot sits at the entry
    nn = coupling.needle_node_count
    tail = coupling.strand_sigma > knot + 1e-3
    assert np.all(state.strand_status[tail] != NODE_IN) and np.all(state.strand_sdist[tail] > 0.0)
    entry = access_point(coupling, scene.state.tissue.particle_q, state.path_entry_tri[0], state.path_entry_bary[0])
    strand = np.vstack([scene.state.needle.body_pos + (quat_to_matrix(scene.state.needle.body_quat)
                                                       @ scene.model.needle.node_pos_body.T).T,
                        scene.state.suture.node_pos[1:]])
    knot_point = np.array([np.interp(knot, coupling.strand_sigma, strand[:, i]) for i in range(3)])
    # node-access holds a strand piece one segment long (1 mm) centred on the knot: the knot lies within half a
    # segment of the entry, plus the constraint's residual
    assert np.linalg.norm(knot_point - entry) < 0.6e-3
    assert nn < np.searchsorted(coupling.strand_sigma, knot)  # (the knot is on the suture, not the needle)
    # tension against the knot closes the wound, without tearing the tissue
    assert not run["diverged"] and not state.damaged
    assert run["gap_final_m"] < 0.25 * run["gap_rest_m"]
