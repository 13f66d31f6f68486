"""Needle/suture-tissue coupling (paper section 4): constraint maths, rigid helpers, path spacing, matching,
access points, release, snapshots and determinism of the detection; contact frames, depenetration floors,
the tip's anchor friction, the tear bound and rigid supports. No solver here (see test_suturing.py and
test_robustness.py)."""

import math
from dataclasses import replace

import numpy as np
import pytest

from suture_gym.sim.coupling import (
    NODE_HEAD,
    NODE_IN,
    NODE_OUT,
    PATH_ROW_VERTICES,
    ROW_ANCHOR,
    ROW_NONE,
    ROW_PATH,
    ROW_TRIANGLE,
    ROW_WALL,
    CouplingModel,
    CouplingParams,
    CouplingState,
    CouplingWork,
    access_point,
    apply_contact_reaction,
    contact_floors,
    contact_frames,
    coupling_detect,
    coupling_finish,
    node_access_constraint,
    node_path_constraint,
    node_surface_constraint,
    path_spacing_count,
    project_needle_rows,
    project_onto_path,
    surface_normal,
    suture_contact_rows,
    suture_friction_rows,
    tip_crossing,
    track_sigma,
    xpbd_delta_lambda,
)
from suture_gym.sim.coupling.compliance import diagonal
from suture_gym.sim.mesh import box_tet_grid
from suture_gym.sim.model import TissueModel
from suture_gym.sim.needle import NeedleModel, NeedleState
from suture_gym.sim.quat import quat_from_axis_angle, quat_mul, quat_to_matrix
from suture_gym.sim.rigid import (
    apply_point_impulse,
    point_inv_mass,
    rigid_apply,
    rigid_generalized_inv_mass,
    world_inv_inertia,
)
from suture_gym.sim.rod import RodModel, SutureParams
from suture_gym.sim.scenes import PAPER_TISSUE

#: A bare point-tip coupling: no insertion force model (no tip patch, cutting or exit force), 1 N to puncture,
#: 4 N to tear, 10 N/m axial friction.
POINT_TIP_COUPLING = CouplingParams(puncture_force=1.0, exit_puncture_force=0.0, cutting_force=0.0,
                                    tip_contact_radius=0.0, tear_force=4.0, needle_axial_friction=10.0)

RNG = np.random.default_rng(7)
H = 1e-7  # central-difference step, m


def project_particles(c, grads, inv_mass, alpha_tilde, lam):
    """One XPBD projection of a constraint on point masses (Macklin et al. 2016): ``(dlambda, dx)`` with
    ``dx_i = w_i grad_i C dlambda``; grads (k, 3), inv_mass (k,) 1/kg. The reference the kernels are checked by."""
    w_sum = float(np.einsum("i,ij,ij->", inv_mass, grads, grads))
    dlam = xpbd_delta_lambda(c, w_sum, alpha_tilde, lam)
    return dlam, inv_mass[:, None] * dlam * grads


def _fd_gradient(fn, x, h=H):
    g = np.zeros_like(x)
    for i in np.ndindex(x.shape):
        xp = x.copy()
        xm = x.copy()
        xp[i] += h
        xm[i] -= h
        g[i] = (fn(xp) - fn(xm)) / (2 * h)
    return g


# --- parameters -------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "field, value",
    [
        ("puncture_force", 0.0),
        ("puncture_force", math.nan),
        ("resistance_eps", -1e-3),
        ("path_spacing_min", math.inf),
        ("tear_force", "big"),
        ("needle_axial_friction", -1.0),
        ("max_paths", 0),
        ("max_path_nodes", 2.5),
    ],
)
def test_bad_params_are_named(field, value):
    with pytest.raises(ValueError, match=f"CouplingParams.{field}"):
        CouplingParams(**{field: value})


def test_spacing_order_is_checked():
    with pytest.raises(ValueError, match="path_spacing_min"):
        CouplingParams(path_spacing_min=2e-3, path_spacing_max=1e-3, puncture_force=1.0, exit_puncture_force=0.0,
                       cutting_force=0.0, tip_contact_radius=0.0, tear_force=4.0, needle_axial_friction=10.0)


# --- constraint maths -------------------------------------------------------------------------------------


def _triangle():
    p = np.array([[0.0, 0.0, 0.0], [0.01, 0.001, 0.0], [0.002, 0.012, 0.001]]) + RNG.normal(0, 1e-4, (3, 3))
    return p


def test_node_path_value_and_gradient_match_finite_differences():
    t = np.array([0.3, -0.2, 0.9])
    t /= np.linalg.norm(t)
    tet = RNG.normal(0, 3e-3, (4, 3))
    w = np.array([0.1, 0.2, 0.3, 0.4])
    q = w @ tet + np.array([1e-3, 2e-3, -5e-4])
    x = np.vstack([q[None], tet])

    def c_of(xx):
        return node_path_constraint(xx[0], w @ xx[1:], t)[1]

    ok, c, n = node_path_constraint(q, w @ tet, t)
    assert ok
    assert c == pytest.approx(np.linalg.norm(np.cross(w @ tet - q, t)), rel=1e-12)
    grad = np.vstack([n[None], -w[:, None] * n[None]])
    np.testing.assert_allclose(grad, _fd_gradient(c_of, x), atol=1e-7)
    assert abs(n @ t) < 1e-12


def test_node_path_on_the_line_gives_no_correction():
    t = np.array([0.0, 0.0, 1.0])
    ok, c, n = node_path_constraint(np.array([1.0, 2.0, 7.0]), np.array([1.0, 2.0, 3.0]), t)
    assert not ok and c == 0.0


def test_node_access_value_and_gradient_match_finite_differences():
    pa = np.array([0.0, 0.0, 1e-3])
    pb = np.array([1e-3, 2e-4, -5e-4])
    b = np.array([4e-4, 3e-4, 2e-4])
    rest = float(np.linalg.norm(pb - pa))
    x = np.vstack([pa, pb, b])

    def c_of(xx):
        return node_access_constraint(xx[0], xx[1], xx[2], rest)[1]

    ok, c, ga, gb = node_access_constraint(pa, pb, b, rest)
    assert ok and c > 0
    grad = np.vstack([ga, gb, -(ga + gb)])
    np.testing.assert_allclose(grad, _fd_gradient(c_of, x), atol=1e-7)


def test_node_access_is_zero_when_the_segment_passes_through_the_access_point():
    pa = np.array([0.0, 0.0, 1e-3])
    pb = np.array([1e-3, 2e-4, -5e-4])
    b = pa + 0.37 * (pb - pa)
    ok, c, ga, gb = node_access_constraint(pa, pb, b, float(np.linalg.norm(pb - pa)))
    assert ok and abs(c) < 1e-18
    assert not node_access_constraint(pa, pb, pa.copy(), 1e-3)[0]


