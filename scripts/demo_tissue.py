"""Tissue demo: a forceps grasps the wound edge of the paper's two-bar scene, pulls it across, and lets go.

The two soft bars of ``two_bar_wound`` (paper Fig. 5; 1 kPa, nu = 0.49, resting on a rigid base) are
simulated with the XPBD solver. A patch of top-surface particles on the left bar's wound edge is held
kinematically (as a forceps would) and moved ``--pull`` metres towards the right bar over ``--pull-time``
seconds, held, then released. The script prints the wound gap (mean distance between the facing wound
faces, measured along the wound over its upper quarter) in each phase and writes the deformed mesh at maximum pull
to ``out/demo_tissue.vtu`` (open it in ParaView).

Usage::

    python scripts/demo_tissue.py [--pull 0.003] [--pull-time 0.5] [--release-time 1.0] [--dt 0.001]
"""

from __future__ import annotations

import argparse
import sys
import time

from _common import ROOT, configure

configure(threads=2)

import numpy as np  # noqa: E402
from tqdm import tqdm  # noqa: E402

from suture_gym.sim.mesh import TetMesh  # noqa: E402
from suture_gym.sim.model import Control, Model, State, TissueModel, TissueState  # noqa: E402
from suture_gym.sim.scenes import PAPER_SOLVER, PAPER_TISSUE, two_bar_wound  # noqa: E402


def wound_face_pairs(rest: np.ndarray, left: np.ndarray, right: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Pair each left wound-face particle with the right one at the same (x, z) rest position."""
    key_l = np.round(rest[left][:, [0, 2]], 9)
    key_r = np.round(rest[right][:, [0, 2]], 9)
    order_l = np.lexsort(key_l.T[::-1])
    order_r = np.lexsort(key_r.T[::-1])
    if not np.array_equal(key_l[order_l], key_r[order_r]):
        raise ValueError("the wound faces of this scene do not match node for node")
    return left[order_l], right[order_r]


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--pull", type=float, default=0.003, help="forceps displacement towards the wound, m")
    parser.add_argument("--pull-time", type=float, default=0.5, help="duration of the pull, s")
    parser.add_argument("--release-time", type=float, default=1.0, help="simulated time after release, s")
    parser.add_argument("--dt", type=float, default=0.001, help="substep, s")
    args = parser.parse_args(argv)
    for name in ("pull", "pull_time", "release_time", "dt"):
        value = getattr(args, name)
        if not (np.isfinite(value) and value > 0):
            parser.error(f"--{name.replace('_', '-')} must be a positive number, got {value}")

    scene = two_bar_wound(material=PAPER_TISSUE)
    tissue = scene.model.tissue
    rest = tissue.particle_rest_q
    width, height = scene.settings["bar_size_m"][1], scene.settings["bar_size_m"][2]
    length = scene.settings["bar_size_m"][0]

    # The forceps: top-surface particles of the left bar within 7.5 mm of the wound, mid-length.
    is_left = np.zeros(tissue.particle_count, dtype=bool)
    is_left[scene.regions["left_bar"]] = True
    grasp = (
        is_left
        & (np.abs(rest[:, 2] - height) < 1e-9)
        & (rest[:, 1] > width - 0.0075)
        & (np.abs(rest[:, 0] - length / 2) < 0.0075)
    )
    mesh = TetMesh(vertices=rest, tets=tissue.tet_indices)
    pinned = (tissue.particle_inv_mass == 0.0) | grasp
    model = Model(
        tissue=TissueModel.from_mesh(mesh, PAPER_TISSUE,
                                     pinned=pinned), gravity=scene.model.gravity
    )
    state = State(tissue=TissueState.at_rest(model.tissue))
    solver, control = PAPER_SOLVER, Control()

    left, right = wound_face_pairs(rest, scene.regions["left_wound_face"], scene.regions["right_wound_face"])
    top = rest[left, 2] >= 0.75 * height  # the upper quarter, where the forceps acts

    def gap() -> float:
        q = state.tissue.particle_q
        return float(np.mean(q[right[top], 1] - q[left[top], 1]))

    grasped = np.flatnonzero(grasp)
    start = rest[grasped].copy()
    settle, n_pull = int(round(1.0 / args.dt)), int(round(args.pull_time / args.dt))
    n_hold, n_release = n_pull // 2, int(round(args.release_time / args.dt))
    total = settle + n_pull + n_hold + n_release
    gaps: dict[str, float] = {}
    t0 = time.perf_counter()
    for k in tqdm(range(total), desc="simulating", unit="substep", file=sys.stderr):
        if k == settle:
            gaps["settled under gravity"] = gap()
        if settle <= k < settle + n_pull + n_hold:
            s = min(1.0, (k - settle + 1) / n_pull)
            state.tissue.particle_q[grasped] = start + np.array([0.0, args.pull * s, 0.0])
        if k == settle + n_pull + n_hold:
            gaps["held at full pull"] = gap()
            out = ROOT / "out"
            out.mkdir(exist_ok=True)
            try:
                from suture_gym.sim.mesh_io import write_tet_mesh

                write_tet_mesh(
                    out / "demo_tissue.vtu", mesh, {"displacement_m": state.tissue.particle_q - rest}
                )
            except ImportError as exc:
                print(f"(not writing out/demo_tissue.vtu: {exc})", file=sys.stderr)
            # Release: hand the grasped particles back to the solver.
            model = Model(tissue=tissue, gravity=scene.model.gravity)
        solver.step(model, state, control, args.dt)
        if state.diverged:
            print(f"simulation diverged at t = {state.time:.4f} s", file=sys.stderr)
            return 1
    gaps["after release"] = gap()
    wall = time.perf_counter() - t0

    print(f"two_bar_wound: {tissue.tet_count} tets, {tissue.particle_count} particles, dt = {args.dt} s")
    print(f"rest wound gap: {scene.settings['gap_m'] * 1e3:.3f} mm; forceps pull: {args.pull * 1e3:.2f} mm")
    for phase, value in gaps.items():
        print(f"  wound gap {phase:24s} {value * 1e3:7.3f} mm")
    print(f"simulated {state.time:.2f} s in {wall:.1f} s wall ({state.time / wall:.2f}x real time)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
