"""Pixel and point-cloud observations (``observation.mode`` other than ``state``): what a camera fixed in the
world sees of the scene, or points on its surfaces, for visual RL.

Keys of the ``Dict`` observation (spaces in :func:`~suture_gym.envs.spaces.sensor_spaces`; the config in
:class:`~suture_gym.envs.config.CameraConfig` and :class:`~suture_gym.envs.config.PointCloudConfig`):

* ``rgb`` (modes ``rgb``, ``rgbd``): ``(H, W, 3) uint8``, the tissue surface, needle and thread shaded as in
  ``render()``, with the planned stitches' entry (green) and exit (red) markers and no caption or force gauge,
  drawn straight at ``observation.camera.width x height`` (default 84 x 84) by the offline renderer
  (:meth:`~suture_gym.render.SceneRenderer.render_sensor`).
* ``depth`` (modes ``depth``, ``rgbd``): ``(H, W, 1) float32``, m, the distance along the camera's optical axis
  to the nearest tissue, needle or thread surface at each pixel centre (what a depth camera reports, not the
  length of the ray); ``observation.camera.far`` (default 1 m) where the pixel sees none of them, the
  background. The markers are not part of it.
* ``point_cloud`` (mode ``point_cloud``): ``(N, 3) float32``, m, in the world frame (the scene's: the tissue on
  its base at ``z = 0``, gravity along ``-z``), ``N = point_cloud.tissue + point_cloud.needle (+
  point_cloud.suture`` in a scene with a thread), in that order of rows, so a row's entity is known from its
  index:

  - tissue rows: material points on the tissue's surface triangles (those with a vertex that is not pinned;
    the pinned ones never move), sampled once, area-weighted on the surface at rest with a fixed generator, so
    every row follows the same material point through the episode and every episode of the config;
  - needle rows: on the needle's centreline, evenly spaced by arc length from the tip to the swage;
  - suture rows: on the thread's centreline, evenly spaced in node index from the swage to the free end.

  Coordinates are clipped to ``+-POINT_CLOUD_BOUND`` (far beyond any scene; only a diverging simulation gets
  there).
* ``state``: the usual observation vector (:mod:`suture_gym.envs.spaces`), unless ``observation.include_state``
  is false.

The camera is placed once, when the env is built (from the tissue at rest and the needle's start), and stays put.
"""

from __future__ import annotations

import numpy as np

from suture_gym.envs.config import CameraConfig, EnvConfig, PointCloudConfig
from suture_gym.envs.spaces import POINT_CLOUD_BOUND, sensor_spaces
from suture_gym.render.camera import Camera, frame_box
from suture_gym.render.scene import SceneRenderer
from suture_gym.sim.quat import quat_to_matrix

#: The scene's box fills the central ``1 / FRAME_MARGIN`` of the image when ``camera.distance`` is 0.
FRAME_MARGIN = 1.02
#: Seed of the generator that places the tissue's points (fixed: the same points in every env of a config).
TISSUE_SAMPLE_SEED = 0


def observation_camera(config: CameraConfig, view_points: np.ndarray) -> Camera:
    """The camera of ``config`` for a scene whose box is spanned by ``view_points`` (N, 3) m (the tissue at rest
    and the needle's start: :meth:`~suture_gym.envs.simulation.Simulation.view_points`).

    Raises:
        ValueError naming ``observation.camera``: a pose that gives no camera (``eye`` on the point looked at,
        ``up`` along the view direction) or that puts the point looked at or a corner of the scene's box beyond
        ``far``.
    """
    lo, hi = view_points.min(axis=0), view_points.max(axis=0)
    look_at = np.array(config.look_at, dtype=np.float64) if config.look_at else 0.5 * (lo + hi)
    direction = np.array(config.direction, dtype=np.float64)
    direction /= np.linalg.norm(direction)
    if config.eye:
        eye = np.array(config.eye, dtype=np.float64)
    elif config.distance:
        eye = look_at + config.distance * direction
    else:
        framed = frame_box(lo, hi, width=config.width, height=config.height, direction=direction, up=config.up,
                           fov_y_deg=config.fov_y, margin=FRAME_MARGIN)
        eye = look_at + float(np.linalg.norm(framed.eye - framed.target)) * direction
    try:
        camera = Camera(eye, look_at, config.up, config.fov_y, config.width, config.height, config.near, config.far)
    except ValueError as error:
        raise ValueError(f"observation.camera: {error}") from None
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1]) for z in (lo[2], hi[2])])
    deepest = float(np.max(-camera.to_camera(np.vstack([corners, look_at]))[:, 2]))
    if deepest >= config.far:
        raise ValueError(f"observation.camera.far = {config.far} m must exceed {deepest:.4g} m, the depth of the point "
                         "looked at and of the farthest corner of the scene's box (the tissue at rest and the needle's "
                         "start), or the image cuts them off")
    return camera


