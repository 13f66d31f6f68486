"""Scene renderer for the environments: tissue surface, needle, suture, target markers and a force gauge.

:class:`SceneRenderer` turns a :class:`RenderFrame` (plain arrays, SI units) into an ``(H, W, 3) uint8`` image
with the numba kernels of :mod:`suture_gym.render.raster`. It needs no display, GPU or system library.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from suture_gym.render.camera import Camera, frame_box
from suture_gym.render.overlay import FONT_GLYPHS, blend_rect, draw_gauge_bar, draw_text, text_glyph_indices, text_size
from suture_gym.render.raster import (
    clear_gbuffer,
    depth_image,
    raster_capsules,
    raster_discs,
    raster_triangles,
    shade_resolve,
    transform_points,
    vertex_normals,
)

#: Material ids written into the G-buffer (0 is the background).
MATERIAL_TISSUE, MATERIAL_NEEDLE, MATERIAL_SUTURE, MATERIAL_MARKER = 1, 2, 3, 4


@dataclass(frozen=True)
class Material:
    """Shading coefficients: ``colour = albedo (ambient + diffuse max(0, n.l)) + specular max(0, n.h)^shininess``.

    All unitless; ``ambient = 1, diffuse = 0, specular = 0`` draws the albedo unchanged (flat). ``shininess``
    is an integer exponent (evaluated by repeated squaring, which is much cheaper than a real power).
    """

    ambient: float
    diffuse: float
    specular: float = 0.0
    shininess: int = 32

    def __post_init__(self) -> None:
        for name in ("ambient", "diffuse", "specular"):
            value = getattr(self, name)
            if not (isinstance(value, (int, float)) and math.isfinite(value) and value >= 0.0):
                raise ValueError(f"Material.{name} must be a finite number >= 0, got {value!r}")
        if isinstance(self.shininess, bool) or not isinstance(self.shininess, (int, np.integer)) or self.shininess < 0:
            raise ValueError(f"Material.shininess must be an integer >= 0, got {self.shininess!r}")


def _rgb(value, name: str) -> np.ndarray:
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,) or not np.all(np.isfinite(arr)) or np.any(arr < 0.0) or np.any(arr > 1.0):
        raise ValueError(f"{name} must be an RGB triple in [0, 1], got {value!r}")
    return arr


@dataclass(frozen=True)
class SceneStyle:
    """Colours (RGB in [0, 1]), materials, light and minimum on-screen sizes of a :class:`SceneRenderer`.

    Fields:
        tissue_color, needle_color, suture_color: default albedos (tissue pink, needle silver, thread violet).
        entry_color, exit_color: default marker colours, used alternately (entry, exit, entry, ...).
        background_top, background_bottom: vertical background gradient.
        tissue_material, needle_material, suture_material, marker_material: :class:`Material` per entity
            (markers are flat by default so their colour is exact).
        light_direction: (3,) towards the light in camera space (x right, y up, z towards the viewer); the
            light moves with the camera, upper left and in front by default. Normalised on use.
        min_strand_width_px: smallest drawn width of the needle and the suture, output pixels.
        min_marker_radius_px: smallest drawn marker radius, output pixels.
        marker_rim_px: width of the darker marker outline, output pixels.
    """

    tissue_color: tuple = (0.91, 0.60, 0.60)
    needle_color: tuple = (0.78, 0.80, 0.84)
    suture_color: tuple = (0.22, 0.18, 0.62)
    entry_color: tuple = (0.10, 0.72, 0.22)
    exit_color: tuple = (0.86, 0.12, 0.10)
    background_top: tuple = (0.90, 0.92, 0.95)
    background_bottom: tuple = (0.62, 0.66, 0.72)
    tissue_material: Material = field(default_factory=lambda: Material(0.35, 0.70, 0.10, 24))
    needle_material: Material = field(default_factory=lambda: Material(0.35, 0.65, 0.85, 48))
    suture_material: Material = field(default_factory=lambda: Material(0.45, 0.65, 0.15, 16))
    marker_material: Material = field(default_factory=lambda: Material(1.0, 0.0, 0.0, 1))
    light_direction: tuple = (-0.35, 0.55, 0.75)
    min_strand_width_px: float = 1.5
    min_marker_radius_px: float = 3.0
    marker_rim_px: float = 1.0

    def __post_init__(self) -> None:
        for name in (
            "tissue_color",
            "needle_color",
            "suture_color",
            "entry_color",
            "exit_color",
            "background_top",
            "background_bottom",
        ):
            _rgb(getattr(self, name), name)
        light = np.asarray(self.light_direction, dtype=np.float64)
        if light.shape != (3,) or not np.all(np.isfinite(light)) or not np.any(light):
            raise ValueError(f"light_direction must be a finite non-zero (3,) vector, got {self.light_direction!r}")
        for name in ("min_strand_width_px", "min_marker_radius_px", "marker_rim_px"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0.0):
                raise ValueError(f"{name} must be a finite number >= 0 px, got {value!r}")


@dataclass
class RenderFrame:
    """Everything drawn in one frame, as arrays pulled from the simulator state (SI units).

    Fields:
        tissue_q: (N,3) float, m. Tissue vertex positions (the deformed surface mesh's vertices).
        tissue_triangles: (F,3) int, indices into ``tissue_q``; orientation does not matter (two-sided).
        tissue_vertex_color: optional (N,3) RGB in [0, 1] (float) or 0-255 (uint8), interpolated.
        tissue_face_color: optional (F,3) RGB per triangle (flat); wins over ``tissue_vertex_color``.
        needle_q: optional (K,3) float, m. Needle centreline, tip to swage or back.
        needle_radius: float, m. Needle wire radius.
        suture_q: optional (M,3) float, m. Suture centreline.
        suture_radius: float, m. Thread radius (3-0 suture: 0.1 mm).
        marker_q: optional (P,3) float, m. Marker centres (e.g. entry and exit targets).
        marker_color: optional (P,3) RGB; default alternates the style's entry and exit colours.
        marker_radius: float or (P,) float, m.
        marker_on_top: bool or (P,) bool; True draws the marker over everything (no depth test).
        tip_force: optional float, N. The needle tip's contact force, shown by the ``TIP`` gauge (bottom left)
            when given.
        force_threshold: float, N > 0. Puncture threshold, the ``TIP`` gauge's tick; the bar spans 1.5 times it.
        haptic_force: optional float, N. Magnitude of the reaction force on the instrument (what a haptic device
            renders to the hand), shown by the ``HAPTIC`` gauge above the ``TIP`` gauge when given.
        haptic_span: float, N > 0. Full scale of the ``HAPTIC`` gauge (the env's ``action.max_force``).
        caption: text drawn top left (digits, A-Z, ``.,:-+=/%()_!?``; lower case is drawn as upper case).

    Non-finite positions are not an error: the primitives that use them are skipped.
    """

    tissue_q: np.ndarray
    tissue_triangles: np.ndarray
    tissue_vertex_color: np.ndarray | None = None
    tissue_face_color: np.ndarray | None = None
    needle_q: np.ndarray | None = None
    needle_radius: float = 4e-4
    suture_q: np.ndarray | None = None
    suture_radius: float = 1e-4
    marker_q: np.ndarray | None = None
    marker_color: np.ndarray | None = None
    marker_radius: float | np.ndarray = 1e-3
    marker_on_top: bool | np.ndarray = False
    tip_force: float | None = None
    force_threshold: float = 1.0
    haptic_force: float | None = None
    haptic_span: float = 5.0
    caption: str = ""


def _points(value, name: str, allow_none: bool = True) -> np.ndarray | None:
    if value is None:
        if allow_none:
            return None
        raise ValueError(f"{name} is required")
    arr = np.asarray(value)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"{name} must have shape (n, 3), got {arr.shape}")
    if arr.dtype not in (np.float32, np.float64):
        arr = arr.astype(np.float64)
    return arr


def _colors(value, rows: int, name: str) -> np.ndarray:
    arr = np.asarray(value)
    if arr.shape != (rows, 3):
        raise ValueError(f"{name} must have shape ({rows}, 3), got {arr.shape}")
    if arr.dtype == np.uint8:
        return arr.astype(np.float32) / np.float32(255.0)
    arr = np.asarray(arr, dtype=np.float32)
    if not (np.all(np.isfinite(arr)) and arr.min(initial=0.0) >= 0.0 and arr.max(initial=0.0) <= 1.0):
        raise ValueError(f"{name} must hold RGB values in [0, 1] (or uint8 0-255)")
    return arr


def _radius(value, name: str) -> float:
    r = float(value)
    if not (math.isfinite(r) and r >= 0.0):
        raise ValueError(f"{name} must be a finite radius >= 0 m, got {value!r}")
    return r


class SceneRenderer:
    """Render :class:`RenderFrame` objects to ``(height, width, 3) uint8`` images on the CPU.

    Args:
        width, height: output size, pixels.
        camera: a :class:`Camera` of the same size, or None to frame the first frame's tissue (its finite
            vertices) with :func:`frame_box` from above at an angle; the fitted camera is then kept, so the
            view does not follow the deformation. :meth:`set_camera` replaces it.
        ssaa: supersampling factor ``k`` >= 1: render at ``k`` times the size and box-filter down.
        style: colours, materials and light (:class:`SceneStyle`).
        guard_band_px: how far outside the image (output pixels) triangles are kept before clipping.
        cull_back_faces: skip tissue triangles facing away from the eye. Halves the triangle work, but is only
            right for a closed surface oriented outward (as ``surface_triangles`` of a tet mesh) seen from
            outside; inverted elements or a camera inside the tissue then show holes. Off by default.

    The G-buffer is allocated once; per-frame scratch arrays grow to the largest frame seen and are reused,
    so a frame allocates little beyond its output image (a new array, safe to keep).
    """

    def __init__(
        self,
        width: int = 256,
        height: int = 256,
        *,
        camera: Camera | None = None,
        ssaa: int = 1,
        style: SceneStyle | None = None,
        guard_band_px: float | None = None,
        cull_back_faces: bool = False,
    ) -> None:
        for name, value in (("width", width), ("height", height), ("ssaa", ssaa)):
            if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
                raise ValueError(f"{name} must be a positive integer, got {value!r}")
        self.width, self.height, self.ssaa = int(width), int(height), int(ssaa)
        self.style = style if style is not None else SceneStyle()
        if not isinstance(self.style, SceneStyle):
            raise ValueError(f"style must be a SceneStyle, got {type(self.style).__name__}")
        guard = float(max(width, height)) if guard_band_px is None else float(guard_band_px)
        if not (math.isfinite(guard) and guard >= 0.0):
            raise ValueError(f"guard_band_px must be a finite number >= 0, got {guard_band_px!r}")
        self.guard_band_px = guard
        self.cull_back_faces = bool(cull_back_faces)
        self._camera: Camera | None = None
        if camera is not None:
            self.set_camera(camera)
        hs, ws = self.height * self.ssaa, self.width * self.ssaa
        self._gb_inv_depth = np.zeros((hs, ws), dtype=np.float64)
        self._gb_normal = np.zeros((hs, ws, 3), dtype=np.float32)
        self._gb_albedo = np.zeros((hs, ws, 3), dtype=np.float32)
        self._gb_material = np.zeros((hs, ws), dtype=np.uint8)
        self._scratch: dict[str, np.ndarray] = {}
        st = self.style
        self._materials = np.zeros((5, 4), dtype=np.float64)
        for mid, mat in (
            (MATERIAL_TISSUE, st.tissue_material),
            (MATERIAL_NEEDLE, st.needle_material),
            (MATERIAL_SUTURE, st.suture_material),
            (MATERIAL_MARKER, st.marker_material),
        ):
            self._materials[mid] = (mat.ambient, mat.diffuse, mat.specular, mat.shininess)
        light = np.asarray(st.light_direction, dtype=np.float64)
        self._light = light / np.linalg.norm(light)
        self._bg_top = np.asarray(st.background_top, dtype=np.float64)
        self._bg_bottom = np.asarray(st.background_bottom, dtype=np.float64)
        self._tissue_rgb = np.asarray(st.tissue_color, dtype=np.float32)
        self._needle_rgb = np.asarray(st.needle_color, dtype=np.float64)
        self._suture_rgb = np.asarray(st.suture_color, dtype=np.float64)
        self._no_face_color = np.zeros((0, 3), dtype=np.float32)

    # ------------------------------------------------------------------------------------------------------
    # Camera
    # ------------------------------------------------------------------------------------------------------

    @property
    def camera(self) -> Camera | None:
        """The current camera, or None until a frame with finite tissue vertices has been rendered."""
        return self._camera

    def set_camera(self, camera: Camera) -> None:
        """Use ``camera`` (same width and height as the renderer) from the next frame on."""
        if not isinstance(camera, Camera):
            raise ValueError(f"camera must be a Camera, got {type(camera).__name__}")
        if (camera.width, camera.height) != (self.width, self.height):
            raise ValueError(
                f"camera is {camera.width}x{camera.height} px but the renderer is {self.width}x{self.height} px"
            )
        self._camera = camera

    def fit_camera(self, points: np.ndarray, **frame_box_kwargs) -> Camera:
        """Frame the bounding box of the finite rows of ``points`` (N,3) m; keyword arguments go to
        :func:`frame_box` (``direction``, ``up``, ``fov_y_deg``, ``margin``). Returns the new camera."""
        pts = _points(points, "points", allow_none=False)
        finite = pts[np.all(np.isfinite(pts), axis=1)]
        if len(finite) == 0:
            raise ValueError("points has no finite row to frame")
        camera = frame_box(
            finite.min(axis=0), finite.max(axis=0), width=self.width, height=self.height, **frame_box_kwargs
        )
        self._camera = camera
        return camera

    # ------------------------------------------------------------------------------------------------------
    # Rendering
    # ------------------------------------------------------------------------------------------------------

    def _buffer(self, name: str, rows: int, dtype=np.float64) -> np.ndarray:
        """A reused (rows, 3) scratch array (grown when needed)."""
        buf = self._scratch.get(name)
        if buf is None or buf.shape[0] < rows:
            buf = np.empty((max(rows, 1), 3), dtype=dtype)
            self._scratch[name] = buf
        return buf[:rows]

    def _view(self, camera: Camera) -> np.ndarray:
        k = self.ssaa
        cx, cy = camera.principal_point
        return np.array([camera.focal_px * k, cx * k, cy * k, camera.near, camera.far, self.guard_band_px * k])

    def render(self, frame: RenderFrame) -> np.ndarray:
        """Draw ``frame``; returns a new (height, width, 3) uint8 RGB image.

        Raises ValueError (naming the field) for arrays of the wrong shape, triangle indices out of range,
        negative or non-finite radii or thresholds; non-finite positions only skip their primitives.
        """
        out = np.empty((self.height, self.width, 3), dtype=np.uint8)
        threshold, view = self._draw(frame, None)
        shade_resolve(*self._gbuffer, self._materials, self._light, view, self._bg_top, self._bg_bottom, out)
        self._draw_overlays(frame, threshold, out)
        return out

    def render_sensor(self, frame: RenderFrame, rgb: bool, depth: bool) -> tuple[np.ndarray | None, np.ndarray | None]:
        """What a camera sees of ``frame``: ``(rgb, depth)``, each a new array or None when not asked for.

        ``rgb``: ``(height, width, 3) uint8``, as :meth:`render` without the caption and the force gauge.
        ``depth``: ``(height, width, 1) float32``, m along the optical axis, of the nearest tissue, needle or
        thread surface at each pixel centre; ``camera.far`` where none is (markers are not part of it).
        Needs a camera (:meth:`set_camera`) and no supersampling (``ssaa = 1``); ValueError otherwise, and as
        :meth:`render` for a bad frame.
        """
        if self._camera is None:
            raise ValueError("render_sensor needs a camera: call set_camera or fit_camera first")
        if self.ssaa != 1:
            raise ValueError(f"render_sensor draws at the output resolution and needs ssaa = 1, got {self.ssaa}")
        depth_out = np.empty((self.height, self.width, 1), dtype=np.float32) if depth else None
        _, view = self._draw(frame, depth_out)
        rgb_out = None
        if rgb:
            rgb_out = np.empty((self.height, self.width, 3), dtype=np.uint8)
            shade_resolve(*self._gbuffer, self._materials, self._light, view, self._bg_top, self._bg_bottom, rgb_out)
        return rgb_out, depth_out

    def _draw(self, frame: RenderFrame, depth_out: np.ndarray | None) -> tuple[float, np.ndarray]:
        """Validate ``frame`` and draw it into the G-buffer (framing the tissue first if there is no camera yet);
        with ``depth_out`` (``(H, W, 1) float32``) the depth of the tissue, needle and thread is read back into it
        before the markers are drawn. Returns the gauge's threshold (N) and the view vector of the kernels."""
        if not isinstance(frame, RenderFrame):
            raise ValueError(f"frame must be a RenderFrame, got {type(frame).__name__}")
        tissue_q = _points(frame.tissue_q, "tissue_q", allow_none=False)
        tris = np.asarray(frame.tissue_triangles)
        if tris.ndim != 2 or tris.shape[1] != 3 or not np.issubdtype(tris.dtype, np.integer):
            raise ValueError(f"tissue_triangles must be an (F, 3) integer array, got {tris.shape} {tris.dtype}")
        n_vert = len(tissue_q)
        if tris.size and (tris.min() < 0 or tris.max() >= n_vert):
            raise ValueError(f"tissue_triangles indices must lie in [0, {n_vert}), got [{tris.min()}, {tris.max()}]")
        vertex_color = None
        if frame.tissue_vertex_color is not None:
            vertex_color = _colors(frame.tissue_vertex_color, n_vert, "tissue_vertex_color")
        face_color = self._no_face_color
        if frame.tissue_face_color is not None:
            face_color = _colors(frame.tissue_face_color, len(tris), "tissue_face_color")
        needle_q = _points(frame.needle_q, "needle_q")
        suture_q = _points(frame.suture_q, "suture_q")
        needle_radius = _radius(frame.needle_radius, "needle_radius")
        suture_radius = _radius(frame.suture_radius, "suture_radius")
        marker_q = _points(frame.marker_q, "marker_q")
        markers = self._marker_arrays(frame, marker_q) if marker_q is not None else None
        threshold = float(frame.force_threshold)
        if not (math.isfinite(threshold) and threshold > 0.0):
            raise ValueError(f"force_threshold must be a finite force > 0 N, got {frame.force_threshold!r}")
        span = float(frame.haptic_span)
        if not (math.isfinite(span) and span > 0.0):
            raise ValueError(f"haptic_span must be a finite force > 0 N, got {frame.haptic_span!r}")
        if not isinstance(frame.caption, str):
            raise ValueError(f"caption must be a str, got {type(frame.caption).__name__}")

        if self._camera is None and n_vert and np.isfinite(tissue_q).all(axis=1).any():
            self.fit_camera(tissue_q)
        gb = self._gbuffer
        clear_gbuffer(self._gb_inv_depth, self._gb_material)
        camera = self._camera
        # Without a camera nothing is drawn and the shading pass only paints the background.
        view = self._view(camera) if camera is not None else np.array([1.0, 0.0, 0.0, 1.0, 2.0, 0.0])
        if camera is not None:
            rot, eye = camera.rotation, camera.eye
            cam_q = self._buffer("tissue_q", n_vert)
            transform_points(rot, eye, tissue_q, cam_q)
            cam_n = self._buffer("tissue_n", n_vert)
            vertex_normals(cam_q, tris, cam_n)
            if vertex_color is None:
                vertex_color = self._buffer("tissue_rgb", n_vert, np.float32)
                vertex_color[:] = self._tissue_rgb
            raster_triangles(
                cam_q, cam_n, vertex_color, tris, face_color, self.cull_back_faces, MATERIAL_TISSUE, view, *gb
            )
            min_half = 0.5 * self.style.min_strand_width_px * self.ssaa
            for name, q, radius, rgb, mid in (
                ("needle_q", needle_q, needle_radius, self._needle_rgb, MATERIAL_NEEDLE),
                ("suture_q", suture_q, suture_radius, self._suture_rgb, MATERIAL_SUTURE),
            ):
                if q is None or len(q) == 0:
                    continue
                cam_s = self._buffer(name, len(q))
                transform_points(rot, eye, q, cam_s)
                raster_capsules(cam_s, radius, min_half, rgb, mid, view, *gb)
            if depth_out is not None:
                depth_image(self._gb_inv_depth, camera.far, depth_out)
            if markers is not None:
                radius, rgb, on_top = markers
                cam_m = self._buffer("marker_q", len(marker_q))
                transform_points(rot, eye, marker_q, cam_m)
                raster_discs(
                    cam_m,
                    radius,
                    rgb,
                    on_top,
                    self.style.min_marker_radius_px * self.ssaa,
                    self.style.marker_rim_px * self.ssaa,
                    0.55,
                    MATERIAL_MARKER,
                    view,
                    *gb,
                )
        return threshold, view

    @property
    def _gbuffer(self) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        return self._gb_inv_depth, self._gb_normal, self._gb_albedo, self._gb_material

    def _marker_arrays(self, frame: RenderFrame, marker_q: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(radius (P,) m, colour (P,3), on_top (P,) bool) of the markers, validated."""
        p = len(marker_q)
        try:
            radius = np.broadcast_to(np.asarray(frame.marker_radius, dtype=np.float64), (p,)).copy()
        except ValueError as err:
            raise ValueError(f"marker_radius must be a float or a ({p},) array of radii in m") from err
        if np.any(radius < 0.0) or not np.all(np.isfinite(radius)):
            raise ValueError(f"marker_radius must be finite radii >= 0 m, got {radius.tolist()}")
        if frame.marker_color is None:
            rgb = np.empty((p, 3), dtype=np.float64)
            rgb[0::2] = self.style.entry_color
            rgb[1::2] = self.style.exit_color
        else:
            rgb = _colors(frame.marker_color, p, "marker_color").astype(np.float64)
        try:
            on_top = np.broadcast_to(np.asarray(frame.marker_on_top, dtype=np.bool_), (p,)).copy()
        except ValueError as err:
            raise ValueError(f"marker_on_top must be a bool or a ({p},) bool array") from err
        return radius, rgb, on_top

    # ------------------------------------------------------------------------------------------------------
    # Overlays
    # ------------------------------------------------------------------------------------------------------

    @property
    def text_scale(self) -> int:
        """Pixel size of one font cell: 1 up to about 384 px images, then growing with the image."""
        return max(1, round(min(self.width, self.height) / 256))

    def gauge_layout(self, text: str, row: int = 0) -> dict[str, tuple[int, int, int, int]]:
        """Rectangles ``(x, y, width, height)`` in output pixels of a gauge's ``panel``, ``label``, ``bar`` and
        ``text`` (the value it prints, ``text``). Gauges stack up from the bottom left of the image: ``row`` 0 is
        the ``TIP`` gauge, row 1 the ``HAPTIC`` gauge. Every row's label column is as wide as the longest label,
        so the bars line up."""
        s = self.text_scale
        margin, pad = 4 * s, 3 * s
        text_w, text_h = text_size(text, s)
        label_w, _ = text_size(max(_GAUGE_LABELS, key=len), s)
        fixed_w = pad + label_w + 4 * s + 4 * s + text_w + pad
        bar_w, bar_h = max(min(round(0.3 * self.width), self.width - 2 * margin - fixed_w), 12 * s), text_h
        panel_w = fixed_w + bar_w
        panel_h = pad + bar_h + pad
        px, py = margin, self.height - margin - panel_h - row * (panel_h + s)
        bar_x = px + pad + label_w + 4 * s
        return {
            "panel": (px, py, panel_w, panel_h),
            "label": (px + pad, py + pad, label_w, text_h),
            "bar": (bar_x, py + pad, bar_w, bar_h),
            "text": (bar_x + bar_w + 4 * s, py + pad, text_w, text_h),
        }

    def _draw_overlays(self, frame: RenderFrame, threshold: float, out: np.ndarray) -> None:
        s = self.text_scale
        white = np.full(3, 255, dtype=np.uint8)
        black = np.zeros(3, dtype=np.uint8)
        if frame.caption:
            text_w, text_h = text_size(frame.caption, s)
            pad = 3 * s
            blend_rect(2 * s, 2 * s, 2 * s + text_w + 2 * pad, 2 * s + text_h + 2 * pad, black, 0.55, out)
            draw_text(text_glyph_indices(frame.caption), FONT_GLYPHS, 2 * s + pad, 2 * s + pad, s, white, out)
        # (label, force N, full scale N, tick as a fraction of the bar): tip against the puncture threshold,
        # haptic against the largest commanded force.
        gauges = []
        if frame.tip_force is not None:
            gauges.append(("TIP", float(frame.tip_force), _GAUGE_SPAN * threshold, 1.0 / _GAUGE_SPAN))
        if frame.haptic_force is not None:
            gauges.append(("HAPTIC", float(frame.haptic_force), float(frame.haptic_span), 1.0))
        for row, (label, force, span, tick) in enumerate(gauges):
            text = f"{force:.2f} N" if math.isfinite(force) else "--- N"
            lay = self.gauge_layout(text, row)
            x, y, w, h = lay["panel"]
            blend_rect(x, y, x + w, y + h, black, 0.55, out)
            x, y, _, _ = lay["label"]
            draw_text(text_glyph_indices(label), FONT_GLYPHS, x, y, s, white, out)
            x, y, w, h = lay["bar"]
            fill = min(max(force / span, 0.0), 1.0) if math.isfinite(force) else math.nan
            draw_gauge_bar(x, y, w, h, fill, tick, _RAMP_AT, _RAMP_COLOR, _EMPTY_COLOR, white, max(s, 2), 2 * s, out)
            x, y, _, _ = lay["text"]
            draw_text(text_glyph_indices(text), FONT_GLYPHS, x, y, s, white, out)


#: The gauges' labels, bottom up.
_GAUGE_LABELS = ("TIP", "HAPTIC")
#: The ``TIP`` gauge spans [0, _GAUGE_SPAN * threshold]; its tick marks the threshold.
_GAUGE_SPAN = 1.5
#: Colour ramp of a gauge in units of its tick: green, yellow at 75 %, red from the tick on.
_RAMP_AT = np.array([0.0, 0.75, 1.0])
_RAMP_COLOR = np.array([[40, 190, 70], [240, 210, 40], [220, 40, 30]], dtype=np.uint8)
_EMPTY_COLOR = np.array([70, 70, 70], dtype=np.uint8)