@pytest.mark.parametrize("kind", ["triangle", "path", "access"])
def test_particle_projection_conserves_momentum_and_reduces_the_violation(kind):
    mass = RNG.uniform(1e-5, 1e-3, 5)
    if kind == "triangle":
        p = _triangle()
        normal = np.cross(p[1] - p[0], p[2] - p[0])
        normal /= np.linalg.norm(normal)
        bary = np.array([0.2, 0.5, 0.3])
        x = np.vstack([(bary @ p - 4e-4 * normal)[None], p])
        m = mass[:4]

        def evaluate(xx):
            c = node_surface_constraint(xx[0], xx[1], xx[2], xx[3], bary, normal, 0.0)
            return c, np.vstack([normal[None], -bary[:, None] * normal[None]])

    elif kind == "path":
        t = np.array([0.0, 0.6, 0.8])
        tet = RNG.normal(0, 3e-3, (4, 3))
        w = np.array([0.25, 0.25, 0.3, 0.2])
        x = np.vstack([(w @ tet + [1e-3, 0, 0])[None], tet])
        m = mass

        def evaluate(xx):
            ok, c, n = node_path_constraint(xx[0], w @ xx[1:], t)
            return c, np.vstack([n[None], -w[:, None] * n[None]])

    else:
        tri = _triangle()
        bary = np.array([0.2, 0.3, 0.5])
        b = bary @ tri
        pa = b + np.array([1e-3, 1e-3, 1e-3])
        pb = b + np.array([-1e-3, 2e-3, -1e-3])
        rest = float(np.linalg.norm(pb - pa)) * 0.999
        x = np.vstack([pa, pb, tri])
        m = mass

        def evaluate(xx):
            ok, c, ga, gb = node_access_constraint(xx[0], xx[1], bary @ xx[2:], rest)
            gs = -(ga + gb)
            return c, np.vstack([ga, gb, bary[:, None] * gs[None]])

    c0, grads = evaluate(x)
    lam = 0.0
    history = [abs(c0)]
    c = c0
    for _ in range(4):  # repeated projections of the linearised constraint converge (Newton-like)
        dlam, dx = project_particles(c, grads, 1.0 / m, 0.0, lam)
        np.testing.assert_allclose((m[:, None] * dx).sum(axis=0), 0.0, atol=1e-15)
        lam += dlam
        x = x + dx
        c, grads = evaluate(x)
        history.append(abs(c))
    assert history[1] < 0.1 * history[0]
    assert all(b <= a + 1e-15 for a, b in zip(history, history[1:], strict=False))
    assert history[-1] < 1e-6 * history[0]


def test_satisfied_constraints_give_zero_correction():
    dlam, dx = project_particles(0.0, np.ones((3, 3)), np.ones(3), 0.0, 0.0)
    assert dlam == 0.0 and not dx.any()
    assert xpbd_delta_lambda(1.0, 0.0, 0.0, 0.0) == 0.0  # nothing can move


# --- rigid helpers ----------------------------------------------------------------------------------------


def test_rigid_inverse_mass_matches_needle_point_inverse_mass_and_finite_differences():
    model = NeedleModel.from_shape()
    quat = quat_from_axis_angle(np.array([0.3, 1.0, -0.2]), 0.7)
    inv_i = world_inv_inertia(quat, model.body_inv_inertia)
    r = np.array([3e-3, -2e-3, 1e-3])
    n = np.array([0.0, 0.6, 0.8])
    w = rigid_generalized_inv_mass(model.body_inv_mass, inv_i, n, np.cross(r, n))
    assert w == pytest.approx(point_inv_mass(model.body_inv_mass, inv_i, r, n), rel=1e-12)
    # a small impulse along n moves the point along n by w times the impulse (first order)
    pos = np.zeros(3)
    q = quat.copy()
    impulse = 1e-9
    rigid_apply(pos, q, model.body_inv_mass, inv_i, n, np.cross(r, n), impulse)
    moved = pos + quat_to_matrix(q) @ (quat_to_matrix(quat).T @ r) - r
    assert moved @ n == pytest.approx(w * impulse, rel=1e-6)
    pos_ref, quat_ref = apply_point_impulse(np.zeros(3), quat, model.body_inv_mass, inv_i, r, impulse * n)
    np.testing.assert_allclose(pos, pos_ref, atol=1e-20)
    np.testing.assert_allclose(q, quat_ref, atol=1e-15)


# --- path spacing, tracking, projection -------------------------------------------------------------------


@pytest.mark.parametrize(
    "d, expected",
    [
        (0.0, 0),
        (1.19e-3, 0),
        (1.2e-3, 1),
        (1.5e-3, 1),
        (1.7e-3, 1),
        (1.71e-3, 1),
        (3.4e-3, 2),
        (3.5e-3, 2),
        (6.0e-3, 3),
    ],
)
def test_path_spacing_rule(d, expected):
    assert path_spacing_count(d, 1.2e-3, 1.7e-3) == expected


def test_track_sigma_finds_the_crossing_near_the_previous_coordinate():
    # a U-shaped strand: down along x = 0 and back up along x = 1 cm; both legs pass y = 0
    s = np.linspace(0, 1, 41)
    leg1 = np.stack([np.zeros(21), np.zeros(21), -0.01 * s[:21] * 2], axis=1)
    leg2 = np.stack([0.01 * np.ones(20), np.zeros(20), -0.01 + 0.01 * (s[21:] - 0.5) * 2], axis=1)
    strand = np.vstack([leg1, leg2])
    sigma = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(strand, axis=0), axis=1))])
    target = np.array([0.005, 0.0, -0.004])  # equidistant from both legs
    total = sigma[-1]
    s1, d1 = track_sigma(strand, sigma, target, 0.004, 0.004, 0.0, total)
    s2, d2 = track_sigma(strand, sigma, target, total - 0.004, 0.004, 0.0, total)
    assert s1 == pytest.approx(0.004, abs=1e-12) and d1 == pytest.approx(0.005)
    assert s2 > sigma[21] and d2 == pytest.approx(0.005)
    s3, _ = track_sigma(strand, sigma, np.array([0.0, 1e-4, -0.0031]), 0.003, 0.002, 0.0, total)
    assert s3 == pytest.approx(0.0031, abs=1e-12)


def test_track_sigma_bounds_keep_the_coordinate_off_another_branch():
    # a hairpin: the return leg passes 0.2 mm from the target, the leg being tracked 0.5 mm from it
    leg1 = np.stack([np.zeros(11), np.linspace(0.0, 0.01, 11), np.zeros(11)], axis=1)
    leg2 = np.stack([np.full(11, 7e-4), np.linspace(0.01, 0.0, 11), np.zeros(11)], axis=1)
    strand = np.vstack([leg1, leg2])
    sigma = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(strand, axis=0), axis=1))])
    target = np.array([5e-4, 0.005, 0.0])
    free, d_free = track_sigma(strand, sigma, target, 0.005, 0.02, 0.0, sigma[-1])
    assert free > sigma[10] and d_free == pytest.approx(2e-4)  # unbounded, it jumps to the return leg
    bounded, d = track_sigma(strand, sigma, target, 0.005, 0.02, 0.0, sigma[10])
    assert bounded == pytest.approx(0.005) and d == pytest.approx(5e-4)
    windowed, _ = track_sigma(strand, sigma, target, 0.005, 0.002, 0.0, sigma[-1])
    assert windowed == pytest.approx(0.005)


