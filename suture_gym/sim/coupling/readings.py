"""Force readings after the projection (tip force, friction, largest force, damage)."""

from __future__ import annotations

import math

import numpy as np

from suture_gym.sim.coupling.model import CouplingModel, CouplingState, CouplingWork
from suture_gym.sim.coupling.params import ROW_ANCHOR, ROW_EXIT, ROW_NONE, ROW_PATH, ROW_TRIANGLE


def coupling_finish(
    model: CouplingModel, state: CouplingState, work: CouplingWork, dt: float, tip_direction: np.ndarray
) -> None:
    """Force readings after the projection: the tip force, the total axial friction, the cutting force, the
    largest coupling force
    the tissue bore (rows against rigid faces, the base or a clamp, do not count) and the sticky damage flag
    (``max_force >= tear_force``); and the anchor's release when the tip slid.

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
    nn = model.needle_node_count
    d = np.asarray(tip_direction, dtype=np.float64)
    kind = work.row_kind[:nn]
    tip = model.strand_sigma[:nn] <= model.params.tip_length
    touching = tip & (kind == ROW_TRIANGLE)
    axial = -(work.row_contact_normal[:nn][touching] @ d)
    load = float(work.row_lambda[:nn][touching] @ axial)
    anchored = kind[0] == ROW_ANCHOR or kind[0] == ROW_EXIT
    if anchored:
        load -= work.row_lambda[0] * float(work.row_contact_normal[0] @ d) + float(work.tip_friction[:3] @ d)
        if work.tip_friction[3] > 0.0:
            state.tip_anchor_tri = -1
    state.tip_force = max(0.0, load * inv_dt2)
    state.friction_force = float(np.abs(work.row_friction_lambda).sum() * inv_dt2)
    state.cut_force = -float(work.cut_rows[4][0]) * inv_dt2
    on_support = (work.row_kind != ROW_NONE) & (work.row_kind != ROW_PATH) & model.tri_rigid[work.row_tri]
    largest = float(np.abs(np.where(on_support, 0.0, work.row_lambda)).max(initial=0.0))
    if anchored and not on_support[0]:
        largest = max(largest, math.hypot(work.row_lambda[0], float(np.linalg.norm(work.tip_friction[:3]))))
    if work.access_count:
        largest = max(largest, float(np.abs(work.access_lambda[: work.access_count]).max()))
    state.max_force = largest * inv_dt2
    if state.max_force >= (1.0 - 1.0e-9) * model.params.tear_force:  # a row held at its cap reads tear_force
        state.damaged = True