class PointCloudSampler:
    """The fixed points of the ``point_cloud`` observation (module docstring) of one scene.

    Args:
        config: the point counts.
        tissue_triangles: ``(F, 3)`` the tissue's surface triangles (particle indices).
        tissue_rest_q: ``(P, 3)`` particle positions at rest, m (where the points are placed, by area).
        tissue_pinned: ``(P,)`` bool, particles held fixed.
        needle_nodes: ``(K, 3)`` the needle's centreline in its body frame, m, tip first.
        suture_nodes: nodes of the thread (0: no thread).
    """

    def __init__(self, config: PointCloudConfig, tissue_triangles: np.ndarray, tissue_rest_q: np.ndarray,
                 tissue_pinned: np.ndarray, needle_nodes: np.ndarray, suture_nodes: int) -> None:
        tris = np.asarray(tissue_triangles, dtype=np.int64)
        tris = tris[~np.all(tissue_pinned[tris], axis=1)]
        corners = tissue_rest_q[tris]
        area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1)
        if len(tris) == 0 or not area.sum() > 0.0:
            raise ValueError("the tissue has no surface triangle that can move to place points on")
        rng = np.random.default_rng(TISSUE_SAMPLE_SEED)
        pick = rng.choice(len(tris), size=config.tissue, p=area / area.sum())
        r1, r2 = np.sqrt(rng.random(config.tissue)), rng.random(config.tissue)
        #: (n, 3) particle indices and (n, 3) barycentric weights of the tissue points (uniform on a triangle).
        self.tissue_vertices = tris[pick]
        self.tissue_weights = np.stack([1.0 - r1, r1 * (1.0 - r2), r1 * r2], axis=1)
        seg = np.linalg.norm(np.diff(needle_nodes, axis=0), axis=1)
        arc = np.concatenate([[0.0], np.cumsum(seg)])
        at = np.linspace(0.0, arc[-1], config.needle)
        #: (m, 3) needle points in its body frame, m.
        self.needle_body = np.stack([np.interp(at, arc, needle_nodes[:, k]) for k in range(3)], axis=1)
        suture = config.suture if suture_nodes else 0
        t = np.linspace(0.0, suture_nodes - 1, suture)
        #: (s,) lower node index and (s,) weight of the next node of each thread point.
        self.suture_index = np.minimum(np.floor(t).astype(np.int64), max(suture_nodes - 2, 0))
        self.suture_weight = t - self.suture_index
        self.size = config.tissue + config.needle + suture

    def points(self, tissue_q: np.ndarray, needle_pos: np.ndarray, needle_quat: np.ndarray,
               suture_q: np.ndarray | None) -> np.ndarray:
        """A new ``(N, 3) float32`` point cloud, m, world frame, for the tissue particles ``tissue_q`` (P, 3) m, the
        needle's body pose (``needle_pos`` (3,) m, ``needle_quat`` (4,) w, x, y, z) and the thread's nodes
        ``suture_q`` (S, 3) m (None without a thread)."""
        out = np.empty((self.size, 3), dtype=np.float32)
        n_t, n_n = len(self.tissue_weights), len(self.needle_body)
        out[:n_t] = np.einsum("nk,nkj->nj", self.tissue_weights, tissue_q[self.tissue_vertices])
        out[n_t:n_t + n_n] = needle_pos + self.needle_body @ quat_to_matrix(needle_quat).T
        if n_t + n_n < self.size:
            i, w = self.suture_index, self.suture_weight[:, None]
            out[n_t + n_n:] = (1.0 - w) * suture_q[i] + w * suture_q[i + 1]
        return np.clip(out, -POINT_CLOUD_BOUND, POINT_CLOUD_BOUND, out=out)


class Sensors:
    """The camera images or point cloud of one env (:class:`~suture_gym.envs.base.SutureEnv` holds one when
    ``observation.mode`` is not ``state``).

    Args:
        config: the env's config.
        sim: its simulation (the camera frames :meth:`~suture_gym.envs.simulation.Simulation.view_points`).
    """

    def __init__(self, config: EnvConfig, sim) -> None:
        mode = config.observation.mode
        #: The observation keys it fills (:func:`~suture_gym.envs.spaces.sensor_spaces`).
        self.keys: tuple[str, ...] = tuple(sensor_spaces(config))
        self._config = config
        self._renderer = None
        if mode != "point_cloud":
            cam = config.observation.camera
            # The tissue's triangles bound its volume, counter-clockwise seen from outside (TissueModel.tri_indices),
            # so the faces turned away are always hidden: culling them leaves the images as they are, 20 % sooner.
            self._renderer = SceneRenderer(cam.width, cam.height, ssaa=1, cull_back_faces=True)
            self._renderer.set_camera(observation_camera(cam, sim.view_points()))
        self._sampler = None
        self._sampler_model = None
        if mode == "point_cloud":
            self._sampler = self._make_sampler(sim.model)

    @property
    def camera(self) -> Camera | None:
        """The camera of the image modes (None in ``point_cloud`` mode)."""
        return None if self._renderer is None else self._renderer.camera

    def observe(self, sim, markers: np.ndarray) -> dict[str, np.ndarray]:
        """New arrays of the current state of ``sim``, one per key of :attr:`keys`, with the planned entry and exit
        ``markers`` (P, 3) m drawn in ``rgb``."""
        if self._renderer is not None:
            rgb, depth = self._renderer.render_sensor(sim.render_frame(markers, ""), "rgb" in self.keys,
                                                      "depth" in self.keys)
            return {key: value for key, value in (("rgb", rgb), ("depth", depth)) if value is not None}
        model, state = sim.model, sim.state
        if model is not self._sampler_model:
            # A scene rebuilt for an episode's parameters has the same surface: the points stay the same material
            # points. Only another surface (never from randomisation) places them anew.
            if not np.array_equal(model.tissue.tri_indices, self._sampler_model.tissue.tri_indices):
                self._sampler = self._make_sampler(model)
            self._sampler_model = model
        suture = None if state.suture is None else state.suture.node_pos
        return {"point_cloud": self._sampler.points(state.tissue.particle_q, state.needle.body_pos,
                                                    state.needle.body_quat, suture)}

    def _make_sampler(self, model) -> PointCloudSampler:
        tissue = model.tissue
        self._sampler_model = model
        return PointCloudSampler(self._config.observation.point_cloud, tissue.tri_indices, tissue.particle_rest_q,
                                 tissue.particle_inv_mass == 0.0, model.needle.node_pos_body,
                                 self._config.suture.node_count)
