"""Needle/suture-tissue interaction (paper section 4), made XPBD: puncture, paths, access points and the
node-triangle, node-path and node-access constraints.

The strand
----------
The needle's arc nodes and the suture's nodes form one polyline, the *strand*, ordered from the needle tip to
the suture tail: strand node ``k < Nn`` is needle node ``k`` (node 0 is the tip, the HEAD; node ``Nn - 1`` the
swage) and strand node ``k >= Nn`` is suture node ``k - Nn + 1`` (suture node 0 sits on the swage through the
rod's attachment and is represented by the needle's swage node). Every strand node carries a material
coordinate ``sigma`` (m): its rest arc length from the tip along the polyline.

Detection (once per substep, after the prediction; :func:`coupling_detect`)
---------------------------------------------------------------------------
1. Broad phase: strand nodes outside the tissue's bounding box grown by ``broad_phase_margin`` are skipped;
   the others get their signed distance to the deformed surface with the closest triangle (BVHs refitted).
   Layers (paper Fig. 2a): inside ``s < 0``, resistance ``0 <= s < eps``, outside ``s >= eps``.
2. Matching (paper section 4.1, made continuous): each path records the strand coordinates ``sigma_entry``
   and ``sigma_exit`` of the strand points passing through its entry and exit access points, re-found every
   substep as the strand point nearest the access point within ``track_window`` of the previous value.
   A strand node with ``sigma_exit <= sigma < sigma_entry`` is IN that path; so is the strand's last node at
   ``sigma = sigma_entry``, where the entry coordinate stops once the thread's free end has gone in. Paths
   are made tip first, so the newest path holds the front of the strand, as in the paper; unlike a
   per-substep re-matching of segments, the coordinates move continuously and cannot swap paths when two
   strand segments come close.
3. Puncture: while no path is open, the tip is held out of the tissue by its *anchor*: the surface point it
   first comes within ``eps + contact_margin`` of (triangle + barycentric coordinates, a material point),
   kept while the tip stays within that band of it along the normal. The anchor row is paper eq. 2 against
   that point plus Coulomb friction (``tip_friction``): a sharp tip digs into the surface it touches and
   does not slide into the crease between two faces of the dent it makes (a node held against the
   closest face alone alternates between the faces of a crease and sinks through). A tip that slides (its
   friction at the Coulomb bound) lets go of the anchor and is anchored again where it is. When the force
   the tip region exerted on the tissue (the anchor row, and the contact rows of the needle nodes within
   ``tip_length`` of the point) against the tip's direction of travel in the previous substep reaches
   ``puncture_force``, the tip punctures: a new path opens whose first node and entry access point are the
   anchor; once the tip is through, both move to where the strand crosses the surface. Rigid faces (all
   three vertices pinned: the base, clamps) are never punctured. With ``tip_contact_radius > 0`` the anchor
   row spreads the tip's load over a surface patch in series with a local compliance
   (:func:`~suture_gym.sim.coupling.paths.tip_patch`, :func:`tip_series_compliance`).
4. Path growth (paper section 4.3): while the path is open and the tip moves on, with ``d`` the distance from
   the tip to the last path node: no node if ``d < l``, ``floor(d / h)`` evenly spaced nodes (the last at the
   tip) if ``d > h``, one at the tip otherwise. Path nodes are tet index + barycentric coordinates located
   in the deformed mesh, so they move with the tissue.
5. Exit: once the tip has been inside and is outside again, the point where the strand crosses the surface
   ahead of the path's entry (nearest the tip; the tip's closest surface point if none does) becomes the exit
   access point, at that strand coordinate, and the path's last node; the path closes. No exit through a rigid face;
   a needle whose front left the tissue without crossing its surface loses the open path. With
   ``exit_puncture_force > 0`` the tip heading out is first held by an *exit anchor* (the anchor row from the
   inside, ROW_EXIT) until its force on it reaches that threshold; a tip that backs out through its own entry
   then releases the open path (:func:`~suture_gym.sim.coupling.paths.tip_events`). While a path is open the
   tip's advance is resisted by ``cutting_force`` (:func:`project_cutting`).
6. Stopper knot (optional, :meth:`CouplingModel.build`'s ``knot_tail``): the thread carries a knot at strand
   coordinate ``knot_sigma``, too big to enter a hole. The oldest path's entry coordinate is bounded by it, so
   once the knot reaches that entry the entry's node-access row holds the knot's strand piece at the access
   point (to within half a strand segment): the thread no longer slides in there, and pulling it loads the
   tissue at the entry (two-way, within ``tear_force``) as a tied first stitch does.
7. Release: an open path whose tip backed out (``sigma_entry <= 0`` and the tip more than ``l`` away from
   the entry) and a closed path with no strand left inside (``sigma_exit >= sigma_entry``, e.g. the thread's
   free end pulled through) are removed.
8. Constraint rows: HEAD inside an open path: none (it cuts). IN nodes: node-path (eq. 1) onto the matched
   path's polyline (nodes of an open path ahead of its last path node: none, the tip region cuts freely).
   Other nodes within ``eps + contact_margin`` of the surface (the tip too while no path is open, by its
   anchor): a contact row (eq. 2), except the nodes of a strand piece through an access point. Needle nodes
   inside a path with no row (the cutting front) within the band of a rigid face: a wall row, eq. 2 from
   the inside, so a needle driven through the tissue stops at the base. Rigid supports: a strand node whose
   motion this substep crosses a rigid face gets a row with that face keeping it on its side, whatever row it
   had. Every access point with the strand through it: node-access (eq. 3) on the strand piece of one
   segment's length centred on ``sigma_entry`` / ``sigma_exit`` (so the access point never sits at a piece's
   end, where eq. 3's gradient would drag the tissue along with the strand).
9. Contact frames: every contact row holds its node against a fixed surface point (the closest point, the
   anchor or the crossing) along a normal fixed for the substep, the smooth (vertex-normal blend) normal
   there (:func:`surface_normal`; the face normal of a rigid face): eq. 2 linearised at detection
   (:func:`node_surface_constraint`). Face normals flip between neighbouring faces as a node moves across
   an edge or the tissue folds, which made the heavy needle knock light surface nodes back and forth.
   The solver then bounds how far each row may push its node out this substep (:func:`contact_floors`).

Projection (called by :class:`~suture_gym.sim.solver.Solver`)
--------------------------------------------------------------
* Needle rows act on the rigid needle through its generalised inverse mass (Muller et al. 2020), Gauss-Seidel
  (:func:`project_needle_rows`), with a kinetic axial friction per node inside the tissue.
* The thread is 4e-8 kg per node against 1e-4 kg tissue nodes and is solved by the rod's direct solver, so
  a plain Gauss-Seidel coupling would move only the thread: the rod pulls a taut thread straight across the
  path's bends, the node-path projection puts the node back, and the tissue never feels the tension. Hence
  suture nodes held on a path or passing an access point carry the inertia of the tissue point they are
  embedded in across the path and their own along it (:func:`embedded_inv_mass`), in their Gauss-Seidel
  node-path rows (:func:`project_suture_path_rows`) and in the rod's solve, so they slide freely along the
  path.
* Suture contact rows are one-sided contact rows inside the rod's direct solve, made two-way with the
  tissue: :func:`suture_contact_rows` gives each row the triangle's share of its inverse mass, which
  :func:`~suture_gym.sim.rod_solver.rod_iteration_kernel` adds to the row, and :func:`apply_contact_reaction` moves
  the tissue by its share. A node has one contact row: a static obstacle's (the base) takes it where its gap
  is the smaller one. Triangles on a support plane (``CouplingModel.tri_on_support``) give suture nodes no rows,
  nor do rigid triangles to suture nodes inside the tissue (the support is behind them: such a node came in
  through a free face, and a row out through the rigid one hooks the thread on the support).
* Node-access rows are Gauss-Seidel on the strand piece centred on the access point (:func:`project_access_rows`).
* Thread friction in the paths (``suture_axial_friction``, off by default) is a bounded row of the rod's direct
  solve per suture node on a path (:func:`suture_friction_rows`, :func:`apply_friction_reaction`): along its
  tangent the node is as light as the thread, so only a row inside the solve loads the pull.
* Contact rows of a node that started the substep inside the resistance layer push it out by at most
  ``depenetration_speed * dt`` (:func:`contact_floors`): an old penetration is resolved over several
  substeps instead of launching the node.
* The rows that hold a strand in the tissue (node-path and node-access) transmit at most ``tear_force``
  each (a needle node's path row: the size of its impulse summed as a vector, since its direction turns with the
  node's offset from the path): beyond it the tissue gives way and the strand cuts through it (the damage flag
  is set). Without this bound a needle wrenched sideways drags and crushes the tissue along its path until it
  inverts.

All rows are two-way: the tissue vertices take the reaction with their barycentric weights, so a needle pushed
against the tissue deforms it and a pulled thread closes the wound.
"""

