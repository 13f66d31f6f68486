"""The path lifecycle: puncture, the tip's anchor, path growth, exit and release (detection steps 3-7),
and the path nodes' kinematics."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.bvh import refit_bvh
from suture_gym.sim.collision import (
    locate_points,
    segment_crossings,
)
from suture_gym.sim.coupling.constraints import surface_normal
from suture_gym.sim.coupling.model import CouplingModel, CouplingState, CouplingWork
from suture_gym.sim.coupling.params import TINY_LENGTH, TIP_PATCH_CAPACITY


@njit(cache=True)
def path_spacing_count(d, spacing_min, spacing_max):
    """Number of path nodes to add for a tip at distance ``d`` (m) from the last path node (paper section
    4.3): 0 if ``d < l``, ``floor(d / h)`` if ``d > h``, else 1 (0 for a non-finite ``d``)."""
    if not (d >= spacing_min) or not math.isfinite(d):
        return 0
    if d > spacing_max:
        return int(math.floor(d / spacing_max))
    return 1


@njit(cache=True)
def pathnode_point(pathnode_tet, pathnode_bary, tet_indices, tissue_q, s, out):
    """Position (m) of path node ``s`` in the deformed mesh, ``sum_a b_a x_a`` over its tet; writes ``out`` (3,)."""
    t = pathnode_tet[s]
    for i in range(3):
        acc = 0.0
        for a in range(4):
            acc += pathnode_bary[s, a] * tissue_q[tet_indices[t, a], i]
        out[i] = acc


@njit(cache=True)
def path_node_kinematics(
    pathnode_tet, pathnode_bary, tet_indices, tissue_q, path_first, path_len, path_count, out_q, out_tangent
):
    """Positions (m) and unit tangents of all path nodes in the deformed mesh.

    A node's tangent is the normalised mean of the unit vectors of its adjacent path edges (paper eq. 1's
    "arithmetic mean of the adjacent edge vectors", with edges normalised so uneven spacing does not tilt
    it); a single-node path gets a zero tangent. Writes ``out_q`` and ``out_tangent`` (P, 3).
    """
    for k in range(path_count):
        first = path_first[k]
        count = path_len[k]
        for s in range(first, first + count):
            pathnode_point(pathnode_tet, pathnode_bary, tet_indices, tissue_q, s, out_q[s])
        for s in range(first, first + count):
            tan = np.zeros(3)
            if s > first:
                e = out_q[s] - out_q[s - 1]
                ne = math.sqrt(e @ e)
                if ne > TINY_LENGTH:
                    tan += e / ne
            if s < first + count - 1:
                e = out_q[s + 1] - out_q[s]
                ne = math.sqrt(e @ e)
                if ne > TINY_LENGTH:
                    tan += e / ne
            nt = math.sqrt(tan @ tan)
            if nt > TINY_LENGTH:
                out_tangent[s] = tan / nt
            else:
                out_tangent[s] = 0.0


@njit(cache=True, inline="always")
def project_onto_path(q, first, count, pathnode_q, pathnode_tangent, is_open):
    """Where strand node ``q`` (3,) meets its path's polyline: the closest point over the path's segments.

    The first segment extends backwards and the last forwards (a node beyond an end is held on the line
    through that end along its tangent), except that nothing is returned ahead of the last node of an open
    path, where the tip cuts freely.

    Returns:
        ``(ok, slot, u)``: the projection lies on segment ``slot -> slot + 1`` at parameter ``u`` in [0, 1]
        (clamped); ``ok`` False for paths with fewer than two nodes or ahead of an open path's end.
    """
    if count < 2:
        return False, 0, 0.0
    best_d2 = np.inf
    best_slot = first
    best_u = 0.0
    best_raw = 0.0
    for s in range(first, first + count - 1):
        a = pathnode_q[s]
        e = pathnode_q[s + 1] - a
        ee = e @ e
        raw = 0.0
        if ee > 0.0:
            raw = ((q - a) @ e) / ee
        u = min(max(raw, 0.0), 1.0)
        diff = a + u * e - q
        d2 = diff @ diff
        if d2 < best_d2:
            best_d2 = d2
            best_slot = s
            best_u = u
            best_raw = raw
    if is_open and best_slot == first + count - 2 and best_raw > 1.0:
        return False, best_slot, best_u
    return True, best_slot, best_u


def access_point(model: CouplingModel, tissue_q: np.ndarray, tri: int, bary: np.ndarray) -> np.ndarray:
    """World position (3,) m of the surface point (``tri``, ``bary``)."""
    v = model.surface.tri_vertices[tri]
    return bary @ tissue_q[v]


def surface_point_tet(model: CouplingModel, tissue, tri: int, bary: np.ndarray) -> tuple[int, np.ndarray]:
    """(tet, (4,) barycentrics) of the surface point (``tri``, ``bary``) in the tet owning the triangle."""
    tet = int(tissue.tri_tet[tri])
    out = np.zeros(4)
    out[model.tri_tet_local[tri].astype(np.int64)] = bary
    return tet, out


def append_path_nodes(state: CouplingState, model: CouplingModel, tets: np.ndarray, barys: np.ndarray) -> None:
    """Append path nodes to the newest path (the last used slots); flag overflow when the buffer is full."""
    capacity = model.params.max_path_nodes
    for tet, bary in zip(tets, barys, strict=True):
        if tet < 0:
            continue
        if state.pathnode_count >= capacity:
            state.overflow = True
            return
        slot = state.pathnode_count
        state.pathnode_tet[slot] = tet
        state.pathnode_bary[slot] = bary
        state.pathnode_count += 1
        state.path_len[state.path_count - 1] += 1


def release_path(state: CouplingState, k: int) -> None:
    """Remove path ``k`` and its nodes from the buffers, keeping the order of the others."""
    first, length = int(state.path_first[k]), int(state.path_len[k])
    end = state.pathnode_count
    state.pathnode_tet[first : end - length] = state.pathnode_tet[first + length : end]
    state.pathnode_bary[first : end - length] = state.pathnode_bary[first + length : end]
    state.pathnode_tet[end - length : end] = -1
    state.pathnode_bary[end - length : end] = 0.0
    state.pathnode_count -= length
    n = state.path_count
    for name in (
        "path_first",
        "path_len",
        "path_open",
        "path_entered",
        "path_entry_tri",
        "path_entry_bary",
        "path_exit_tri",
        "path_exit_bary",
        "path_sigma_entry",
        "path_sigma_exit",
    ):
        array = getattr(state, name)
        array[k : n - 1] = array[k + 1 : n]
    state.path_first[k : n - 1] -= length
    state.path_open[n - 1] = False
    state.path_entered[n - 1] = False
    state.path_len[n - 1] = 0
    state.path_entry_tri[n - 1] = -1
    state.path_exit_tri[n - 1] = -1
    state.path_sigma_exit[n - 1] = -np.inf
    state.path_count -= 1


def update_tip_anchor(model: CouplingModel, state: CouplingState, tissue_q, strand_q) -> None:
    """Keep, release or set the tip's anchor (module docstring, detection step 3) for the strand at ``strand_q``
    (M, 3) m (the tip is node 0): while no path is open, the tip engages the surface point it first comes
    within the contact band of and keeps it until it moves off the surface (its gap along the anchor normal
    exceeds the band) or slides (:func:`coupling_finish`); with the tip-contact model on
    (``tip_contact_radius > 0``) the anchor gets its contact patch (:func:`tip_patch`).

    With an exit threshold (``exit_puncture_force > 0``), the tip inside an open path that heads out through a
    deformable face (its direction, from the needle node behind it, points out of the surface) and comes within
    the band of it from the inside, farther than ``path_spacing_min`` from its own entry, gets an *exit anchor*
    there (``tip_anchor_inside``), kept until it moves back into the tissue by more than the band, slides, or
    pierces the exit (:func:`tip_events`)."""
    params = model.params
    band = params.resistance_eps + params.contact_margin
    surface = model.surface
    tip = strand_q[0]
    if state.punctured and not state.tip_anchor_inside:
        state.tip_anchor_tri = -1
    if state.tip_anchor_tri >= 0:
        n = surface_normal(
            state.tip_anchor_tri, state.tip_anchor_bary, surface.tri_vertices, surface.vertex_tri_start,
            surface.vertex_tri_index, tissue_q,
        )  # fmt: skip
        p = access_point(model, tissue_q, state.tip_anchor_tri, state.tip_anchor_bary)
        gap = float((tip - p) @ n)
        if not n.any() or (-gap if state.tip_anchor_inside else gap) > band:
            state.tip_anchor_tri = -1
    if state.tip_anchor_tri < 0:
        state.tip_anchor_inside = False
        state.tip_patch_count = 0
        state.tip_patch_compliance = 0.0
    if state.tip_anchor_tri >= 0 or state.strand_tri[0] < 0:
        return
    if not state.punctured:
        if state.strand_sdist[0] < band:
            state.tip_anchor_tri = int(state.strand_tri[0])
            state.tip_anchor_bary[:] = state.strand_bary[0]
            if params.tip_contact_radius > 0.0:
                tip_patch(model, state, tissue_q, tip)
        return
    k = state.path_count - 1
    tri = int(state.strand_tri[0])
    if (
        params.exit_puncture_force > 0.0
        and state.path_entered[k]
        and not state.exit_pierced
        and not model.tri_rigid[tri]
        and state.strand_sdist[0] > -band
    ):
        bary = state.strand_bary[0]
        n = surface_normal(
            tri, bary, surface.tri_vertices, surface.vertex_tri_start, surface.vertex_tri_index, tissue_q
        )  # fmt: skip
        entry = access_point(model, tissue_q, state.path_entry_tri[k], state.path_entry_bary[k])
        point = access_point(model, tissue_q, tri, bary)
        heading_out = float((tip - strand_q[1]) @ n) > 0.0
        if heading_out and np.linalg.norm(point - entry) > params.path_spacing_min:
            state.tip_anchor_tri = tri
            state.tip_anchor_bary[:] = bary
            state.tip_anchor_inside = True


def tip_patch(model: CouplingModel, state: CouplingState, tissue_q: np.ndarray, tip: np.ndarray) -> None:
    """The tip's contact patch for its new anchor (``state.tip_anchor_tri``, ``tip_anchor_bary``): the surface
    vertices within ``model.tip_patch_radius`` of the anchor in the rest shape (the nearest
    :data:`TIP_PATCH_CAPACITY`), weighted by their lumped areas (a uniform pressure; weights sum to 1), or the
    anchor triangle's vertices with its barycentrics where no vertex is that near; the anchor triangle's series
    compliance ``alpha``; and the offset that puts the patch's weighted mean on the anchor at ``tissue_q``
    (N, 3) m. A tip anchored anew after it slid off its last anchor (``state.tip_slid``: that anchor's spring
    carried the last tip force ``F`` > 0) keeps the spring's deflection: the anchor is moved along the surface
    normal ``n`` there until the tip at ``tip`` (3,) m sits ``alpha F - eps`` below it, ``(tip - p) . n = eps -
    alpha F``, instead of jumping back to the surface. A tip force read without an anchor (the rigid contact rows
    of the nodes behind the point) deflected no spring, and that anchor starts at the surface. Writes the
    ``tip_patch_*`` fields of ``state``."""
    tri = state.tip_anchor_tri
    corners = model.surface.tri_vertices[tri]
    rest = model.tissue_rest_q
    anchor_rest = state.tip_anchor_bary @ rest[corners]
    d = np.linalg.norm(rest[model.surface_vertex] - anchor_rest, axis=1)
    inside = np.flatnonzero(d <= model.tip_patch_radius)
    if inside.size > TIP_PATCH_CAPACITY:
        inside = inside[np.argsort(d[inside], kind="stable")[:TIP_PATCH_CAPACITY]]
    if inside.size:
        vertices = model.surface_vertex[inside]
        weights = model.surface_vertex_area[inside] / model.surface_vertex_area[inside].sum()
    else:
        vertices, weights = corners, state.tip_anchor_bary.copy()
    count = vertices.size
    state.tip_patch_count = count
    state.tip_patch_vertex[:count] = vertices
    state.tip_patch_weight[:count] = weights
    state.tip_patch_weight[count:] = 0.0
    anchor = state.tip_anchor_bary @ tissue_q[corners]
    compliance = float(model.tri_tip_compliance[tri])
    if state.tip_slid and state.tip_force > 0.0:
        surface = model.surface
        n = surface_normal(
            tri, state.tip_anchor_bary, surface.tri_vertices, surface.vertex_tri_start, surface.vertex_tri_index,
            tissue_q,
        )  # fmt: skip
        anchor = anchor + float((tip - anchor) @ n - model.params.resistance_eps + compliance * state.tip_force) * n
    state.tip_patch_offset[:] = anchor - weights @ tissue_q[vertices]
    state.tip_patch_compliance = compliance


def tip_events(
    model: CouplingModel, state: CouplingState, work: CouplingWork, tissue, tissue_q: np.ndarray, tip: np.ndarray
) -> None:
    """Puncture, path growth, exit and backing out of the tip at ``tip`` (3,) m (module docstring, steps 3-5),
    for the tissue (:class:`~suture_gym.sim.model.TissueModel` ``tissue``) at ``tissue_q`` (N, 3) m; updates
    ``state``'s paths.

    Exit with a threshold (``exit_puncture_force > 0``): once the previous substep's tip force on the exit anchor
    (:func:`update_tip_anchor`) reaches it, the exit is pierced and the anchor let go; until then a tip found
    outside is not let out but anchored where it crossed, so the anchor pulls it back.

    Backing out: a tip that is outside while its entry lies on its own segment (``sigma_entry`` below the first
    needle segment's length) went back out through its entry. With an exit threshold the open path is then
    released at once (no exit is recorded), and the next push must puncture anew. Without one (today's default,
    kept bit for bit) the back-out is taken as an exit at the entry: the path closes with its exit next to its
    entry and is released by :func:`release_finished_paths` once no strand is left between the two (the next
    substeps while the tip moves away); a tip that stops right outside keeps that closed path, and its
    access rows hold the tip's segment at the surface, until it moves on."""
    params = model.params
    n = state.path_count
    open_k = n - 1 if n > 0 and state.path_open[n - 1] else -1
    tip_sdist = state.strand_sdist[0]
    if open_k < 0:
        _puncture(model, state, tissue)
        return
    if state.tip_anchor_inside and state.tip_anchor_tri >= 0 and state.tip_force >= params.exit_puncture_force:
        state.exit_pierced = True
        state.tip_anchor_tri = -1
        state.tip_anchor_inside = False
    if tip_sdist < 0.0 and not state.path_entered[open_k]:
        # the tip is through: the entry is where the strand crosses the surface (the puncture recorded the
        # tip's closest point from just outside)
        state.path_entered[open_k] = True
        tri, bary, _ = tip_crossing(model, state, work, tissue_q)
        state.path_entry_tri[open_k] = tri
        state.path_entry_bary[open_k] = bary
        slot = state.path_first[open_k]
        state.pathnode_tet[slot], state.pathnode_bary[slot] = surface_point_tet(model, tissue, tri, bary)
        return
    if state.path_entered[open_k] and tip_sdist > 0.0:
        if params.exit_puncture_force > 0.0 and state.path_sigma_entry[open_k] < model.strand_sigma[1]:
            release_path(state, open_k)  # backed out through the entry
            return
        tri, bary, crossed_at = tip_crossing(model, state, work, tissue_q, state.path_sigma_entry[open_k])
        if tri < 0:  # the needle's front left the tissue without crossing its surface: the bite is lost
            release_path(state, open_k)
            return
        if model.tri_rigid[tri]:
            return
        if params.exit_puncture_force > 0.0 and not state.exit_pierced:
            if state.tip_anchor_tri < 0:
                state.tip_anchor_tri = tri
                state.tip_anchor_bary[:] = bary
                state.tip_anchor_inside = True
            return
        state.path_open[open_k] = False
        state.path_exit_tri[open_k] = tri
        state.path_exit_bary[open_k] = bary
        state.path_sigma_exit[open_k] = crossed_at
        tet, tet_bary = surface_point_tet(model, tissue, tri, bary)
        append_path_nodes(state, model, np.array([tet]), tet_bary[None, :])
        return
    last = state.path_first[open_k] + state.path_len[open_k] - 1
    p_last = np.empty(3)
    pathnode_point(state.pathnode_tet, state.pathnode_bary, tissue.tet_indices, tissue_q, last, p_last)
    step = tip - p_last
    d = float(np.linalg.norm(step))
    count = path_spacing_count(d, params.path_spacing_min, params.path_spacing_max)
    if count == 0:
        return
    free = params.max_path_nodes - state.pathnode_count
    if count > free:
        state.overflow = True
        count = free
        if count == 0:
            return
    if state.path_len[open_k] >= 2:
        p_before = np.empty(3)
        pathnode_point(state.pathnode_tet, state.pathnode_bary, tissue.tet_indices, tissue_q, last - 1, p_before)
        forward = float(step @ (p_last - p_before)) > 0.0
    else:
        forward = tip_sdist < 0.0
    if not forward:
        return
    points = p_last + np.arange(1, count + 1)[:, None] / count * step
    if work.tet_bvh_stale:  # refitted here, the detection's one reader of it (most substeps grow no path)
        refit_bvh(work.tet_bvh, tissue_q, check_finite=False)
        work.tet_bvh_stale = False
    tets, barys = locate_points(points, work.tet_bvh, tissue_q, tolerance=1e-6)
    append_path_nodes(state, model, tets, barys)


def tip_crossing(
    model: CouplingModel, state: CouplingState, work: CouplingWork, tissue_q: np.ndarray, before: float = math.inf
) -> tuple[int, np.ndarray, float]:
    """(triangle, barycentrics, strand coordinate m) where the strand at detection (``work.strand_q`` (M, 3) m)
    nearest the tip crosses the surface (``work.surface``, refitted to ``tissue_q`` (N, 3) m) at a coordinate below
    ``before`` (m; an exit is searched for ahead of its path's entry), searched over the first four strand
    segments, then over the whole needle; the tip's closest surface point, at coordinate 0, when none crosses
    (triangle -1 when the tip is beyond the broad phase)."""
    nn = model.needle_node_count
    strand_q = work.strand_q
    sigma = model.strand_sigma
    for k in (min(4, strand_q.shape[0] - 1), nn - 1):
        hits = segment_crossings(strand_q[:k], strand_q[1 : k + 1], work.surface, tissue_q)
        for h in range(hits.crossing_tri.size):
            j = int(hits.crossing_segment[h])
            at = float(sigma[j] + hits.crossing_t[h] * (sigma[j + 1] - sigma[j]))
            if at < before:
                return int(hits.crossing_tri[h]), hits.crossing_bary[h].copy(), at
    return int(state.strand_tri[0]), state.strand_bary[0].copy(), 0.0


def release_finished_paths(model: CouplingModel, state: CouplingState, tissue_q: np.ndarray, tip: np.ndarray) -> None:
    """Release (module docstring, detection step 7): remove an open path whose tip, at ``tip`` (3,) m, backed out
    (``sigma_entry <= 0`` and more than ``path_spacing_min`` from the entry) and a closed path with no strand
    left inside (``sigma_exit >= sigma_entry``); ``tissue_q`` (N, 3) m."""
    for k in range(state.path_count - 1, -1, -1):
        if state.path_open[k]:
            b = access_point(model, tissue_q, state.path_entry_tri[k], state.path_entry_bary[k])
            release = state.path_sigma_entry[k] <= 0.0 and np.linalg.norm(tip - b) > model.params.path_spacing_min
        else:
            release = state.path_sigma_exit[k] >= state.path_sigma_entry[k]
        if release:
            release_path(state, k)


def _puncture(model: CouplingModel, state: CouplingState, tissue) -> None:
    """Puncture (module docstring, detection step 3) while no path is open: once the previous substep's tip
    force reaches ``puncture_force`` at a deformable face (the anchor's, else the tip's closest), a new open
    path starts there with its entry access point and first node; a full path vector flags overflow."""
    params = model.params
    n = state.path_count
    if state.tip_anchor_tri >= 0:
        tri, bary = int(state.tip_anchor_tri), state.tip_anchor_bary.copy()
    else:
        tri, bary = int(state.strand_tri[0]), state.strand_bary[0].copy()
    if state.tip_force >= params.puncture_force and tri >= 0 and not model.tri_rigid[tri]:
        if n >= params.max_paths or state.pathnode_count >= params.max_path_nodes:
            state.overflow = True
            return
        state.tip_anchor_tri = -1
        state.tip_patch_count = 0
        state.tip_patch_compliance = 0.0
        state.exit_pierced = False
        state.path_first[n] = state.pathnode_count
        state.path_len[n] = 0
        state.path_open[n] = True
        state.path_entered[n] = False
        state.path_entry_tri[n] = tri
        state.path_entry_bary[n] = bary
        state.path_exit_tri[n] = -1
        state.path_exit_bary[n] = 0.0
        state.path_sigma_entry[n] = 0.0
        state.path_sigma_exit[n] = -np.inf
        state.path_count = n + 1
        state.punctures += 1
        tet, tet_bary = surface_point_tet(model, tissue, tri, bary)
        append_path_nodes(state, model, np.array([tet]), tet_bary[None, :])
