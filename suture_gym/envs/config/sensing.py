"""The sensing sections of the env config: observation, camera, point cloud and rendering."""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import ClassVar

from suture_gym.envs.config.checks import _choice, _count, _fail, _point, _real, _Section

#: Observation modes: the flat state vector, or a Dict with images or a point cloud (:class:`ObservationConfig`).
OBSERVATION_MODES: tuple[str, ...] = ("state", "rgb", "depth", "rgbd", "point_cloud")


@dataclass(frozen=True)
class CameraConfig(_Section):
    """The camera of the pixel observations (``observation.mode`` rgb, depth, rgbd): a pinhole camera
    (:class:`~suture_gym.render.Camera`) fixed in the world for the whole episode, square pixels, rendered straight
    at ``width x height`` (no supersampling).

    Pose: it looks at ``look_at`` (default: the centre of the box spanned by the tissue at rest and the needle's
    start) from ``eye``, or, when ``eye`` is empty, from ``look_at + distance * direction / |direction|``, where
    ``distance = 0`` picks the nearest distance at which that whole box is in view
    (:func:`~suture_gym.render.frame_box`). ``up`` fixes the roll. Depth is the distance along the optical axis;
    only ``near <= depth <= far`` is drawn, and a pixel that sees nothing has depth ``far``, which must lie beyond
    the scene's box (checked when the env is built; the default fits every shipped scene, the hand's reaching
    0.48 m).
    """

    SECTION: ClassVar[str] = "observation.camera"

    width: int = 84  # px
    height: int = 84  # px
    fov_y: float = 35.0  # degrees, vertical field of view, in (0, 180)
    look_at: tuple[float, ...] = ()  # m, world point at the image centre (empty: the scene box's centre)
    eye: tuple[float, ...] = ()  # m, world position of the camera (empty: from direction and distance)
    direction: tuple[float, float, float] = (1.0, -0.35, 0.9)  # from look_at towards the eye, any length
    distance: float = 0.0  # m, eye to look_at (0: the nearest that frames the scene box); needs an empty eye
    up: tuple[float, float, float] = (0.0, 0.0, 1.0)  # world direction shown upwards in the image
    near: float = 0.001  # m, nearest depth drawn
    far: float = 1.0  # m, farthest depth drawn (beyond the scene's box), and the depth of the background

    def validate(self, path: str) -> None:
        _count(f"{path}.width", self.width, 1)
        _count(f"{path}.height", self.height, 1)
        _real(f"{path}.fov_y", self.fov_y, low=0.0, high=180.0, strict_low=True, strict_high=True)
        _point(f"{path}.look_at", self.look_at, optional=True)
        _point(f"{path}.eye", self.eye, optional=True)
        _point(f"{path}.direction", self.direction, optional=False)
        _point(f"{path}.up", self.up, optional=False)
        _real(f"{path}.distance", self.distance, low=0.0)
        _real(f"{path}.near", self.near, low=0.0, strict_low=True)
        _real(f"{path}.far", self.far, low=self.near, strict_low=True)
        if not any(self.up):
            _fail(f"{path}.up", f"must be a non-zero vector, got {list(self.up)}")
        if self.eye:
            if self.distance:
                _fail(f"{path}.distance", f"= {self.distance} m is unused when {path}.eye is given; leave it 0")
            if self.look_at and tuple(self.eye) == tuple(self.look_at):
                _fail(f"{path}.eye", f"= {list(self.eye)} m must differ from {path}.look_at")
        else:
            if not any(self.direction):
                _fail(f"{path}.direction", f"must be a non-zero vector, got {list(self.direction)}")
            cross = math.dist((0.0, 0.0, 0.0), (
                self.direction[1] * self.up[2] - self.direction[2] * self.up[1],
                self.direction[2] * self.up[0] - self.direction[0] * self.up[2],
                self.direction[0] * self.up[1] - self.direction[1] * self.up[0]))
            if cross <= 1e-9 * math.hypot(*self.direction) * math.hypot(*self.up):
                _fail(f"{path}.up", f"= {list(self.up)} is parallel to {path}.direction = {list(self.direction)}")
            if self.distance and not self.near < self.distance < self.far:
                _fail(f"{path}.distance", f"= {self.distance} m must lie between near = {self.near} m and far = "
                      f"{self.far} m, or the point looked at is not drawn")


