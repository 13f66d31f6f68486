"""Tetrahedral mesh quality: the seed paper's max/min face-angle ratio, dihedral angles and the radius ratio.

The seed paper (Yu et al. 2020, section 6) rates its meshes by "the max/min ratio of face angle" (26 for its
TetWild abdominal wall, 80 for TetGen's, 100 for its hand; lower is better) and reports that poor meshes made
the simulation unstable. Here that figure is, per tet, the largest of the twelve corner angles of its four
triangular faces divided by the smallest (1 for a regular tet), and for a mesh the worst (largest) over its
tets. It catches needles and caps, whose faces have a tiny angle, but not slivers: four nearly coplanar
vertices at the corners of a square make four right isosceles faces (ratio 2) and no volume. The dihedral
angle range and the radius ratio catch those:

- dihedral angles: the six interior angles between the two faces meeting at each edge (70.53 deg for all six
  of a regular tet; a sliver has some near 0 and some near 180 deg);
- radius ratio: ``3 r / R`` with ``r`` the inscribed and ``R`` the circumscribed sphere's radius; 1 for a
  regular tet, 0 for a flat one, and given the sign of the tet's volume here, so an inverted tet scores below 0.

Everything is vectorised NumPy over the tets; angles are in radians unless a name says ``_deg``.
"""

from __future__ import annotations

import numpy as np

from suture_gym.sim.mesh import TET_FACES

#: The six edges of a tet as local vertex pairs, and the two faces (by the local vertex opposite each, see
#: :data:`~suture_gym.sim.mesh.TET_FACES`) that meet at each: edge ``(i, j)`` joins the faces opposite the
#: other two vertices.
TET_EDGES = np.array([[0, 1], [0, 2], [0, 3], [1, 2], [1, 3], [2, 3]], dtype=np.int64)
_EDGE_FACES = np.array([[2, 3], [1, 3], [1, 2], [0, 3], [0, 2], [0, 1]], dtype=np.int64)


