"""Force readings after the projection (tip force, friction, largest force, damage)."""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from suture_gym.sim.coupling.model import CouplingModel, CouplingState, CouplingWork
from suture_gym.sim.coupling.params import ROW_ANCHOR, ROW_EXIT, ROW_NONE, ROW_PATH, ROW_TRIANGLE


def coupling_finish(
    model: CouplingModel, state: CouplingState, work: CouplingWork, dt: float, tip_direction: np.ndarray
) -> None:
    """Force readings after the projection: the tip force, the total axial friction, the cutting force, the
    largest coupling force the tissue bore (``max_force``; rows against rigid faces, the base or a clamp, do not
    count) and the sticky damage flag; and the anchor's release when the tip slid.

    Damage is set when a row that holds a strand in the tissue (node-path or node-access) transmits
    ``tear_force``, the cap at which it gives way and the strand cuts through. Contact rows (node-triangle, the
    tip's anchor) count in ``max_force`` (the tissue-force reading and cost) but never tear: nothing in the
    model cuts under them, the surface dents; a squeezed contact can read over the tear force for a substep
    (the thread wrapping a held edge as the swage enters: 11-14 N for one substep, about 1 N the next).

    The tip force (N), the puncture test of the next substep, is the force the tissue's contact rows exert
    against the tip's direction of travel ``tip_direction`` (3,) (unit, world) on the needle nodes within
    ``tip_length`` of the point: ``sum_i lambda_i (n_i . -d) / dt^2`` over their node-triangle rows, plus the
    anchor row's (entry or exit anchor's) normal and friction force along ``-d``, clipped at 0: the load that
    drives the cut (the exit puncture test too, while the tip presses on the exit anchor from the inside). (In a
    dent the surface normals tilt, and the lateral part of the contact force is carried by the holder, not by
    the cutting edge.) A tip that slid this substep (its friction at the Coulomb bound) lets go of its anchor;
    the next detection anchors it where it is.
    """
    inv_dt2 = 1.0 / (dt * dt)
    d = np.ascontiguousarray(tip_direction, dtype=np.float64)
    load, friction, largest, held, slid = _readings(
        model.needle_node_count, model.params.tip_length, model.strand_sigma, model.tri_rigid, work.row_kind,
        work.row_tri, work.row_contact_normal, work.row_lambda, work.row_friction_lambda, work.tip_friction,
        work.access_lambda, work.access_count, d,
    )  # fmt: skip
    if slid:
        state.tip_anchor_tri = -1
    state.tip_slid = bool(slid)
    state.tip_force = max(0.0, load * inv_dt2)
    state.friction_force = friction * inv_dt2
    state.cut_force = -float(work.cut_rows[4][0]) * inv_dt2
    state.max_force = largest * inv_dt2
    if held * inv_dt2 >= (1.0 - 1.0e-9) * model.params.tear_force:  # a row held at its cap reads tear_force
        state.damaged = True


@njit(cache=True)
def _readings(nn, tip_length, strand_sigma, tri_rigid, row_kind, row_tri, row_contact_normal, row_lambda,
              row_friction_lambda, tip_friction, access_lambda, access_count, d):  # fmt: skip
    """The sums of :func:`coupling_finish` in one pass over the rows: ``(load, friction, largest, held, slid)``,
    the tip's axial load and the summed friction multipliers (kg m, summed in node order), the largest multiplier
    the tissue bore and the largest of a node-path or node-access row (kg m), and whether the anchored tip
    slid."""
    load = 0.0
    for i in range(nn):
        if strand_sigma[i] <= tip_length and row_kind[i] == ROW_TRIANGLE:
            n = row_contact_normal[i]
            load += row_lambda[i] * -(n[0] * d[0] + n[1] * d[1] + n[2] * d[2])
    anchored = row_kind[0] == ROW_ANCHOR or row_kind[0] == ROW_EXIT
    slid = False
    if anchored:
        n = row_contact_normal[0]
        load -= row_lambda[0] * (n[0] * d[0] + n[1] * d[1] + n[2] * d[2]) + (
            tip_friction[0] * d[0] + tip_friction[1] * d[1] + tip_friction[2] * d[2]
        )
        slid = tip_friction[3] > 0.0
    friction = 0.0
    for i in range(row_friction_lambda.shape[0]):
        friction += abs(row_friction_lambda[i])
    largest = 0.0
    held = 0.0
    support_0 = False
    for i in range(row_kind.shape[0]):
        if row_kind[i] == ROW_PATH:
            held = max(held, abs(row_lambda[i]))
        # rows against rigid faces (the base, a clamp) are not borne by the tissue
        on_support = row_kind[i] != ROW_NONE and row_kind[i] != ROW_PATH and tri_rigid[row_tri[i]]
        if i == 0:
            support_0 = on_support
        if not on_support:
            largest = max(largest, abs(row_lambda[i]))
    if anchored and not support_0:
        f = tip_friction
        largest = max(largest, math.hypot(row_lambda[0], math.sqrt(f[0] * f[0] + f[1] * f[1] + f[2] * f[2])))
    for i in range(access_count):
        held = max(held, abs(access_lambda[i]))
    largest = max(largest, held)
    return load, friction, largest, held, slid
