"""Contact between a wound's two faces: the projection, the pairing, and a tissue pushed through its own wound."""

import numpy as np
import pytest

from suture_gym.envs.config import load_config
from suture_gym.sim.coupling.compliance import diagonal
from suture_gym.sim.incision import Incision, incise, with_wound_contact, wound_contact_pairs
from suture_gym.sim.mesh import box_tet_grid
from suture_gym.sim.model import Control, TissueMaterial, TissueModel
from suture_gym.sim.scenes import two_bar_wound
from suture_gym.sim.solver import Solver
from suture_gym.sim.tissue import face_contact, project_face_contacts
from suture_gym.sim.tissue_implicit import implicit_tissue

# one boundary triangle in the plane z = 0, outward normal +z
TRIANGLE = np.array([[0, 1, 2]], np.int32)
CORNERS = np.array([[0.0, 0.0, 0.0], [1e-3, 0.0, 0.0], [0.0, 1e-3, 0.0]])


def _project(particle, inv_mass=(1.0, 2.0, 3.0, 4.0), reach=5e-4):
    q = np.vstack([CORNERS, particle])
    w = np.array(inv_mass, dtype=float)
    corrected = project_face_contacts(TRIANGLE, np.array([3], np.int32), np.array([0], np.int32), reach, q, diagonal(w))
    return q, w, corrected


def test_a_particle_behind_the_face_is_pushed_onto_it_keeping_the_mass_weighted_mean():
    before = np.vstack([CORNERS, [2e-4, 3e-4, -1e-4]])
    q, w, corrected = _project(before[3])
    assert corrected == 1
    b = np.array([1.0 - 0.2 - 0.3, 0.2, 0.3])  # the particle's barycentrics in the triangle
    contact = b @ q[:3]
    assert q[3, 2] - contact[2] == pytest.approx(0.0, abs=1e-15)  # on the face: the gap closed
    np.testing.assert_allclose(q[:, :2], before[:, :2], atol=1e-18)  # frictionless: along the normal only
    assert q[3, 2] > before[3, 2] and np.all(q[:3, 2] < 0.0)  # apart: the particle out, the face back
    mass = 1.0 / w
    np.testing.assert_allclose(mass @ q, mass @ before, atol=1e-18)  # no net impulse


@pytest.mark.parametrize(
    "particle",
    [[2e-4, 3e-4, 1e-4], [2e-4, 3e-4, -6e-4], [8e-4, 8e-4, -1e-4], [-1e-4, 3e-4, -1e-4]],
    ids=["in_front", "beyond_reach", "outside_the_triangle", "outside_an_edge"],
)
def test_a_particle_not_in_contact_is_left_alone(particle):
    q, _, corrected = _project(np.array(particle))
    assert corrected == 0
    np.testing.assert_array_equal(q, np.vstack([CORNERS, particle]))


def test_a_particle_just_outside_an_edge_touches_the_nearest_point_of_the_triangle():
    """Within FACE_CONTACT_EDGE of an edge (an incision's mirrored vertices meet corner to corner): the particle is
    pushed out as from the nearest point in the triangle (barycentrics clamped), onto the plane."""
    q, _, corrected = _project(np.array([-2e-5, 3e-4, -1e-4]))
    assert corrected == 1
    b = np.array([0.72, 0.0, 0.3]) / 1.02  # clamped from (0.72, -0.02, 0.3) into the triangle
    assert q[3, 2] - (b @ q[:3])[2] == pytest.approx(0.0, abs=1e-15)
    assert q[1, 2] == 0.0  # the corner with no weight is not moved


def test_pinned_particles_take_no_correction():
    q, _, corrected = _project(np.array([2e-4, 3e-4, -1e-4]), inv_mass=(0.0, 0.0, 0.0, 1.0))
    assert corrected == 1
    np.testing.assert_array_equal(q[:3], CORNERS)
    assert q[3, 2] == pytest.approx(0.0, abs=1e-15)


def test_with_a_block_a_pair_with_a_free_vertex_outside_it_waits_for_the_next_pass():
    """An implicit tissue's compliance block holds the vertices of the pairs touching when the pass began; a pair
    that touches with a free vertex outside it (here the triangle's corner 1) is left alone, not weighed on the
    other vertices alone (that once threw a vertex 37 m), and is corrected once the block holds it."""
    particle = np.array([2e-4, 3e-4, -1e-4])
    w = np.array([1.0, 2.0, 3.0, 4.0])

    def block(vertices):
        slot = np.full(4, -1, np.int32)
        slot[vertices] = np.arange(len(vertices))
        matrix = np.kron(np.diag(w[vertices]), np.eye(3))  # the diagonal compliance, as a block
        return (w, slot, np.array(vertices, np.int32), matrix, np.zeros((4, 3)))

    q = np.vstack([CORNERS, particle])
    assert project_face_contacts(TRIANGLE, np.array([3], np.int32), np.array([0], np.int32), 5e-4, q,
                                 block([0, 2, 3])) == 0  # fmt: skip
    np.testing.assert_array_equal(q, np.vstack([CORNERS, particle]))
    assert project_face_contacts(TRIANGLE, np.array([3], np.int32), np.array([0], np.int32), 5e-4, q,
                                 block([0, 1, 2, 3])) == 1  # fmt: skip
    expected, _, _ = _project(particle)
    np.testing.assert_allclose(q, expected, atol=1e-18)  # the diagonal block moves as the diagonal compliance