def test_project_onto_path_extends_closed_ends_and_leaves_the_open_tip_free():
    pq = np.array([[0.0, 0, 0], [1e-3, 0, 0], [2e-3, 0, 0]])
    tan = np.tile([1.0, 0, 0], (3, 1))
    ok, slot, u = project_onto_path(np.array([1.5e-3, 1e-4, 0]), 0, 3, pq, tan, False)
    assert ok and slot == 1 and u == pytest.approx(0.5)
    ok, slot, u = project_onto_path(np.array([3e-3, 1e-4, 0]), 0, 3, pq, tan, False)
    assert ok and slot == 1 and u == 1.0
    ok, _, _ = project_onto_path(np.array([3e-3, 1e-4, 0]), 0, 3, pq, tan, True)
    assert not ok
    assert not project_onto_path(np.zeros(3), 0, 1, pq, tan, False)[0]


# --- detection with a kinematic needle through a block -----------------------------------------------------

BLOCK = (0.03, 0.02, 0.02)  # m
CENTRE_HEIGHT = 0.002  # m, needle circle centre above the top face
# Body orientation: shape x -> world -y, shape y -> world +z, shape z -> world -x. The tip starts on the -y
# side pointing down and drives forward as the needle turns about world +x.
Q0 = np.array([0.5, 0.5, -0.5, -0.5])


def _block_tissue():
    mesh = box_tet_grid(BLOCK, (6, 4, 4))
    return TissueModel.from_mesh(mesh, PAPER_TISSUE)


def _needle_pose(model: NeedleModel, angle: float):
    quat = quat_mul(quat_from_axis_angle(np.array([1.0, 0.0, 0.0]), angle), Q0)
    centre = np.array([0.5 * BLOCK[0], 0.5 * BLOCK[1], BLOCK[2] + CENTRE_HEIGHT])
    pos = centre - quat_to_matrix(quat) @ model.arc_center_body
    return NeedleState.at_rest(pos, quat)


def _strand(model: NeedleModel, state: NeedleState) -> np.ndarray:
    return state.body_pos + model.node_pos_body @ quat_to_matrix(state.body_quat).T


def test_orientation_convention_of_the_kinematic_needle():
    needle = NeedleModel.from_shape()
    state = _needle_pose(needle, 0.0)
    x = _strand(needle, state)
    radius = needle.shape.curvature_radius
    np.testing.assert_allclose(x[0], [0.015, 0.01 - radius, BLOCK[2] + CENTRE_HEIGHT], atol=1e-12)
    state = _needle_pose(needle, 0.1)
    assert _strand(needle, state)[0, 2] < BLOCK[2] + CENTRE_HEIGHT  # the tip goes down


def _sweep(params=None, angles=None):
    """Turn a needle (no suture) through the block and run the detection each step; the tip force is set
    above the threshold while the tip has a node-triangle row and is within eps of the surface (standing in
    for the solver's reading of that row's force)."""
    tissue = _block_tissue()
    needle = NeedleModel.from_shape()
    model = CouplingModel.build(tissue, needle, None, params or POINT_TIP_COUPLING)
    state = CouplingState.empty(model)
    work = CouplingWork(model)
    q = tissue.particle_rest_q.copy()
    log = []
    for angle in angles:
        ns = _needle_pose(needle, angle)
        x = _strand(needle, ns)
        pressing = work.row_kind[0] == ROW_ANCHOR and state.strand_sdist[0] < model.params.resistance_eps
        state.tip_force = 2.0 * model.params.puncture_force if pressing else 0.0
        coupling_detect(model, state, work, tissue, q, x)
        log.append(
            (
                angle,
                state.copy(),
                x.copy(),
                {k: np.array(getattr(work, k)) for k in ("row_kind", "access_node", "access_weight", "access_rest")},
                work.access_count,
            )
        )
    return model, tissue, q, log


def test_puncture_path_growth_exit_and_release_by_a_sweeping_needle():
    angles = np.linspace(0.0, 2 * math.pi - 0.1, 700)  # the swage leaves at 2 pi - 0.24
    model, tissue, q, log = _sweep(angles=angles)
    params = model.params
    counts = [s.path_count for _, s, *_ in log]
    punctures = [s.punctures for _, s, *_ in log]
    assert max(punctures) == 1  # one bite
    first = counts.index(1)
    angle, state, x, _, _ = log[first]
    # the entry access point is the tip's closest surface point, on the top face
    entry = access_point(model, q, state.path_entry_tri[0], state.path_entry_bary[0])
    assert entry[2] == pytest.approx(BLOCK[2], abs=1e-12)
    assert np.linalg.norm(entry - x[0]) < 1e-3
    # the path is open and grows while the tip cuts; the exit closes it on the top face again
    closed = next(i for i, (_, s, *_) in enumerate(log) if s.path_count == 1 and not s.path_open[0])
    _, state, x, _, _ = log[closed]
    exit_point = access_point(model, q, state.path_exit_tri[0], state.path_exit_bary[0])
    assert exit_point[2] == pytest.approx(BLOCK[2], abs=1e-12)
    assert exit_point[1] > entry[1] + 0.01
    n = state.path_len[0]
    assert n >= 10
    nodes = np.array([state.pathnode_bary[s] @ q[tissue.tet_indices[state.pathnode_tet[s]]] for s in range(n)])
    spacing = np.linalg.norm(np.diff(nodes, axis=0), axis=1)
    # interior spacing within [l, 2h) (one node per step of at least l; the exit node may be closer)
    assert np.all(spacing[:-1] >= params.path_spacing_min - 1e-12)
    assert np.all(spacing < 2 * params.path_spacing_max)
    # every path node lies on the needle's circle
    centre = np.array([0.5 * BLOCK[0], 0.5 * BLOCK[1], BLOCK[2] + CENTRE_HEIGHT])
    radius = NeedleModel.from_shape().shape.curvature_radius
    np.testing.assert_allclose(np.linalg.norm(nodes[1:-1] - centre, axis=1), radius, atol=2e-5)
    # later the whole needle has passed through: the path is released
    assert counts[-1] == 0 and max(counts) == 1


def test_matching_states_and_rows_while_the_needle_is_through():
    angles = np.linspace(0.0, 2.2, 300)
    model, tissue, q, log = _sweep(angles=angles)
    angle, state, x, rows, access_count = log[-1]
    assert state.path_count == 1 and state.path_open[0]  # the tip is still inside
    sigma = model.strand_sigma
    inside = sigma < state.path_sigma_entry[0]
    assert state.strand_status[0] == NODE_HEAD
    assert np.all(state.strand_status[1:][inside[1:]] == NODE_IN)
    assert np.all(state.strand_status[~inside] == NODE_OUT)
    # the strand coordinate at the entry is where the needle crosses the top face
    entry = access_point(model, q, state.path_entry_tri[0], state.path_entry_bary[0])
    j = int(np.searchsorted(sigma, state.path_sigma_entry[0]) - 1)
    assert x[j, 2] <= BLOCK[2] + 1e-9 <= x[j + 1, 2] + 2e-9 or x[j + 1, 2] <= BLOCK[2] + 1e-9 <= x[j, 2] + 2e-9
    s_frac = (state.path_sigma_entry[0] - sigma[j]) / (sigma[j + 1] - sigma[j])
    assert np.linalg.norm(x[j] + s_frac * (x[j + 1] - x[j]) - entry) < 1e-4
    # rows: IN nodes behind the last path node are held on the path, the HEAD has none, the access
    # segment is the one holding sigma_entry
    kinds = rows["row_kind"]
    assert kinds[0] == ROW_NONE
    assert np.count_nonzero(kinds == ROW_PATH) >= 10
    assert np.all(kinds[~inside] != ROW_PATH)
    assert access_count == 1
    # the access row's strand piece is centred on sigma_entry, half a segment either side
    nodes, weights = rows["access_node"][0], rows["access_weight"][0]
    ends = [
        weights[0] * sigma[nodes[0]] + weights[1] * sigma[nodes[1]],
        weights[2] * sigma[nodes[2]] + weights[3] * sigma[nodes[3]],
    ]
    half = 0.5 * (sigma[j + 1] - sigma[j])
    assert ends == pytest.approx([state.path_sigma_entry[0] - half, state.path_sigma_entry[0] + half], abs=1e-12)
    assert rows["access_rest"][0] == pytest.approx(2 * half)


