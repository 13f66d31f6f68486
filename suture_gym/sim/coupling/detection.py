"""Detection: broad phase, constraint rows and their contact frames (detection steps 1, 8 and 9)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.bvh import refit_bvh
from suture_gym.sim.collision import (
    segment_crossings,
    signed_distance,
)
from suture_gym.sim.coupling.constraints import node_surface_constraint, surface_normal
from suture_gym.sim.coupling.model import CouplingModel, CouplingState, CouplingWork
from suture_gym.sim.coupling.params import (
    NODE_HEAD,
    NODE_IN,
    NODE_OUT,
    ROW_ANCHOR,
    ROW_NONE,
    ROW_PATH,
    ROW_TRIANGLE,
    ROW_WALL,
    TINY_LENGTH,
)
from suture_gym.sim.coupling.paths import (
    access_point,
    path_node_kinematics,
    project_onto_path,
    release_path,
    tip_events,
    update_tip_anchor,
)
from suture_gym.sim.coupling.tracking import track_sigma
from suture_gym.sim.quat import quat_to_matrix


@njit(cache=True)
def _segment_of(sigma, s):
    """Strand segment index j with ``sigma[j] <= s <= sigma[j+1]`` (clamped to valid segments)."""
    m = sigma.shape[0]
    lo = 0
    hi = m - 2
    while lo < hi:
        mid = (lo + hi + 1) // 2
        if sigma[mid] <= s:
            lo = mid
        else:
            hi = mid - 1
    return lo


@njit(cache=True)
def build_rows(
    sigma,
    strand_q,
    sdist,
    strand_tri,
    row_band,
    path_count,
    path_first,
    path_len,
    path_open,
    path_sigma_entry,
    path_sigma_exit,
    path_entry_tri,
    path_entry_bary,
    path_exit_tri,
    path_exit_bary,
    pathnode_tet,
    pathnode_bary,
    pathnode_q,
    pathnode_tangent,
    tet_indices,
    out_status,
    out_path,
    row_kind,
    row_tri,
    row_tissue,
    row_weight,
    row_tangent,
    access_node,
    access_weight,
    access_rest,
    access_tri,
    access_bary,
):
    """Node states and constraint rows of every strand node, and the node-access rows (module docstring,
    detection step 7); nodes not on a path get a node-triangle row when their signed distance is below
    ``row_band`` (m). Returns the number of access rows written.

    A node-access row acts on the strand piece of rest length ``2 h`` centred on the strand coordinate at
    the access point, with ``h`` half the rest length of the segment holding it; its ends are interpolated
    between strand nodes (clamped to the strand's ends)."""
    m = sigma.shape[0]
    total = sigma[m - 1]
    n_access = 0
    for k in range(path_count):
        for end in range(2):
            if end == 0:
                s = path_sigma_entry[k]
                tri = path_entry_tri[k]
            else:
                s = path_sigma_exit[k]
                tri = path_exit_tri[k]
            if tri < 0 or not (0.0 < s < total):
                continue
            j = _segment_of(sigma, s)
            half = 0.5 * (sigma[j + 1] - sigma[j])
            lo = max(s - half, 0.0)
            hi = min(s + half, total)
            for end_k in range(2):
                se = lo if end_k == 0 else hi
                je = _segment_of(sigma, se)
                alpha = (se - sigma[je]) / (sigma[je + 1] - sigma[je])
                access_node[n_access, 2 * end_k] = je
                access_node[n_access, 2 * end_k + 1] = je + 1
                access_weight[n_access, 2 * end_k] = 1.0 - alpha
                access_weight[n_access, 2 * end_k + 1] = alpha
            access_rest[n_access] = hi - lo
            access_tri[n_access] = tri
            if end == 0:
                access_bary[n_access] = path_entry_bary[k]
            else:
                access_bary[n_access] = path_exit_bary[k]
            n_access += 1
    for i in range(m):
        out_status[i] = NODE_HEAD if i == 0 else NODE_OUT
        out_path[i] = -1
        row_kind[i] = ROW_NONE
        row_tri[i] = -1
        if i == 0 and path_count > 0 and path_open[path_count - 1]:
            out_path[0] = path_count - 1  # the HEAD cuts its way: no row
            continue
        s = sigma[i]
        matched = -1
        for k in range(path_count):
            lo = -np.inf if path_open[k] else path_sigma_exit[k]
            if lo <= s < path_sigma_entry[k]:
                matched = k
                break
        if matched >= 0:
            out_path[i] = matched
            if i > 0:
                out_status[i] = NODE_IN
            ok, slot, u = project_onto_path(
                strand_q[i], path_first[matched], path_len[matched], pathnode_q, pathnode_tangent, path_open[matched]
            )
            if not ok:
                continue
            tan = (1.0 - u) * pathnode_tangent[slot] + u * pathnode_tangent[slot + 1]
            nt = math.sqrt(tan @ tan)
            if nt <= TINY_LENGTH:
                continue
            row_kind[i] = ROW_PATH
            row_tangent[i] = tan / nt
            for a in range(4):
                row_tissue[i, a] = tet_indices[pathnode_tet[slot], a]
                row_weight[i, a] = (1.0 - u) * pathnode_bary[slot, a]
                row_tissue[i, 4 + a] = tet_indices[pathnode_tet[slot + 1], a]
                row_weight[i, 4 + a] = u * pathnode_bary[slot + 1, a]
            continue
        if strand_tri[i] < 0 or not (sdist[i] < row_band):
            continue
        near_access = False
        for a in range(n_access):
            for e in range(4):
                if access_node[a, e] == i and access_weight[a, e] > 0.0:
                    near_access = True
        if near_access:
            continue
        row_kind[i] = ROW_TRIANGLE
        row_tri[i] = strand_tri[i]
    return n_access


@njit(cache=True)
def contact_frames(
    row_kind, row_tri, row_bary, tri_rigid, tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q, row_normal
):
    """Unit contact normal of every contact row at detection, at its surface point (``row_tri``, ``row_bary``):
    the face normal of a rigid triangle (``tri_rigid``), the smooth normal (:func:`surface_normal`) of a
    deforming one; turned inward for ROW_WALL. A row whose normal is undefined (a collapsed neighbourhood)
    is dropped (ROW_NONE). Writes ``row_normal`` (M, 3); updates ``row_kind``."""
    for i in range(row_kind.shape[0]):
        kind = row_kind[i]
        if kind != ROW_TRIANGLE and kind != ROW_WALL and kind != ROW_ANCHOR:
            continue
        tri = row_tri[i]
        if tri_rigid[tri]:
            a = tissue_q[tri_vertices[tri, 0]]
            n = np.cross(tissue_q[tri_vertices[tri, 1]] - a, tissue_q[tri_vertices[tri, 2]] - a)
            length = math.sqrt(n @ n)
            if length > 0.0:
                n /= length
        else:
            n = surface_normal(tri, row_bary[i], tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q)
        if not (n[0] != 0.0 or n[1] != 0.0 or n[2] != 0.0):
            row_kind[i] = ROW_NONE
            continue
        row_normal[i] = -n if kind == ROW_WALL else n


@njit(cache=True)
def contact_floors(
    needle_node_count,
    eps,
    depenetration,
    row_kind,
    row_tri,
    row_bary,
    row_normal,
    tri_vertices,
    needle_pos_prev,
    needle_quat_prev,
    needle_node_body,
    suture_q_prev,
    tissue_q_prev,
    out_floor,
):
    """Lower bound of each contact row's ``C`` this substep, from where the node was at the start of it:
    ``floor = min(0, C_0 + depenetration)`` with ``C_0`` the row's constraint (:func:`node_surface_constraint`,
    same frame) at the start-of-substep positions and ``depenetration`` (m) the most a node may be moved out
    per substep.

    A node that starts outside the resistance layer (``C_0 >= 0``) gets ``floor = 0``: the row removes the
    whole penetration the prediction caused, as a rigid contact must. A node that starts inside by ``-C_0``
    (the tissue folded over it, a path was released around it, a detection found it late) is moved out by at
    most ``depenetration`` per substep, so resolving an old penetration never launches the node or the tissue
    (the "maximum depenetration velocity" of game physics engines). Rows of other kinds get 0. Writes
    ``out_floor`` (M,) in m.
    """
    nn = needle_node_count
    r = quat_to_matrix(needle_quat_prev)
    for i in range(row_kind.shape[0]):
        out_floor[i] = 0.0
        kind = row_kind[i]
        if kind != ROW_TRIANGLE and kind != ROW_ANCHOR and kind != ROW_WALL:
            continue
        if i < nn:
            q0 = needle_pos_prev + r @ needle_node_body[i]
        else:
            q0 = suture_q_prev[i - nn + 1]
        tri = row_tri[i]
        c0 = node_surface_constraint(
            q0,
            tissue_q_prev[tri_vertices[tri, 0]],
            tissue_q_prev[tri_vertices[tri, 1]],
            tissue_q_prev[tri_vertices[tri, 2]],
            row_bary[i],
            row_normal[i],
            eps,
        )
        out_floor[i] = min(0.0, c0 + depenetration)


def rigid_crossings(model: CouplingModel, work: CouplingWork, tissue_q, strand_q_start, strand_q) -> None:
    """Rigid supports (module docstring, detection step 7): a strand node whose motion this substep,
    ``strand_q_start -> strand_q``, crosses a rigid face gets a contact row with that face at the crossing
    point that keeps it on the side it came from (outside: ROW_TRIANGLE, inside: ROW_WALL), whatever row it
    had; so neither a needle dragging the tissue down nor a tip cutting through it passes the base."""
    hits = segment_crossings(strand_q_start, strand_q, work.surface, tissue_q)
    done = np.zeros(strand_q.shape[0], dtype=bool)
    for h in np.flatnonzero(model.tri_rigid[hits.crossing_tri]):
        i = hits.crossing_segment[h]
        if done[i]:
            continue
        done[i] = True
        work.row_kind[i] = ROW_TRIANGLE if hits.crossing_direction[h] < 0 else ROW_WALL
        work.row_tri[i] = hits.crossing_tri[h]
        work.row_bary[i] = hits.crossing_bary[h]


def coupling_detect(
    model: CouplingModel,
    state: CouplingState,
    work: CouplingWork,
    tissue,
    tissue_q: np.ndarray,
    strand_q: np.ndarray,
    strand_q_start: np.ndarray | None = None,
) -> None:
    """Detection phase (module docstring, steps 1-7) for strand positions ``strand_q`` (M, 3) m against the
    tissue (:class:`~suture_gym.sim.model.TissueModel` ``tissue``, positions ``tissue_q`` (N, 3) m).
    ``strand_q_start`` (M, 3) m, the positions at the start of the substep, enables the rigid-support rows
    (:func:`rigid_crossings`).

    Updates ``state`` (distances, node states, paths, access points, puncture) and fills ``work``'s rows with
    zeroed multipliers. Uses ``state.tip_force`` from the previous substep for the puncture test.
    """
    params = model.params
    m = model.strand_node_count
    if strand_q.shape != (m, 3):
        raise ValueError(f"strand_q must have shape ({m}, 3), got {strand_q.shape}")
    work.strand_q[:] = strand_q
    refit_bvh(work.surface.bvh, tissue_q)
    refit_bvh(work.tet_bvh, tissue_q)

    lo = work.surface.bvh.node_lo[0] - params.broad_phase_margin
    hi = work.surface.bvh.node_hi[0] + params.broad_phase_margin
    near = np.flatnonzero(np.all((strand_q >= lo) & (strand_q <= hi), axis=1))
    state.strand_sdist[:] = np.inf
    state.strand_tri[:] = -1
    state.strand_bary[:] = 0.0
    if near.size:
        sdist, tri, bary = signed_distance(strand_q[near], work.surface, tissue_q)
        state.strand_sdist[near] = sdist
        state.strand_tri[near] = tri
        state.strand_bary[near] = bary

    sigma = model.strand_sigma
    window = params.track_window
    total = model.strand_length
    for k in range(state.path_count - 1, -1, -1):  # newest (front of the strand) first
        upper = state.path_sigma_exit[k - 1] if k > 0 else min(total, model.knot_sigma)
        newer_entry = state.path_sigma_entry[k + 1] if k + 1 < state.path_count else 0.0
        if not state.path_open[k]:
            b = access_point(model, tissue_q, state.path_exit_tri[k], state.path_exit_bary[k])
            state.path_sigma_exit[k] = track_sigma(
                strand_q, sigma, b, state.path_sigma_exit[k], window, newer_entry, state.path_sigma_entry[k]
            )[0]
            lower = state.path_sigma_exit[k]
        else:
            lower = 0.0
        b = access_point(model, tissue_q, state.path_entry_tri[k], state.path_entry_bary[k])
        state.path_sigma_entry[k] = track_sigma(strand_q, sigma, b, state.path_sigma_entry[k], window, lower, upper)[0]

    tip = strand_q[0]
    for k in range(state.path_count - 1, -1, -1):
        if state.path_open[k]:
            b = access_point(model, tissue_q, state.path_entry_tri[k], state.path_entry_bary[k])
            release = state.path_sigma_entry[k] <= 0.0 and np.linalg.norm(tip - b) > params.path_spacing_min
        else:
            release = state.path_sigma_exit[k] >= state.path_sigma_entry[k]
        if release:
            release_path(state, k)

    path_node_kinematics(
        state.pathnode_tet,
        state.pathnode_bary,
        tissue.tet_indices,
        tissue_q,
        state.path_first,
        state.path_len,
        state.path_count,
        work.pathnode_q,
        work.pathnode_tangent,
    )
    tip_events(model, state, work, tissue, tissue_q, tip)
    update_tip_anchor(model, state, tissue_q, tip)
    path_node_kinematics(
        state.pathnode_tet,
        state.pathnode_bary,
        tissue.tet_indices,
        tissue_q,
        state.path_first,
        state.path_len,
        state.path_count,
        work.pathnode_q,
        work.pathnode_tangent,
    )

    work.access_count = build_rows(
        sigma,
        strand_q,
        state.strand_sdist,
        state.strand_tri,
        params.resistance_eps + params.contact_margin,
        state.path_count,
        state.path_first,
        state.path_len,
        state.path_open,
        state.path_sigma_entry,
        state.path_sigma_exit,
        state.path_entry_tri,
        state.path_entry_bary,
        state.path_exit_tri,
        state.path_exit_bary,
        state.pathnode_tet,
        state.pathnode_bary,
        work.pathnode_q,
        work.pathnode_tangent,
        tissue.tet_indices,
        state.strand_status,
        state.strand_path,
        work.row_kind,
        work.row_tri,
        work.row_tissue,
        work.row_weight,
        work.row_tangent,
        work.access_node,
        work.access_weight,
        work.access_rest,
        work.access_tri,
        work.access_bary,
    )
    nn = model.needle_node_count
    tri = state.strand_tri[:nn]
    band = params.resistance_eps + params.contact_margin
    wall = (
        (work.row_kind[:nn] == ROW_NONE)
        & (state.strand_path[:nn] >= 0)
        & (tri >= 0)
        & (state.strand_sdist[:nn] > -band)
    )
    wall[wall] = model.tri_rigid[tri[wall]]
    work.row_kind[:nn][wall] = ROW_WALL
    work.row_tri[:nn][wall] = tri[wall]
    if state.tip_anchor_tri >= 0 and work.row_kind[0] != ROW_PATH:
        in_access = np.any((work.access_node[: work.access_count] == 0) & (work.access_weight[: work.access_count] > 0))
        if not in_access:
            work.row_kind[0] = ROW_ANCHOR
            work.row_tri[0] = state.tip_anchor_tri
    work.row_bary[:] = state.strand_bary
    if work.row_kind[0] == ROW_ANCHOR:
        work.row_bary[0] = state.tip_anchor_bary
    if strand_q_start is not None and model.tri_rigid.any():
        rigid_crossings(model, work, tissue_q, strand_q_start, strand_q)
    contact_frames(
        work.row_kind, work.row_tri, work.row_bary, model.tri_rigid, model.surface.tri_vertices,
        model.surface.vertex_tri_start, model.surface.vertex_tri_index, tissue_q, work.row_contact_normal,
    )  # fmt: skip
    work.row_lambda[:] = 0.0
    work.row_friction_lambda[:] = 0.0
    work.access_lambda[:] = 0.0
    work.tip_friction[:] = 0.0
