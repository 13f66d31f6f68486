"""Incisions: a cut through a box reproduces the two-bar wound; partial cuts, gaps and malformed incisions."""

import numpy as np
import pytest

from suture_gym.sim.incision import Incision, incise
from suture_gym.sim.mesh import TetMesh, box_tet_grid, surface_triangles
from suture_gym.sim.mesh_io import voxel_fill
from suture_gym.sim.scenes import two_bar_wound

# Each bar of the two-bar wound: 4 x 1 x 1 cm in 4 x 2 x 2 cells; the box is both bars side by side, no gap.
L, W, H = 0.04, 0.01, 0.01
BAR_CELLS = (4, 2, 2)
BOX = box_tet_grid((L, 2 * W, H), (4, 4, 2))
TOP_LINE = [[0.0, W, H], [L, W, H]]


def _rows(points: np.ndarray) -> set:
    return {tuple(p) for p in np.round(points, 12).tolist()}


def _tets_by_position(mesh: TetMesh) -> set:
    """Each tet as its four corner positions in order (orientation included), as a set over the mesh."""
    x = np.round(mesh.vertices[mesh.tets], 12)
    return {tuple(map(tuple, t)) for t in x.tolist()}


def test_full_cut_of_a_box_reproduces_the_two_bar_wound():
    """A cut along the whole length and height of a box of both bars gives the two-bar wound's mesh: the same
    vertices, tets (by position and orientation) and wound faces once each piece is moved by half the gap."""
    gap = 0.004
    wound = two_bar_wound(bar_size=(L, W, H), cells=BAR_CELLS, gap=gap)
    cut = incise(BOX, Incision(TOP_LINE, depth=H, gap=gap), allow_split=True)
    shifted = TetMesh(cut.mesh.vertices + [0.0, 0.5 * gap, 0.0], cut.mesh.tets)
    tissue = wound.model.tissue
    reference = TetMesh(tissue.particle_rest_q, tissue.tet_indices)
    assert shifted.vertex_count == reference.vertex_count == BOX.vertex_count + 5 * 3
    assert shifted.tet_count == reference.tet_count
    assert len(surface_triangles(shifted.tets)) == len(surface_triangles(reference.tets))
    assert _rows(shifted.vertices) == _rows(reference.vertices)
    assert _tets_by_position(shifted) == _tets_by_position(reference)
    rest = tissue.particle_rest_q
    assert _rows(shifted.vertices[cut.left_face]) == _rows(rest[wound.regions["left_wound_face"]])
    assert _rows(shifted.vertices[cut.right_face]) == _rows(rest[wound.regions["right_wound_face"]])
    assert len(cut.crack_front) == 0 and cut.cut_faces == 2 * 4 * 2 and cut.dropped_faces == 0


def test_partial_cut_opens_the_top_and_keeps_the_mesh_whole():
    depth = 0.5 * H  # one of the two cell layers
    cut = incise(BOX, Incision(TOP_LINE, depth=depth))
    mesh = cut.mesh
    # The cut plane y = W has 5 x 3 grid vertices; the bottom row of the cut (z = H/2) is the crack front.
    z = mesh.vertices[:, 2]
    assert np.allclose(z[cut.crack_front], H - depth) and len(cut.crack_front) == 5
    assert np.allclose(z[cut.left_face], H) and np.allclose(z[cut.right_face], H)
    assert mesh.vertex_count == BOX.vertex_count + 5
    assert mesh.tet_count == BOX.tet_count
    assert cut.cut_faces == 2 * 4 * 1
    assert len(surface_triangles(mesh.tets)) == len(surface_triangles(BOX.tets)) + 2 * cut.cut_faces
    assert np.array_equal(mesh.vertices, BOX.vertices[cut.source_vertex])


def test_points_near_the_surface_are_moved_onto_it():
    """Points 2 mm under the top (within the tolerance, as points taken on a smooth surface lie off a voxel
    staircase) are moved onto it: the same cut as the exact line."""
    line = [[0.005, W, H], [0.035, W, H]]
    exact = incise(BOX, Incision(line, depth=0.5 * H))
    sunk = incise(BOX, Incision(np.array(line) - [0.0, 0.0, 0.002], depth=0.5 * H))
    assert np.allclose(sunk.points, line)
    assert np.array_equal(sunk.mesh.tets, exact.mesh.tets) and np.array_equal(sunk.left_face, exact.left_face)