from suture_gym.sim.coupling.constraints import (
    node_access_constraint,
    node_path_constraint,
    node_surface_constraint,
    surface_normal,
    tissue_point,
    xpbd_delta_lambda,
)
from suture_gym.sim.coupling.detection import (
    build_access_rows,
    build_node_rows,
    contact_floors,
    contact_frames,
    coupling_detect,
    rigid_crossings,
)
from suture_gym.sim.coupling.model import CouplingModel, CouplingState, CouplingWork, tip_series_compliance
from suture_gym.sim.coupling.needle_projection import project_cutting, project_needle_rows
from suture_gym.sim.coupling.params import (
    NODE_HEAD,
    NODE_IN,
    NODE_OUT,
    PATH_ROW_VERTICES,
    ROW_ANCHOR,
    ROW_EXIT,
    ROW_NONE,
    ROW_PATH,
    ROW_TRIANGLE,
    ROW_WALL,
    CouplingParams,
)
from suture_gym.sim.coupling.paths import (
    access_point,
    append_path_nodes,
    path_node_kinematics,
    path_spacing_count,
    project_onto_path,
    release_path,
    surface_point_tet,
    tip_crossing,
    tip_events,
    tip_patch,
    update_tip_anchor,
)
from suture_gym.sim.coupling.readings import coupling_finish
from suture_gym.sim.coupling.suture_projection import (
    apply_contact_reaction,
    apply_friction_reaction,
    embedded_inv_mass,
    project_access_rows,
    project_suture_path_rows,
    suture_contact_rows,
    suture_friction_rows,
)
from suture_gym.sim.coupling.tracking import strand_positions_kernel, track_sigma