def test_pairs_join_each_face_to_the_other_and_skip_the_crack_front():
    """On a box cut half-way down (the faces meet at the crack front, shared by both): every pair is a free
    particle of one face and a boundary triangle all of whose corners lie on the other face, never a triangle
    of the particle itself, and neither side is left without pairs."""
    cut = incise(box_tet_grid((0.02, 0.02, 0.01), (4, 4, 2)), Incision([[0.0, 0.01, 0.01], [0.02, 0.01, 0.01]],
                                                                      depth=0.005, gap=0.0))  # fmt: skip
    tissue = TissueModel.from_mesh(cut.mesh, TissueMaterial())
    left, right = cut.left_face, cut.right_face
    vertex, face = wound_contact_pairs(tissue, left, right, radius=0.006, front=cut.crack_front)
    assert vertex.size > 0
    on_left, on_right = np.isin(vertex, left), np.isin(vertex, right)
    assert on_left.sum() + on_right.sum() == vertex.size and not np.isin(vertex, cut.crack_front).any()
    corners = tissue.tri_indices[face]
    right_side, left_side = np.append(right, cut.crack_front), np.append(left, cut.crack_front)
    assert np.all(np.isin(corners[on_left], right_side).all(axis=1) & np.isin(corners[on_left], right).any(axis=1))
    assert np.all(np.isin(corners[on_right], left_side).all(axis=1) & np.isin(corners[on_right], left).any(axis=1))
    assert on_left.any() and on_right.any()
    assert not np.any((corners == vertex[:, None]).any(axis=1))
    with pytest.raises(ValueError, match="radius > 0"):
        wound_contact_pairs(tissue, left, right, radius=0.0)


def _deepest(q, tri, vertex, face):
    """The deepest any paired particle lies behind its facing triangle, among the pairs whose particle projects
    inside the triangle, m (negative: all in front)."""
    a, b, c = (q[tri[face, k]] for k in range(3))
    n = np.cross(b - a, c - a)
    n /= np.linalg.norm(n, axis=1)[:, None]
    d = q[vertex] - a
    gap = np.einsum("ij,ij->i", d, n)
    p = d - gap[:, None] * n
    area = np.einsum("ij,ij->i", np.cross(b - a, c - a), n)
    b1 = np.einsum("ij,ij->i", np.cross(p, c - a), n) / area
    b2 = np.einsum("ij,ij->i", np.cross(b - a, p), n) / area
    inside = (b1 >= 0.0) & (b2 >= 0.0) & (b1 + b2 <= 1.0)
    return float(np.max(-gap[inside], initial=-np.inf))


def test_a_bar_thrown_at_the_other_stops_at_its_face():
    """The left bar of a two-bar wound of 3 kPa (ends and base pinned) set moving at 0.5 m/s toward the right bar
    across the 1 mm gap: with contact its wound face stops at the right bar's face (and pushes it); without, it
    passes into it (0.19 mm). Measured over 40 substeps: the deepest a particle of one face gets behind a
    triangle of the other. (Much harder collisions, 1 m/s into 3 kPa, invert facing triangles; an inverted
    triangle's normal points into its own tissue, and no contact along it can hold.)"""
    depth = {}
    for contact in (False, True):
        scene = two_bar_wound(bar_size=(0.02, 0.006, 0.006), cells=(4, 2, 2), gap=0.001, gravity=0.0,
                              material=TissueMaterial(youngs_modulus=3000.0))  # fmt: skip
        paired = with_wound_contact(scene)
        pairs = paired.model.tissue.contact_vertex, paired.model.tissue.contact_face
        assert pairs[0].size > 0
        if contact:
            scene = paired
        tissue, state = scene.model.tissue, scene.state
        bar = scene.regions["left_bar"]
        state.tissue.particle_qd[bar[tissue.particle_inv_mass[bar] > 0.0], 1] = 0.5
        solver = Solver(tissue_integrator="quasi_newton", iterations=2)
        deepest = -np.inf
        for _ in range(40):
            solver.step(scene.model, state, Control(), 1e-3)
            deepest = max(deepest, _deepest(state.tissue.particle_q, tissue.tri_indices, *pairs))
        assert not state.diverged
        depth[contact] = deepest
    assert depth[False] > 1e-4  # into the other face
    assert depth[True] < 1e-6  # held at it


