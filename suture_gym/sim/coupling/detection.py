"""Detection: broad phase, constraint rows and their contact frames (detection steps 1, 8 and 9)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.bvh import refit_bvh
from suture_gym.sim.collision_kernels import crossings_kernel, signed_distance_kernel
from suture_gym.sim.coupling.constraints import node_surface_constraint, surface_normal
from suture_gym.sim.coupling.model import CouplingModel, CouplingState, CouplingWork, crossing_buffers
from suture_gym.sim.coupling.params import (
    NODE_HEAD,
    NODE_IN,
    NODE_OUT,
    ROW_ANCHOR,
    ROW_EXIT,
    ROW_NONE,
    ROW_PATH,
    ROW_TRIANGLE,
    ROW_WALL,
    TINY_LENGTH,
)
from suture_gym.sim.coupling.paths import (
    path_node_kinematics,
    project_onto_path,
    release_finished_paths,
    tip_events,
    update_tip_anchor,
)
from suture_gym.sim.coupling.tracking import track_access_points
from suture_gym.sim.quat import cross3, quat_to_matrix


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
def build_access_rows(sigma, paths, access):
    """The node-access rows of every path's entry and exit with the strand through them (module docstring,
    detection step 8); returns how many were written.

    A node-access row acts on the strand piece of rest length ``2 h`` centred on the strand coordinate at the
    access point, with ``h`` half the rest length of the segment holding it; its ends are interpolated between
    strand nodes (clamped to the strand's ends).

    Args:
        sigma: ``(M,)`` strand node coordinates, m.
        paths: :func:`path_arrays` of the coupling state.
        access: ``CouplingWork.access_rows``, written: ``(access_node (2K, 4), access_weight (2K, 4),
            access_rest (2K,) m, access_tri (2K,), access_bary (2K, 3))``.
    """
    path_count, _, _, _, sigma_entry, sigma_exit, entry_tri, entry_bary, exit_tri, exit_bary = paths
    access_node, access_weight, access_rest, access_tri, access_bary = access
    m = sigma.shape[0]
    total = sigma[m - 1]
    n_access = 0
    for k in range(path_count):
        for end in range(2):
            s = sigma_entry[k] if end == 0 else sigma_exit[k]
            tri = entry_tri[k] if end == 0 else exit_tri[k]
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
                access_bary[n_access] = entry_bary[k]
            else:
                access_bary[n_access] = exit_bary[k]
            n_access += 1
    return n_access


@njit(cache=True, inline="always")
def _path_row(i, q, first, count, is_open, pathnodes, tet_indices, rows):
    """Node-path row (eq. 1) of strand node ``i`` at ``q`` (3,) m on the path with path-node slots
    ``first .. first + count - 1``: the tangent and the eight tissue vertices and weights of the projection
    point (:func:`project_onto_path`), or no row where the projection is undefined."""
    pathnode_tet, pathnode_bary, pathnode_q, pathnode_tangent = pathnodes
    row_kind, _, row_tissue, row_weight, row_tangent = rows
    ok, slot, u = project_onto_path(q, first, count, pathnode_q, pathnode_tangent, is_open)
    if not ok:
        return
    tan = (1.0 - u) * pathnode_tangent[slot] + u * pathnode_tangent[slot + 1]
    nt = math.sqrt(tan @ tan)
    if nt <= TINY_LENGTH:
        return
    row_kind[i] = ROW_PATH
    row_tangent[i] = tan / nt
    for a in range(4):
        row_tissue[i, a] = tet_indices[pathnode_tet[slot], a]
        row_weight[i, a] = (1.0 - u) * pathnode_bary[slot, a]
        row_tissue[i, 4 + a] = tet_indices[pathnode_tet[slot + 1], a]
        row_weight[i, 4 + a] = u * pathnode_bary[slot + 1, a]


@njit(cache=True, inline="always")
def _in_access_piece(i, n_access, access_node, access_weight):
    """Strand node ``i`` carries weight in one of the first ``n_access`` node-access rows."""
    for a in range(n_access):
        for e in range(4):
            if access_node[a, e] == i and access_weight[a, e] > 0.0:
                return True
    return False


@njit(cache=True)
def build_node_rows(sigma, strand_q, sdist, strand_tri, row_band, paths, pathnodes, tet_indices, access, n_access,
                    suture_skip, out_status, out_path, rows):  # fmt: skip
    """Node states and constraint rows of every strand node (module docstring, detection step 8): the HEAD of
    an open path none; nodes matched to a path (``sigma_exit <= sigma < sigma_entry``, or ``<= sigma_entry``
    for the strand's last node: the entry coordinate cannot pass the free end, so once the thread's end has
    gone in through the entry it stays at the end, and the end node, inside the tissue, is still in the path) a
    node-path row (:func:`_path_row`); others a node-triangle row with their closest triangle when their signed distance
    is below ``row_band`` (m), unless they carry one of the ``n_access`` node-access rows or are suture nodes
    (from strand index ``suture_skip[0]``) whose closest triangle lies on a support (``suture_skip[1]`` (F,)
    bool, ``CouplingModel.tri_on_support``: the base is the suture's obstacle there) or, for a node inside the
    tissue (``sdist < 0``), is rigid (``suture_skip[2]`` (F,) bool, ``CouplingModel.tri_rigid``): a face glued
    to a support (a clamp, the body holding an anatomy patch at its edges) has the support behind it, so a
    thread node that sank into the tissue beside it came in through a free face and cannot leave through that
    one; its row there would hold the thread against the pull like a hook on the support.

    Args:
        sigma: ``(M,)`` m. strand_q: ``(M, 3)`` m. sdist: ``(M,)`` m. strand_tri: ``(M,)`` closest triangles.
        paths: :func:`path_arrays`. pathnodes: ``(pathnode_tet (P,), pathnode_bary (P, 4), pathnode_q (P, 3) m,
            pathnode_tangent (P, 3))``. tet_indices: ``(T, 4)``. access: ``CouplingWork.access_rows``.
        out_status: ``(M,) int8`` written. out_path: ``(M,) int32`` written.
        rows: ``CouplingWork.node_rows`` ``(row_kind, row_tri, row_tissue, row_weight, row_tangent)``, written.
    """
    path_count, path_first, path_len, path_open, sigma_entry, sigma_exit = paths[:6]
    row_kind, row_tri = rows[0], rows[1]
    for i in range(sigma.shape[0]):
        out_status[i] = NODE_HEAD if i == 0 else NODE_OUT
        out_path[i] = -1
        row_kind[i] = ROW_NONE
        row_tri[i] = -1
        if i == 0 and path_count > 0 and path_open[path_count - 1]:
            out_path[0] = path_count - 1  # the HEAD cuts its way: no row
            continue
        matched = -1
        last = i == sigma.shape[0] - 1
        for k in range(path_count):
            lo = -np.inf if path_open[k] else sigma_exit[k]
            if lo <= sigma[i] < sigma_entry[k] or (last and lo <= sigma[i] == sigma_entry[k]):
                matched = k
                break
        if matched >= 0:
            out_path[i] = matched
            if i > 0:
                out_status[i] = NODE_IN
            _path_row(i, strand_q[i], path_first[matched], path_len[matched], path_open[matched], pathnodes,
                      tet_indices, rows)  # fmt: skip
            continue
        if strand_tri[i] < 0 or not (sdist[i] < row_band) or _in_access_piece(i, n_access, access[0], access[1]):
            continue
        tri = strand_tri[i]
        if i >= suture_skip[0] and (suture_skip[1][tri] or (sdist[i] < 0.0 and suture_skip[2][tri])):
            continue
        row_kind[i] = ROW_TRIANGLE
        row_tri[i] = strand_tri[i]


def path_arrays(state: CouplingState) -> tuple:
    """The path vector of ``state`` as the kernels take it: ``(path_count, path_first, path_len, path_open,
    path_sigma_entry, path_sigma_exit, path_entry_tri, path_entry_bary, path_exit_tri, path_exit_bary)``
    (shapes and units as in :class:`CouplingState`)."""
    return (
        state.path_count, state.path_first, state.path_len, state.path_open, state.path_sigma_entry,
        state.path_sigma_exit, state.path_entry_tri, state.path_entry_bary, state.path_exit_tri, state.path_exit_bary,
    )  # fmt: skip


@njit(cache=True)
def contact_frames(
    row_kind, row_tri, row_bary, tri_rigid, tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q, strand_q,
    row_normal,
):  # fmt: skip
    """Unit contact normal of every contact row at detection, at its surface point (``row_tri``, ``row_bary``):
    on a rigid triangle (``tri_rigid``) the face normal, or for a node outside it (ROW_TRIANGLE, ``strand_q``
    (M, 3) m in front of the face's plane) the direction from the surface point to the node: the gradient of
    the distance, which past a convex edge of a rigid body (a clamped end face meeting the top) tilts around
    the edge instead of holding the node to the face's plane beyond its end; on a deforming one the smooth
    normal (:func:`surface_normal`). Turned inward for the rows from the inside (ROW_WALL, ROW_EXIT). A row
    whose normal is undefined (a collapsed neighbourhood) is dropped (ROW_NONE). Writes ``row_normal`` (M, 3);
    updates ``row_kind``."""
    d = np.empty(3)
    for i in range(row_kind.shape[0]):
        kind = row_kind[i]
        if kind != ROW_TRIANGLE and kind != ROW_WALL and kind != ROW_ANCHOR and kind != ROW_EXIT:
            continue
        tri = row_tri[i]
        if tri_rigid[tri]:
            a = tissue_q[tri_vertices[tri, 0]]
            n = cross3(tissue_q[tri_vertices[tri, 1]] - a, tissue_q[tri_vertices[tri, 2]] - a)
            length = math.sqrt(n @ n)
            if length > 0.0:
                n /= length
            if kind == ROW_TRIANGLE:
                for k in range(3):
                    d[k] = strand_q[i, k]
                    for v in range(3):
                        d[k] -= row_bary[i, v] * tissue_q[tri_vertices[tri, v], k]
                distance = math.sqrt(d @ d)
                if distance > 0.0 and d @ n > 0.0:
                    n = d / distance
        else:
            n = surface_normal(tri, row_bary[i], tri_vertices, vertex_tri_start, vertex_tri_index, tissue_q)
        if not (n[0] != 0.0 or n[1] != 0.0 or n[2] != 0.0):
            row_kind[i] = ROW_NONE
            continue
        row_normal[i] = -n if kind == ROW_WALL or kind == ROW_EXIT else n


@njit(cache=True)
def contact_floors(needle_node_count, eps, depenetration, contact_rows, tri_vertices, needle_start, suture_q_prev,
                   tissue_q_prev):  # fmt: skip
    """Lower bound of each contact row's ``C`` this substep, from where the node was at the start of it:
    ``floor = min(0, C_0 + depenetration)`` with ``C_0`` the row's constraint (:func:`node_surface_constraint`,
    same frame) at the start-of-substep positions and ``depenetration`` (m) the most a node may be moved out
    per substep.

    A node that starts outside the resistance layer (``C_0 >= 0``) gets ``floor = 0``: the row removes the
    whole penetration the prediction caused, as a rigid contact must. A node that starts inside by ``-C_0``
    (the tissue folded over it, a path was released around it, a detection found it late) is moved out by at
    most ``depenetration`` per substep, so resolving an old penetration never launches the node or the tissue
    (the "maximum depenetration velocity" of game physics engines). Rows of other kinds get 0.

    Args:
        contact_rows: ``CouplingWork.contact_rows``, ``(row_kind, row_tri, row_bary, row_contact_normal,
            row_floor)``; writes ``row_floor`` (M,) in m.
        needle_start: ``(pos_prev (3,) m, quat_prev (4,), node_body (Nn, 3) m)``, the needle at the substep's start.
        suture_q_prev: ``(Ns, 3)`` m. tissue_q_prev: ``(N, 3)`` m.
    """
    row_kind, row_tri, row_bary, row_normal, out_floor = contact_rows
    needle_pos_prev, needle_quat_prev, needle_node_body = needle_start
    nn = needle_node_count
    r = quat_to_matrix(needle_quat_prev)
    for i in range(row_kind.shape[0]):
        out_floor[i] = 0.0
        kind = row_kind[i]
        if kind != ROW_TRIANGLE and kind != ROW_ANCHOR and kind != ROW_WALL and kind != ROW_EXIT:
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
    had; so neither a needle dragging the tissue down nor a tip cutting through it passes the base. Of several
    rigid crossings of one node the first (smallest ``t``, then triangle) counts, as in
    :func:`~suture_gym.sim.collision.segment_crossings`' order. The crossings go to ``work.crossings`` (grown when
    full), so a substep allocates nothing."""
    tree = work.surface.bvh.tree
    count = crossings_kernel(strand_q_start, strand_q, tree, tissue_q, *work.crossings)
    if count > work.crossings[0].shape[0]:
        work.crossings = crossing_buffers(count)
        count = crossings_kernel(strand_q_start, strand_q, tree, tissue_q, *work.crossings)
    if count:
        _rigid_rows(count, *work.crossings, model.tri_rigid, work.row_kind, work.row_tri, work.row_bary)


@njit(cache=True)
def _rigid_rows(count, segment, tri, bary, t, direction, tri_rigid, row_kind, row_tri, row_bary):
    """:func:`rigid_crossings`' rows from its first ``count`` crossings (``segment``, ``tri``, ``bary``, ``t``,
    ``direction``: :func:`~suture_gym.sim.collision_kernels.crossings_kernel`'s outputs, unsorted)."""
    first = np.full(row_kind.shape[0], -1, np.int64)
    for h in range(count):
        if not tri_rigid[tri[h]]:
            continue
        i = segment[h]
        b = first[i]
        if b < 0 or t[h] < t[b] or (t[h] == t[b] and tri[h] < tri[b]):
            first[i] = h
    for i in range(row_kind.shape[0]):
        h = first[i]
        if h < 0:
            continue
        row_kind[i] = ROW_TRIANGLE if direction[h] < 0 else ROW_WALL
        row_tri[i] = tri[h]
        row_bary[i] = bary[h]


def coupling_detect(
    model: CouplingModel,
    state: CouplingState,
    work: CouplingWork,
    tissue,
    tissue_q: np.ndarray,
    strand_q: np.ndarray,
    strand_q_start: np.ndarray | None = None,
) -> None:
    """Detection phase (module docstring, steps 1-9) for strand positions ``strand_q`` (M, 3) m against the
    tissue (:class:`~suture_gym.sim.model.TissueModel` ``tissue``, positions ``tissue_q`` (N, 3) m).
    ``strand_q_start`` (M, 3) m, the positions at the start of the substep, enables the rigid-support rows
    (:func:`rigid_crossings`).

    Updates ``state`` (distances, node states, paths, access points, puncture) and fills ``work``'s rows with
    zeroed multipliers. Uses ``state.tip_force`` from the previous substep for the puncture test.
    """
    m = model.strand_node_count
    if strand_q.shape != (m, 3):
        raise ValueError(f"strand_q must have shape ({m}, 3), got {strand_q.shape}")
    work.strand_q[:] = strand_q
    strand_distances(model, state, work, tissue_q, strand_q)
    track_access_points(model, state, tissue_q, strand_q)
    release_finished_paths(model, state, tissue_q, strand_q[0])
    tip_events(model, state, work, tissue, tissue_q, strand_q[0])
    update_tip_anchor(model, state, tissue_q, strand_q)
    path_node_kinematics(
        state.pathnode_tet, state.pathnode_bary, tissue.tet_indices, tissue_q, state.path_first, state.path_len,
        state.path_count, work.pathnode_q, work.pathnode_tangent,
    )  # fmt: skip
    paths = path_arrays(state)
    band = model.params.resistance_eps + model.params.contact_margin
    work.access_count = build_access_rows(model.strand_sigma, paths, work.access_rows)
    pathnodes = (state.pathnode_tet, state.pathnode_bary, work.pathnode_q, work.pathnode_tangent)
    suture_skip = (model.needle_node_count, model.tri_on_support, model.tri_rigid)
    build_node_rows(
        model.strand_sigma, strand_q, state.strand_sdist, state.strand_tri, band, paths, pathnodes,
        tissue.tet_indices, work.access_rows, work.access_count, suture_skip, state.strand_status, state.strand_path,
        work.node_rows,
    )  # fmt: skip
    _wall_and_anchor_rows(model, state, work)
    if strand_q_start is not None and model.tri_rigid.any():
        rigid_crossings(model, work, tissue_q, strand_q_start, strand_q)
    contact_frames(
        work.row_kind, work.row_tri, work.row_bary, model.tri_rigid, model.surface.tri_vertices,
        model.surface.vertex_tri_start, model.surface.vertex_tri_index, tissue_q, strand_q, work.row_contact_normal,
    )  # fmt: skip
    work.row_lambda[:] = 0.0
    work.row_friction_lambda[:] = 0.0
    work.row_impulse[:] = 0.0
    work.access_lambda[:] = 0.0
    work.tip_friction[:] = 0.0
    _tip_patch_row(state, work)
    _cutting_row(model, state, work, tissue.tet_indices, strand_q)


def strand_distances(
    model: CouplingModel, state: CouplingState, work: CouplingWork, tissue_q: np.ndarray, strand_q: np.ndarray
) -> None:
    """Broad phase and signed distances (module docstring, detection step 1): refit ``work``'s surface BVH to
    ``tissue_q`` (N, 3) m (and mark its tet BVH stale: :func:`~suture_gym.sim.coupling.paths.tip_events` refits it
    when a path grows, the one detection step that reads it); strand nodes (``strand_q`` (M, 3) m) within
    ``broad_phase_margin`` of the tissue's box get their signed distance, closest triangle and barycentrics in
    ``state``, the others ``+inf``, -1, 0."""
    # No validation here: the solver checked tissue_q and the strand's positions finite just before detection.
    refit_bvh(work.surface.bvh, tissue_q, check_finite=False)
    work.tet_bvh_stale = True
    surface = work.surface
    signed_distance_kernel(
        strand_q, model.params.broad_phase_margin, surface.bvh.tree, surface.tri_neighbors, surface.vertex_tri_start,
        surface.vertex_tri_index, tissue_q, state.strand_sdist, state.strand_tri, state.strand_bary,
    )  # fmt: skip


def _wall_and_anchor_rows(model: CouplingModel, state: CouplingState, work: CouplingWork) -> None:
    """Wall rows for needle nodes inside a path with no row within the band of a rigid face, the tip's anchor
    row (unless it carries a node-access row or a path row), and every row's surface point (the closest point,
    or the anchor) (:func:`_wall_and_anchor_kernel`)."""
    _wall_and_anchor_kernel(
        model.needle_node_count, model.params.resistance_eps + model.params.contact_margin, model.tri_rigid,
        model.strand_sigma, model.params.tip_length, state.strand_tri, state.strand_path, state.strand_sdist,
        state.strand_bary, int(state.tip_anchor_tri), bool(state.tip_anchor_inside), state.tip_anchor_bary,
        int(state.tip_patch_count), work.access_node, work.access_weight, int(work.access_count), work.row_kind,
        work.row_tri, work.row_bary,
    )  # fmt: skip


@njit(cache=True)
def _wall_and_anchor_kernel(nn, band, tri_rigid, strand_sigma, tip_length, strand_tri, strand_path, strand_sdist,
                            strand_bary, anchor_tri, anchor_inside, anchor_bary, patch_count, access_node,
                            access_weight, access_count, row_kind, row_tri, row_bary):  # fmt: skip
    """:func:`_wall_and_anchor_rows` over the ``nn`` needle nodes (one pass instead of a dozen numpy calls on
    arrays of a few elements): a node with no row, inside a path (``strand_path >= 0``) and within ``band`` (m)
    of a rigid face gets a ROW_WALL with it; the tip gets its anchor's row (ROW_EXIT from the inside, else
    ROW_ANCHOR) unless it has a path row or is in a node-access row; an anchor with a contact patch takes the
    contact rows of the nodes within ``tip_length`` (m) behind the point; ``row_bary`` gets the closest points,
    the tip's the anchor's."""
    for i in range(nn):
        tri = strand_tri[i]
        if row_kind[i] == ROW_NONE and strand_path[i] >= 0 and tri >= 0 and strand_sdist[i] > -band and tri_rigid[tri]:
            row_kind[i] = ROW_WALL
            row_tri[i] = tri
    if anchor_tri >= 0 and row_kind[0] != ROW_PATH:
        in_access = False
        for a in range(access_count):
            for k in range(access_node.shape[1]):
                if access_node[a, k] == 0 and access_weight[a, k] > 0:
                    in_access = True
        if not in_access:
            row_kind[0] = ROW_EXIT if anchor_inside else ROW_ANCHOR
            row_tri[0] = anchor_tri
    if row_kind[0] == ROW_ANCHOR and patch_count > 0:
        # the tip-contact row stands for the whole taper: no rows of its own for the nodes behind the point
        for i in range(1, nn):
            if strand_sigma[i] <= tip_length and row_kind[i] == ROW_TRIANGLE:
                row_kind[i] = ROW_NONE
    row_bary[:] = strand_bary
    if row_kind[0] == ROW_ANCHOR or row_kind[0] == ROW_EXIT:
        row_bary[0] = anchor_bary


def _tip_patch_row(state: CouplingState, work: CouplingWork) -> None:
    """This substep's copy of the tip's contact patch (``state.tip_patch_*``) for the anchor row; an empty
    patch (the anchor is a point of its triangle) unless the tip's row is a ROW_ANCHOR."""
    vertex, weight, count, offset, compliance = work.tip_patch
    count[0] = state.tip_patch_count if work.row_kind[0] == ROW_ANCHOR else 0
    vertex[:] = state.tip_patch_vertex
    weight[:] = state.tip_patch_weight
    offset[:] = state.tip_patch_offset
    compliance[0] = state.tip_patch_compliance if count[0] > 0 else 0.0


def _cutting_row(model: CouplingModel, state: CouplingState, work: CouplingWork, tet_indices, strand_q) -> None:
    """The tip's cutting row this substep (``CouplingWork.cut_rows``): while a path is open and the tip has no
    contact row (it is not held by an exit anchor or a rigid face), a cap of ``cutting_force`` against its advance
    along its direction (from strand node 1 to the tip, ``strand_q`` (M, 3) m) relative to the tissue at the
    open path's last node (tet ``tet_indices`` (T, 4) and barycentrics); cap 0 otherwise."""
    tissue_idx, tissue_w, direction, cap, lam = work.cut_rows
    cap[0] = 0.0
    lam[0] = 0.0
    force = model.params.cutting_force
    if force <= 0.0 or not state.punctured or work.row_kind[0] != ROW_NONE:
        return
    k = state.path_count - 1
    last = state.path_first[k] + state.path_len[k] - 1
    chord = strand_q[0] - strand_q[1]
    length = float(np.linalg.norm(chord))
    if last < state.path_first[k] or length <= TINY_LENGTH:
        return
    tissue_idx[:] = tet_indices[state.pathnode_tet[last]]
    tissue_w[:] = state.pathnode_bary[last]
    direction[:] = chord / length
    cap[0] = force