__all__ = [
    "CouplingModel",
    "CouplingParams",
    "CouplingState",
    "CouplingWork",
    "NODE_HEAD",
    "NODE_IN",
    "NODE_OUT",
    "PATH_ROW_VERTICES",
    "ROW_ANCHOR",
    "ROW_EXIT",
    "ROW_NONE",
    "ROW_PATH",
    "ROW_TRIANGLE",
    "ROW_WALL",
    "access_point",
    "append_path_nodes",
    "apply_contact_reaction",
    "apply_friction_reaction",
    "build_access_rows",
    "build_node_rows",
    "contact_floors",
    "contact_frames",
    "coupling_detect",
    "coupling_finish",
    "embedded_inv_mass",
    "node_access_constraint",
    "node_path_constraint",
    "node_surface_constraint",
    "path_node_kinematics",
    "path_spacing_count",
    "project_access_rows",
    "project_cutting",
    "project_needle_rows",
    "project_onto_path",
    "project_suture_path_rows",
    "release_path",
    "rigid_crossings",
    "strand_positions_kernel",
    "surface_normal",
    "surface_point_tet",
    "suture_contact_rows",
    "suture_friction_rows",
    "tip_crossing",
    "tip_events",
    "tip_patch",
    "tip_series_compliance",
    "tissue_point",
    "track_sigma",
    "update_tip_anchor",
    "xpbd_delta_lambda",
]
