"""Greedy graph colouring of constraints that share particles.

Two constraints conflict when they act on a common particle. Constraints of one colour are pairwise
independent, so a solver may project them in any order, or in parallel, with the same result. The Gauss-Seidel
sweeps of :mod:`suture_gym.sim.solver` visit constraints colour by colour in the order returned here.
"""

from __future__ import annotations

import numpy as np
from numba import njit


@njit(cache=True)
def _greedy_colors(indices: np.ndarray, particle_count: int, colors: np.ndarray) -> int:
    """Give each constraint (row of ``indices``) the smallest colour unused by its already coloured neighbours.

    Constraints are visited in row order, so the result is deterministic. Writes ``colors (C,)`` and returns
    the number of colours used.
    """
    constraint_count, width = indices.shape
    # Particle -> constraints adjacency in CSR form.
    start = np.zeros(particle_count + 1, dtype=np.int64)
    for c in range(constraint_count):
        for j in range(width):
            start[indices[c, j] + 1] += 1
    for p in range(particle_count):
        start[p + 1] += start[p]
    fill = start[:-1].copy()
    adjacent = np.empty(start[-1], dtype=np.int64)
    for c in range(constraint_count):
        for j in range(width):
            p = indices[c, j]
            adjacent[fill[p]] = c
            fill[p] += 1

    # marked[k] == c means colour k is taken by a neighbour of constraint c.
    marked = np.full(constraint_count + 1, -1, dtype=np.int64)
    color_count = 0
    for c in range(constraint_count):
        for j in range(width):
            p = indices[c, j]
            for a in range(start[p], start[p + 1]):
                k = colors[adjacent[a]]
                if k >= 0:
                    marked[k] = c
        k = 0
        while marked[k] == c:
            k += 1
        colors[c] = k
        if k + 1 > color_count:
            color_count = k + 1
    return color_count


def color_constraints(indices: np.ndarray, particle_count: int) -> tuple[np.ndarray, np.ndarray]:
    """Colour constraints so that no two constraints of one colour share a particle.

    Args:
        indices: ``(C, k)`` integer particle indices of each constraint (e.g. ``(T, 4)`` tet vertices).
        particle_count: number of particles ``N``; every index must lie in ``0..N-1``.

    Returns:
        ``order (C,) int32``: constraint indices sorted by colour (ascending constraint index within a
        colour), and ``offsets (K + 1,) int32``: colour ``k`` is ``order[offsets[k]:offsets[k + 1]]``.
        The greedy colouring visits constraints in index order, so the result is deterministic.
    """
    indices = np.asarray(indices)
    if indices.ndim != 2 or indices.shape[1] < 1:
        raise ValueError(f"indices must have shape (C, k) with k >= 1, got {indices.shape}")
    if indices.size and not np.issubdtype(indices.dtype, np.integer):
        raise ValueError(f"indices must be integers, got dtype {indices.dtype}")
    if particle_count < 0:
        raise ValueError(f"particle_count must be non-negative, got {particle_count}")
    if indices.size and (indices.min() < 0 or indices.max() >= particle_count):
        row = int(np.flatnonzero(((indices < 0) | (indices >= particle_count)).any(axis=1))[0])
        raise ValueError(
            f"constraint {row} references a particle outside 0..{particle_count - 1}: {indices[row].tolist()}"
        )
    colors = np.full(len(indices), -1, dtype=np.int64)
    color_count = _greedy_colors(np.ascontiguousarray(indices, dtype=np.int64), int(particle_count), colors)
    order = np.argsort(colors, kind="stable").astype(np.int32)
    offsets = np.searchsorted(colors[order], np.arange(color_count + 1)).astype(np.int32)
    return order, offsets