@dataclass(frozen=True)
class PointCloudConfig(_Section):
    """Points of the ``point_cloud`` observation, per entity (:mod:`suture_gym.envs.sensors`): a fixed count on
    the tissue's surface, the needle's centreline and the thread's centreline (the last only in scenes with a
    thread, ``suture.node_count > 0``)."""

    SECTION: ClassVar[str] = "observation.point_cloud"

    tissue: int = 448  # points on the tissue's surface triangles that can move
    needle: int = 32  # points evenly spaced along the needle's centreline, tip to swage
    suture: int = 32  # points along the thread's centreline, swage to tail (scenes with a thread)

    def validate(self, path: str) -> None:
        _count(f"{path}.tissue", self.tissue, 1)
        _count(f"{path}.needle", self.needle, 0)
        _count(f"{path}.suture", self.suture, 0)


@dataclass(frozen=True)
class ObservationConfig(_Section):
    """What the observation holds, and its units (see :mod:`suture_gym.envs.spaces`).

    ``mode``: ``state`` is the flat vector (a ``Box``); ``rgb``, ``depth``, ``rgbd`` and ``point_cloud`` give a
    ``Dict`` observation with the keys ``rgb`` ``(H, W, 3) uint8``, ``depth`` ``(H, W, 1) float32`` m (``rgbd``:
    both), or ``point_cloud`` ``(N, 3) float32`` m in the world frame, plus ``state`` (the vector) unless
    ``include_state`` is false (:mod:`suture_gym.envs.sensors`).
    """

    SECTION: ClassVar[str] = "observation"

    suture_samples: int = 0  # thread nodes sampled evenly from the swage to the tail (0: none)
    privileged: bool = False  # append the randomised parameters
    scaled: bool = True  # each entry divided by its field's scale and clipped to its bound; false: raw SI values
    mode: str = "state"  # one of OBSERVATION_MODES
    include_state: bool = True  # the pixel and point-cloud modes also hold the vector, key "state"
    camera: CameraConfig = field(default_factory=CameraConfig)  # the rgb, depth and rgbd modes
    point_cloud: PointCloudConfig = field(default_factory=PointCloudConfig)  # the point_cloud mode

    def validate(self, path: str) -> None:
        _count(f"{path}.suture_samples", self.suture_samples, 0)
        for name in ("privileged", "scaled", "include_state"):
            if not isinstance(getattr(self, name), bool):
                _fail(f"{path}.{name}", f"must be true or false, got {getattr(self, name)!r}")
        _choice(f"{path}.mode", self.mode, OBSERVATION_MODES)
        if self.mode == "state" and not self.include_state:
            _fail(f"{path}.include_state", f"= false needs a pixel or point-cloud {path}.mode, got 'state'")


@dataclass(frozen=True)
class RenderConfig(_Section):
    """``render_mode="rgb_array"`` image size and supersampling; ``render_mode="human"`` live view's server and
    frame rate (:class:`suture_gym.render.live.LiveView`)."""

    SECTION: ClassVar[str] = "render"

    width: int = 320  # px (even, for video encoding)
    height: int = 240  # px (even)
    ssaa: int = 2  # supersampling factor
    viewer_host: str = "127.0.0.1"  # interface the live view serves on ("0.0.0.0": every interface)
    viewer_port: int = 8080  # TCP port (0: any free port; a taken one makes viser try the next)
    viewer_fps: float = 30.0  # most frames pushed to the browser per wall-clock second

    def validate(self, path: str) -> None:
        _count(f"{path}.width", self.width, 2)
        _count(f"{path}.height", self.height, 2)
        _count(f"{path}.ssaa", self.ssaa, 1)
        if not isinstance(self.viewer_host, str) or not self.viewer_host:
            _fail(f"{path}.viewer_host", f"must be a host name or address, got {self.viewer_host!r}")
        _count(f"{path}.viewer_port", self.viewer_port, 0)
        if self.viewer_port > 65535:
            _fail(f"{path}.viewer_port", f"must be a TCP port <= 65535, got {self.viewer_port!r}")
        _real(f"{path}.viewer_fps", self.viewer_fps, low=0.0, strict_low=True)
