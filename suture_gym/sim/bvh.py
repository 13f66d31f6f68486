"""Axis-aligned bounding boxes and bounding volume hierarchies over deforming mesh elements.

The broad phase of the needle/suture-tissue interaction (paper §4.1: "we first compute and update axis-aligned
bounding boxes ... as a broad phase"). The paper builds kd-trees once before the simulation loop and traverses
them each step; we do the same with a BVH whose *topology* is built once (median split of element centroids
at the rest pose) and whose *boxes* are refitted every substep from the deformed vertex positions in O(n):
nodes are numbered so that every parent comes before its children, so one backward sweep over the node array
updates leaves from their elements and inner nodes from their two children.

The same structure serves surface triangles (``element_vertices`` of shape (T,3)) and tetrahedra ((K,4)).
All positions are in metres.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numba import njit

__all__ = [
    "BVH",
    "aabb_overlap",
    "build_bvh",
    "mesh_aabb",
    "points_aabb",
    "refit_bvh",
]


@dataclass
class BVH:
    """Binary bounding volume hierarchy over the elements of a mesh (triangles or tetrahedra).

    Node 0 is the root; every inner node has exactly two children whose indices are larger than its own.
    Leaves own the contiguous slice ``sorted_element[node_first : node_first + node_count]``.

    Attributes:
        element_vertices: (K, k) int32, vertex indices of each element (k = 3 triangles, k = 4 tets).
        vertex_count: number of vertices N the element indices refer to; ``vertex_q`` passed to
            :func:`refit_bvh` must have shape (N, 3).
        node_lo: (Nn, 3) float64 [m], lower corner of each node's box (valid after the last refit).
        node_hi: (Nn, 3) float64 [m], upper corner of each node's box.
        node_child: (Nn, 2) int32, left and right child node indices; (-1, -1) for a leaf.
        node_first: (Nn,) int32, first slot in ``sorted_element`` covered by the node.
        node_count: (Nn,) int32, number of elements covered by the node (> 0).
        sorted_element: (K,) int32, element indices in leaf order.
        depth: number of levels (a lone root leaf has depth 1).
    """

    element_vertices: np.ndarray
    vertex_count: int
    node_lo: np.ndarray
    node_hi: np.ndarray
    node_child: np.ndarray
    node_first: np.ndarray
    node_count: np.ndarray
    sorted_element: np.ndarray
    depth: int

    @property
    def tree(self) -> tuple:
        """The arrays the traversal kernels take, as one argument: ``(node_lo, node_hi, node_child, node_first,
        node_count, sorted_element, element_vertices)`` (the same arrays, not copies)."""
        return (
            self.node_lo, self.node_hi, self.node_child, self.node_first, self.node_count, self.sorted_element,
            self.element_vertices,
        )  # fmt: skip


@njit(cache=True)
def aabb_overlap(lo_a, hi_a, lo_b, hi_b, margin):
    """True when box a, grown by ``margin`` [m] on every side, overlaps box b (touching counts).

    Args:
        lo_a, hi_a, lo_b, hi_b: (3,) float64 [m] box corners.
        margin: float [m], non-negative growth of box a (e.g. the resistance-layer thickness eps).
    """
    for j in range(3):
        if lo_a[j] - margin > hi_b[j] or lo_b[j] > hi_a[j] + margin:
            return False
    return True


@njit(cache=True)
def _points_aabb_kernel(points, lo, hi):
    for j in range(3):
        lo[j] = np.inf
        hi[j] = -np.inf
    for i in range(points.shape[0]):
        for j in range(3):
            x = points[i, j]
            if x < lo[j]:
                lo[j] = x
            if x > hi[j]:
                hi[j] = x


@njit(cache=True)
def _mesh_aabb_kernel(element_vertices, vertex_q, lo, hi):
    for j in range(3):
        lo[j] = np.inf
        hi[j] = -np.inf
    for e in range(element_vertices.shape[0]):
        for a in range(element_vertices.shape[1]):
            v = element_vertices[e, a]
            for j in range(3):
                x = vertex_q[v, j]
                if x < lo[j]:
                    lo[j] = x
                if x > hi[j]:
                    hi[j] = x


@njit(cache=True)
def _build_kernel(element_vertices, vertex_q, leaf_size, node_child, node_first, node_count, sorted_element):
    """Median-split build; returns (number of nodes, depth). Output arrays are sized for 2K - 1 nodes."""
    n_elem, arity = element_vertices.shape
    centroid = np.zeros((n_elem, 3))
    for e in range(n_elem):
        for a in range(arity):
            for j in range(3):
                centroid[e, j] += vertex_q[element_vertices[e, a], j]
        for j in range(3):
            centroid[e, j] /= arity
    for e in range(n_elem):
        sorted_element[e] = e
    stack_node = np.empty(2 * n_elem, np.int32)
    stack_level = np.empty(2 * n_elem, np.int32)
    stack_node[0] = 0
    stack_level[0] = 1
    top = 1
    node_first[0] = 0
    node_count[0] = n_elem
    n_nodes = 1
    depth = 1
    while top > 0:
        top -= 1
        node = stack_node[top]
        level = stack_level[top]
        if level > depth:
            depth = level
        first = node_first[node]
        count = node_count[node]
        if count <= leaf_size:
            node_child[node, 0] = -1
            node_child[node, 1] = -1
            continue
        lo = np.full(3, np.inf)
        hi = np.full(3, -np.inf)
        for s in range(first, first + count):
            e = sorted_element[s]
            for j in range(3):
                lo[j] = min(lo[j], centroid[e, j])
                hi[j] = max(hi[j], centroid[e, j])
        axis = 0
        for j in range(1, 3):
            if hi[j] - lo[j] > hi[axis] - lo[axis]:
                axis = j
        members = sorted_element[first : first + count].copy()
        keys = np.empty(count)
        for s in range(count):
            keys[s] = centroid[members[s], axis]
        perm = np.argsort(keys, kind="mergesort")
        for s in range(count):
            sorted_element[first + s] = members[perm[s]]
        half = count // 2
        left = n_nodes
        right = n_nodes + 1
        n_nodes += 2
        node_child[node, 0] = left
        node_child[node, 1] = right
        node_first[left] = first
        node_count[left] = half
        node_first[right] = first + half
        node_count[right] = count - half
        stack_node[top] = right
        stack_level[top] = level + 1
        stack_node[top + 1] = left
        stack_level[top + 1] = level + 1
        top += 2
    return n_nodes, depth


@njit(cache=True)
def _refit_kernel(
    element_vertices, vertex_q, node_child, node_first, node_count, sorted_element, node_lo, node_hi
):
    """Recompute every node box bottom-up; children have larger indices than parents."""
    arity = element_vertices.shape[1]
    for node in range(node_child.shape[0] - 1, -1, -1):
        left = node_child[node, 0]
        if left >= 0:
            right = node_child[node, 1]
            for j in range(3):
                node_lo[node, j] = min(node_lo[left, j], node_lo[right, j])
                node_hi[node, j] = max(node_hi[left, j], node_hi[right, j])
            continue
        lo0 = np.inf
        lo1 = np.inf
        lo2 = np.inf
        hi0 = -np.inf
        hi1 = -np.inf
        hi2 = -np.inf
        for s in range(node_first[node], node_first[node] + node_count[node]):
            e = sorted_element[s]
            for a in range(arity):
                v = element_vertices[e, a]
                x = vertex_q[v, 0]
                y = vertex_q[v, 1]
                z = vertex_q[v, 2]
                lo0 = min(lo0, x)
                hi0 = max(hi0, x)
                lo1 = min(lo1, y)
                hi1 = max(hi1, y)
                lo2 = min(lo2, z)
                hi2 = max(hi2, z)
        node_lo[node, 0] = lo0
        node_lo[node, 1] = lo1
        node_lo[node, 2] = lo2
        node_hi[node, 0] = hi0
        node_hi[node, 1] = hi1
        node_hi[node, 2] = hi2


def _check_positions(vertex_q: np.ndarray, name: str, rows: int | None = None) -> np.ndarray:
    q = np.ascontiguousarray(vertex_q, dtype=np.float64)
    if q.ndim != 2 or q.shape[1] != 3:
        raise ValueError(f"{name} must have shape (N, 3), got {q.shape}")
    if rows is not None and q.shape[0] != rows:
        raise ValueError(f"{name} has {q.shape[0]} rows; the mesh was built with {rows} vertices")
    if not np.isfinite(q).all():
        bad = int(np.argwhere(~np.isfinite(q))[0, 0])
        raise ValueError(f"{name} row {bad} is not finite: {q[bad]}")
    return q


def points_aabb(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box of a point set.

    Args:
        points: (M, 3) float64 [m], M >= 1, finite.

    Returns:
        ``(lo, hi)``, each (3,) float64 [m].
    """
    p = _check_positions(points, "points")
    if p.shape[0] == 0:
        raise ValueError("points is empty; the box of no points is undefined")
    lo = np.empty(3)
    hi = np.empty(3)
    _points_aabb_kernel(p, lo, hi)
    return lo, hi


