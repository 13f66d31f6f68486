"""Software renderer (suture_gym/render) against hand computations and exact pixel-level expectations.

References: projections computed by hand from the pinhole formulas; pixel coverage from point-in-triangle
tests at pixel centres (float64, away from the edges); the top-left fill rule's exact pixel sets for meshes
whose vertices sit on pixel centres; a floor plane seen from a camera standing on it (ray-plane
intersection per pixel) for near-plane clipping; Lambert/Blinn shading from the formulas.
"""

import math
import sys

import numpy as np
import pytest

from suture_gym.measure.render import box_surface, paper_cube_frame, paper_cube_scene
from suture_gym.render import Camera, Material, RenderFrame, SceneRenderer, SceneStyle, frame_box, save_png, write_video
from suture_gym.render.overlay import FONT_GLYPHS, text_bitmap, text_glyph_indices
from suture_gym.render.raster import clear_gbuffer, raster_triangles, vertex_normals

FLAT = Material(1.0, 0.0, 0.0, 1)
WHITE_BG = {"background_top": (1.0, 1.0, 1.0), "background_bottom": (1.0, 1.0, 1.0)}


def _flat_style(**kw) -> SceneStyle:
    """Every entity drawn in its exact albedo on a white background."""
    base = dict(tissue_material=FLAT, needle_material=FLAT, suture_material=FLAT, marker_material=FLAT, **WHITE_BG)
    base.update(kw)
    return SceneStyle(**base)


def _top_camera(size=64, fov=90.0, **kw) -> Camera:
    """Camera at z = 1 looking down -z with +y up on screen: u = c + f x, v = c - f y for points at z = 0."""
    return Camera(
        eye=(0.0, 0.0, 1.0), target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0), fov_y_deg=fov, width=size, height=size, **kw
    )


def _view(camera: Camera, guard=None) -> np.ndarray:
    cx, cy = camera.principal_point
    g = float(max(camera.width, camera.height)) if guard is None else guard
    return np.array([camera.focal_px, cx, cy, camera.near, camera.far, g])


def _coverage(camera: Camera, q_world: np.ndarray, tris: np.ndarray) -> np.ndarray:
    """(H,W) bool mask of the samples the triangle kernel covers (a fresh G-buffer)."""
    h, w = camera.height, camera.width
    inv_depth = np.zeros((h, w))
    normal = np.zeros((h, w, 3), dtype=np.float32)
    albedo = np.zeros((h, w, 3), dtype=np.float32)
    material = np.zeros((h, w), dtype=np.uint8)
    clear_gbuffer(inv_depth, material)
    cam_q = camera.to_camera(q_world)
    cam_n = np.zeros_like(cam_q)
    vertex_normals(cam_q, tris, cam_n)
    colors = np.ones((len(q_world), 3), dtype=np.float32)
    no_face_color = np.zeros((0, 3), np.float32)
    raster_triangles(
        cam_q, cam_n, colors, tris, no_face_color, False, 1, _view(camera), inv_depth, normal, albedo, material
    )
    return material == 1


def _centres(h, w):
    v, u = np.mgrid[0:h, 0:w]
    return u + 0.5, v + 0.5


# ------------------------------------------------------------------------------------------ camera


def test_projection_matches_hand_computation():
    cam = _top_camera(size=100)  # fov 90 -> f = 50 px
    uv, depth = cam.project(np.array([[0.5, 0.25, 0.0], [0.0, 0.0, 2.0]]))
    np.testing.assert_allclose(uv[0], [75.0, 37.5], atol=1e-12)
    assert depth[0] == pytest.approx(1.0)
    assert np.all(np.isnan(uv[1])) and depth[1] == pytest.approx(-1.0)

    # Eye on +x looking at the origin, z up, 60 degree fov, 200 x 100: right = +y, f = 50 / tan(30 deg).
    cam = Camera(eye=(2.0, 0.0, 0.0), target=(0.0, 0.0, 0.0), up=(0.0, 0.0, 1.0), fov_y_deg=60.0, width=200, height=100)
    f = 50.0 / math.tan(math.radians(30.0))
    uv, depth = cam.project(np.array([[0.0, 0.5, 0.25]]))
    np.testing.assert_allclose(uv[0], [100.0 + f * 0.5 / 2.0, 50.0 - f * 0.25 / 2.0], atol=1e-12)
    assert depth[0] == pytest.approx(2.0)
    np.testing.assert_allclose(cam.rotation @ cam.rotation.T, np.eye(3), atol=1e-15)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"fov_y_deg": 0.0}, "fov_y_deg"),
        ({"fov_y_deg": 180.0}, "fov_y_deg"),
        ({"width": 0}, "width"),
        ({"height": 2.5}, "height"),
        ({"near": 0.0}, "near"),
        ({"far": 1e-3}, "far"),
        ({"eye": (0.0, 0.0, 0.0)}, "eye and target"),
        ({"up": (0.0, 0.0, 2.0)}, "up"),
        ({"eye": (np.nan, 0.0, 1.0)}, "eye"),
        ({"target": (0.0, 0.0)}, "target"),
    ],
)
def test_camera_rejects_bad_input_naming_the_field(kwargs, field):
    args = {"eye": (0.0, 0.0, 1.0), "target": (0.0, 0.0, 0.0), "up": (0.0, 1.0, 0.0)}
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        Camera(**args)