def _corners(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """``(T, 4, 3)`` float64 corner positions; ValueError on bad shapes or indices."""
    vertices = np.asarray(vertices, dtype=np.float64)
    tets = np.asarray(tets)
    if vertices.ndim != 2 or vertices.shape[1] != 3:
        raise ValueError(f"vertices must have shape (N, 3), got {vertices.shape}")
    if tets.ndim != 2 or tets.shape[1] != 4 or not np.issubdtype(tets.dtype, np.integer):
        raise ValueError(f"tets must be integer vertex indices of shape (T, 4), got {tets.shape} {tets.dtype}")
    if tets.size and (tets.min() < 0 or tets.max() >= len(vertices)):
        raise ValueError(f"tets reference vertices outside 0..{len(vertices) - 1}")
    return vertices[tets]


def _angle(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Angle between the vectors ``a`` and ``b`` along the last axis, rad: ``atan2(|a x b|, a . b)`` (accurate
    near 0 and pi, where ``acos`` of the cosine is not); 0 where either vector is zero."""
    return np.arctan2(np.linalg.norm(np.cross(a, b), axis=-1), np.einsum("...k,...k->...", a, b))


def face_angles(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The corner angles of every tet's four faces.

    Args:
        vertices: ``(N, 3)`` positions, m.
        tets: ``(T, 4)`` vertex indices.

    Returns:
        ``(T, 4, 3) float64``, rad: ``[t, k, c]`` is the angle at corner ``c`` of face ``k`` (the face opposite
        local vertex ``k``, :data:`~suture_gym.sim.mesh.TET_FACES`). Each face's three sum to pi.
    """
    x = _corners(vertices, tets)[:, TET_FACES]  # (T, 4, 3 corners, 3)
    prev, nxt = np.roll(x, 1, axis=2), np.roll(x, -1, axis=2)
    return _angle(prev - x, nxt - x)


def dihedral_angles(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The interior dihedral angle at each of every tet's six edges.

    Args:
        vertices: ``(N, 3)`` positions, m.
        tets: ``(T, 4)`` vertex indices.

    Returns:
        ``(T, 6) float64``, rad, in ``[0, pi]``, at the edges :data:`TET_EDGES`: pi minus the angle between the
        outward normals of the two faces meeting there (``acos(1/3)`` = 70.53 deg for all six of a regular tet).
        A face of zero area has no normal: its edges get NaN.
    """
    x = _corners(vertices, tets)
    f = x[:, TET_FACES]  # (T, 4, 3, 3)
    normals = np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0])  # outward for a positive tet
    length = np.linalg.norm(normals, axis=2, keepdims=True)
    with np.errstate(invalid="ignore", divide="ignore"):
        unit = np.where(length > 0.0, normals / length, np.nan)
    a, b = unit[:, _EDGE_FACES[:, 0]], unit[:, _EDGE_FACES[:, 1]]
    cosine = np.clip(np.einsum("tek,tek->te", a, b), -1.0, 1.0)
    return np.pi - np.arccos(cosine)


def radius_ratio(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """Signed radius ratio ``3 r / R`` of every tet (``r`` inscribed, ``R`` circumscribed radius, m).

    With ``V`` the signed volume and ``A`` the total face area, ``r = 3 |V| / A``; the circumradius follows from
    the products of opposite edge lengths ``p, q, s``: ``R = sqrt((p+q+s)(p+q-s)(p-q+s)(-p+q+s)) / (24 |V|)``.
    So ``3 r / R = 216 V |V| / (A sqrt(...))``: 1 for a regular tet, 0 for a flat one (four coplanar vertices;
    also when all four are collinear), negative for an inverted one.

    Args:
        vertices: ``(N, 3)`` positions, m.
        tets: ``(T, 4)`` vertex indices.

    Returns:
        ``(T,) float64``, dimensionless, in ``[-1, 1]``.
    """
    x = _corners(vertices, tets)
    e1, e2, e3 = x[:, 1] - x[:, 0], x[:, 2] - x[:, 0], x[:, 3] - x[:, 0]
    volume = np.einsum("ij,ij->i", np.cross(e1, e2), e3) / 6.0
    f = x[:, TET_FACES]
    area = 0.5 * np.linalg.norm(np.cross(f[:, :, 1] - f[:, :, 0], f[:, :, 2] - f[:, :, 0]), axis=2).sum(axis=1)
    edge = np.linalg.norm(x[:, TET_EDGES[:, 1]] - x[:, TET_EDGES[:, 0]], axis=2)  # (T, 6)
    # Opposite edge pairs of TET_EDGES: (0,1)-(2,3), (0,2)-(1,3), (0,3)-(1,2).
    p, q, s = edge[:, 0] * edge[:, 5], edge[:, 1] * edge[:, 4], edge[:, 2] * edge[:, 3]
    product = np.clip((p + q + s) * (p + q - s) * (p - q + s) * (-p + q + s), 0.0, None)
    denominator = area * np.sqrt(product)
    with np.errstate(invalid="ignore", divide="ignore"):
        ratio = np.where(denominator > 0.0, 216.0 * volume * np.abs(volume) / denominator, 0.0)
    return np.clip(ratio, -1.0, 1.0)


def face_angle_ratio(vertices: np.ndarray, tets: np.ndarray) -> np.ndarray:
    """The seed paper's quality figure per tet: largest over smallest face corner angle (:func:`face_angles`).

    Returns:
        ``(T,) float64``, dimensionless, >= 1 (1 for a regular tet); ``inf`` where a face has a zero angle.
    """
    angles = face_angles(vertices, tets).reshape(len(np.asarray(tets)), 12)
    with np.errstate(divide="ignore"):
        return angles.max(axis=1) / angles.min(axis=1)


def mesh_quality(vertices: np.ndarray, tets: np.ndarray) -> dict[str, float]:
    """Quality summary of a tet mesh, JSON-ready.

    Args:
        vertices: ``(N, 3)`` positions, m.
        tets: ``(T, 4)`` vertex indices (at least one tet).

    Returns:
        ``tets``; ``max_face_angle_ratio`` (the seed paper's figure: the worst tet's, lower is better) and its
        median over the tets; ``min_dihedral_deg`` and ``max_dihedral_deg`` (the range over all tets' edges,
        NaN edges ignored); ``min_radius_ratio`` (worst tet) and ``mean_radius_ratio``.
    """
    if len(np.asarray(tets)) == 0:
        raise ValueError("tets is empty: a mesh needs at least one tet to rate")
    ratio = face_angle_ratio(vertices, tets)
    dihedral = np.degrees(dihedral_angles(vertices, tets))
    rho = radius_ratio(vertices, tets)
    return {
        "tets": int(len(ratio)),
        "max_face_angle_ratio": float(ratio.max()),
        "median_face_angle_ratio": float(np.median(ratio)),
        "min_dihedral_deg": float(np.nanmin(dihedral)),
        "max_dihedral_deg": float(np.nanmax(dihedral)),
        "min_radius_ratio": float(rho.min()),
        "mean_radius_ratio": float(rho.mean()),
    }