def test_the_strand_end_stays_in_its_path_once_it_has_gone_in_through_the_entry():
    """The entry coordinate cannot pass the strand's end, so once the end (here the swage of a needle without
    thread; a thread's free end alike) has gone in through the entry, ``sigma_entry`` sits on it. The end node,
    inside the tissue, must stay IN its path with a node-path row: as OUT it got a contact row from the inside,
    which kicked it at the surface (a thread's free end pulled through a pad pulled 1-12 N with no friction and
    diverged)."""
    model, _, _, log = _sweep(angles=np.linspace(0.0, 2 * math.pi - 0.1, 700))
    end = model.strand_sigma[-1]
    inside = [(s, rows) for _, s, _, rows, _ in log
              if s.path_count == 1 and not s.path_open[0] and s.path_sigma_entry[0] == end
              and s.strand_sdist[-1] < 0.0]  # fmt: skip
    assert len(inside) >= 10
    for state, rows in inside:
        assert state.strand_status[-1] == NODE_IN and state.strand_path[-1] == 0
        assert rows["row_kind"][-1] == ROW_PATH


def test_no_puncture_below_the_threshold_keeps_the_tip_anchored():
    tissue = _block_tissue()
    needle = NeedleModel.from_shape()
    model = CouplingModel.build(tissue, needle, None, POINT_TIP_COUPLING)
    state = CouplingState.empty(model)
    work = CouplingWork(model)
    q = tissue.particle_rest_q
    angle = math.asin((CENTRE_HEIGHT - 1e-4) / needle.shape.curvature_radius)  # tip 0.1 mm above the top
    x = _strand(needle, _needle_pose(needle, angle))
    state.tip_force = 0.99 * model.params.puncture_force
    coupling_detect(model, state, work, tissue, q, x)
    assert state.path_count == 0 and not state.punctured
    assert work.row_kind[0] == ROW_ANCHOR and state.strand_status[0] == NODE_HEAD
    assert state.strand_sdist[0] == pytest.approx(1e-4, abs=1e-9)
    # the anchor is the tip's closest surface point; its normal is the smooth one there (tilted towards the
    # y = 0 face, 1.7 mm away, by the blend of vertex normals)
    assert work.row_tri[0] == state.tip_anchor_tri == state.strand_tri[0]
    np.testing.assert_array_equal(state.tip_anchor_bary, state.strand_bary[0])
    n = work.row_contact_normal[0]
    assert np.linalg.norm(n) == pytest.approx(1.0) and n[0] == pytest.approx(0.0, abs=1e-12)
    assert 0.8 < n[2] < 1.0 and n[1] < 0.0
    anchor = access_point(model, q, state.tip_anchor_tri, state.tip_anchor_bary)
    state.tip_force = model.params.puncture_force
    coupling_detect(model, state, work, tissue, q, x)
    assert state.punctured and work.row_kind[0] == ROW_NONE and state.tip_anchor_tri == -1
    entry = access_point(model, q, state.path_entry_tri[0], state.path_entry_bary[0])
    np.testing.assert_array_equal(entry, anchor)  # the path starts where the tip engaged the surface


def test_retracted_tip_releases_its_open_path():
    angles = np.concatenate([np.linspace(0.0, 0.6, 80), np.linspace(0.6, 0.0, 80)])
    _, _, _, log = _sweep(angles=angles)
    assert max(s.path_count for _, s, *_ in log) == 1
    assert log[-1][1].path_count == 0 and log[-1][1].pathnode_count == 0


def test_buffers_overflow_is_flagged_not_raised():
    angles = np.linspace(0.0, 2.0, 200)
    _, _, _, log = _sweep(params=replace(POINT_TIP_COUPLING, max_path_nodes=4), angles=angles)
    state = log[-1][1]
    assert state.overflow and state.pathnode_count == 4


def test_snapshot_copy_is_deep_and_detection_is_deterministic():
    angles = np.linspace(0.0, 2.5, 150)
    _, _, _, log_a = _sweep(angles=angles)
    _, _, _, log_b = _sweep(angles=angles)
    for (_, sa, _xa, ra, ca), (_, sb, _xb, rb, cb) in zip(log_a, log_b, strict=True):
        for name, value in vars(sa).items():
            other = getattr(sb, name)
            if isinstance(value, np.ndarray):
                assert value.tobytes() == other.tobytes(), name
            else:
                assert value == other, name
        assert ca == cb and ra["row_kind"].tobytes() == rb["row_kind"].tobytes()
    state = log_a[-1][1]
    snap = state.copy()
    state.pathnode_bary[:] = 7.0
    state.path_count = 99
    assert not np.any(snap.pathnode_bary == 7.0) and snap.path_count != 99


def test_suture_extends_the_strand_coordinates():
    tissue = _block_tissue()
    needle = NeedleModel.from_shape()
    suture = RodModel.from_params(SutureParams(length=0.05, node_count=51))
    model = CouplingModel.build(tissue, needle, suture, POINT_TIP_COUPLING)
    nn = needle.node_count
    assert model.strand_node_count == nn + 50
    chord = np.linalg.norm(np.diff(needle.node_pos_body, axis=0), axis=1).sum()
    assert model.strand_length == pytest.approx(chord + 0.05)
    np.testing.assert_allclose(np.diff(model.strand_sigma[nn - 1 :]), 1e-3)
    assert model.strand_friction[nn:].max() == 0.0
    assert model.strand_friction[:nn].sum() == pytest.approx(model.params.needle_axial_friction * chord)
    status = CouplingState.empty(model).strand_status
    assert status[0] == NODE_HEAD and np.all(status[1:] == NODE_OUT)
    assert model.knot_sigma == np.inf


def test_knot_sits_knot_tail_from_the_free_end_and_bad_tails_are_named():
    tissue = _block_tissue()
    needle = NeedleModel.from_shape()
    suture = RodModel.from_params(SutureParams(length=0.05, node_count=51))
    model = CouplingModel.build(tissue, needle, suture, POINT_TIP_COUPLING, knot_tail=0.008)
    assert model.knot_sigma == pytest.approx(model.strand_length - 0.008)
    for bad in (-1e-3, 0.05, float("nan")):
        with pytest.raises(ValueError, match="knot_tail"):
            CouplingModel.build(tissue, needle, suture, knot_tail=bad)
    with pytest.raises(ValueError, match="knot_tail"):
        CouplingModel.build(tissue, needle, None, knot_tail=0.008)  # no thread to tie it in


# --- contact frames, floors, the tip's anchor, tear bound, rigid supports -----------------------------------