def test_the_implicit_tissue_answers_a_contact_with_its_compliance():
    """With an implicit integrator a touching pair closes its gap through the substep compliance: the impulses
    between the faces are equal and opposite, the whole tissue moves by its linear response to them
    (``A0^-1`` times their forces, checked against a fresh solve), so the particle's neighbours move with it (on
    inverse masses only the pair's four vertices move), and the gap is closed."""
    scene = with_wound_contact(two_bar_wound(bar_size=(0.02, 0.006, 0.006), cells=(4, 2, 2), gap=0.001,
                                             gravity=0.0, material=TissueMaterial(youngs_modulus=3.0e5)))  # fmt: skip
    tissue = scene.model.tissue
    integrator = implicit_tissue(tissue, "quasi_newton", 1e-3)
    q = tissue.particle_rest_q.copy()
    free = tissue.particle_inv_mass > 0.0
    # push a free particle of the left face 0.3 mm into the right bar, behind the triangle it faces
    pairs = [(v, f) for v, f in zip(tissue.contact_vertex, tissue.contact_face, strict=True)
             if free[v] and np.isin(scene.regions["left_wound_face"], v).any()]  # fmt: skip
    v, f = pairs[0]
    _, gap0, nx, ny, nz = face_contact(tissue.tri_indices, v, f, 1.0, q)[:5]
    q[v] -= (gap0 + 3e-4) * np.array([nx, ny, nz])
    assert face_contact(tissue.tri_indices, v, f, tissue.contact_reach, q)[0]
    before = q.copy()
    assert integrator.project_face_contacts(q) >= 1
    touching, gap = face_contact(tissue.tri_indices, v, f, tissue.contact_reach, q)[:2]
    assert not touching and gap == pytest.approx(0.0, abs=1e-9)
    force = integrator.external  # the impulses over h^2, N
    np.testing.assert_allclose(force.sum(axis=0), 0.0, atol=1e-12 * np.abs(force).max())
    expected = integrator.factor.solve(force.reshape(-1)[integrator.free_index])
    moved = (q - before).reshape(-1)[integrator.free_index]
    np.testing.assert_allclose(moved, expected, rtol=0.0, atol=1e-9 * np.abs(expected).max())
    neighbours = np.unique(tissue.tet_indices[np.isin(tissue.tet_indices, v).any(axis=1)])
    others = np.setdiff1d(neighbours, np.append(tissue.tri_indices[f], v))
    assert np.linalg.norm(q[others] - before[others], axis=1).max() > 1e-5  # the neighbourhood moved too
    # the pair's neighbours on the same face may now touch their triangles, but only by round-off
    gaps = [face_contact(tissue.tri_indices, a, b, tissue.contact_reach, q)[:2]
            for a, b in zip(tissue.contact_vertex, tissue.contact_face, strict=True)]  # fmt: skip
    assert max((-g for touching, g in gaps if touching), default=0.0) < 1e-12


def test_the_fuzzed_bang_bang_episode_on_the_soft_fat_wall_does_not_diverge(monkeypatch):
    """The fuzzer's reproducer (scripts/fuzz.py) that diverged when the wound's contact moved face vertices on
    their inverse masses: bang-bang wrenches drive the needle, in the soft fat, sideways through the wound."""
    from conftest import assert_fuzz_event_does_not_diverge

    event = {"id": "SutureGym/WoundClosure-v3", "config": "abdominal_wall_wound_closure_soft_fat.yaml",
             "action_mode": "wrench", "strategy": "bang_bang", "seed": 889009434, "step": 41}  # fmt: skip
    assert_fuzz_event_does_not_diverge(monkeypatch, event)


def test_the_fuzzed_random_episode_on_the_soft_fat_wall_does_not_diverge(monkeypatch):
    """The fuzzer's reproducer (scripts/fuzz.py, at the wall's 5/3 ms substep) that diverged when a pair began to
    touch during a contact pass with vertices outside the pass's compliance block: its impulse, weighed on one
    corner of weight 1e-3, threw the tissue 37 m in one substep."""
    from conftest import assert_fuzz_event_does_not_diverge

    event = {"id": "SutureGym/WoundClosureGoal-v3", "config": "abdominal_wall_wound_closure_soft_fat.yaml",
             "action_mode": "wrench", "strategy": "random", "seed": 1639205032, "step": 148}  # fmt: skip
    assert_fuzz_event_does_not_diverge(monkeypatch, event)


def test_the_switch_is_validated_and_reaches_the_tissue():
    with pytest.raises(ValueError, match="scene.wound_contact"):
        load_config("needle_insert", {"scene": {"wound_contact": True}})
    config = load_config("wound_closure", {"scene": {"wound_contact": True}})
    assert config.scene.wound_contact
