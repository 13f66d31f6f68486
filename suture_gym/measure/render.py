"""Benchmark of the software renderer (:mod:`suture_gym.render`) on a scene at the paper's Table 1 row 1 scale.

Scene (built here from boxes, without the simulator): two 95 x 30 x 30 mm bars side by side with a 4 mm wound
gap, each surface subdivided into 20 x 6 x 6 cells (2,208 triangles, 1,108 vertices in all), pressed down
near the wound and swaying a little so the vertex normals change every frame; a 30-node semicircular needle
(radius 8 mm, wire radius 0.4 mm) through both wound edges; a 200-node suture (radius 0.1 mm) trailing over
the tissue; an entry and an exit marker; the force gauge and a caption.

Benchmark ``render_paper_cube``: median milliseconds per frame of :meth:`SceneRenderer.render` (everything:
transform, normals, rasterisation, shading, overlays, the output image) at 256 x 256 and 480 x 480, at
256 x 256 with 2 x 2 supersampling, and at both sizes with back-face culling (the scene's boxes are closed and
outward-oriented, so culling draws the same image with about half the triangle work). For comparison, the
paper's renderer took 4.81 % of its 28.57 ms step (1.37 ms, on a GPU).
"""

from __future__ import annotations

import time

import numpy as np

from suture_gym.measure.registry import benchmark
from suture_gym.render import RenderFrame, SceneRenderer

BAR_SIZE = (0.095, 0.03, 0.03)  # m
BAR_CELLS = (20, 6, 6)
WOUND_GAP = 0.004  # m, between the bars along y
NEEDLE_NODES = 30
NEEDLE_RADIUS = 0.008  # m, radius of the needle's arc
NEEDLE_WIRE_RADIUS = 4e-4  # m
SUTURE_NODES = 200
SUTURE_RADIUS = 1e-4  # m
FRAMES = 40  # timed frames per resolution