def test_node_surface_constraint_value_and_gradient_match_finite_differences():
    p = _triangle()
    bary = np.array([0.2, 0.5, 0.3])
    normal = np.array([0.36, -0.48, 0.8])
    q = bary @ p + np.array([2e-4, -1e-4, 3e-4])
    x = np.vstack([q[None], p])

    def c_of(xx):
        return node_surface_constraint(xx[0], xx[1], xx[2], xx[3], bary, normal, 3e-4)

    assert c_of(x) == pytest.approx((q - bary @ p) @ normal - 3e-4, abs=1e-18)
    grad = np.vstack([normal[None], -bary[:, None] * normal[None]])
    np.testing.assert_allclose(grad, _fd_gradient(c_of, x), atol=1e-8)


def test_surface_normal_is_the_face_normal_on_flat_ground_and_continuous_across_edges():
    tissue = _block_tissue()
    surface = CouplingModel.build(tissue, NeedleModel.from_shape(), None, POINT_TIP_COUPLING).surface
    q = tissue.particle_rest_q
    tv = surface.tri_vertices
    args = (tv, surface.vertex_tri_start, surface.vertex_tri_index, q)
    # a top-face triangle away from the block's edges: its vertex normals all point up
    centroid = q[tv].mean(axis=1)
    top = np.flatnonzero(
        (np.abs(q[tv][:, :, 2] - BLOCK[2]) < 1e-12).all(axis=1)
        & (np.abs(centroid[:, 0] - 0.5 * BLOCK[0]) < 6e-3)
        & (np.abs(centroid[:, 1] - 0.5 * BLOCK[1]) < 4e-3)
    )
    assert top.size
    np.testing.assert_allclose(surface_normal(top[0], np.array([0.2, 0.3, 0.5]), *args), [0.0, 0.0, 1.0], atol=1e-12)
    # on an edge shared by a top-face and a side-face triangle the normal is the same seen from either
    checked = 0
    for t in range(tv.shape[0]):
        for k in range(3):
            other = surface.tri_neighbors[t, k]
            n_t = np.cross(q[tv[t, 1]] - q[tv[t, 0]], q[tv[t, 2]] - q[tv[t, 0]])
            n_o = np.cross(q[tv[other, 1]] - q[tv[other, 0]], q[tv[other, 2]] - q[tv[other, 0]])
            if np.cross(n_t, n_o) @ np.cross(n_t, n_o) < 1e-20:
                continue  # coplanar neighbours
            a, b = tv[t, k], tv[t, (k + 1) % 3]
            bary_t = np.zeros(3)
            bary_t[k], bary_t[(k + 1) % 3] = 0.4, 0.6
            bary_o = np.zeros(3)
            bary_o[list(tv[other]).index(a)], bary_o[list(tv[other]).index(b)] = 0.4, 0.6
            np.testing.assert_allclose(
                surface_normal(t, bary_t, *args), surface_normal(other, bary_o, *args), atol=1e-12
            )
            checked += 1
    assert checked > 10


def test_a_contact_row_on_a_collapsed_neighbourhood_is_dropped():
    tissue = _block_tissue()
    surface = CouplingModel.build(tissue, NeedleModel.from_shape(), None, POINT_TIP_COUPLING).surface
    q = np.full_like(tissue.particle_rest_q, 0.004)  # every vertex at one point: no normal anywhere
    tv = surface.tri_vertices
    n = surface_normal(0, np.full(3, 1.0 / 3.0), tv, surface.vertex_tri_start, surface.vertex_tri_index, q)
    assert not n.any()
    kind = np.array([ROW_TRIANGLE, ROW_PATH], np.int8)
    normals = np.zeros((2, 3))
    contact_frames(
        kind, np.zeros(2, np.int32), np.full((2, 3), 1.0 / 3.0), np.zeros(tv.shape[0], np.bool_), tv,
        surface.vertex_tri_start, surface.vertex_tri_index, q, np.zeros((2, 3)), normals,
    )  # fmt: skip
    assert kind.tolist() == [ROW_NONE, ROW_PATH] and not normals.any()



def test_a_node_past_the_edge_of_a_rigid_face_is_pushed_along_the_distance_gradient():
    """A rigid (clamped) end face x = 0.01 ending at z = 0.008: a node beside it gets the face normal, a node
    above its top edge the direction from the edge to it, not the face normal, which would hold the node to
    the face's plane beyond the end of the face (a thread sliding over the edge snagged on it)."""
    tv = np.array([[0, 1, 2]], np.int32)
    q = np.array([[0.01, 0.0, 0.008], [0.01, 0.0, 0.0], [0.01, 0.01, 0.008]])  # normal +x (right-handed)
    bary = np.array([[0.5, 0.0, 0.5], [0.25, 0.5, 0.25], [0.5, 0.0, 0.5], [0.5, 0.0, 0.5]])  # edge, inside
    strand = np.array([[0.0103, 0.005, 0.009], [0.011, 0.0025, 0.004], [0.0098, 0.005, 0.0079], [0.0103, 0.005, 0.009]])
    kind = np.array([ROW_TRIANGLE, ROW_TRIANGLE, ROW_TRIANGLE, ROW_WALL], np.int8)
    normals = np.zeros((4, 3))
    empty = np.zeros(0, np.int32)
    contact_frames(kind, np.zeros(4, np.int32), bary, np.ones(1, np.bool_), tv, empty, empty, q, strand, normals)
    edge_to_node = strand[0] - (0.5 * q[0] + 0.5 * q[2])
    np.testing.assert_allclose(normals[0], edge_to_node / np.linalg.norm(edge_to_node))
    assert normals[0][2] > 0.9  # mostly up: the node can slide over the edge
    np.testing.assert_allclose(normals[1], [1.0, 0.0, 0.0])  # in front of the face: its normal
    np.testing.assert_allclose(normals[2], [1.0, 0.0, 0.0])  # behind it (a crossing row): its normal
    np.testing.assert_allclose(normals[3], [-1.0, 0.0, 0.0])  # a row from the inside: turned inward

def _floor(start_height, depenetration, eps=3e-4):
    """contact_floors for one needle node (body origin) that starts ``start_height`` above a z = 0 triangle."""
    tri = np.array([[0, 1, 2]], dtype=np.int32)
    tissue_q = np.array([[-0.01, -0.01, 0.0], [0.02, -0.01, 0.0], [-0.01, 0.02, 0.0]])
    out = np.full(1, np.nan)
    rows = (np.array([ROW_TRIANGLE], np.int8), np.zeros(1, np.int32), np.full((1, 3), 1.0 / 3.0),
            np.array([[0.0, 0.0, 1.0]]), out)  # fmt: skip
    needle_start = (np.array([0.0, 0.0, start_height]), np.array([1.0, 0.0, 0.0, 0.0]), np.zeros((1, 3)))
    contact_floors(1, eps, depenetration, rows, tri, needle_start, np.zeros((0, 3)), tissue_q)
    return float(out[0])


def test_contact_floors_bound_only_penetrations_older_than_the_substep():
    assert _floor(1e-3, 1e-4) == 0.0  # started outside: the whole penetration is removed
    assert _floor(3e-4, 1e-4) == 0.0  # started exactly eps out
    assert _floor(-1e-3, 1e-4) == pytest.approx(-1e-3 - 3e-4 + 1e-4)  # started 1.3 mm in: 0.1 mm out per substep
    assert _floor(2.5e-4, 1e-4) == 0.0  # within reach: fully resolved


