"""Strand tracking: strand node positions and the strand coordinates of the access points (module
docstring of :mod:`suture_gym.sim.coupling`, detection step 2)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.coupling.model import CouplingModel, CouplingState
from suture_gym.sim.rigid import (
    body_points_world,
)


@njit(cache=True)
def strand_positions_kernel(needle_pos, needle_quat, needle_node_body, suture_q, out):
    """Strand node positions: needle nodes from the pose, then suture nodes 1.. . Writes ``out`` (M, 3), m."""
    nn = needle_node_body.shape[0]
    body_points_world(needle_pos, needle_quat, needle_node_body, out[:nn])
    for j in range(1, suture_q.shape[0]):
        out[nn + j - 1] = suture_q[j]


@njit(cache=True)
def track_sigma(strand_q, sigma, target, sigma_prev, window, lower, upper):
    """Strand coordinate (m) of the strand point nearest ``target`` (3,), searched over the strand interval
    ``[max(sigma_prev - window, lower), min(sigma_prev + window, upper)]``; ties go to the coordinate nearer
    ``sigma_prev``.

    The bounds keep the coordinates of the access points in strand order (a path's exit before its entry,
    a newer path before an older one), so a tracker cannot jump to another branch of a looping thread that
    passes close to its access point.

    Args:
        strand_q: (M, 3) strand node positions, m. sigma: (M,) their material coordinates, m.
        target: (3,) access point, m. sigma_prev: last coordinate, m. window: search half-width, m.
        lower, upper: hard bounds of the coordinate, m.

    Returns:
        ``(sigma_new, distance)``; the coordinate lies in ``[max(lower, 0), min(upper, sigma[-1])]``.
    """
    m = sigma.shape[0]
    lo = max(sigma_prev - window, lower, 0.0)
    hi = min(sigma_prev + window, upper, sigma[m - 1])
    if lo > hi:
        lo = max(min(lower, upper), 0.0)
        hi = lo
    best_s = min(max(sigma_prev, lo), hi)
    best_d2 = np.inf
    for j in range(m - 1):
        if sigma[j + 1] < lo or sigma[j] > hi:
            continue
        a = strand_q[j]
        e = strand_q[j + 1] - a
        length = sigma[j + 1] - sigma[j]
        t_lo = max((lo - sigma[j]) / length, 0.0)
        t_hi = min((hi - sigma[j]) / length, 1.0)
        ee = e @ e
        t = t_lo
        if ee > 0.0:
            t = min(max(((target - a) @ e) / ee, t_lo), t_hi)
        diff = a + t * e - target
        d2 = diff @ diff
        s = sigma[j] + t * length
        if d2 < best_d2 or (d2 == best_d2 and abs(s - sigma_prev) < abs(best_s - sigma_prev)):
            best_d2 = d2
            best_s = s
    if best_d2 == np.inf:
        return best_s, np.inf
    return best_s, math.sqrt(best_d2)


def track_access_points(model: CouplingModel, state: CouplingState, tissue_q: np.ndarray, strand_q: np.ndarray) -> None:
    """Matching (module docstring, detection step 2): re-find the strand coordinates of every path's access
    points on the strand at ``strand_q`` (M, 3) m (:func:`track_sigma`), newest path first, each bounded by its
    neighbours' (and the oldest entry by the stopper knot); ``tissue_q`` (N, 3) m. Updates ``state``."""
    _track_kernel(
        strand_q, model.strand_sigma, model.params.track_window, min(model.strand_length, model.knot_sigma),
        model.surface.tri_vertices, tissue_q, int(state.path_count), state.path_open, state.path_entry_tri,
        state.path_entry_bary, state.path_exit_tri, state.path_exit_bary, state.path_sigma_entry,
        state.path_sigma_exit,
    )  # fmt: skip


@njit(cache=True)
def _track_kernel(strand_q, sigma, window, oldest_upper, tri_vertices, tissue_q, path_count, path_open, entry_tri,
                  entry_bary, exit_tri, exit_bary, sigma_entry, sigma_exit):  # fmt: skip
    """:func:`track_access_points` in one compiled loop (the access point of triangle ``tri`` at barycentrics
    ``b`` is ``b @ tissue_q[tri_vertices[tri]]``, as :func:`~suture_gym.sim.coupling.paths.access_point`)."""
    for k in range(path_count - 1, -1, -1):  # newest (front of the strand) first
        upper = sigma_exit[k - 1] if k > 0 else oldest_upper
        newer_entry = sigma_entry[k + 1] if k + 1 < path_count else 0.0
        if not path_open[k]:
            b = exit_bary[k] @ tissue_q[tri_vertices[exit_tri[k]]]
            sigma_exit[k] = track_sigma(strand_q, sigma, b, sigma_exit[k], window, newer_entry, sigma_entry[k])[0]
            lower = sigma_exit[k]
        else:
            lower = 0.0
        b = entry_bary[k] @ tissue_q[tri_vertices[entry_tri[k]]]
        sigma_entry[k] = track_sigma(strand_q, sigma, b, sigma_entry[k], window, lower, upper)[0]