def test_frame_box_sees_every_corner_tightly():
    lo, hi = np.array([0.0, 0.0, 0.0]), np.array([0.095, 0.064, 0.03])
    cam = frame_box(lo, hi, width=320, height=240, margin=1.1)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    uv, depth = cam.project(corners)
    assert np.all(depth > cam.near)
    off = np.abs(uv - [160.0, 120.0]) / [160.0 / 1.1, 120.0 / 1.1]  # 1 = on the margin's border
    assert off.max() <= 1.0 + 1e-9
    assert off.max() >= 1.0 - 1e-9  # the closest distance that fits: some corner touches the border
    with pytest.raises(ValueError, match="zero size"):
        frame_box(lo, lo, width=64, height=64)
    with pytest.raises(ValueError, match="up"):
        frame_box(lo, hi, width=64, height=64, direction=(0.0, 0.0, 1.0))


# ------------------------------------------------------------------------------------------ triangles


def test_triangle_covers_exactly_the_pixel_centres_inside_it():
    cam = _top_camera(size=96)
    tri_xy = np.array([[-0.61, -0.47], [0.73, -0.12], [-0.2, 0.81]])
    q = np.column_stack([tri_xy, np.zeros(3)])
    mask = _coverage(cam, q, np.array([[0, 1, 2]], dtype=np.int32))
    uv, _ = cam.project(q)
    u, v = _centres(96, 96)
    # Signed distances (px) of every pixel centre to the three edges, positive inside.
    dists = []
    for i in range(3):
        a, b = uv[i], uv[(i + 1) % 3]
        edge = b - a
        normal = np.array([edge[1], -edge[0]]) / np.linalg.norm(edge)
        c = uv[(i + 2) % 3]
        sign = np.sign(normal @ (c - a))
        dists.append(sign * ((u - a[0]) * normal[0] + (v - a[1]) * normal[1]))
    dmin = np.min(dists, axis=0)
    band = 0.01  # px; vertices are snapped to 1/256 px
    assert mask[dmin > band].all()
    assert not mask[dmin < -band].any()
    area = 0.5 * abs((uv[1, 0] - uv[0, 0]) * (uv[2, 1] - uv[0, 1]) - (uv[1, 1] - uv[0, 1]) * (uv[2, 0] - uv[0, 0]))
    perimeter = sum(np.linalg.norm(uv[(i + 1) % 3] - uv[i]) for i in range(3))
    assert abs(mask.sum() - area) <= 0.5 * perimeter  # pixel count vs projected area, within the edge band


@pytest.mark.parametrize("jitter", [False, True])
def test_shared_edges_leave_no_gap_and_no_double_coverage(jitter):
    """A square of 6 x 6 cells (2 triangles each) with corners on pixel centres: every pixel is covered by
    exactly one triangle, and the union is exactly the top-left-rule pixel set of the square."""
    size, f = 64, 32.0  # fov 90 -> f = 32: x = (u - 32) / 32 is exact in binary
    cam = _top_camera(size=size)
    i0, i1, j0, j1 = 10, 46, 12, 48  # corner pixel columns/rows; centres at i + 0.5
    n = 6
    us = np.linspace(i0 + 0.5, i1 + 0.5, n + 1)
    vs = np.linspace(j0 + 0.5, j1 + 0.5, n + 1)
    uu, vv = np.meshgrid(us, vs, indexing="ij")
    if jitter:
        rng = np.random.default_rng(3)
        inner = (slice(1, n), slice(1, n))
        uu[inner] += rng.uniform(-1.7, 1.7, size=(n - 1, n - 1))
        vv[inner] += rng.uniform(-1.7, 1.7, size=(n - 1, n - 1))
    q = np.column_stack([(uu.ravel() - 32.0) / f, -(vv.ravel() - 32.0) / f, np.zeros(uu.size)])
    idx = np.arange((n + 1) ** 2).reshape(n + 1, n + 1)
    tris = []
    for a in range(n):
        for b in range(n):
            p00, p10, p11, p01 = idx[a, b], idx[a + 1, b], idx[a + 1, b + 1], idx[a, b + 1]
            if (a + b) % 2:
                tris += [[p00, p10, p11], [p00, p11, p01]]
            else:
                tris += [[p00, p10, p01], [p10, p11, p01]]
    count = np.zeros((size, size), dtype=np.int32)
    for t in tris:
        count += _coverage(cam, q, np.array([t], dtype=np.int32))
    assert count.max() == 1
    expected = np.zeros((size, size), dtype=bool)
    expected[j0:j1, i0:i1] = True  # top and left edges included, bottom and right excluded
    np.testing.assert_array_equal(count == 1, expected)