def no_patch():
    """An empty tip contact patch (``CouplingWork.tip_patch``): the anchor is a point of its triangle."""
    return (np.zeros(4, np.int32), np.zeros(4), np.zeros(1, np.int64), np.zeros(3), np.zeros(1))


def no_cut():
    """No cutting row (``CouplingWork.cut_rows`` with cap 0)."""
    return (np.zeros(4, np.int32), np.zeros(4), np.zeros(3), np.zeros(1), np.zeros(1))


def _anchor_projection(friction, offset, penetration=1e-4, eps=3e-4):
    """Project one anchor row of the default needle's tip against a static (pinned) triangle whose anchor
    point lies ``offset`` (m) along +x of the tip's foot and ``penetration`` (m) above the contact layer."""
    needle = NeedleModel.from_shape()
    pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    tip = pos + needle.node_pos_body[0]
    normal = np.array([0.0, 0.0, 1.0])
    anchor = tip - (eps - penetration) * normal + np.array([offset, 0.0, 0.0])
    tissue_q = anchor + np.array([[-1e-3, -1e-3, 0.0], [2e-3, -1e-3, 0.0], [-1e-3, 2e-3, 0.0]])
    nn = needle.node_count
    kind = np.zeros(nn, np.int8)
    kind[0] = ROW_ANCHOR
    bary = np.full((nn, 3), 1.0 / 3.0)
    normals = np.tile(normal, (nn, 1))
    lam, lam_t, slip = np.zeros(nn), np.zeros(nn), np.zeros(4)
    project_needle_rows(
        (nn, needle.body_inv_mass, needle.body_inv_inertia, needle.node_pos_body, pos.copy(), quat.copy()),
        (diagonal(np.zeros(3)), tissue_q.copy(), np.array([[0, 1, 2]], np.int32)),
        (np.zeros(nn), eps, 1e-3, friction, 4.0),
        (kind, np.zeros(nn, np.int32), bary, normals, np.zeros(nn), np.zeros((nn, 8), np.int32), np.zeros((nn, 8)),
         np.zeros((nn, 3)), lam, lam_t, no_patch(), no_cut(), np.zeros((nn, 3))),
        slip, pos, quat, tissue_q,
    )  # fmt: skip
    new_tip = pos + quat_to_matrix(quat) @ needle.node_pos_body[0]
    return new_tip - anchor, lam[0], slip


def test_anchored_tip_sticks_inside_the_friction_cone_and_slides_outside():
    # the tip 0.1 mm into the contact layer and 20 um beside its anchor: within a cone of friction 1 it is
    # put back eps over the anchor (normal and friction solved together for the rigid needle; exact to first
    # order in the needle's turn, so to 0.5 um here)
    rel, lam_n, slip = _anchor_projection(friction=1.0, offset=2e-5)
    assert lam_n > 0.0 and 0.0 < np.linalg.norm(slip[:3]) < lam_n
    np.testing.assert_allclose(rel, [0.0, 0.0, 3e-4], atol=5e-7)
    assert slip[3] == 0.0 and slip[0] > 0.0  # the friction impulse pulls the tip towards +x
    # with friction 0.05 the tip slides: the friction impulse sits on the cone, the offset is only reduced,
    # and the tip is still put eps over the surface
    rel, lam_n, slip = _anchor_projection(friction=0.05, offset=2e-5)
    assert np.linalg.norm(slip[:3]) == pytest.approx(0.05 * lam_n, rel=1e-12)
    assert 5e-6 < slip[3] < 2e-5 and np.hypot(rel[0], rel[1]) == pytest.approx(slip[3], abs=5e-7)
    assert rel[2] == pytest.approx(3e-4, abs=5e-7)


def _path_row_projection(offsets, tear=0.5, dt=1e-3):
    """Project the path row of the default needle's node 5, whose path point is a pinned vertex at ``offset``
    (3,) m from the node (tangent +z), once per offset in ``offsets`` (the vertex moved between projections, the
    row's impulse kept). Returns ``(row_lambda[5], row_impulse[5], gap m)``."""
    needle = NeedleModel.from_shape()
    nn = needle.node_count
    pos, quat = np.zeros(3), np.array([1.0, 0.0, 0.0, 0.0])
    kind = np.zeros(nn, np.int8)
    kind[5] = ROW_PATH
    idx = np.zeros((nn, 8), np.int32)
    idx[5] = [0, 1, 2, 3, 0, 1, 2, 3]
    weight = np.zeros((nn, 8))
    weight[5, :4] = [1.0, 0.0, 0.0, 0.0]  # the path point is vertex 0 (held fixed)
    tangent = np.tile([0.0, 0.0, 1.0], (nn, 1))
    lam, impulse = np.zeros(nn), np.zeros((nn, 3))
    rows = (kind, np.zeros(nn, np.int32), np.zeros((nn, 3)), np.zeros((nn, 3)), np.zeros(nn), idx, weight, tangent, lam,
            np.zeros(nn), no_patch(), no_cut(), impulse)  # fmt: skip
    for offset in offsets:
        node = pos + quat_to_matrix(quat) @ needle.node_pos_body[5]
        tissue_q = node + np.array(offset) + np.array([[0.0, 0.0, 0.0], [0.0, 1e-3, 0.0], [0.0, 0.0, 1e-3],
                                                       [1e-3, 0.0, 0.0]])  # fmt: skip
        project_needle_rows(
            (nn, needle.body_inv_mass, needle.body_inv_inertia, needle.node_pos_body, pos.copy(), quat.copy()),
            (diagonal(np.zeros(4)), tissue_q.copy(), np.zeros((1, 3), np.int32)), (np.zeros(nn), 3e-4, dt, 0.0, tear),
            rows, np.zeros(4), pos, quat, tissue_q,
        )  # fmt: skip
    gap = np.linalg.norm((pos + quat_to_matrix(quat) @ needle.node_pos_body[5] - tissue_q[0])[:2])
    return lam[5], impulse[5], gap


def test_a_path_row_transmits_at_most_the_tear_force():
    lam, impulse, gap = _path_row_projection([[2e-3, 0.0, 0.0]])  # the path point 2 mm from the node along x
    assert lam == pytest.approx(-0.5e-6, rel=1e-12)  # tear force 0.5 N at 1 ms
    np.testing.assert_allclose(impulse, [0.5e-6, 0.0, 0.0], rtol=1e-12, atol=1e-20)  # pulling the node along +x
    assert gap > 1e-3  # the tissue gave way: the row could not pull node and path together


def test_a_path_row_bounds_and_reads_its_summed_impulse_not_the_sum_of_its_steps():
    """The row's direction turns with the node's offset from the path: pulled 10 um one way, then back, it has
    given the needle nearly nothing in sum, and that (not the sum of its steps' sizes) is what it reads and what
    the tear force bounds."""
    lam, impulse, _ = _path_row_projection([[1e-5, 0.0, 0.0], [-1e-5, 0.0, 0.0]], tear=100.0)
    one, _, _ = _path_row_projection([[1e-5, 0.0, 0.0]], tear=100.0)
    assert lam == pytest.approx(-np.linalg.norm(impulse), rel=1e-12)
    assert abs(lam) < 0.1 * abs(one)  # a scalar sum of the two steps would read about 2 |one|
    # bounded by its size: pulled 2 mm one way with a tear force of 0.5 N, then back 10 um, it reads under 0.5 N
    lam, _, _ = _path_row_projection([[2e-3, 0.0, 0.0], [-1e-5, 0.0, 0.0]])
    assert abs(lam) < 0.5e-6