def test_gap_opens_the_mouth_and_leaves_the_crack_front():
    gap = 0.002
    cut = incise(BOX, Incision(TOP_LINE, depth=0.5 * H, gap=gap))
    v = cut.mesh.vertices
    left = v[cut.left_face][np.argsort(v[cut.left_face, 0])]
    right = v[cut.right_face][np.argsort(v[cut.right_face, 0])]
    assert np.allclose(right[:, 1] - left[:, 1], gap)  # at the mouth, one depth above the front: fully open
    assert np.allclose(right[:, [0, 2]], left[:, [0, 2]])
    assert np.allclose(v[cut.crack_front], BOX.vertices[cut.source_vertex[cut.crack_front]])


def test_curved_polyline_on_a_finer_box_stays_valid():
    box = box_tet_grid((0.04, 0.04, 0.01), (8, 8, 2))
    x = np.linspace(0.005, 0.035, 7)
    line = np.stack([x, 0.02 + 0.004 * np.sin(x / 0.01), np.full_like(x, 0.01)], axis=1)
    cut = incise(box, Incision(line, depth=0.006, gap=0.001))
    assert cut.mesh.tet_count == box.tet_count
    assert len(cut.left_face) > 0 and len(cut.right_face) > 0 and len(cut.crack_front) > 0
    assert cut.mesh.vertex_count == box.vertex_count + len(cut.right_face)


def test_cut_over_a_step_drops_the_faces_that_would_make_it_non_manifold():
    """A polyline over a 4 mm step of a voxel block: the staircase cut under its slanted segment touches the
    step's edge, so a few faces there stay uncut; the rest opens, and the mesh is valid."""

    class Step:
        bounds = (np.zeros(3), np.array([0.04, 0.02, 0.012]))

        @staticmethod
        def contains(p):
            return p[:, 2] < np.where(p[:, 0] < 0.02, 0.012, 0.008)

    block = voxel_fill(Step(), 0.002)
    line = [[0.004, 0.01, 0.012], [0.018, 0.01, 0.012], [0.022, 0.01, 0.008], [0.036, 0.01, 0.008]]
    cut = incise(block, Incision(line, depth=0.005))
    assert cut.dropped_faces > 0 and cut.cut_faces > 0
    assert len(cut.left_face) == len(cut.right_face) > 0
    straight = incise(block, Incision([[0.004, 0.01, 0.012], [0.018, 0.01, 0.012]], depth=0.005))
    assert straight.dropped_faces == 0


@pytest.mark.parametrize("incision, message", [
    (Incision([[0.0, W, H + 0.02], [L, W, H + 0.02]], depth=0.005), "from the tissue surface"),
    (Incision([[0.005, 0.005, H], [0.03, 0.015, H], [0.03, 0.005, H], [0.005, 0.015, H]], depth=0.005),
     "turns back"),
    (Incision([[0.005, 0.005, H], [0.03, 0.005, H], [0.03, 0.015, H], [0.015, 0.015, H], [0.012, 0.002, H]],
              depth=0.005), "crosses itself"),
    (Incision(TOP_LINE, depth=H), "cuts the mesh in two"),
    (Incision(TOP_LINE, depth=0.001), "cuts no face"),
    (Incision(TOP_LINE, depth=0.005, gap=0.02), "gap 0.02 m distorts the mesh"),
])
def test_malformed_incision_is_named(incision, message):
    with pytest.raises(ValueError, match=message):
        incise(BOX, incision)


@pytest.mark.parametrize("kwargs, message", [
    ({"points": [[0.0, 0, 0]], "depth": 0.01}, r"shape \(K, 3\) with K >= 2"),
    ({"points": [[0.0, 0, 0], [np.nan, 0, 0]], "depth": 0.01}, "finite"),
    ({"points": TOP_LINE, "depth": 0.0}, "depth must be a positive"),
    ({"points": TOP_LINE, "depth": 0.01, "gap": -1e-3}, "gap must be a finite length >= 0"),
])
def test_bad_incision_arguments_are_named(kwargs, message):
    with pytest.raises(ValueError, match=message):
        Incision(**kwargs)
