"""Numba z-buffer rasteriser: triangles, thick polylines, discs, deferred shading and 2-D overlays.

Everything here is pure graphics on arrays; nothing imports the simulator.

Pipeline (driven by :class:`suture_gym.render.scene.SceneRenderer`):

1. :func:`transform_points` moves world points (m) into camera space (see :mod:`suture_gym.render.camera`
   for the axis conventions); :func:`vertex_normals` computes area-weighted vertex normals of the deformed mesh.
2. Primitives write a G-buffer at the (possibly supersampled) resolution ``(Hs, Ws)``:
   ``gb_inv_depth (Hs,Ws) float64`` 1/m (``1/d``, 0 where empty; larger is nearer), ``gb_normal (Hs,Ws,3)
   float32`` camera-space unit normal, ``gb_albedo (Hs,Ws,3) float32`` RGB in [0, 1] and ``gb_material (Hs,Ws)
   uint8`` material id (0 = background). A fragment is written only if its ``1/d`` is strictly larger than the
   stored one, so of two equally deep fragments the first drawn wins.

   * :func:`raster_triangles`: triangles clipped in camera space against the near plane and a guard band
     around the image, then scan-converted with integer edge functions on a 1/256-pixel grid and the
     top-left fill rule (a pixel centre on an edge shared by two triangles belongs to exactly one of them).
     Depth and attributes are interpolated perspective-correctly (``1/d`` and ``a/d`` are affine in screen
     space).
   * :func:`raster_capsules`: a polyline drawn as screen-space capsules (a tube seen from the camera) whose
     half-width is the projected radius, at least ``min_half_width_px``.
   * :func:`raster_discs`: filled discs (spheres seen from the camera), depth-tested or always on top.
   :func:`depth_image` reads the depth plane back in metres (the depth observations).
3. :func:`shade_resolve` shades every sample (ambient + Lambert + Blinn-Phong, one directional light fixed
   in camera space), box-filters ``k x k`` samples to one output pixel and writes ``uint8`` RGB.
4. Overlays in output pixels (:mod:`suture_gym.render.overlay`): :func:`blend_rect`,
   :func:`draw_gauge_bar` and :func:`draw_text` with the built-in 5x7 bitmap font (:data:`FONT_GLYPHS`).

The ``view`` argument of the raster kernels is a float64 array ``[focal_px, cx_px, cy_px, near_m, far_m,
guard_px]`` in the G-buffer's pixel units (multiply the camera's focal length and principal point by the
supersampling factor). Non-finite or degenerate primitives are skipped.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

#: Fixed-point steps per pixel for the triangle edge functions (8 sub-pixel bits).
SUBPIXEL = 256
_HALF = SUBPIXEL // 2
#: Slots of a clip-space polygon vertex: camera-space position (3), normal (3), colour (3).
_VERTEX_SLOTS = 9
#: A triangle clipped by 5 planes has at most 3 + 5 vertices.
_MAX_POLY = 9


# ----------------------------------------------------------------------------------------------------------
# Geometry
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def transform_points(rotation, origin, q, out):
    """Rigid transform ``out[i] = rotation @ (q[i] - origin)``.

    rotation (3,3), origin (3,) m, q (N,3) m; out (N,3) m. Non-finite points stay non-finite.
    """
    for i in range(q.shape[0]):
        x = q[i, 0] - origin[0]
        y = q[i, 1] - origin[1]
        z = q[i, 2] - origin[2]
        for r in range(3):
            out[i, r] = rotation[r, 0] * x + rotation[r, 1] * y + rotation[r, 2] * z


@njit(cache=True)
def _finite3(a, i):
    return math.isfinite(a[i, 0]) and math.isfinite(a[i, 1]) and math.isfinite(a[i, 2])


@njit(cache=True)
def vertex_normals(q, triangles, out):
    """Area-weighted unit vertex normals of a triangle mesh.

    q (N,3) m, triangles (F,3) integer indices into q; out (N,3) unitless. Each triangle adds its
    (unnormalised) cross product ``(q1-q0) x (q2-q0)`` to its three vertices, so larger faces weigh more.
    Triangles with a non-finite vertex are skipped; a vertex with no usable triangle gets the zero vector.
    """
    out[:, :] = 0.0
    for t in range(triangles.shape[0]):
        i0, i1, i2 = triangles[t, 0], triangles[t, 1], triangles[t, 2]
        if not (_finite3(q, i0) and _finite3(q, i1) and _finite3(q, i2)):
            continue
        ax = q[i1, 0] - q[i0, 0]
        ay = q[i1, 1] - q[i0, 1]
        az = q[i1, 2] - q[i0, 2]
        bx = q[i2, 0] - q[i0, 0]
        by = q[i2, 1] - q[i0, 1]
        bz = q[i2, 2] - q[i0, 2]
        nx = ay * bz - az * by
        ny = az * bx - ax * bz
        nz = ax * by - ay * bx
        for i in (i0, i1, i2):
            out[i, 0] += nx
            out[i, 1] += ny
            out[i, 2] += nz
    for i in range(out.shape[0]):
        n = math.sqrt(out[i, 0] ** 2 + out[i, 1] ** 2 + out[i, 2] ** 2)
        if n > 0.0 and math.isfinite(n):
            out[i, 0] /= n
            out[i, 1] /= n
            out[i, 2] /= n
        else:
            out[i, 0] = 0.0
            out[i, 1] = 0.0
            out[i, 2] = 0.0


@njit(cache=True)
def clear_gbuffer(gb_inv_depth, gb_material):
    """Reset the depth (to 0 = infinitely far) and material (to 0 = background) planes of a G-buffer."""
    gb_inv_depth[:, :] = 0.0
    gb_material[:, :] = 0


# ----------------------------------------------------------------------------------------------------------
# Triangles
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _clip_planes(view, width, height):
    """(5,4) camera-space half-spaces ``a x + b y + c z + e >= 0``: near plane, then the guard band's sides.

    The side planes bound ``-guard <= u <= width + guard`` and ``-guard <= v <= height + guard`` (pixels).
    """
    f, cx, cy, near, guard = view[0], view[1], view[2], view[3], view[5]
    planes = np.zeros((5, 4))
    planes[0, 2] = -1.0
    planes[0, 3] = -near
    planes[1, 0] = f
    planes[1, 2] = -(cx + guard)
    planes[2, 0] = -f
    planes[2, 2] = -(width + guard - cx)
    planes[3, 1] = -f
    planes[3, 2] = -(cy + guard)
    planes[4, 1] = f
    planes[4, 2] = -(height + guard - cy)
    return planes


@njit(cache=True)
def _plane_value(plane, poly, i):
    return plane[0] * poly[i, 0] + plane[1] * poly[i, 1] + plane[2] * poly[i, 2] + plane[3]


@njit(cache=True)
def _clip_polygon(poly_in, n_in, plane, poly_out):
    """Sutherland-Hodgman: clip the convex polygon ``poly_in[:n_in]`` to ``plane >= 0``; returns the new count.

    Attributes (all slots) are interpolated linearly along cut edges, which is exact for camera-space
    positions and for attributes that are affine over the triangle.
    """
    n_out = 0
    for i in range(n_in):
        j = i + 1 if i + 1 < n_in else 0
        da = _plane_value(plane, poly_in, i)
        db = _plane_value(plane, poly_in, j)
        if da >= 0.0:
            poly_out[n_out, :] = poly_in[i, :]
            n_out += 1
        if (da >= 0.0) != (db >= 0.0):
            t = da / (da - db)
            for s in range(_VERTEX_SLOTS):
                poly_out[n_out, s] = poly_in[i, s] + t * (poly_in[j, s] - poly_in[i, s])
            n_out += 1
    return n_out


@njit(cache=True)
def _is_top_left(dx, dy):
    """Top-left rule for an edge of a triangle with positive area in y-down pixel space (interior on the
    edge's right-hand side when walking ``a -> b`` on screen): top edges are horizontal with ``dx > 0``,
    left edges go up (``dy < 0``)."""
    return dy < 0 or (dy == 0 and dx > 0)


@njit(cache=True)
def _raster_screen_triangle(scr, i0, i1, i2, material_id, inv_far, gb_inv_depth, gb_normal, gb_albedo, gb_material):
    """Scan-convert one screen-space triangle of ``scr`` (rows ``[u, v, 1/d, n/d (3), rgb/d (3)]``).

    Vertices are snapped to 1/SUBPIXEL of a pixel and the edge functions are evaluated exactly in int64, so
    two triangles sharing an edge split its pixels without gaps or overlaps (top-left rule). Degenerate
    (zero-area after snapping) triangles draw nothing.
    """
    height, width = gb_inv_depth.shape
    x0 = np.int64(math.floor(scr[i0, 0] * SUBPIXEL + 0.5))
    y0 = np.int64(math.floor(scr[i0, 1] * SUBPIXEL + 0.5))
    x1 = np.int64(math.floor(scr[i1, 0] * SUBPIXEL + 0.5))
    y1 = np.int64(math.floor(scr[i1, 1] * SUBPIXEL + 0.5))
    x2 = np.int64(math.floor(scr[i2, 0] * SUBPIXEL + 0.5))
    y2 = np.int64(math.floor(scr[i2, 1] * SUBPIXEL + 0.5))
    area = (x1 - x0) * (y2 - y0) - (y1 - y0) * (x2 - x0)
    if area == 0:
        return
    if area < 0:
        i1, i2 = i2, i1
        x1, y1, x2, y2 = x2, y2, x1, y1
        area = -area
    # Pixel columns/rows whose centres (SUBPIXEL * i + HALF) lie inside the snapped bounding box.
    px_lo = max(-((_HALF - min(x0, x1, x2)) // SUBPIXEL), 0)
    px_hi = min((max(x0, x1, x2) - _HALF) // SUBPIXEL, width - 1)
    py_lo = max(-((_HALF - min(y0, y1, y2)) // SUBPIXEL), 0)
    py_hi = min((max(y0, y1, y2) - _HALF) // SUBPIXEL, height - 1)
    if px_lo > px_hi or py_lo > py_hi:
        return
    # Edge k is opposite vertex k: e0 = (v1 -> v2), e1 = (v2 -> v0), e2 = (v0 -> v1).
    bias0 = 0 if _is_top_left(x2 - x1, y2 - y1) else -1
    bias1 = 0 if _is_top_left(x0 - x2, y0 - y2) else -1
    bias2 = 0 if _is_top_left(x1 - x0, y1 - y0) else -1
    sx = px_lo * SUBPIXEL + _HALF
    sy = py_lo * SUBPIXEL + _HALF
    row0 = (x2 - x1) * (sy - y1) - (y2 - y1) * (sx - x1)
    row1 = (x0 - x2) * (sy - y2) - (y0 - y2) * (sx - x2)
    row2 = (x1 - x0) * (sy - y0) - (y1 - y0) * (sx - x0)
    step_x0 = -(y2 - y1) * SUBPIXEL
    step_x1 = -(y0 - y2) * SUBPIXEL
    step_x2 = -(y1 - y0) * SUBPIXEL
    step_y0 = (x2 - x1) * SUBPIXEL
    step_y1 = (x0 - x2) * SUBPIXEL
    step_y2 = (x1 - x0) * SUBPIXEL
    inv_area = 1.0 / area
    for py in range(py_lo, py_hi + 1):
        e0, e1, e2 = row0, row1, row2
        for px in range(px_lo, px_hi + 1):
            if e0 + bias0 >= 0 and e1 + bias1 >= 0 and e2 + bias2 >= 0:
                l0 = e0 * inv_area
                l1 = e1 * inv_area
                l2 = e2 * inv_area
                w = l0 * scr[i0, 2] + l1 * scr[i1, 2] + l2 * scr[i2, 2]
                if w > gb_inv_depth[py, px] and w >= inv_far:
                    d = 1.0 / w
                    gb_inv_depth[py, px] = w
                    for c in range(3):
                        gb_normal[py, px, c] = d * (l0 * scr[i0, 3 + c] + l1 * scr[i1, 3 + c] + l2 * scr[i2, 3 + c])
                        gb_albedo[py, px, c] = d * (l0 * scr[i0, 6 + c] + l1 * scr[i1, 6 + c] + l2 * scr[i2, 6 + c])
                    gb_material[py, px] = material_id
            e0 += step_x0
            e1 += step_x1
            e2 += step_x2
        row0 += step_y0
        row1 += step_y1
        row2 += step_y2


@njit(cache=True)
def raster_triangles(
    cam_q,
    cam_n,
    vertex_color,
    triangles,
    face_color,
    cull_back_faces,
    material_id,
    view,
    gb_inv_depth,
    gb_normal,
    gb_albedo,
    gb_material,
):
    """Draw a triangle mesh into the G-buffer with depth test.

    Args:
        cam_q: (N,3) camera-space vertex positions, m.
        cam_n: (N,3) camera-space unit vertex normals (e.g. from :func:`vertex_normals` on ``cam_q``).
        vertex_color: (N,3) RGB in [0, 1] per vertex (interpolated), used when ``face_color`` has no rows.
        triangles: (F,3) integer vertex indices.
        face_color: (F,3) RGB in [0, 1] per triangle (flat), or an empty (0,3) array.
        cull_back_faces: skip triangles whose ``(q1-q0) x (q2-q0)`` normal faces away from the eye (only right
            for closed, outward-oriented surfaces seen from outside; about halves the work).
        material_id: material written for the covered samples (1..255).
        view: (6,) float64 ``[focal_px, cx_px, cy_px, near_m, far_m, guard_px]``.
        gb_*: the G-buffer (see the module docstring), updated in place.

    Without culling, triangles are two-sided: if a triangle faces away from the camera its vertex normals are
    flipped for shading. Triangles with a non-finite vertex or zero area are skipped.
    """
    height, width = gb_inv_depth.shape
    planes = _clip_planes(view, width, height)
    f, cx, cy, inv_far = view[0], view[1], view[2], 1.0 / view[4]
    use_face_color = face_color.shape[0] == triangles.shape[0] and triangles.shape[0] > 0
    poly_a = np.empty((_MAX_POLY, _VERTEX_SLOTS))
    poly_b = np.empty((_MAX_POLY, _VERTEX_SLOTS))
    scr = np.empty((_MAX_POLY, _VERTEX_SLOTS))
    for t in range(triangles.shape[0]):
        ok = True
        for k in range(3):
            i = triangles[t, k]
            if not _finite3(cam_q, i):
                ok = False
                break
            for s in range(3):
                poly_a[k, s] = cam_q[i, s]
                poly_a[k, 3 + s] = cam_n[i, s]
                poly_a[k, 6 + s] = face_color[t, s] if use_face_color else vertex_color[i, s]
        if not ok:
            continue
        # Face normal and facing: the view vector from the surface to the eye (origin) is -p0.
        ax = poly_a[1, 0] - poly_a[0, 0]
        ay = poly_a[1, 1] - poly_a[0, 1]
        az = poly_a[1, 2] - poly_a[0, 2]
        bx = poly_a[2, 0] - poly_a[0, 0]
        by = poly_a[2, 1] - poly_a[0, 1]
        bz = poly_a[2, 2] - poly_a[0, 2]
        fx = ay * bz - az * by
        fy = az * bx - ax * bz
        fz = ax * by - ay * bx
        facing = -(fx * poly_a[0, 0] + fy * poly_a[0, 1] + fz * poly_a[0, 2])
        if facing == 0.0 and fx == 0.0 and fy == 0.0 and fz == 0.0:
            continue
        if facing < 0.0:
            if cull_back_faces:
                continue
            for k in range(3):
                for s in range(3, 6):
                    poly_a[k, s] = -poly_a[k, s]
        # Trivial accept / reject against the clip planes, else clip.
        n = 3
        reject = False
        inside_all = True
        for p in range(5):
            v0 = _plane_value(planes[p], poly_a, 0)
            v1 = _plane_value(planes[p], poly_a, 1)
            v2 = _plane_value(planes[p], poly_a, 2)
            if v0 < 0.0 and v1 < 0.0 and v2 < 0.0:
                reject = True
                break
            if v0 < 0.0 or v1 < 0.0 or v2 < 0.0:
                inside_all = False
        if reject:
            continue
        src = poly_a
        if not inside_all:
            dst = poly_b
            for p in range(5):
                n = _clip_polygon(src, n, planes[p], dst)
                if n < 3:
                    break
                src, dst = dst, src
            if n < 3:
                continue
        for k in range(n):
            w = -1.0 / src[k, 2]
            scr[k, 0] = cx + f * src[k, 0] * w
            scr[k, 1] = cy - f * src[k, 1] * w
            scr[k, 2] = w
            for s in range(3, _VERTEX_SLOTS):
                scr[k, s] = src[k, s] * w
        for k in range(1, n - 1):
            _raster_screen_triangle(
                scr, 0, k, k + 1, material_id, inv_far, gb_inv_depth, gb_normal, gb_albedo, gb_material
            )


# ----------------------------------------------------------------------------------------------------------
# Strands and markers
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _clip_segment_near(a, b, near):
    """Parameters ``(t0, t1)`` of the part of segment ``a -> b`` (camera space) with depth ``-z >= near``;
    ``t0 > t1`` when none of it is."""
    da = -a[2] - near
    db = -b[2] - near
    if da < 0.0 and db < 0.0:
        return 1.0, 0.0
    if da >= 0.0 and db >= 0.0:
        return 0.0, 1.0
    t = da / (da - db)
    if da < 0.0:
        return t, 1.0
    return 0.0, t


@njit(cache=True)
def _tube_frame(a, b):
    """Shading frame of the camera-space segment ``a -> b`` seen from the eye (origin).

    Returns ``(mx, my, mz, sx, sy, sz, sin_phi)``: ``m`` the unit direction from the segment midpoint towards
    the eye with its component along the segment removed, ``s = axis x m`` the unit side direction, and
    ``sin_phi`` the sine of the angle between the axis and the line of sight (1 for a degenerate segment or
    one pointing at the eye, which are then shaded like a sphere around the line of sight).
    """
    mx = -(a[0] + b[0])
    my = -(a[1] + b[1])
    mz = -(a[2] + b[2])
    mn = math.sqrt(mx * mx + my * my + mz * mz)
    mx /= mn
    my /= mn
    mz /= mn
    ux = b[0] - a[0]
    uy = b[1] - a[1]
    uz = b[2] - a[2]
    un = math.sqrt(ux * ux + uy * uy + uz * uz)
    if un > 0.0:
        ux /= un
        uy /= un
        uz /= un
        mu = mx * ux + my * uy + mz * uz
        px = mx - mu * ux
        py = my - mu * uy
        pz = mz - mu * uz
        sin_phi = math.sqrt(px * px + py * py + pz * pz)
        if sin_phi > 1e-6:
            px /= sin_phi
            py /= sin_phi
            pz /= sin_phi
            return px, py, pz, uy * pz - uz * py, uz * px - ux * pz, ux * py - uy * px, sin_phi
    # Sphere-like: the side axis is the camera's x axis made orthogonal to m.
    sx = 1.0 - mx * mx
    sy = -mx * my
    sz = -mx * mz
    sn = math.sqrt(sx * sx + sy * sy + sz * sz)
    if sn == 0.0:
        return mx, my, mz, 0.0, 1.0, 0.0, 1.0
    return mx, my, mz, sx / sn, sy / sn, sz / sn, 1.0


@njit(cache=True)
def raster_capsules(
    cam_q, radius, min_half_width_px, color, material_id, view, gb_inv_depth, gb_normal, gb_albedo, gb_material
):
    """Draw the polyline ``cam_q[0] - cam_q[1] - ...`` as a tube of world radius ``radius`` (m).

    Each segment (clipped to the near plane) becomes a screen-space capsule around its projected centreline.
    The half-width at a point is ``max(radius * f / d, min_half_width_px)`` pixels, interpolated along the
    segment, so a thread thinner than a pixel stays visible. A covered sample at fractional screen distance
    ``s`` from the centreline gets the depth of the near side of a cylinder tilted by ``phi`` from the line of
    sight, ``d_centre - radius sqrt(1 - s^2) / sin(phi)`` (no nearer than the segment's nearer end minus the
    radius), so the tube body hides the round caps at the joints, and the cylinder's normal; beyond the ends
    the caps are spheres (``d_end - radius sqrt(1 - s^2)``). Segments with a non-finite end are skipped; a
    single node is drawn as a disc.

    cam_q (K,3) m camera space; color (3,) RGB in [0, 1]; other arguments as in :func:`raster_triangles`.
    """
    height, width = gb_inv_depth.shape
    f, cx, cy, near, inv_far = view[0], view[1], view[2], view[3], 1.0 / view[4]
    n_nodes = cam_q.shape[0]
    n_seg = max(n_nodes - 1, 1) if n_nodes > 0 else 0
    a = np.empty(3)
    b = np.empty(3)
    for sgm in range(n_seg):
        j = sgm + 1 if n_nodes > 1 else sgm
        if not (_finite3(cam_q, sgm) and _finite3(cam_q, j)):
            continue
        t0, t1 = _clip_segment_near(cam_q[sgm], cam_q[j], near)
        if t0 > t1:
            continue
        for s in range(3):
            a[s] = cam_q[sgm, s] + t0 * (cam_q[j, s] - cam_q[sgm, s])
            b[s] = cam_q[sgm, s] + t1 * (cam_q[j, s] - cam_q[sgm, s])
        wa = -1.0 / a[2]
        wb = -1.0 / b[2]
        ua = cx + f * a[0] * wa
        va = cy - f * a[1] * wa
        ub = cx + f * b[0] * wb
        vb = cy - f * b[1] * wb
        ra = max(radius * f * wa, min_half_width_px)
        rb = max(radius * f * wb, min_half_width_px)
        r_max = max(ra, rb)
        px_lo = max(int(math.floor(min(ua, ub) - r_max - 0.5)), 0)
        px_hi = min(int(math.ceil(max(ua, ub) + r_max - 0.5)), width - 1)
        py_lo = max(int(math.floor(min(va, vb) - r_max - 0.5)), 0)
        py_hi = min(int(math.ceil(max(va, vb) + r_max - 0.5)), height - 1)
        if px_lo > px_hi or py_lo > py_hi:
            continue
        du = ub - ua
        dv = vb - va
        len2 = du * du + dv * dv
        mx, my, mz, sx, sy, sz, sin_phi = _tube_frame(a, b)
        d_min = min(-a[2], -b[2]) - radius
        for py in range(py_lo, py_hi + 1):
            pv = py + 0.5
            for px in range(px_lo, px_hi + 1):
                pu = px + 0.5
                t = 0.0
                if len2 > 0.0:
                    t = ((pu - ua) * du + (pv - va) * dv) / len2
                cap = t <= 0.0 or t >= 1.0
                t = min(max(t, 0.0), 1.0)
                qu = pu - (ua + t * du)
                qv = pv - (va + t * dv)
                dist = math.sqrt(qu * qu + qv * qv)
                r = ra + t * (rb - ra)
                if dist > r:
                    continue
                s_rel = dist / r
                bulge = math.sqrt(max(1.0 - s_rel * s_rel, 0.0))
                d_centre = 1.0 / (wa + t * (wb - wa))
                if cap:
                    d = d_centre - radius * bulge
                else:
                    d = max(d_centre - radius * bulge / sin_phi, d_min)
                w = 1.0 / max(d, near)
                if w > gb_inv_depth[py, px] and w >= inv_far:
                    gb_inv_depth[py, px] = w
                    # Which side of the axis the sample is on: screen offset (u right, v down) vs. the side axis.
                    side = s_rel if qu * sx - qv * sy >= 0.0 else -s_rel
                    nx = side * sx + bulge * mx
                    ny = side * sy + bulge * my
                    nz = side * sz + bulge * mz
                    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
                    gb_normal[py, px, 0] = nx / nn
                    gb_normal[py, px, 1] = ny / nn
                    gb_normal[py, px, 2] = nz / nn
                    for c in range(3):
                        gb_albedo[py, px, c] = color[c]
                    gb_material[py, px] = material_id


@njit(cache=True)
def raster_discs(
    cam_q,
    radius,
    color,
    on_top,
    min_radius_px,
    rim_px,
    rim_shade,
    material_id,
    view,
    gb_inv_depth,
    gb_normal,
    gb_albedo,
    gb_material,
):
    """Draw markers as filled discs facing the camera.

    Args:
        cam_q: (P,3) camera-space centres, m.
        radius: (P,) world radii, m; the screen radius is ``max(radius * f / d, min_radius_px)`` pixels.
        color: (P,3) RGB in [0, 1].
        on_top: (P,) bool; True draws the disc over everything drawn before it (no depth test), False tests
            and writes depth like a sphere of that radius (near side ``d - radius sqrt(1 - s^2)``).
        rim_px: width of a darker outline ring, pixels (0 for none); ``rim_shade`` multiplies its colour.
        Other arguments as in :func:`raster_triangles`.

    Markers with a non-finite centre or radius, or whose centre is nearer than the near plane, are skipped.
    """
    height, width = gb_inv_depth.shape
    f, cx, cy, near, inv_far = view[0], view[1], view[2], view[3], 1.0 / view[4]
    for m in range(cam_q.shape[0]):
        if not (_finite3(cam_q, m) and math.isfinite(radius[m])):
            continue
        d_c = -cam_q[m, 2]
        if d_c < near:
            continue
        w_c = 1.0 / d_c
        uc = cx + f * cam_q[m, 0] * w_c
        vc = cy - f * cam_q[m, 1] * w_c
        r = max(radius[m] * f * w_c, min_radius_px)
        px_lo = max(int(math.floor(uc - r - 0.5)), 0)
        px_hi = min(int(math.ceil(uc + r - 0.5)), width - 1)
        py_lo = max(int(math.floor(vc - r - 0.5)), 0)
        py_hi = min(int(math.ceil(vc + r - 0.5)), height - 1)
        for py in range(py_lo, py_hi + 1):
            for px in range(px_lo, px_hi + 1):
                qu = px + 0.5 - uc
                qv = py + 0.5 - vc
                dist = math.sqrt(qu * qu + qv * qv)
                if dist > r:
                    continue
                s_rel = dist / r
                bulge = math.sqrt(max(1.0 - s_rel * s_rel, 0.0))
                if on_top[m]:
                    w = math.inf
                else:
                    w = 1.0 / max(d_c - radius[m] * bulge, near)
                    if not (w > gb_inv_depth[py, px] and w >= inv_far):
                        continue
                gb_inv_depth[py, px] = w
                nx = qu / r
                ny = -qv / r
                gb_normal[py, px, 0] = nx
                gb_normal[py, px, 1] = ny
                gb_normal[py, px, 2] = bulge
                shade = rim_shade if dist > r - rim_px else 1.0
                for c in range(3):
                    gb_albedo[py, px, c] = shade * color[m, c]
                gb_material[py, px] = material_id


@njit(cache=True)
def depth_image(gb_inv_depth, far, out):
    """Depth image of a G-buffer drawn at the output resolution (no supersampling).

    gb_inv_depth (H,W) float64 1/m; far: float, m; out (H,W,1) float32, written: the depth ``d = 1 / w`` of the
    nearest fragment (m along the optical axis), or ``far`` where nothing was drawn (``w = 0``).
    """
    for y in range(gb_inv_depth.shape[0]):
        for x in range(gb_inv_depth.shape[1]):
            w = gb_inv_depth[y, x]
            out[y, x, 0] = min(1.0 / w, far) if w > 0.0 else far


# ----------------------------------------------------------------------------------------------------------
# Shading
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def _int_pow(x, n):
    """``x ** n`` for an integer ``n >= 0`` by repeated squaring (a few multiplications instead of exp/log)."""
    result = 1.0
    base = x
    while n > 0:
        if n & 1:
            result *= base
        base *= base
        n >>= 1
    return result


@njit(cache=True)
def shade_resolve(
    gb_inv_depth, gb_normal, gb_albedo, gb_material, materials, light_dir, view, background_top, background_bottom, out
):
    """Shade the G-buffer and box-filter it down into the output image.

    Args:
        gb_*: G-buffer of shape (k H, k W) for an output of (H, W); ``k`` is the supersampling factor.
        materials: (M,4) rows ``[ambient, diffuse, specular, shininess]`` indexed by material id; row 0
            (background) is unused; shininess is used as an integer (truncated).
        light_dir: (3,) camera-space unit vector from the surface towards the light (a directional light).
        view: (6,) as in :func:`raster_triangles` (focal length and principal point give the view rays).
        background_top, background_bottom: (3,) RGB in [0, 1] of a vertical background gradient.
        out: (H,W,3) uint8, written.

    A surface sample's colour is ``albedo (ambient + diffuse max(0, n.l)) + specular max(0, n.h)^shininess``
    (Blinn-Phong, ``h`` the unit half vector between ``l`` and the view direction), clamped to [0, 1].
    The output pixel is the mean of its ``k x k`` samples, rounded to 8 bits.
    """
    hs, ws = gb_material.shape
    h_out, w_out = out.shape[0], out.shape[1]
    k = hs // h_out
    f, cx, cy = view[0], view[1], view[2]
    inv_count = 1.0 / (k * k)
    for oy in range(h_out):
        for ox in range(w_out):
            acc0 = 0.0
            acc1 = 0.0
            acc2 = 0.0
            for sy in range(oy * k, oy * k + k):
                for sx in range(ox * k, ox * k + k):
                    mat = gb_material[sy, sx]
                    if mat == 0:
                        g = (sy + 0.5) / hs
                        acc0 += background_top[0] + g * (background_bottom[0] - background_top[0])
                        acc1 += background_top[1] + g * (background_bottom[1] - background_top[1])
                        acc2 += background_top[2] + g * (background_bottom[2] - background_top[2])
                        continue
                    nx = gb_normal[sy, sx, 0]
                    ny = gb_normal[sy, sx, 1]
                    nz = gb_normal[sy, sx, 2]
                    nn = math.sqrt(nx * nx + ny * ny + nz * nz)
                    lambert = 0.0
                    spec = 0.0
                    if nn > 0.0:
                        nx /= nn
                        ny /= nn
                        nz /= nn
                        lambert = max(nx * light_dir[0] + ny * light_dir[1] + nz * light_dir[2], 0.0)
                        if materials[mat, 2] > 0.0:
                            # View direction: from the sample towards the eye, i.e. minus the pixel ray.
                            vx = -((sx + 0.5) - cx) / f
                            vy = ((sy + 0.5) - cy) / f
                            vz = 1.0
                            vn = math.sqrt(vx * vx + vy * vy + vz * vz)
                            hx = light_dir[0] + vx / vn
                            hy = light_dir[1] + vy / vn
                            hz = light_dir[2] + vz / vn
                            hn = math.sqrt(hx * hx + hy * hy + hz * hz)
                            if hn > 0.0:
                                ndoth = max((nx * hx + ny * hy + nz * hz) / hn, 0.0)
                                spec = materials[mat, 2] * _int_pow(ndoth, int(materials[mat, 3]))
                    light = materials[mat, 0] + materials[mat, 1] * lambert
                    acc0 += min(max(gb_albedo[sy, sx, 0] * light + spec, 0.0), 1.0)
                    acc1 += min(max(gb_albedo[sy, sx, 1] * light + spec, 0.0), 1.0)
                    acc2 += min(max(gb_albedo[sy, sx, 2] * light + spec, 0.0), 1.0)
            out[oy, ox, 0] = np.uint8(min(max(int(acc0 * inv_count * 255.0 + 0.5), 0), 255))
            out[oy, ox, 1] = np.uint8(min(max(int(acc1 * inv_count * 255.0 + 0.5), 0), 255))
            out[oy, ox, 2] = np.uint8(min(max(int(acc2 * inv_count * 255.0 + 0.5), 0), 255))
