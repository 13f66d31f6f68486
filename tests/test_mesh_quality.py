"""Mesh quality metrics against hand-computed values: a regular tet, a right-corner tet, a flat sliver, a needle."""

import math

import numpy as np
import pytest

from suture_gym.sim.mesh import box_tet_grid
from suture_gym.sim.mesh_quality import (
    dihedral_angles,
    face_angle_ratio,
    face_angles,
    mesh_quality,
    radius_ratio,
)

ONE = np.array([[0, 1, 2, 3]])
#: Alternate corners of a cube: a regular tet of edge 2 sqrt(2), positively oriented.
REGULAR = np.array([[1.0, 1, 1], [-1, 1, -1], [1, -1, -1], [-1, -1, 1]])
#: The corner of the unit cube: three right angles at the origin.
CORNER = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]])
#: Four coplanar corners of a unit square: a sliver of zero volume whose faces are all right isosceles.
SQUARE_SLIVER = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [1, 1, 0]])


def test_regular_tet():
    assert np.allclose(face_angles(REGULAR, ONE), math.pi / 3)
    assert np.allclose(dihedral_angles(REGULAR, ONE), math.acos(1 / 3))
    assert radius_ratio(REGULAR, ONE) == pytest.approx([1.0])
    assert face_angle_ratio(REGULAR, ONE) == pytest.approx([1.0])


def test_inverted_tet_has_a_negative_radius_ratio_and_the_same_angles():
    flipped = ONE[:, [0, 2, 1, 3]]
    assert radius_ratio(REGULAR, flipped) == pytest.approx([-1.0])
    assert np.allclose(dihedral_angles(REGULAR, flipped), math.acos(1 / 3))


def test_corner_tet():
    # Faces: three right isosceles (90, 45, 45) and one equilateral (60): max/min = 90/45.
    assert face_angle_ratio(CORNER, ONE) == pytest.approx([2.0])
    # 90 deg at the three axis edges, acos(1/sqrt(3)) at the three edges of the slanted face.
    expected = np.radians([90, 90, 90]).tolist() + [math.acos(1 / math.sqrt(3))] * 3
    assert dihedral_angles(CORNER, ONE)[0] == pytest.approx(expected)
    # r = 3V/A = 1/(3 + sqrt(3)), R = sqrt(3)/2: 3 r / R = sqrt(3) - 1.
    assert radius_ratio(CORNER, ONE) == pytest.approx([math.sqrt(3) - 1])


def test_flat_sliver_passes_the_face_angle_ratio_but_not_the_others():
    assert face_angle_ratio(SQUARE_SLIVER, ONE) == pytest.approx([2.0])
    # The square's sides fold the faces onto each other (0 deg), its diagonals open them flat (180 deg).
    assert np.degrees(dihedral_angles(SQUARE_SLIVER, ONE))[0] == pytest.approx([0, 0, 180, 180, 0, 0])
    assert radius_ratio(SQUARE_SLIVER, ONE) == pytest.approx([0.0])


def test_needle_tet_face_angle_ratio():
    # Apex at height h over the corner: the vertical faces have an angle atan(h) at their far corners, the
    # largest angle stays the 90 deg at the origin.
    h = 1e-3
    needle = np.array([[0.0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, h]])
    assert face_angle_ratio(needle, ONE) == pytest.approx([(math.pi / 2) / math.atan(h)])


def test_five_tet_cube_summary():
    """A cube cell of the five-tet scheme is one regular central tet and four corner tets."""
    mesh = box_tet_grid((1.0, 1.0, 1.0), (1, 1, 1), scheme="five")
    quality = mesh_quality(mesh.vertices, mesh.tets)
    assert quality["tets"] == 5
    assert quality["max_face_angle_ratio"] == pytest.approx(2.0)
    assert quality["median_face_angle_ratio"] == pytest.approx(2.0)
    assert quality["min_dihedral_deg"] == pytest.approx(math.degrees(math.acos(1 / math.sqrt(3))))
    assert quality["max_dihedral_deg"] == pytest.approx(90.0)
    assert quality["min_radius_ratio"] == pytest.approx(math.sqrt(3) - 1)
    assert quality["mean_radius_ratio"] == pytest.approx((1 + 4 * (math.sqrt(3) - 1)) / 5)


@pytest.mark.parametrize("vertices, tets, message", [
    (np.zeros((4, 2)), ONE, r"vertices must have shape \(N, 3\)"),
    (CORNER, np.array([[0, 1, 2]]), r"tets must be integer vertex indices of shape \(T, 4\)"),
    (CORNER, np.array([[0, 1, 2, 4]]), r"outside 0..3"),
    (CORNER, np.zeros((0, 4), dtype=int), "tets is empty"),
])
def test_bad_input_is_named(vertices, tets, message):
    with pytest.raises(ValueError, match=message):
        mesh_quality(vertices, tets)