def box_surface(size, cells, origin=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """Outward-oriented triangulated surface of an axis-aligned box.

    size (3,) m, cells (3,) ints (subdivisions along x, y, z), origin (3,) m (the minimum corner).
    Returns ``(vertices (V,3) float64 m, triangles (F,3) int32)`` with vertices shared between faces and
    ``F = 4 (nx ny + ny nz + nz nx)``.
    """
    n = np.asarray(cells, dtype=np.int64)
    quads = []
    for a in range(3):
        b, c = (a + 1) % 3, (a + 2) % 3
        ib, ic = np.meshgrid(np.arange(n[b]), np.arange(n[c]), indexing="ij")
        ib, ic = ib.ravel(), ic.ravel()
        for side in (0, n[a]):
            corners = []
            for db, dc in ((0, 0), (1, 0), (1, 1), (0, 1)):
                lattice = np.zeros((len(ib), 3), dtype=np.int64)
                lattice[:, a] = side
                lattice[:, b] = ib + db
                lattice[:, c] = ic + dc
                corners.append(lattice)
            if side == 0:  # e_b x e_c = +e_a, so reverse the corners on the minimum side
                corners = corners[::-1]
            quads.append(np.stack(corners, axis=1))
    quads = np.concatenate(quads)  # (Q, 4, 3) lattice coordinates
    lattice, inverse = np.unique(quads.reshape(-1, 3), axis=0, return_inverse=True)
    idx = inverse.reshape(-1, 4)
    triangles = np.concatenate([idx[:, [0, 1, 2]], idx[:, [0, 2, 3]]]).astype(np.int32)
    vertices = np.asarray(origin, dtype=np.float64) + lattice * (np.asarray(size) / n)
    return vertices, triangles


def paper_cube_scene() -> tuple[np.ndarray, np.ndarray]:
    """Rest vertices (V,3) m and triangles (F,3) int32 of the two bars."""
    va, ta = box_surface(BAR_SIZE, BAR_CELLS)
    vb, tb = box_surface(BAR_SIZE, BAR_CELLS, origin=(0.0, BAR_SIZE[1] + WOUND_GAP, 0.0))
    return np.vstack([va, vb]), np.vstack([ta, tb + len(va)]).astype(np.int32)


def paper_cube_frame(rest_q: np.ndarray, triangles: np.ndarray, time_s: float) -> RenderFrame:
    """The benchmark frame at ``time_s``: pressed tissue, needle through the wound, trailing suture, markers."""
    top = BAR_SIZE[2]
    y_mid = BAR_SIZE[1] + 0.5 * WOUND_GAP
    centre = np.array([0.5 * BAR_SIZE[0], y_mid])
    r2 = ((rest_q[:, :2] - centre) ** 2).sum(axis=1)
    depth = 0.003 * (0.5 + 0.5 * np.sin(2 * np.pi * 1.0 * time_s))
    q = rest_q.copy()
    q[:, 2] -= depth * np.exp(-r2 / 0.02**2) * (rest_q[:, 2] / top)
    q[:, 1] += 0.0005 * np.sin(2 * np.pi * 0.5 * time_s + 40.0 * rest_q[:, 0])

    x_needle = 0.045 + 0.005 * np.sin(2 * np.pi * 0.25 * time_s)
    theta = np.linspace(0.0, np.pi, NEEDLE_NODES)
    needle = np.column_stack(
        [
            np.full(NEEDLE_NODES, x_needle),
            y_mid + NEEDLE_RADIUS * np.cos(theta),
            top + 0.003 - NEEDLE_RADIUS * np.sin(theta),
        ]
    )
    # Suture: from the needle's swage end (theta = 0) in a loose loop over the tissue towards -x.
    s = np.linspace(0.0, 1.0, SUTURE_NODES)
    swage = needle[0]
    suture = np.column_stack(
        [
            swage[0] - 0.04 * s,
            swage[1] + 0.012 * np.sin(np.pi * s) * np.cos(2 * np.pi * (s + 0.1 * time_s)),
            swage[2] + 0.004 * np.sin(np.pi * s) * (1.0 - s) + 0.0005 * s,
        ]
    )
    markers = np.array([[x_needle + 0.012, y_mid - 0.006, top], [x_needle + 0.012, y_mid + 0.006, top]])
    return RenderFrame(
        tissue_q=q,
        tissue_triangles=triangles,
        needle_q=needle,
        needle_radius=NEEDLE_WIRE_RADIUS,
        suture_q=suture,
        suture_radius=SUTURE_RADIUS,
        marker_q=markers,
        marker_radius=1e-3,
        tip_force=0.83 + 0.3 * np.sin(2 * np.pi * 0.5 * time_s),
        force_threshold=1.0,
        caption=f"SutureThrow t={time_s:.2f} s",
    )


def _median_frame_ms(renderer: SceneRenderer, rest_q: np.ndarray, triangles: np.ndarray) -> tuple[float, float]:
    """(median, 90th percentile) ms per frame over FRAMES frames after one warm-up frame."""
    renderer.render(paper_cube_frame(rest_q, triangles, 0.0))
    frames = [paper_cube_frame(rest_q, triangles, 0.02 * i) for i in range(FRAMES)]
    times = []
    for frame in frames:
        t0 = time.perf_counter()
        renderer.render(frame)
        times.append(time.perf_counter() - t0)
    return float(np.median(times) * 1e3), float(np.percentile(times, 90) * 1e3)


@benchmark("render_paper_cube")
def render_paper_cube() -> dict:
    """Frame times of the scene renderer; ``substep_ms`` holds the median 256 x 256 frame time."""
    rest_q, triangles = paper_cube_scene()
    results = {}
    for label, size, ssaa, cull in (
        ("256x256", 256, 1, False),
        ("480x480", 480, 1, False),
        ("256x256_ssaa2", 256, 2, False),
        ("256x256_cull", 256, 1, True),
        ("480x480_cull", 480, 1, True),
    ):
        renderer = SceneRenderer(size, size, ssaa=ssaa, cull_back_faces=cull)
        renderer.fit_camera(rest_q)
        results[label] = _median_frame_ms(renderer, rest_q, triangles)
    ms_256 = results["256x256"][0]
    return {
        "tets": 0,
        "particles": int(len(rest_q)),
        "strand_nodes": NEEDLE_NODES + SUTURE_NODES,
        "substep_ms": ms_256,
        "substeps_per_s": 1e3 / ms_256,
        "collision_fraction": 0.0,
        "solver_fraction": 0.0,
        "note": "a render benchmark: substep_ms is the median frame time at 256x256; tets = 0 (surface only)",
        "surface_triangles": int(len(triangles)),
        "frame_ms_256x256": ms_256,
        "p90_frame_ms_256x256": results["256x256"][1],
        "frame_ms_480x480": results["480x480"][0],
        "p90_frame_ms_480x480": results["480x480"][1],
        "frame_ms_256x256_ssaa2": results["256x256_ssaa2"][0],
        "frame_ms_256x256_cull_back_faces": results["256x256_cull"][0],
        "frame_ms_480x480_cull_back_faces": results["480x480_cull"][0],
        "frames_per_s_256x256": 1e3 / ms_256,
        "target_ms_256x256": 5.0,
        "paper_render_ms": 0.0481 * 28.57,
        "frames_timed": FRAMES,
    }
