"""Parameters of the strand-tissue interaction and the codes of node states and row kinds."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass

from suture_gym.sim.checks import is_real

#: Node states of paper section 4.1.
NODE_HEAD = 0
NODE_IN = 1
NODE_OUT = 2

#: Constraint row kinds of a strand node.
ROW_NONE = 0
ROW_TRIANGLE = 1
ROW_PATH = 2
ROW_ANCHOR = 3
ROW_WALL = 4
ROW_EXIT = 5

#: Tissue vertices a node-path row touches: the two tets of the path nodes either side of the projection.
PATH_ROW_VERTICES = 8

#: Radius of the tip's contact patch in mean boundary edge lengths, at least (``tip_contact_radius``): wide
#: enough that the mesh resolves the patch's load (a disc of one edge length covers one to four vertices).
TIP_PATCH_CELLS = 1.5

#: Most surface vertices in the tip's contact patch (the nearest are kept).
TIP_PATCH_CAPACITY = 64

#: Below this length (m) a direction is undefined and the constraint is skipped (degenerate geometry).
TINY_LENGTH = 1.0e-12


@dataclass(frozen=True)
class CouplingParams:
    """Parameters of the strand-tissue interaction (SI units).

    Attributes:
        puncture_force: force, N, the tip must exert on the surface to puncture it. Default 0.5 N, for the
            default 300 kPa tissue (measured suture-needle punctures: 0.5-2 N). Scale it with the tissue (the
            dent a force makes goes as ``F / E``): 1 N indents a 1 kPa tissue by several centimetres before it
            is reached; the seed paper's 1 kPa scenes use 15 mN (:data:`suture_gym.sim.scenes.PAPER_COUPLING`).
        tip_length: m; the tip force is the contact force of the needle nodes within this arc length of the
            point (the tapered tip: the default 2 mm spans the first three of the default needle's 30 nodes,
            which share the load once the dent is deeper than the node spacing).
        resistance_eps: ``eps`` of paper eq. 2 and Fig. 2a, m: thickness of the resistance layer, the gap the
            node-triangle constraint keeps between strand nodes and the surface.
        path_spacing_min: ``l`` of paper section 4.3, m: no path node is added closer than this to the last.
        path_spacing_max: ``h``, m: a longer step adds ``floor(d / h)`` nodes. Defaults ``l = 1.2 mm``,
            ``h = 1.7 mm`` (the paper's 1.2 / 1.7 cm scaled to a 26 mm needle): a bite through one 30 mm wound
            edge of the two-bar scene with the default half-circle needle is 10-14 mm of path, 6-11 nodes.
        tear_force: N, the largest force one node-path or node-access row transmits: beyond it the tissue gives
            way and the strand cuts through (tear-through forces of sutures are 3-4 N in soft tissue; the
            default 10 N is twenty times the default puncture force). A coupling force reaching it sets the
            sticky damage flag.
        tip_friction: Coulomb friction coefficient of the tip on the surface before puncture (>= 0): the sharp
            tip engages the surface point it first touches (the *anchor*) and slides only while the tangential
            force exceeds ``tip_friction`` times the normal force.
        depenetration_speed: m/s; a strand node that starts a substep inside a contact's resistance layer is
            moved out by at most ``depenetration_speed * dt`` per substep instead of all at once (a contact
            the prediction violates from outside is still resolved fully).
        needle_axial_friction: kinetic friction force per metre of needle inside the tissue, N/m, resisting
            the needle's motion along its path relative to the tissue (0 disables it). Coulomb-like: a constant
            force per length while it slides (no dependence on speed or on the normal load, which a constant
            radial pressure of the tissue on the wire makes constant too), any smaller force while it sticks.
            Default 150 N/m, for the default tissue.
        suture_axial_friction: kinetic friction force per metre of thread inside the tissue, N/m, resisting the
            thread's slide along its paths relative to the tissue, Coulomb-like as ``needle_axial_friction``
            (0, the default: the thread slides freely). Solved as rows of the rod's direct solve
            (:func:`~suture_gym.sim.coupling.suture_friction_rows`), so pulling the thread through feels it.
        exit_puncture_force: N; while the tip is inside and heads out through the surface, the surface holds
            it (the *exit anchor*, a contact from the inside with ``tip_friction``) until the force the tip
            exerts on it reaches this threshold, the second peak of an insertion (Frick et al. 2001 measure it
            at about half the entry's: the default 0.25 N). 0: the tip leaves with no threshold.
        cutting_force: N; while a puncture is open, the force that resists the tip's advance through the tissue
            along its direction (Okamura et al. 2004: constant for a given tip and tissue); zero while the tip
            does not advance. Default 0.1 N, a fifth of the puncture force; 0 disables it.
        tip_contact_radius: m; before puncture the tip loads the tissue as a flat punch of this radius: its
            contact force is spread over the surface patch within ``max(tip_contact_radius,
            TIP_PATCH_CELLS x`` the mean surface edge length ``)`` of its anchor, in series with the local
            half-space compliance the mesh cannot resolve (:func:`tip_series_compliance`), so the force-depth
            slope before puncture is set by the tip and the tissue, not by the cell size (default 1 mm). 0: the
            tip is one point of its anchor triangle and the needle nodes within ``tip_length`` share the load
            through their own contact rows. Measured (``pre_puncture_stiffness_vs_mesh``, 150 kPa, implicit
            tissue): the point tip's slope changes by 15% from 2 mm to 1 mm cells, this model's (1 mm) by 47%.
        contact_margin: m; node-triangle rows are made for strand nodes closer than ``eps + contact_margin`` to
            the surface (speculative contacts: a one-sided row acts only once violated, and a node that a
            projection left exactly at ``eps`` keeps its row in the next substep instead of flickering).
        track_window: half-width, m, of the strand interval searched around the previous strand coordinate
            of each access point: the farthest the strand may slide through an access point in one substep
            (2 mm: 2 m/s at 1 ms substeps).
        broad_phase_margin: m; strand nodes farther than this outside the tissue's bounding box are skipped.
        max_paths: capacity of the path vector; a puncture with no free slot is refused and flags overflow.
        max_path_nodes: capacity of the path-node buffer shared by all paths; growth stops (overflow) when full.
    """

    puncture_force: float = 0.5
    tip_length: float = 2.0e-3
    resistance_eps: float = 3.0e-4
    path_spacing_min: float = 1.2e-3
    path_spacing_max: float = 1.7e-3
    tear_force: float = 10.0
    tip_friction: float = 1.0
    depenetration_speed: float = 0.1
    needle_axial_friction: float = 150.0
    suture_axial_friction: float = 0.0
    exit_puncture_force: float = 0.25
    cutting_force: float = 0.1
    tip_contact_radius: float = 1.0e-3
    contact_margin: float = 1.0e-3
    track_window: float = 2.0e-3
    broad_phase_margin: float = 5.0e-3
    max_paths: int = 16
    max_path_nodes: int = 1024

    def __post_init__(self) -> None:
        for name in (
            "puncture_force",
            "tip_length",
            "resistance_eps",
            "path_spacing_min",
            "path_spacing_max",
            "tear_force",
            "depenetration_speed",
            "contact_margin",
            "track_window",
            "broad_phase_margin",
        ):
            value = getattr(self, name)
            if not (is_real(value) and math.isfinite(value) and value > 0.0):
                raise ValueError(f"CouplingParams.{name} must be a finite number > 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        for name in (
            "needle_axial_friction",
            "suture_axial_friction",
            "tip_friction",
            "exit_puncture_force",
            "cutting_force",
            "tip_contact_radius",
        ):
            value = getattr(self, name)
            if not (is_real(value) and math.isfinite(value) and value >= 0.0):
                raise ValueError(f"CouplingParams.{name} must be a finite number >= 0, got {value!r}")
            object.__setattr__(self, name, float(value))
        if self.path_spacing_min > self.path_spacing_max:
            raise ValueError(
                f"CouplingParams.path_spacing_min ({self.path_spacing_min}) must not exceed "
                f"path_spacing_max ({self.path_spacing_max})"
            )
        for name in ("max_paths", "max_path_nodes"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, numbers.Integral) or value < 1:
                raise ValueError(f"CouplingParams.{name} must be an integer >= 1, got {value!r}")
            object.__setattr__(self, name, int(value))
