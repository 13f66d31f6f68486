"""The one place where the environments read the simulator's state: the events of a substep (punctures and exits,
as material points) and the :class:`~suture_gym.tasks.Observables` the tasks read.

The coupling state keeps counters and per-path arrays, not an event record, so the events of a substep are
inferred by comparing :func:`coupling_mark` (taken before it) with the state after it (:func:`substep_events`).
Event points are material points: the access point's triangle and barycentric coordinates evaluated in the
tissue's rest shape, so "where the needle went in" does not depend on how far the needle had dented the surface
at that moment, and compares directly with the planned points (defined on the rest shape).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from suture_gym.sim.coupling import access_point
from suture_gym.sim.model import Model, State
from suture_gym.sim.quat import quat_to_matrix
from suture_gym.tasks import Observables


@dataclass(frozen=True)
class CouplingMark:
    """The coupling counters before a substep: punctures so far, paths, and whether the tip's path was open."""

    punctures: int
    path_count: int
    punctured: bool


def coupling_mark(state: State) -> CouplingMark:
    """:class:`CouplingMark` of ``state`` (take it before a substep)."""
    c = state.coupling
    return CouplingMark(int(c.punctures), int(c.path_count), bool(c.punctured))


def substep_events(model: Model, mark: CouplingMark, state: State) -> tuple[np.ndarray | None, np.ndarray | None]:
    """``(entry, exit)`` of the substep that led from ``mark`` to ``state``: the ``(3,)`` material point (m, rest
    shape) of a new puncture and of the tip coming out of the path it was in, or None for each that did not
    happen."""
    c = state.coupling
    rest = model.tissue.particle_rest_q
    entry = exit_ = None
    if c.punctures > mark.punctures and c.path_count > 0:
        k = c.path_count - 1
        entry = access_point(model.coupling, rest, c.path_entry_tri[k], c.path_entry_bary[k])
    if mark.punctured and c.path_count == mark.path_count and not c.path_open[mark.path_count - 1]:
        k = mark.path_count - 1
        exit_ = access_point(model.coupling, rest, c.path_exit_tri[k], c.path_exit_bary[k])
    return entry, exit_


def thread_through(model: Model, state: State) -> float:
    """Thread beyond the needle that has come out of the newest exit point, m (0 before any exit)."""
    c = state.coupling
    n = c.path_count
    newest = n - 1 if n > 0 and not c.path_open[n - 1] else n - 2
    if newest < 0:
        return 0.0
    swage = float(model.coupling.strand_sigma[model.needle.node_count - 1])
    return max(0.0, float(c.path_sigma_exit[newest]) - swage)


def mean_gap(q: np.ndarray, left: np.ndarray, right: np.ndarray) -> float:
    """Mean y of the ``right`` (k,) particles of ``q`` (N, 3) minus that of the ``left`` ones, m (0 when there
    are none)."""
    if left.size == 0 or right.size == 0:
        return 0.0
    return float(q[right, 1].mean() - q[left, 1].mean())


def observables(model: Model, state: State, entries: list, exits: list, faces: tuple[np.ndarray, np.ndarray],
                suture_samples: int) -> Observables:
    """The :class:`~suture_gym.tasks.Observables` of ``state`` (copies) with the recorded ``entries`` and
    ``exits`` (lists of ``(3,)`` points, m), the wound gap between the ``faces`` (left, right particle indices)
    and ``suture_samples`` thread nodes sampled evenly from the swage to the tail."""
    needle_model = model.needle
    needle = state.needle
    coupling = state.coupling
    rot = quat_to_matrix(needle.body_quat)
    pos = needle.body_pos
    samples = np.zeros((0, 3))
    if state.suture is not None and suture_samples:
        nodes = state.suture.node_pos
        samples = nodes[np.round(np.linspace(0, len(nodes) - 1, suture_samples)).astype(np.int64)].copy()
    gap = mean_gap(state.tissue.particle_q, *faces)
    return Observables(
        time=float(state.time),
        tip_pos=pos + rot @ needle_model.tip_pos_body,
        tip_dir=rot @ needle_model.tip_dir_body,
        needle_normal=rot @ needle_model.plane_normal_body,
        needle_center=pos + rot @ needle_model.arc_center_body,
        grip_pos=pos + rot @ needle_model.grip_pos_body,
        needle_vel=needle.body_vel.copy(),
        needle_omega=needle.body_omega.copy(),
        tip_sdist=float(coupling.strand_sdist[0]),
        punctured=bool(coupling.punctured),
        path_count=int(coupling.path_count),
        new_entries=np.array(entries).reshape(-1, 3),
        new_exits=np.array(exits).reshape(-1, 3),
        tip_force=float(coupling.tip_force),
        tissue_force=float(coupling.max_force),
        haptic_wrench=state.needle_reaction.copy(),
        damaged=bool(coupling.damaged),
        wound_gap=max(gap, 0.0),
        wound_overlap=max(-gap, 0.0),
        thread_through=thread_through(model, state),
        suture_samples=samples,
        diverged=bool(state.diverged),
    )
