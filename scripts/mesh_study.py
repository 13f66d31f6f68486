"""Mesh-quality study: the seed paper's Tables 1-2 for this project.

The same two surfaces (the abdominal wall of ``configs/envs/abdominal_wall_*.yaml`` and the hand of
``suture_gym.sim.anatomy``) are tetrahedralised by every backend available, at the element size that gives about
the paper's tet counts (4,333 and 8,656), and each mesh is rated (:mod:`suture_gym.sim.mesh_quality`: the paper's
max/min face-angle ratio, the dihedral angle range, the radius ratio). Backends:

* ``structured``: the abdominal wall's own bent grid (what its env scene uses; abdominal wall only);
* ``voxel``: the built-in voxel backend (:func:`~suture_gym.sim.mesh_io.tetrahedralize_surface`);
* ``tetwild``: fTetWild through ``pytetwild`` (the ``mesh`` extra), if installed;
* ``tetgen``: TetGen through the ``tetgen`` package, if installed (AGPL: an optional study dependency only,
  never required; TetGen's quality switch on, ``maxvolume`` from the target edge; it keeps every triangle of the
  surface, so its counts follow the surface's).

With ``--suture`` each mesh also gets an incision (the scene's: along the wall's crest, along the back of the
hand) and the scripted surgeon makes one SutureThrow stitch on it (``scene.kind = mesh``, the default
SutureThrow settings, env seed 0): the row adds whether it succeeded or diverged, and the env steps per second
and real-time factor over the episode.

Usage::

    python scripts/mesh_study.py --json             # one row per (surface, backend)
    python scripts/mesh_study.py --json --suture    # and a scripted stitch on each (minutes)
"""

from __future__ import annotations

import argparse
import importlib.util
import json
import math
import sys
import tempfile
import time
from pathlib import Path

from _common import configure

configure(threads=1)

import numpy as np  # noqa: E402
import trimesh  # noqa: E402

from suture_gym.sim.anatomy import curved_slab, hand_surface, surface_height  # noqa: E402
from suture_gym.sim.mesh import TetMesh, surface_triangles  # noqa: E402
from suture_gym.sim.mesh_io import tetrahedralize_surface, write_tet_mesh  # noqa: E402
from suture_gym.sim.mesh_quality import mesh_quality  # noqa: E402

#: The paper's tet counts (Table 1): TetWild's abdominal wall and TetGen's hand.
PAPER_TETS = {"abdominal_wall": 4333, "hand": 8656}
#: Marching-tets spacing of the hand's surface, m: 7,400 triangles. TetGen keeps every surface triangle and
#: refines the skinny ones, so a finer surface gives it many more tets (57k here, 176k at 4 mm).
HAND_SPACING = 0.006
#: Meshes above this many times the paper's tets get no scripted stitch (``--suture``): not the paper's scale.
STITCH_TETS_FACTOR = 2
#: The abdominal wall of configs/envs/abdominal_wall_*.yaml: size (m) and grid.
WALL_SIZE, WALL_GRID = (0.06, 0.04, 0.012), (14, 10, 6)


def _surfaces() -> dict:
    wall, _ = curved_slab(WALL_SIZE, WALL_GRID)
    wall_surface = trimesh.Trimesh(wall.vertices, surface_triangles(wall.tets))
    return {"abdominal_wall": (wall_surface, wall), "hand": (hand_surface(HAND_SPACING), None)}


def _tetgen(surface, edge: float) -> TetMesh:
    import tetgen

    generator = tetgen.TetGen(np.asarray(surface.vertices, dtype=np.float64), np.asarray(surface.faces))
    nodes, elements, *_ = generator.tetrahedralize(quality=True, maxvolume=edge**3 / (6.0 * math.sqrt(2.0)))
    from suture_gym.sim.mesh import signed_volumes

    elements = np.asarray(elements, dtype=np.int64)
    flip = signed_volumes(nodes, elements) < 0
    elements[flip, 2], elements[flip, 3] = elements[flip, 3].copy(), elements[flip, 2].copy()
    return TetMesh(nodes, elements.astype(np.int32))


def _backends(name: str, surface, structured) -> dict:
    """``backend -> callable returning a TetMesh`` for the surface ``name``."""
    volume = float(surface.volume)
    target = PAPER_TETS[name]
    regular = (6.0 * math.sqrt(2.0) * volume / target) ** (1.0 / 3.0)  # edge of target regular tets
    cell = (5.0 * volume / target) ** (1.0 / 3.0)  # cell of target five-tet cells
    out = {}
    if structured is not None:
        out["structured"] = lambda: structured
    out["voxel"] = lambda: tetrahedralize_surface(surface, cell, backend="voxel")
    if importlib.util.find_spec("pytetwild") is not None:
        out["tetwild"] = lambda: tetrahedralize_surface(surface, regular, backend="tetwild")
    if importlib.util.find_spec("tetgen") is not None:
        out["tetgen"] = lambda: _tetgen(surface, regular)
    return out


