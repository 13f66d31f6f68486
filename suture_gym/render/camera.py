"""Look-at perspective camera: world (m) -> camera space -> pixels.

Conventions (used by every kernel in :mod:`suture_gym.render.raster`):

* Camera space is right-handed: ``x`` to the right of the image, ``y`` up, the camera looks along ``-z``.
  A point's depth is ``d = -z_cam`` (m), positive in front of the camera.
* Pixel coordinates ``(u, v)`` grow right and down; pixel ``(i, j)`` (column ``i``, row ``j``) covers
  ``[i, i+1) x [j, j+1)`` and is sampled at its centre ``(i + 0.5, j + 0.5)``.
* ``u = cx + f x_cam / d`` and ``v = cy - f y_cam / d`` with the principal point ``(cx, cy) = (W/2, H/2)``
  and the focal length ``f = (H/2) / tan(fov_y/2)`` in pixels (square pixels).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np


def _vec3(value, name: str) -> np.ndarray:
    """``value`` as a finite float64 (3,) array, or ValueError naming ``name``."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.shape != (3,):
        raise ValueError(f"{name} must have shape (3,), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ValueError(f"{name} must be finite, got {arr.tolist()}")
    return arr.copy()


def _positive_int(value, name: str) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value <= 0:
        raise ValueError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole camera looking from ``eye`` at ``target``.

    Fields:
        eye: (3,) float64, m. Centre of projection.
        target: (3,) float64, m. Point on the optical axis (the image centre).
        up: (3,) float64, unitless. Approximate up direction; only its component orthogonal to the view
            direction is used, so it must not be parallel to ``target - eye``.
        fov_y_deg: float, degrees in (0, 180). Vertical field of view.
        width, height: int, pixels.
        near, far: float, m, ``0 < near < far``. Depth range that is drawn; primitives are clipped at ``near``.

    Derived (read-only):
        rotation: (3,3) float64. World-to-camera rotation; its rows are the camera's right, up and backward
            axes in world coordinates, so ``p_cam = rotation @ (p - eye)``.
        focal_px: float, pixels. ``(height/2) / tan(fov_y/2)``.
    """

    eye: np.ndarray
    target: np.ndarray
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    fov_y_deg: float = 35.0
    width: int = 256
    height: int = 256
    near: float = 1e-3
    far: float = 10.0
    rotation: np.ndarray = field(init=False, repr=False)
    focal_px: float = field(init=False, repr=False)

    def __post_init__(self) -> None:
        eye = _vec3(self.eye, "eye")
        target = _vec3(self.target, "target")
        up = _vec3(self.up, "up")
        width = _positive_int(self.width, "width")
        height = _positive_int(self.height, "height")
        fov = float(self.fov_y_deg)
        if not (0.0 < fov < 180.0):
            raise ValueError(f"fov_y_deg must be in (0, 180) degrees, got {self.fov_y_deg!r}")
        near, far = float(self.near), float(self.far)
        if not (math.isfinite(near) and near > 0.0):
            raise ValueError(f"near must be a finite distance > 0 m, got {self.near!r}")
        if not (math.isfinite(far) and far > near):
            raise ValueError(f"far must be finite and > near ({near} m), got {self.far!r}")
        forward = target - eye
        dist = float(np.linalg.norm(forward))
        if dist == 0.0:
            raise ValueError("eye and target must differ: the view direction is undefined")
        forward /= dist
        right = np.cross(forward, up)
        right_norm = float(np.linalg.norm(right))
        if right_norm <= 1e-9 * float(np.linalg.norm(up)):
            raise ValueError(f"up {up.tolist()} is parallel to the view direction {forward.tolist()}")
        right /= right_norm
        true_up = np.cross(right, forward)
        rotation = np.stack([right, true_up, -forward])
        for name, value in (
            ("eye", eye),
            ("target", target),
            ("up", up),
            ("fov_y_deg", fov),
            ("width", width),
            ("height", height),
            ("near", near),
            ("far", far),
            ("rotation", rotation),
            ("focal_px", 0.5 * height / math.tan(math.radians(0.5 * fov))),
        ):
            object.__setattr__(self, name, value)
        for arr in (self.eye, self.target, self.up, self.rotation):
            arr.setflags(write=False)

    @property
    def principal_point(self) -> tuple[float, float]:
        """``(cx, cy)`` in pixels: the image centre ``(width/2, height/2)``."""
        return 0.5 * self.width, 0.5 * self.height

    def to_camera(self, points: np.ndarray) -> np.ndarray:
        """World points (N,3) m -> camera-space points (N,3) m (``x`` right, ``y`` up, looking along ``-z``)."""
        pts = np.asarray(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3:
            raise ValueError(f"points must have shape (N, 3), got {pts.shape}")
        return (pts - self.eye) @ self.rotation.T

    def project(self, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Project world points (N,3) m to pixels.

        Returns ``(uv, depth)``: ``uv`` (N,2) float64 pixel coordinates (``u`` right, ``v`` down, pixel centres
        at half-integers) and ``depth`` (N,) float64 m along the viewing axis. Points with ``depth <= 0``
        (at or behind the eye) have ``uv = nan``.
        """
        cam = self.to_camera(points)
        depth = -cam[:, 2]
        cx, cy = self.principal_point
        uv = np.full((len(cam), 2), np.nan)
        front = depth > 0.0
        uv[front, 0] = cx + self.focal_px * cam[front, 0] / depth[front]
        uv[front, 1] = cy - self.focal_px * cam[front, 1] / depth[front]
        return uv, depth


def frame_box(
    lo,
    hi,
    *,
    width: int,
    height: int,
    direction=(0.35, -1.0, 1.1),
    up=(0.0, 0.0, 1.0),
    fov_y_deg: float = 35.0,
    margin: float = 1.08,
) -> Camera:
    """A camera that looks at the centre of the box ``[lo, hi]`` (m) from ``direction`` and sees all of it.

    Args:
        lo, hi: (3,) m, box corners with ``lo <= hi``; the box must have a non-zero size.
        width, height: image size, pixels.
        direction: (3,) from the box centre towards the eye (any length); the default looks from the front
            right and above, about 40 degrees above the horizontal for ``up = +z``.
        up: (3,) world up; must not be parallel to ``direction``.
        fov_y_deg: vertical field of view, degrees.
        margin: >= 1; the box's projection fits in the central ``1/margin`` of the image in both directions.

    The eye distance is the smallest at which every box corner projects inside that central region
    (closed form per corner). ``near`` is 1 % of that distance (or half the nearest corner's depth if that
    is smaller) and ``far`` 100 times the distance.
    """
    lo_a, hi_a = _vec3(lo, "lo"), _vec3(hi, "hi")
    if np.any(hi_a < lo_a):
        raise ValueError(f"hi {hi_a.tolist()} must be >= lo {lo_a.tolist()} in every coordinate")
    size = float(np.linalg.norm(hi_a - lo_a))
    if size == 0.0:
        raise ValueError("the box [lo, hi] has zero size; nothing to frame")
    dir_a = _vec3(direction, "direction")
    dir_norm = float(np.linalg.norm(dir_a))
    if dir_norm == 0.0:
        raise ValueError("direction must be non-zero")
    if not (math.isfinite(margin) and margin >= 1.0):
        raise ValueError(f"margin must be >= 1, got {margin!r}")
    centre = 0.5 * (lo_a + hi_a)
    # A provisional camera one box-size away fixes the rotation, which does not depend on the distance.
    probe = Camera(centre + dir_a / dir_norm * size, centre, up, fov_y_deg, width, height, 1e-6 * size, 1e6 * size)
    corners = np.array([[x, y, z] for x in (lo_a[0], hi_a[0]) for y in (lo_a[1], hi_a[1]) for z in (lo_a[2], hi_a[2])])
    rel = (corners - centre) @ probe.rotation.T  # camera axes, origin at the box centre
    half_w = 0.5 * width / margin
    half_h = 0.5 * height / margin
    # depth of a corner = dist + rel_z' with rel_z' = -rel[:, 2]; need f |x| / depth <= half_w (same for y).
    need = np.maximum(probe.focal_px * np.abs(rel[:, 0]) / half_w, probe.focal_px * np.abs(rel[:, 1]) / half_h)
    dist = float(np.max(need + rel[:, 2]))
    dist = max(dist, float(np.max(rel[:, 2])) + 1e-3 * size)  # every corner strictly in front of the eye
    eye = centre + dir_a / dir_norm * dist
    nearest = float(np.min(dist - rel[:, 2]))
    return Camera(eye, centre, up, fov_y_deg, width, height, min(0.01 * dist, 0.5 * nearest), 100.0 * dist)