def test_nearer_triangle_occludes_regardless_of_draw_order():
    cam = _top_camera(size=48)
    far_tri = [[-0.6, -0.6, 0.0], [0.6, -0.6, 0.0], [0.0, 0.6, 0.0]]
    near_tri = [[-0.6, 0.6, 0.2], [0.6, 0.6, 0.2], [0.0, -0.6, 0.2]]
    q = np.array(far_tri + near_tri)
    colors = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0]], dtype=np.float32)  # far blue, near red
    images = []
    for order in ([0, 1], [1, 0]):
        tris = np.array([[0, 1, 2], [3, 4, 5]], dtype=np.int32)[order]
        renderer = SceneRenderer(48, 48, camera=cam, style=_flat_style())
        images.append(renderer.render(RenderFrame(q, tris, tissue_face_color=colors[order])))
    np.testing.assert_array_equal(images[0], images[1])
    uv, _ = cam.project(np.array([[0.0, 0.0, 0.0]]))
    centre = images[0][int(uv[0, 1]), int(uv[0, 0])]
    np.testing.assert_array_equal(centre, [255, 0, 0])
    assert (images[0] == [0, 0, 255]).all(axis=2).any()  # the far triangle still shows outside the overlap


def test_near_plane_clipping_matches_ray_casting_of_a_floor():
    """Camera standing 1 m above a floor triangle that extends behind it (camera space = world space)."""
    size = 64
    cam = Camera(
        eye=(0.0, 0.0, 0.0),
        target=(0.0, 0.0, -1.0),
        up=(0.0, 1.0, 0.0),
        fov_y_deg=90.0,
        width=size,
        height=size,
        near=0.05,
        far=100.0,
    )
    np.testing.assert_allclose(cam.rotation, np.eye(3), atol=0)
    tri = np.array([[-10.0, -1.0, 5.0], [10.0, -1.0, 5.0], [0.0, -1.0, -20.0]])
    mask = _coverage(cam, tri, np.array([[0, 1, 2]], dtype=np.int32))
    # Reference: cast the ray of every pixel centre onto the plane y = -1 and test the hit in (x, z).
    u, v = _centres(size, size)
    xn, yn = (u - 32.0) / 32.0, -(v - 32.0) / 32.0
    below = yn < 0  # rays that meet the floor
    d = np.where(below, -1.0 / np.where(below, yn, -1.0), 0.0)
    hit_x, hit_z = xn * d, -d
    a, b, c = tri[:, [0, 2]]

    def side(p, q_, x, z):
        return (q_[0] - p[0]) * (z - p[1]) - (q_[1] - p[1]) * (x - p[0])

    s = np.stack([side(a, b, hit_x, hit_z), side(b, c, hit_x, hit_z), side(c, a, hit_x, hit_z)])
    expected = (np.all(s > 0, axis=0) | np.all(s < 0, axis=0)) & below & (d >= cam.near)
    assert expected.sum() > 300
    assert not mask[: size // 2].any()  # nothing above the horizon: no garbage from the vertices behind
    mismatch = mask != expected
    # Only pixels on the reference's boundary (a neighbour differs) may disagree.
    pad = np.pad(expected, 1, mode="edge")
    boundary = np.zeros_like(expected)
    for dy in (-1, 0, 1):
        for dx in (-1, 0, 1):
            boundary |= pad[1 + dy : 1 + dy + size, 1 + dx : 1 + dx + size] != expected
    assert not (mismatch & ~boundary).any()


def test_camera_inside_a_closed_box_sees_walls_everywhere():
    q, tris = box_surface((2.0, 2.0, 2.0), (3, 3, 3), origin=(-1.0, -1.0, -1.0))
    for target in ((1.0, 0.3, 0.2), (0.0, 0.0, -1.0), (0.5, 0.5, 0.5)):
        cam = Camera(
            eye=(0.2, -0.1, 0.05),
            target=target,
            up=(0.0, 1.0, 0.3),
            fov_y_deg=100.0,
            width=40,
            height=30,
            near=1e-4,
            far=10.0,
        )
        renderer = SceneRenderer(40, 30, camera=cam, style=_flat_style())
        image = renderer.render(RenderFrame(q, tris))
        tissue = np.round(np.array(renderer.style.tissue_color) * 255).astype(np.uint8)
        assert (image == tissue).all(axis=2).all()


def test_back_face_culling_of_a_closed_outward_surface():
    rest, tris = paper_cube_scene()
    frame = paper_cube_frame(rest, tris, 0.7)
    plain = SceneRenderer(96, 96).render(frame)
    culled = SceneRenderer(96, 96, cull_back_faces=True).render(frame)
    np.testing.assert_array_equal(culled, plain)  # seen from outside, back faces are always hidden
    frame.tissue_triangles = tris[:, ::-1]  # inward-facing: culling now removes the visible side
    assert (SceneRenderer(96, 96, cull_back_faces=True).render(frame) != plain).any(axis=2).sum() > 1000


def test_vertex_normals_of_a_cube():
    q, tris = box_surface((1.0, 1.0, 1.0), (2, 2, 2))
    n = np.zeros_like(q)
    vertex_normals(q, tris, n)
    corner = np.flatnonzero(np.all(q == [1.0, 1.0, 1.0], axis=1))[0]
    face_centre = np.flatnonzero(np.all(q == [0.5, 0.5, 1.0], axis=1))[0]
    np.testing.assert_allclose(n[face_centre], [0.0, 0.0, 1.0], atol=1e-15)
    # The corner touches one triangle of area 1/8 on each face and the other a second: weights equal by symmetry.
    assert n[corner] @ np.ones(3) / math.sqrt(3.0) == pytest.approx(1.0)
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0)