def _check_elements(element_vertices: np.ndarray, vertex_count: int) -> np.ndarray:
    ev = np.asarray(element_vertices)
    if ev.ndim != 2 or ev.shape[1] not in (3, 4):
        raise ValueError(f"element_vertices must have shape (K, 3) or (K, 4), got {ev.shape}")
    if ev.shape[0] == 0:
        raise ValueError("element_vertices is empty")
    if not np.issubdtype(ev.dtype, np.integer):
        raise ValueError(f"element_vertices must hold integers, got dtype {ev.dtype}")
    if ev.min() < 0 or ev.max() >= vertex_count:
        bad = int(np.argwhere((ev < 0) | (ev >= vertex_count))[0, 0])
        raise ValueError(
            f"element_vertices row {bad} = {ev[bad].tolist()} indexes outside the {vertex_count} vertices"
        )
    return np.ascontiguousarray(ev, dtype=np.int32)


def mesh_aabb(element_vertices: np.ndarray, vertex_q: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned box of the vertices used by a mesh's elements.

    Args:
        element_vertices: (K, 3) or (K, 4) int, vertex indices per triangle / tet.
        vertex_q: (N, 3) float64 [m] vertex positions.

    Returns:
        ``(lo, hi)``, each (3,) float64 [m].
    """
    q = _check_positions(vertex_q, "vertex_q")
    ev = _check_elements(element_vertices, q.shape[0])
    lo = np.empty(3)
    hi = np.empty(3)
    _mesh_aabb_kernel(ev, q, lo, hi)
    return lo, hi


def build_bvh(element_vertices: np.ndarray, vertex_q: np.ndarray, leaf_size: int = 4) -> BVH:
    """Build a BVH over mesh elements by median splits of their centroids, and fit it to ``vertex_q``.

    Build once (at the rest pose); call :func:`refit_bvh` whenever the vertices move.

    Args:
        element_vertices: (K, 3) or (K, 4) int, vertex indices of each triangle / tet, K >= 1.
        vertex_q: (N, 3) float64 [m] vertex positions used to choose the splits.
        leaf_size: most elements per leaf (>= 1).

    Returns:
        A fitted :class:`BVH`.
    """
    if int(leaf_size) != leaf_size or leaf_size < 1:
        raise ValueError(f"leaf_size must be a positive integer, got {leaf_size!r}")
    q = _check_positions(vertex_q, "vertex_q")
    ev = _check_elements(element_vertices, q.shape[0])
    n_max = 2 * ev.shape[0] - 1
    node_child = np.empty((n_max, 2), np.int32)
    node_first = np.empty(n_max, np.int32)
    node_count = np.empty(n_max, np.int32)
    sorted_element = np.empty(ev.shape[0], np.int32)
    n_nodes, depth = _build_kernel(ev, q, int(leaf_size), node_child, node_first, node_count, sorted_element)
    bvh = BVH(
        element_vertices=ev,
        vertex_count=q.shape[0],
        node_lo=np.empty((n_nodes, 3)),
        node_hi=np.empty((n_nodes, 3)),
        node_child=node_child[:n_nodes].copy(),
        node_first=node_first[:n_nodes].copy(),
        node_count=node_count[:n_nodes].copy(),
        sorted_element=sorted_element,
        depth=int(depth),
    )
    refit_bvh(bvh, q)
    return bvh


def refit_bvh(bvh: BVH, vertex_q: np.ndarray, check_finite: bool = True) -> None:
    """Refit every box of ``bvh`` to the vertex positions ``vertex_q`` in O(nodes + elements), in place.

    Args:
        bvh: hierarchy from :func:`build_bvh`; its ``node_lo``/``node_hi`` are overwritten.
        vertex_q: (N, 3) float64 [m] current vertex positions, N = ``bvh.vertex_count``, finite.
        check_finite: validate ``vertex_q`` (shape, dtype, finite values; ValueError naming the bad row). The
            solver's detection passes False: it hands over a C-contiguous float64 array of the mesh's vertices
            that :class:`~suture_gym.sim.solver.Solver` has just checked to be finite.
    """
    q = _check_positions(vertex_q, "vertex_q", bvh.vertex_count) if check_finite else vertex_q
    _refit_kernel(
        bvh.element_vertices,
        q,
        bvh.node_child,
        bvh.node_first,
        bvh.node_count,
        bvh.sorted_element,
        bvh.node_lo,
        bvh.node_hi,
    )