def test_an_exit_is_a_crossing_ahead_of_the_entry_at_its_strand_coordinate():
    """:func:`tip_crossing` for an exit: the strand (a U through the block's top face, the tip's segment crossing
    out, the entry ten segments up) crosses at the tip's segment, at that segment's coordinate; where the only
    crossing is the entry's (the front of the strand outside, the rest inside), an exit must not take it: the
    tip's closest point, at coordinate 0, instead (the whole-needle search used to return the entry)."""
    tissue = _block_tissue()
    model = CouplingModel.build(tissue, NeedleModel.from_shape(), None, POINT_TIP_COUPLING)
    state, work = CouplingState.empty(model), CouplingWork(model)
    top = BLOCK[2]
    depth = np.array([0.3, -0.3, -1.0, -2.0, -3.0, -3.0, -3.0, -3.0, -2.0, -1.0, -0.5, 0.5, 1.0])
    strand = np.zeros((model.strand_node_count, 3))
    strand[:, 0] = 0.01 + 1e-3 * np.arange(model.strand_node_count) * 0.5
    strand[:, 1] = 0.01
    strand[:, 2] = top + 1e-3
    strand[: depth.size, 2] = top + 1e-3 * depth
    work.strand_q[:] = strand
    sigma = model.strand_sigma
    q = tissue.particle_rest_q
    entry = sigma[10] + 0.5 * (sigma[11] - sigma[10])  # the U's way out, halfway along segment 10
    tri, _, at = tip_crossing(model, state, work, q, entry)
    assert tri >= 0 and at == pytest.approx(0.5 * sigma[1], rel=1e-9)  # halfway along the tip's segment
    work.strand_q[:, 2] = top - 1e-3  # now the front ten nodes outside, the rest inside: only the entry crosses
    work.strand_q[:10, 2] = top + 0.5e-3
    entry = sigma[9] + (sigma[10] - sigma[9]) / 3.0
    _, _, at = tip_crossing(model, state, work, q)
    assert at == pytest.approx(entry, rel=1e-9)  # without the bound: the entry's own crossing
    state.strand_tri[0], state.strand_bary[0] = 7, [0.2, 0.3, 0.5]
    tri, bary, at = tip_crossing(model, state, work, q, entry)
    assert (tri, at) == (7, 0.0) and np.allclose(bary, [0.2, 0.3, 0.5])


def _pinned_bottom_block():
    mesh = box_tet_grid(BLOCK, (6, 4, 4))
    return TissueModel.from_mesh(mesh, PAPER_TISSUE, pinned=mesh.vertices[:, 2] == 0.0)


@pytest.mark.parametrize("upward", [True, False])
def test_a_node_crossing_a_rigid_face_gets_a_row_keeping_it_on_its_side(upward):
    tissue = _pinned_bottom_block()
    needle = NeedleModel.from_shape()
    model = CouplingModel.build(tissue, needle, None, POINT_TIP_COUPLING)
    assert model.tri_rigid.sum() == 2 * 6 * 4  # the bottom face, and only it
    state, work = CouplingState.empty(model), CouplingWork(model)
    q = tissue.particle_rest_q
    x = np.tile([0.5, 0.5, 0.5], (needle.node_count, 1))  # far away: skipped by the broad phase
    x[7] = [0.011, 0.007, 1e-3 if upward else -1e-3]
    start = x.copy()
    start[7, 2] = -x[7, 2]
    coupling_detect(model, state, work, tissue, q, x, start)
    assert model.tri_rigid[work.row_tri[7]]
    if upward:  # from under the base into the tissue: kept out, below the base
        assert work.row_kind[7] == ROW_TRIANGLE
        np.testing.assert_allclose(work.row_contact_normal[7], [0.0, 0.0, -1.0], atol=1e-12)
    else:  # from inside through the base: kept in
        assert work.row_kind[7] == ROW_WALL
        np.testing.assert_allclose(work.row_contact_normal[7], [0.0, 0.0, 1.0], atol=1e-12)
    np.testing.assert_allclose(
        access_point(model, q, work.row_tri[7], work.row_bary[7]), [0.011, 0.007, 0.0], atol=1e-12
    )
    # without the start positions the node only sees its closest face: it would be pushed out downwards,
    # through the base, when it came from inside
    coupling_detect(model, state, work, tissue, q, x)
    assert work.row_kind[7] == ROW_TRIANGLE
    np.testing.assert_allclose(work.row_contact_normal[7], [0.0, 0.0, -1.0], atol=1e-12)


def test_contacts_never_tear_and_a_push_against_a_rigid_face_is_not_tissue_force():
    tissue = _pinned_bottom_block()
    needle = NeedleModel.from_shape()
    model = CouplingModel.build(tissue, needle, None, POINT_TIP_COUPLING)
    state, work = CouplingState.empty(model), CouplingWork(model)
    rigid, soft = np.flatnonzero(model.tri_rigid)[0], np.flatnonzero(~model.tri_rigid)[0]
    dt = 1e-3
    work.row_kind[5], work.row_tri[5], work.row_lambda[5] = ROW_TRIANGLE, rigid, 10.0 * dt * dt  # 10 N on the base
    work.row_kind[6], work.row_tri[6], work.row_lambda[6] = ROW_TRIANGLE, soft, 0.5 * dt * dt  # 0.5 N on tissue
    coupling_finish(model, state, work, dt, np.array([0.0, 0.0, -1.0]))
    assert state.max_force == pytest.approx(0.5) and not state.damaged
    tear = model.params.tear_force
    work.row_lambda[6] = 1.5 * tear * dt * dt  # a contact on the tissue over the tear force: read, but no cut
    coupling_finish(model, state, work, dt, np.array([0.0, 0.0, -1.0]))
    assert state.max_force == pytest.approx(1.5 * tear) and not state.damaged


@pytest.mark.parametrize("row", ["path", "access"])
def test_a_row_holding_a_strand_at_the_tear_force_damages_the_tissue(row):
    model = CouplingModel.build(_pinned_bottom_block(), NeedleModel.from_shape(), None, POINT_TIP_COUPLING)
    state, work = CouplingState.empty(model), CouplingWork(model)
    dt, tear = 1e-3, model.params.tear_force
    lam = -tear * dt * dt  # the cap of such a row (its multiplier is kept above -tear_force dt^2)
    if row == "path":
        work.row_kind[8], work.row_lambda[8] = ROW_PATH, 0.99 * lam
    else:
        work.access_count, work.access_lambda[0] = 1, 0.99 * lam
    coupling_finish(model, state, work, dt, np.array([0.0, 0.0, -1.0]))
    assert state.max_force == pytest.approx(0.99 * tear) and not state.damaged
    if row == "path":
        work.row_lambda[8] = lam
    else:
        work.access_lambda[0] = lam
    coupling_finish(model, state, work, dt, np.array([0.0, 0.0, -1.0]))
    assert state.damaged and state.max_force == pytest.approx(tear)