# ------------------------------------------------------------------------------------------ shading


@pytest.mark.parametrize("angle_deg", [0.0, 35.0, 70.0])
def test_lambert_shading_of_a_facing_square(angle_deg):
    a = math.radians(angle_deg)
    mat = Material(0.2, 0.7, 0.0, 1)
    style = SceneStyle(
        tissue_material=mat, light_direction=(0.0, math.sin(a), math.cos(a)), tissue_color=(0.8, 0.6, 0.4)
    )
    cam = _top_camera(size=32)
    q = np.array([[-0.9, -0.9, 0.0], [0.9, -0.9, 0.0], [0.9, 0.9, 0.0], [-0.9, 0.9, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    image = SceneRenderer(32, 32, camera=cam, style=style).render(RenderFrame(q, tris))
    albedo = np.array([0.8, 0.6, 0.4], dtype=np.float32).astype(np.float64)  # the G-buffer stores float32
    expected = np.floor(albedo * (0.2 + 0.7 * math.cos(a)) * 255.0 + 0.5)
    np.testing.assert_array_equal(image[16, 16], expected)


def test_blinn_specular_peaks_where_the_half_vector_meets_the_normal():
    """Light along the view axis: at the image centre n = l = v, so n.h = 1 and the full specular adds."""
    mat = Material(0.1, 0.3, 0.4, 50)
    style = SceneStyle(tissue_material=mat, light_direction=(0.0, 0.0, 1.0), tissue_color=(0.5, 0.5, 0.5))
    cam = _top_camera(size=32)
    q = np.array([[-0.9, -0.9, 0.0], [0.9, -0.9, 0.0], [0.9, 0.9, 0.0], [-0.9, 0.9, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    image = SceneRenderer(32, 32, camera=cam, style=style).render(RenderFrame(q, tris)).astype(float)
    f = cam.focal_px
    for row, col in ((16, 16), (2, 2), (9, 27)):
        view = np.array([-(col + 0.5 - 16.0) / f, (row + 0.5 - 16.0) / f, 1.0])
        half = np.array([0.0, 0.0, 1.0]) + view / np.linalg.norm(view)
        n_dot_h = half[2] / np.linalg.norm(half)  # n = l = (0, 0, 1)
        expected = 0.5 * (0.1 + 0.3) + 0.4 * n_dot_h**50
        assert image[row, col, 0] == math.floor(expected * 255.0 + 0.5)
    assert image[16, 16, 0] > image[2, 2, 0] + 20  # the highlight falls off away from the centre


def test_supersampling_blends_an_edge_through_pixel_centres():
    """A vertical edge through pixel centres: with 2 x 2 samples, that column is exactly half covered."""
    cam = _top_camera(size=32)  # f = 16 px
    x_edge = (20.5 - 16.0) / 16.0
    q = np.array([[-2.0, -2.0, 0.0], [x_edge, -2.0, 0.0], [x_edge, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    style = _flat_style(tissue_color=(0.0, 0.0, 0.0))
    image = SceneRenderer(32, 32, camera=cam, ssaa=2, style=style).render(RenderFrame(q, tris))
    np.testing.assert_array_equal(image[:, 19], 0)
    np.testing.assert_array_equal(image[:, 20], 128)  # (0 + 0 + 255 + 255) / 4 = 127.5 -> 128
    np.testing.assert_array_equal(image[:, 21], 255)


# ------------------------------------------------------------------------------------------ strands, markers


def _floor():
    q = np.array([[-2.0, -2.0, 0.0], [2.0, -2.0, 0.0], [2.0, 2.0, 0.0], [-2.0, 2.0, 0.0]])
    return q, np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)


def test_thick_polyline_has_projected_width_and_colour():
    cam = _top_camera(size=64)  # f = 32 px; the line at z = 0.5 lies at depth 0.5 m
    q, tris = _floor()
    line = np.column_stack([np.linspace(-0.4, 0.4, 9), np.zeros(9), np.full(9, 0.5)])  # u from 6.4 to 57.6
    radius = 0.05  # projected half-width 0.05 * 32 / 0.5 = 3.2 px
    style = _flat_style(suture_color=(0.2, 0.0, 0.6))
    image = SceneRenderer(64, 64, camera=cam, style=style).render(
        RenderFrame(q, tris, suture_q=line, suture_radius=radius)
    )
    thread = (image == [51, 0, 153]).all(axis=2)
    rows = np.flatnonzero(thread[:, 32])
    np.testing.assert_array_equal(rows, np.arange(29, 35))  # centres within 3.2 px of v = 32: 28.8 < v < 35.2
    # Round caps on row 32 (centres 0.5 px off the axis) reach sqrt(3.2^2 - 0.5^2) = 3.16 px past the ends.
    cols = np.flatnonzero(thread[32])
    assert cols.min() == 3 and cols.max() == 60


def test_thin_thread_stays_visible_and_hides_behind_tissue():
    cam = _top_camera(size=64)
    q, tris = _floor()
    line = np.column_stack([np.linspace(-0.9, 0.9, 50), 0.4 * np.linspace(-0.9, 0.9, 50), np.full(50, 0.1)])
    style = _flat_style(suture_color=(0.2, 0.0, 0.6))
    renderer = SceneRenderer(64, 64, camera=cam, style=style)
    # 0.1 mm thread 0.9 m away: 0.004 px wide as projected, drawn 1.5 px wide.
    image = renderer.render(RenderFrame(q, tris, suture_q=line, suture_radius=1e-4))
    thread = (image == [51, 0, 153]).all(axis=2)
    per_col = thread[:, 6:58].sum(axis=0)
    assert per_col.min() >= 1 and per_col.max() <= 2
    under = line.copy()
    under[:, 2] = -0.1  # below the floor: hidden by it
    image = renderer.render(RenderFrame(q, tris, suture_q=under, suture_radius=1e-4))
    assert not (image == [51, 0, 153]).all(axis=2).any()


def test_markers_colour_depth_test_and_on_top():
    cam = _top_camera(size=64)
    q, tris = _floor()
    markers = np.array([[-0.5, 0.0, 0.05], [0.5, 0.0, 0.05], [0.0, 0.5, -0.2]])  # the last one below the floor
    style = _flat_style()
    renderer = SceneRenderer(64, 64, camera=cam, style=style)
    uv, _ = cam.project(markers)
    px = np.floor(uv).astype(int)
    green = np.round(np.array(style.entry_color) * 255).astype(np.uint8)
    red = np.round(np.array(style.exit_color) * 255).astype(np.uint8)
    image = renderer.render(RenderFrame(q, tris, marker_q=markers, marker_radius=0.02))
    np.testing.assert_array_equal(image[px[0, 1], px[0, 0]], green)
    np.testing.assert_array_equal(image[px[1, 1], px[1, 0]], red)
    tissue = np.round(np.array(style.tissue_color) * 255).astype(np.uint8)
    np.testing.assert_array_equal(image[px[2, 1], px[2, 0]], tissue)  # the third marker is under the floor
    image = renderer.render(
        RenderFrame(q, tris, marker_q=markers, marker_radius=0.02, marker_on_top=[False, False, True])
    )
    np.testing.assert_array_equal(image[px[2, 1], px[2, 0]], green)
    colors = np.array([[0, 0, 255], [255, 255, 0], [0, 255, 255]], dtype=np.uint8)
    image = renderer.render(RenderFrame(q, tris, marker_q=markers, marker_color=colors, marker_on_top=True))
    for m in range(3):
        np.testing.assert_array_equal(image[px[m, 1], px[m, 0]], colors[m])


# ------------------------------------------------------------------------------------------ sensor images


def test_sensor_depth_of_an_oblique_plane_matches_ray_casting():
    """Depth image of the plane z = 0 seen at 40 degrees: each pixel centre's ray meets the plane at the point
    whose distance along the optical axis is the reference; the background is ``far``."""
    cam = Camera(eye=(0.3, -0.8, 0.7), target=(0.1, 0.1, 0.0), fov_y_deg=50.0, width=48, height=40, near=0.01,
                 far=3.0)
    q = np.array([[-1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, 1.0, 0.0], [-1.0, 1.0, 0.0]])
    tris = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int32)
    rgb, depth = SceneRenderer(48, 40, camera=cam).render_sensor(RenderFrame(q, tris), rgb=False, depth=True)
    assert rgb is None and depth.shape == (40, 48, 1) and depth.dtype == np.float32
    u, v = _centres(40, 48)
    cx, cy = cam.principal_point
    # Ray directions in camera space (depth 1 along -z), then world; hit of z = 0 at eye + s * ray.
    ray = np.stack([(u - cx) / cam.focal_px, -(v - cy) / cam.focal_px, -np.ones_like(u)], axis=-1) @ cam.rotation
    s = -cam.eye[2] / ray[..., 2]
    hit = cam.eye + s[..., None] * ray
    inside = (s > 0) & (np.abs(hit[..., 0]) < 1.0) & (np.abs(hit[..., 1]) < 1.0)
    assert 100 < inside.sum() < inside.size  # the plane's far edge is in view: both cases are tested
    # Depth along the axis is s (the ray's camera z is -1); the vertices snap to 1/256 px, worth about 1e-5 of it.
    np.testing.assert_allclose(depth[inside, 0], s[inside], rtol=1e-4)
    edge = np.abs(np.abs(hit[..., :2]).max(axis=-1) - 1.0) < 0.05  # pixels next to the plane's border
    assert np.all(depth[~inside & ~edge, 0] == np.float32(3.0))


def test_sensor_images_leave_overlays_out_and_markers_out_of_depth():
    cam = _top_camera(size=64)
    q, tris = _floor()
    style = _flat_style()
    renderer = SceneRenderer(64, 64, camera=cam, style=style)
    marker = np.array([[0.1, 0.0, 0.2]])
    frame = RenderFrame(q, tris, marker_q=marker, marker_radius=0.2, tip_force=0.5, caption="caption")
    rgb, depth = renderer.render_sensor(frame, rgb=True, depth=True)
    uv, marker_depth = cam.project(marker)
    radius_px = 0.2 * cam.focal_px / marker_depth[0]  # 8 px
    u, v = _centres(64, 64)
    from_marker = np.hypot(u - uv[0, 0], v - uv[0, 1])
    tissue = np.round(np.array(style.tissue_color) * 255).astype(np.uint8)
    floor = (rgb == tissue).all(axis=2)
    assert not floor[from_marker < radius_px - 1].any()  # the marker is drawn in the colour image
    assert floor[from_marker > radius_px + 1].all()  # and nothing else but the floor: no caption, no gauge
    np.testing.assert_allclose(depth[..., 0], 1.0, rtol=1e-6)  # the floor 1 m below everywhere, marker or not
    full = renderer.render(frame)
    assert not (full == tissue).all(axis=2)[from_marker > radius_px + 1].all()  # render() draws the overlays


def test_sensor_images_need_a_camera_and_no_supersampling():
    q, tris = _floor()
    with pytest.raises(ValueError, match="needs a camera"):
        SceneRenderer(16, 16).render_sensor(RenderFrame(q, tris), rgb=True, depth=False)
    with pytest.raises(ValueError, match="ssaa = 1"):
        SceneRenderer(16, 16, camera=_top_camera(size=16), ssaa=2).render_sensor(RenderFrame(q, tris), True, True)


# ------------------------------------------------------------------------------------------ overlays


def test_font_glyphs_and_gauge_text():
    assert FONT_GLYPHS.shape[1:] == (7, 5)
    n_rows = ("#...#", "#...#", "##..#", "#.#.#", "#..##", "#...#", "#...#")
    np.testing.assert_array_equal(text_bitmap("N"), [[c == "#" for c in row] for row in n_rows])
    np.testing.assert_array_equal(text_glyph_indices("n"), text_glyph_indices("N"))
    np.testing.assert_array_equal(text_glyph_indices("~"), text_glyph_indices("?"))

    q, tris = _floor()
    renderer = SceneRenderer(128, 128, camera=_top_camera(size=128))
    image = renderer.render(RenderFrame(q, tris, tip_force=0.83, force_threshold=1.0))
    x, y, w, h = renderer.gauge_layout("0.83 N")["text"]
    white = (image[y : y + h, x : x + w] == 255).all(axis=2)
    np.testing.assert_array_equal(white, text_bitmap("0.83 N"))
    bx, by, bw, bh = renderer.gauge_layout("0.83 N")["bar"]
    filled = round(0.83 / 1.5 * bw)
    start = image[by + bh // 2, bx].astype(int)
    assert start[1] > start[0] + 80 and start[1] > start[2] + 80  # green at the low end
    np.testing.assert_array_equal(image[by + bh // 2, bx + filled + 1], [70, 70, 70])  # empty part
    image = renderer.render(RenderFrame(q, tris, tip_force=1.4, force_threshold=1.0))
    end = image[by + bh // 2, bx + round(1.4 / 1.5 * bw) - 1].astype(int)
    assert end[0] > 200 and end[1] < 60  # red beyond the threshold
    image = renderer.render(RenderFrame(q, tris, tip_force=float("nan"), caption="step 3"))
    x, y, w, h = renderer.gauge_layout("--- N")["text"]
    np.testing.assert_array_equal((image[y : y + h, x : x + w] == 255).all(axis=2), text_bitmap("--- N"))
    x, y, w, h = renderer.gauge_layout("--- N")["label"]
    np.testing.assert_array_equal((image[y : y + h, x : x + w] == 255).all(axis=2)[:, : text_bitmap("TIP").shape[1]],
                                  text_bitmap("TIP"))


def test_haptic_gauge_shows_the_reaction_force_against_its_span_above_the_tip_gauge():
    q, tris = _floor()
    renderer = SceneRenderer(128, 128, camera=_top_camera(size=128))
    image = renderer.render(RenderFrame(q, tris, tip_force=0.2, force_threshold=0.5, haptic_force=1.5, haptic_span=5.0))
    tip, haptic = renderer.gauge_layout("0.20 N", 0), renderer.gauge_layout("1.50 N", 1)
    assert haptic["panel"][1] + haptic["panel"][3] <= tip["panel"][1]  # stacked, not overlapping
    assert haptic["bar"][0] == tip["bar"][0] and haptic["bar"][2] == tip["bar"][2]  # the bars line up
    for lay, text, label in ((tip, "0.20 N", "TIP"), (haptic, "1.50 N", "HAPTIC")):
        x, y, w, h = lay["text"]
        np.testing.assert_array_equal((image[y : y + h, x : x + w] == 255).all(axis=2), text_bitmap(text))
        x, y, _, h = lay["label"]
        w = text_bitmap(label).shape[1]
        np.testing.assert_array_equal((image[y : y + h, x : x + w] == 255).all(axis=2), text_bitmap(label))
    bx, by, bw, bh = haptic["bar"]
    filled = round(1.5 / 5.0 * bw)
    assert not (image[by + bh // 2, bx + filled - 2] == [70, 70, 70]).all()  # filled to 1.5 / 5 of the bar
    np.testing.assert_array_equal(image[by + bh // 2, bx + filled + 1], [70, 70, 70])
    over = renderer.render(RenderFrame(q, tris, haptic_force=9.0, haptic_span=5.0))
    lay = renderer.gauge_layout("9.00 N", 0)  # alone, the haptic gauge takes the bottom row
    bx, by, bw, bh = lay["bar"]
    start, end = over[by + bh // 2, bx + 1].astype(int), over[by + bh // 2, bx + bw - 2].astype(int)
    assert start[1] > start[0] + 80 and end[0] > 200 and end[1] < 120  # filled to the end: green, then red
    with pytest.raises(ValueError, match="haptic_span"):
        renderer.render(RenderFrame(q, tris, haptic_force=1.0, haptic_span=0.0))


# ------------------------------------------------------------------------------------------ robustness


def test_render_is_deterministic():
    rest, tris = paper_cube_scene()
    frame = paper_cube_frame(rest, tris, 0.3)
    for ssaa in (1, 2):
        a = SceneRenderer(96, 80, ssaa=ssaa).render(frame)
        renderer = SceneRenderer(96, 80, ssaa=ssaa)
        b = renderer.render(frame)
        c = renderer.render(frame)
        assert a.shape == (80, 96, 3) and a.dtype == np.uint8
        assert a.tobytes() == b.tobytes() == c.tobytes()
        assert c is not b  # a new image per frame, safe to keep


def test_non_finite_primitives_are_skipped():
    cam = _top_camera(size=64)
    q, tris = box_surface((1.0, 1.0, 0.2), (4, 4, 1), origin=(-0.5, -0.5, -0.2))
    style = _flat_style(needle_color=(0.3, 0.3, 0.3), suture_color=(0.3, 0.3, 0.3), suture_material=FLAT)
    renderer = SceneRenderer(64, 64, camera=cam, style=style)
    bad = 5
    q_nan = q.copy()
    q_nan[bad] = [np.nan, 0.0, np.inf]
    keep = ~np.any(tris == bad, axis=1)
    strand = np.column_stack([np.linspace(-0.4, 0.4, 12), np.linspace(-0.3, 0.3, 12), np.full(12, 0.1)])
    strand_nan = strand.copy()
    strand_nan[6] = np.nan
    markers = np.array([[0.1, 0.1, 0.1], [np.nan, 0.0, 0.0]])
    with_nan = renderer.render(
        RenderFrame(
            q_nan,
            tris,
            needle_q=strand_nan,
            needle_radius=0.01,
            suture_radius=0.01,
            marker_q=markers,
            marker_radius=0.02,
        )
    )
    # Reference: the same scene with the bad primitives removed (needle split into needle + same-looking suture).
    reference = renderer.render(
        RenderFrame(
            q,
            tris[keep],
            needle_q=strand[:6],
            suture_q=strand[7:],
            needle_radius=0.01,
            suture_radius=0.01,
            marker_q=markers[:1],
            marker_radius=0.02,
        )
    )
    np.testing.assert_array_equal(with_nan, reference)

    empty = SceneRenderer(32, 32)
    image = empty.render(RenderFrame(np.full((4, 3), np.nan), np.array([[0, 1, 2]], dtype=np.int32), tip_force=np.inf))
    assert empty.camera is None and image.shape == (32, 32, 3)


@pytest.mark.parametrize(
    ("kwargs", "field"),
    [
        ({"tissue_q": np.zeros((4, 2))}, "tissue_q"),
        ({"tissue_triangles": np.array([[0, 1, 4]])}, "tissue_triangles"),
        ({"tissue_triangles": np.array([[0.0, 1.0, 2.0]])}, "tissue_triangles"),
        ({"tissue_vertex_color": np.zeros((3, 3))}, "tissue_vertex_color"),
        ({"tissue_face_color": np.full((1, 3), 2.0)}, "tissue_face_color"),
        ({"suture_radius": -1e-4}, "suture_radius"),
        ({"needle_q": np.zeros((5, 2))}, "needle_q"),
        ({"marker_q": np.zeros((2, 3)), "marker_radius": [1e-3, 1e-3, 1e-3]}, "marker_radius"),
        ({"force_threshold": 0.0}, "force_threshold"),
        ({"caption": 3}, "caption"),
    ],
)
def test_render_frame_validation_names_the_field(kwargs, field):
    args = {"tissue_q": np.zeros((4, 3)), "tissue_triangles": np.array([[0, 1, 2], [0, 2, 3]])}
    args.update(kwargs)
    with pytest.raises(ValueError, match=field):
        SceneRenderer(16, 16, camera=_top_camera(size=16)).render(RenderFrame(**args))
    with pytest.raises(ValueError, match="camera is 16x16"):
        SceneRenderer(32, 32, camera=_top_camera(size=16))


# ------------------------------------------------------------------------------------------ files


def _frames(n=6, h=48, w=64):
    out = []
    for i in range(n):
        img = np.zeros((h, w, 3), dtype=np.uint8)
        img[:, :, 0] = 40 * i
        img[:, :, 1] = 200 - 30 * i
        img[h // 2 :, :, 2] = 180
        out.append(img)
    return out


def test_video_round_trip(tmp_path):
    iio = pytest.importorskip("imageio.v3")
    frames = _frames()
    path = tmp_path / "clip.mp4"
    assert write_video(iter(frames), path, fps=12) == len(frames)
    back = list(iio.imiter(path, plugin="FFMPEG"))
    assert len(back) == len(frames)
    for src, got in zip(frames, back, strict=True):
        assert got.shape == (48, 64, 3)
        assert np.abs(got.astype(int) - src).mean() < 6.0  # lossy H.264, but the same picture


def test_video_rejects_bad_input(tmp_path, monkeypatch):
    path = tmp_path / "bad.mp4"
    for fps in (0, -1.0, float("nan"), "30"):
        with pytest.raises(ValueError, match="fps"):
            write_video(_frames(2), path, fps=fps)
    frames = _frames(3) + [np.zeros((40, 64, 3), dtype=np.uint8)]
    with pytest.raises(ValueError, match=r"frames\[3\] has shape"):
        write_video(frames, path, fps=10)
    assert not path.exists()  # the partial file is removed
    with pytest.raises(ValueError, match="even"):
        write_video([np.zeros((9, 16, 3), dtype=np.uint8)], path, fps=10)
    with pytest.raises(ValueError, match="empty"):
        write_video([], path, fps=10)
    with pytest.raises(ValueError, match="uint8"):
        write_video([np.zeros((8, 8, 3))], path, fps=10)
    monkeypatch.setitem(sys.modules, "imageio_ffmpeg", None)
    with pytest.raises(ImportError, match=r"suture_gym\[render\]"):
        write_video(_frames(1), path, fps=10)


def test_png_round_trip(tmp_path):
    iio = pytest.importorskip("imageio.v3")
    image = _frames(1)[0]
    save_png(image, tmp_path / "frame.png")
    np.testing.assert_array_equal(iio.imread(tmp_path / "frame.png"), image)
    with pytest.raises(ValueError, match="image"):
        save_png(image[:, :, :2], tmp_path / "x.png")