def _incision(name: str, mesh: TetMesh) -> dict:
    """The scene's incision on ``mesh``: along the wall's crest over its middle two thirds, 8 mm deep; along the
    back of the hand (on a grid plane near y = 0 for a voxel mesh), 1 cm deep."""
    if name == "abdominal_wall":
        x = np.linspace(WALL_SIZE[0] / 6.0, 5.0 * WALL_SIZE[0] / 6.0, 5)
        y, depth = 0.0, 2.0 / 3.0 * WALL_SIZE[2]
    else:
        x = np.linspace(-0.02, 0.025, 6)
        lattice = np.unique(np.round(mesh.vertices[:, 1], 12))
        near = lattice[np.abs(lattice) < 0.004]
        y = float(near[np.argmin(np.abs(near))]) if len(near) > 20 else 0.0
        depth = 0.01
    points = np.stack([x, np.full_like(x, y), surface_height(mesh, x, y)], axis=1)
    return {"points": points.tolist(), "depth": depth}


def _stitch(name: str, mesh: TetMesh) -> dict:
    """One scripted SutureThrow stitch on ``mesh`` with the scene's incision (``scene.kind = mesh``)."""
    import gymnasium as gym

    import suture_gym.envs  # noqa: F401
    from suture_gym.baselines.expert import ExpertPolicy

    with tempfile.TemporaryDirectory() as tmp:
        path = str(Path(tmp) / f"{name}.vtu")
        write_tet_mesh(path, mesh)
        edge = float(np.median(np.linalg.norm(np.diff(mesh.vertices[mesh.tets[:, :2]], axis=1)[:, 0], axis=1)))
        config = {"scene": {"kind": "mesh", "path": path, "cell_size": edge, "gap": 0.0015,
                            "incision": _incision(name, mesh)}}
        try:
            env = gym.make("SutureGym/SutureThrow-v3", config=config)
        except ValueError as error:
            return {"stitch": "not built", "error": str(error)}
        expert = ExpertPolicy(env)
        obs, _ = env.reset(seed=0)
        start, steps, info = time.perf_counter(), 0, {}
        while True:
            obs, _, terminated, truncated, info = env.step(expert(obs))
            steps += 1
            if terminated or truncated:
                break
        wall = time.perf_counter() - start
        sim = env.unwrapped.sim
        env.close()
    end = next((k for k in ("diverged", "tear", "missed", "out_of_workspace") if info.get(k)), None)
    end = end or ("success" if info.get("is_success") else "time_limit")
    return {"stitch": end, "stitch_env_steps": steps, "env_steps_per_s": steps / wall,
            "realtime_factor": steps * sim.substeps * sim.dt / wall}


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--json", action="store_true", help="print the rows as JSON")
    parser.add_argument("--suture", action="store_true", help="also make a scripted stitch on every mesh")
    args = parser.parse_args(argv)
    rows = []
    for name, (surface, structured) in _surfaces().items():
        for backend, build in _backends(name, surface, structured).items():
            start = time.perf_counter()
            try:
                mesh = build()
            except (ValueError, RuntimeError) as error:
                rows.append({"surface": name, "backend": backend, "error": str(error)})
                continue
            row = {"surface": name, "backend": backend, "mesh_s": time.perf_counter() - start,
                   "paper_tets": PAPER_TETS[name], "vertices": mesh.vertex_count,
                   "boundary_triangles": int(len(surface_triangles(mesh.tets))),
                   **mesh_quality(mesh.vertices, mesh.tets)}
            if args.suture and mesh.tet_count <= STITCH_TETS_FACTOR * PAPER_TETS[name]:
                row.update(_stitch(name, mesh))
            elif args.suture:
                row["stitch"] = f"skipped: above {STITCH_TETS_FACTOR} x the paper's tets"
            rows.append(row)
            print(f"{name} / {backend}: {row['tets']} tets", file=sys.stderr)
    if args.json:
        print(json.dumps(rows, indent=2))
    else:
        for row in rows:
            print(", ".join(f"{k}={v:.4g}" if isinstance(v, float) else f"{k}={v}" for k, v in row.items()))
    return 0


if __name__ == "__main__":
    sys.exit(main())