def test_the_tip_never_punctures_a_rigid_face():
    tissue = _pinned_bottom_block()
    needle = NeedleModel.from_shape()
    model = CouplingModel.build(tissue, needle, None, POINT_TIP_COUPLING)
    state, work = CouplingState.empty(model), CouplingWork(model)
    q = tissue.particle_rest_q
    x = np.tile([0.5, 0.5, 0.5], (needle.node_count, 1))
    x[0] = [0.011, 0.007, -1e-4]  # the tip 0.1 mm under the base, pressing it hard
    state.tip_force = 100.0 * model.params.puncture_force
    for _ in range(2):
        coupling_detect(model, state, work, tissue, q, x)
        assert work.row_kind[0] == ROW_ANCHOR and model.tri_rigid[state.tip_anchor_tri]
    assert state.punctures == 0 and state.path_count == 0


def test_a_suture_node_gets_the_more_violated_of_its_tissue_row_and_a_static_obstacle():
    """One contact row per suture node: where a static obstacle's gap is the smaller one (a node in a wound gap
    sunk into the base, beside the wound face) the obstacle keeps the row and the tissue takes no reaction."""
    nn, eps = 1, 1.0e-4
    tri_vertices = np.array([[0, 1, 2]], dtype=np.int32)
    tissue_q = np.array([[0.0, 0.0, 0.0], [1.0e-3, 0.0, 0.0], [0.0, 0.0, 1.0e-3]])  # a wall y = 0, normal +y
    row_kind = np.array([ROW_NONE, ROW_TRIANGLE, ROW_TRIANGLE])
    rows = (row_kind, np.zeros(3, np.int32), np.full((3, 3), 1.0 / 3.0), np.tile([0.0, 1.0, 0.0], (3, 1)), np.zeros(3))
    suture_q = np.array([[0.0, 5e-3, 5e-3], [2e-4, 3e-4, 2e-4], [2e-4, 3e-4, 2e-4]])  # nodes 1, 2: 0.2 mm off the wall
    obstacle_gap = np.array([np.inf, 1.0e-3, -1.0e-4])  # node 1 well above the base, node 2 sunk into it
    gap, normal = obstacle_gap.copy(), np.tile([0.0, 0.0, 1.0], (3, 1))
    tissue_w, is_tissue = np.zeros(3), np.zeros(3, dtype=np.bool_)
    tissue = diagonal(np.full(3, 2.0))
    suture_contact_rows(nn, eps, rows, tri_vertices, tissue_q, tissue, suture_q, gap, normal, tissue_w, is_tissue)
    np.testing.assert_array_equal(is_tissue, [False, True, False])
    assert gap[1] == pytest.approx(3e-4 - eps) and normal[1] == pytest.approx([0.0, 1.0, 0.0])
    assert tissue_w[1] == pytest.approx(3 * (1.0 / 3.0) ** 2 * 2.0)
    assert gap[2] == obstacle_gap[2] and normal[2] == pytest.approx([0.0, 0.0, 1.0]) and tissue_w[2] == 0.0
    z, row_lambda, moved = np.zeros((3, 7)), np.zeros(3), tissue_q.copy()
    z[2, 6] = 1.0e-9  # the obstacle's push on node 2 is not the tissue's to take
    apply_contact_reaction(nn, rows, tri_vertices, normal, z, is_tissue, tissue, row_lambda, moved)
    np.testing.assert_array_equal(moved, tissue_q)
    assert row_lambda[2] == 0.0
    z[1, 6] = 1.0e-9  # the tissue row's push on node 1 is
    apply_contact_reaction(nn, rows, tri_vertices, normal, z, is_tissue, tissue, row_lambda, moved)
    assert row_lambda[1] == 1.0e-9 and np.all(moved[:, 1] < 0.0)


def test_a_path_node_gets_its_friction_row_unless_a_static_obstacle_holds_it():
    """Thread friction rows beside a static obstacle (the base under a pad): the obstacle gives every free node
    a finite gap however far it is, which kept every friction row out (the thread had no friction in any scene
    with a base). A path node above the base (gap > 0) gets its friction row along the path's tangent with the
    cap ``strand_friction dt^2``; one sunk into the base (gap < 0) keeps the obstacle's contact row."""
    nn, dt = 1, 1.0e-3
    row_kind = np.array([ROW_NONE, ROW_PATH, ROW_PATH], dtype=np.int8)
    row_tissue = np.zeros((3, PATH_ROW_VERTICES), np.int32)
    row_weight = np.zeros((3, PATH_ROW_VERTICES))
    row_weight[:, 0] = 1.0
    row_tangent = np.tile([0.0, 1.0, 0.0], (3, 1))
    strand_friction = np.array([0.0, 0.03, 0.03])  # N: 30 N/m times 1 mm of thread
    suture_q = np.array([[0.0, -1e-3, 4e-3], [0.0, 1e-3, 4e-3], [0.0, 2e-3, 4e-3]])
    tissue_q = np.zeros((1, 3))
    rows = (strand_friction, row_kind, row_tissue, row_weight, row_tangent, suture_q.copy(), tissue_q.copy(), dt)
    obstacle_gap = np.array([4e-3, 4e-3, -1e-5])  # the base 4 mm below nodes 0 and 1; node 2 sunk into it
    gap, normal = obstacle_gap.copy(), np.tile([0.0, 0.0, 1.0], (3, 1))
    tissue_w, cap = np.zeros(3), np.zeros(3)
    suture_friction_rows(nn, rows, tissue_q, diagonal(np.full(1, 2.0)), suture_q, gap, normal, tissue_w, cap)
    assert cap[1] == pytest.approx(0.03 * dt * dt) and gap[1] == 0.0 and normal[1] == pytest.approx([0.0, 1.0, 0.0])
    assert tissue_w[1] == pytest.approx(2.0)
    assert cap[2] == 0.0 and gap[2] == obstacle_gap[2] and normal[2] == pytest.approx([0.0, 0.0, 1.0])
    assert cap[0] == 0.0 and gap[0] == obstacle_gap[0]


def test_rigid_rows_take_each_nodes_first_rigid_crossing():
    """Of a node's crossings only rigid faces count, the first by ``t`` (then triangle) wins, as in
    segment_crossings' sorted order; the crossings arrive unsorted from the kernel."""
    from suture_gym.sim.coupling.detection import _rigid_rows
    from suture_gym.sim.coupling.params import ROW_NONE, ROW_TRIANGLE, ROW_WALL

    tri_rigid = np.array([False, True, True, True])
    segment = np.array([1, 1, 1, 0, 2, 1], np.int32)
    tri = np.array([0, 3, 2, 1, 0, 1], np.int32)  # node 1: rigid 3 and 2 at t 0.5, rigid 1 at t 0.7; tri 0 soft
    t = np.array([0.1, 0.5, 0.5, 0.9, 0.2, 0.7])
    bary = np.arange(18, dtype=float).reshape(6, 3)
    direction = np.array([-1, 1, 1, -1, 1, -1], np.int8)
    row_kind = np.full(3, ROW_NONE, np.int8)
    row_tri = np.full(3, -1, np.int32)
    row_bary = np.zeros((3, 3))
    _rigid_rows(6, segment, tri, bary, t, direction, tri_rigid, row_kind, row_tri, row_bary)
    assert row_kind.tolist() == [ROW_TRIANGLE, ROW_WALL, ROW_NONE]  # node 2 crossed a soft face only
    assert row_tri.tolist() == [1, 2, -1] and np.array_equal(row_bary[1], bary[2])
