"""The live 3D view: a viser server with the scene and read-out panels, updated as an env steps.

:class:`LiveView` owns a :class:`viser.ViserServer` (started on construction, in its own threads; it never waits
for a browser), a :class:`LiveScene` (the 3D scene) and a :class:`StatePanel` (the read-outs). Each
:meth:`LiveView.show` takes plain arrays in SI units: a :class:`~suture_gym.render.RenderFrame` (the same one the
offline renderer draws), the planned arcs, the grip point and the step's ``info``. The scene's nodes are created
on the first frame; later frames assign only the changed arrays (tissue vertices, strand points, the force
arrow), which viser sends as property updates of the existing nodes, so the triangles are sent once per
episode layout, not every frame. :meth:`LiveView.show` pushes at most ``fps`` frames per wall-clock second and
skips the others (the env may step faster or slower than that).

Scene frame: the simulator's world frame, metres, z up (gravity along -z). Like the rest of
:mod:`suture_gym.render` it takes plain arrays and never imports the simulator; viser (the ``viewer`` extra) is
imported only when a view is made (:func:`require_viser`). ``render_mode="human"`` of every env is one of these
views; the viewer application around it is :mod:`suture_gym.viewer`.
"""

from __future__ import annotations

import contextlib
import math
import sys
import time
from dataclasses import dataclass

import numpy as np

from suture_gym.render import RenderFrame, SceneStyle

#: What to install when viser is missing.
INSTALL_HINT = "pip install 'suture_gym[viewer]'  (or: pip install viser)"


def require_viser():
    """The ``viser`` module; ImportError naming the ``viewer`` extra when it is not installed."""
    try:
        import viser
    except ImportError as err:
        raise ImportError(f"the live viewer (render_mode='human', python -m suture_gym.viewer) needs viser, the "
                          f"'viewer' extra: {INSTALL_HINT}") from err
    return viser

#: Reaction-force arrow length per newton, m/N (5 N draws 1 cm, half the tissue pad's height).
ARROW_M_PER_N = 2.0e-3
#: Tip-force gauge span in units of the puncture threshold (as the offline renderer's gauge).
TIP_GAUGE_SPAN = 1.5
#: Thinnest drawn strand, m (the thread's 0.1 mm radius would be hard to see).
MIN_STRAND_THICKNESS = 3.0e-4
#: The scene's layers (:attr:`LiveScene.nodes` keys), each of which can be hidden.
LAYERS = ("tissue", "needle", "suture", "markers", "planned_arcs", "reaction_force", "teleop_proxy")


@dataclass(frozen=True)
class EpisodeStatus:
    """What the episode panel shows besides ``info``.

    Attributes:
        seed: the env seed of the episode's reset (None: unseeded).
        step: env steps taken since the reset.
        time: simulated time, s.
        episode_return: sum of the rewards so far.
        state: a short word: ``running``, ``paused``, or how the episode ended (``success``, ``tear``, ...).
        driver: who acts (``expert``, ``random``, ``teleop``, a model path, or ``env`` for ``render_mode="human"``).
    """

    seed: int | None
    step: int
    time: float
    episode_return: float
    state: str
    driver: str


def _rgb255(rgb) -> tuple[int, int, int]:
    return tuple(int(round(255 * c)) for c in rgb)


def _segments(points: np.ndarray) -> np.ndarray:
    """``(n - 1, 2, 3) float32`` consecutive pairs of the polyline ``points`` (n, 3)."""
    p = np.asarray(points, dtype=np.float32)
    return np.stack([p[:-1], p[1:]], axis=1)


def _finite(a: np.ndarray | None) -> bool:
    return a is not None and len(a) > 0 and bool(np.all(np.isfinite(a)))


class LiveScene:
    """The 3D scene of a viser server: tissue mesh, needle, thread, entry/exit markers, planned arcs, the
    reaction-force arrow and (optionally) the teleoperation proxy.

    Args:
        server: a :class:`viser.ViserServer`.
        style: colours (the offline renderer's :class:`~suture_gym.render.SceneStyle`, so both views agree).
        arrow_m_per_n: reaction-force arrow length per newton, m/N.
        tissue_opacity: the tissue surface's opacity in (0, 1] (below 1 the needle and the planned arc show
            through it).

    :attr:`nodes` maps each layer of :data:`LAYERS` to its viser handle once it has been drawn. Non-finite
    positions (a diverged state) leave the affected node as it was.
    """

    def __init__(self, server, style: SceneStyle | None = None, arrow_m_per_n: float = ARROW_M_PER_N,
                 tissue_opacity: float = 0.8) -> None:
        if not (math.isfinite(arrow_m_per_n) and arrow_m_per_n > 0.0):
            raise ValueError(f"arrow_m_per_n must be a finite length per force > 0 m/N, got {arrow_m_per_n!r}")
        self.server = server
        self.style = style if style is not None else SceneStyle()
        self.arrow_m_per_n = float(arrow_m_per_n)
        self.nodes: dict = {}
        self._hidden: set[str] = set()
        self._tissue_opacity = 1.0
        self.set_tissue_opacity(tissue_opacity)
        self._faces: np.ndarray | None = None
        self._framed = False
        server.scene.set_up_direction("+z")
        # No image-based lighting: viser's HDRI presets would be fetched from the network by the browser.
        server.scene.configure_environment_map(hdri=None)
        server.scene.configure_default_lights(True, cast_shadow=False)

    def set_visible(self, layer: str, visible: bool) -> None:
        """Show or hide a layer of :data:`LAYERS` (kept across updates)."""
        if layer not in LAYERS:
            raise ValueError(f"unknown layer {layer!r}; layers: {list(LAYERS)}")
        if visible:
            self._hidden.discard(layer)
        else:
            self._hidden.add(layer)
        if layer in self.nodes:
            self.nodes[layer].visible = bool(visible)

    def set_tissue_opacity(self, opacity: float) -> None:
        """The tissue surface's opacity, in (0, 1]."""
        if isinstance(opacity, bool) or not isinstance(opacity, (int, float)) or not 0.0 < opacity <= 1.0:
            raise ValueError(f"tissue opacity must be a number in (0, 1], got {opacity!r}")
        self._tissue_opacity = float(opacity)
        if "tissue" in self.nodes:
            self.nodes["tissue"].opacity = None if opacity == 1.0 else self._tissue_opacity

    def _add(self, layer: str, create) -> None:
        """Make ``layer``'s node with ``create()`` (removing the old one first), hidden if the layer is."""
        old = self.nodes.pop(layer, None)
        if old is not None:
            old.remove()
        handle = create()
        handle.visible = layer not in self._hidden
        self.nodes[layer] = handle

    def frame_camera(self, points: np.ndarray) -> None:
        """Point the initial camera (and the client's "reset view") at the box of ``points`` (N, 3) m, from the
        offline renderer's default direction."""
        pts = np.asarray(points, dtype=np.float64)
        pts = pts[np.all(np.isfinite(pts), axis=1)]
        if len(pts) == 0:
            raise ValueError("points has no finite row to frame")
        lo, hi = pts.min(axis=0), pts.max(axis=0)
        center = 0.5 * (lo + hi)
        size = float(np.linalg.norm(hi - lo))
        direction = np.array([1.0, -0.35, 0.9])
        cam = self.server.initial_camera
        cam.near = 0.01 * size
        cam.far = 100.0 * size
        cam.look_at = center
        cam.position = center + direction / np.linalg.norm(direction) * 1.2 * size
        cam.up = (0.0, 0.0, 1.0)
        self._framed = True

    def update(self, frame: RenderFrame, arcs: list[np.ndarray], grip: np.ndarray, force: np.ndarray) -> None:
        """Show ``frame``, the planned ``arcs`` (list of (n, 3) polylines, m) and the reaction ``force`` (3,) N
        on the needle as an arrow from the grip point ``grip`` (3,) m."""
        st = self.style
        scene = self.server.scene
        q = np.asarray(frame.tissue_q, dtype=np.float32)
        faces = np.asarray(frame.tissue_triangles)
        if not self._framed:
            self.frame_camera(q)
        nodes = self.nodes
        if "tissue" not in nodes or self._faces is None or not np.array_equal(self._faces, faces):
            self._faces = faces.copy()
            self._add("tissue", lambda: scene.add_mesh_simple(
                "/tissue", np.nan_to_num(q), faces.astype(np.uint32), color=_rgb255(st.tissue_color),
                side="double", opacity=None if self._tissue_opacity == 1.0 else self._tissue_opacity,
                cast_shadow=False, receive_shadow=False))
        elif _finite(q):
            nodes["tissue"].vertices = q
        self._strand("needle", frame.needle_q, 2.0 * frame.needle_radius, st.needle_color)
        self._strand("suture", frame.suture_q, 2.0 * frame.suture_radius, st.suture_color)
        if frame.marker_q is not None and _finite(np.asarray(frame.marker_q)):
            markers = np.asarray(frame.marker_q, dtype=np.float32)
            colors = np.empty((len(markers), 3), dtype=np.uint8)
            colors[0::2] = _rgb255(st.entry_color)
            colors[1::2] = _rgb255(st.exit_color)
            if "markers" not in nodes or len(nodes["markers"].points) != len(markers):
                radius = float(np.max(frame.marker_radius))
                self._add("markers", lambda: scene.add_point_cloud("/markers", markers, colors,
                                                                   point_size=2.0 * radius, point_shape="circle",
                                                                   precision="float32"))
            else:
                nodes["markers"].points = markers
        arc_segments = [_segments(a) for a in arcs if _finite(np.asarray(a))]
        if arc_segments:
            points = np.concatenate(arc_segments)
            if "planned_arcs" not in nodes or len(nodes["planned_arcs"].points) != len(points):
                self._add("planned_arcs", lambda: scene.add_line_segments(
                    "/planned_arcs", points, (250, 200, 40), thickness=2.0, thickness_units="screen"))
            else:
                nodes["planned_arcs"].points = points
        grip = np.asarray(grip, dtype=np.float64)
        force = np.asarray(force, dtype=np.float64)
        if _finite(grip[None]) and _finite(force[None]):
            arrow = np.array([[grip, grip + self.arrow_m_per_n * force]], dtype=np.float32)
            if "reaction_force" not in nodes:
                self._add("reaction_force", lambda: scene.add_arrows(
                    "/reaction_force", arrow, (230, 60, 30), shaft_radius=2.0e-4, head_radius=5.0e-4,
                    head_length=1.0e-3))
            else:
                nodes["reaction_force"].points = arrow

    def update_proxy(self, position: np.ndarray | None, quat: np.ndarray | None = None) -> None:
        """Show the teleoperation proxy (the pose the holder is pulled toward) as axes at ``position`` (3,) m with
        orientation ``quat`` (4,) (w, x, y, z); None hides it."""
        proxy = self.nodes.get("teleop_proxy")
        if position is None:
            if proxy is not None:
                proxy.visible = False
            return
        position = tuple(float(c) for c in position)
        wxyz = (1.0, 0.0, 0.0, 0.0) if quat is None else tuple(float(c) for c in quat)
        if proxy is None:
            self._add("teleop_proxy", lambda: self.server.scene.add_frame(
                "/teleop_proxy", axes_length=3.0e-3, axes_radius=1.5e-4, position=position, wxyz=wxyz))
        else:
            proxy.position = position
            proxy.wxyz = wxyz
            proxy.visible = "teleop_proxy" not in self._hidden

    def _strand(self, layer: str, q: np.ndarray | None, thickness: float, rgb) -> None:
        """Create or update the polyline of ``layer`` (a needle or thread centreline ``q`` (n, 3) m)."""
        if q is None or len(q) < 2 or not _finite(np.asarray(q)):
            return
        segments = _segments(q)
        handle = self.nodes.get(layer)
        if handle is not None and len(handle.points) == len(segments):
            handle.points = segments
            return
        self._add(layer, lambda: self.server.scene.add_line_segments(
            f"/{layer}", segments, _rgb255(rgb), thickness=max(thickness, MIN_STRAND_THICKNESS)))


def _vector(values, digits: int) -> str:
    return "[" + ", ".join(f"{v:+.{digits}f}" for v in values) + "]"


class StatePanel:
    """Read-outs in viser's GUI panel: episode state, the haptic reaction wrench (N, N m) with a gauge, the tip
    force with a gauge against the puncture threshold, the wound gap and every reward term (this step and the
    episode's sum).

    Args:
        gui: a viser ``GuiApi`` (``server.gui``).
        force_span: the reaction gauge's full scale, N (the env's ``action.max_force``).
    """

    def __init__(self, gui, force_span: float) -> None:
        if not (math.isfinite(force_span) and force_span > 0.0):
            raise ValueError(f"force_span must be a finite force > 0 N, got {force_span!r}")
        self.force_span = float(force_span)
        with gui.add_folder("Episode"):
            self._episode = gui.add_markdown("")
        with gui.add_folder("Haptic reaction (on the needle)"):
            self._wrench = gui.add_markdown("")
            self._wrench_gauge = gui.add_progress_bar(0.0, color="green")
        with gui.add_folder("Tip force"):
            self._tip = gui.add_markdown("")
            self._tip_gauge = gui.add_progress_bar(0.0, color="green")
        with gui.add_folder("Reward terms"):
            self._terms = gui.add_markdown("")
        #: Episode sums of the reward terms (name -> sum), over every step :meth:`count` was given.
        self.sums: dict[str, float] = {}
        self._counted_step = 0
        self.text: dict[str, str] = {}

    def count(self, info: dict, step: int) -> None:
        """Add step ``step``'s reward terms to the episode's sums (``step`` 0, a reset, clears them; a step
        already counted is not counted again). Called for every step, shown or not."""
        if step == 0:
            self.sums, self._counted_step = {}, 0
            return
        if step == self._counted_step:
            return
        self._counted_step = step
        for key, value in info.items():
            if key.startswith("reward_"):
                name = key[len("reward_"):]
                self.sums[name] = self.sums.get(name, 0.0) + float(value)

    @staticmethod
    def _gauge(handle, fraction: float) -> None:
        fraction = min(max(fraction, 0.0), 1.0) if math.isfinite(fraction) else 0.0
        handle.value = 100.0 * fraction
        handle.color = "green" if fraction < 0.5 else "yellow" if fraction < 0.8 else "red"

    def update(self, info: dict, status: EpisodeStatus, force_threshold: float) -> None:
        """Show ``info`` (an env step's or reset's) and ``status``; ``force_threshold`` is the puncture threshold,
        N. The texts shown are kept in :attr:`text` (``episode``, ``wrench``, ``tip``, ``terms``)."""
        wrench = np.asarray(info.get("haptic_wrench", np.zeros(6)), dtype=np.float64)
        force = float(np.linalg.norm(wrench[:3]))
        tip = float(info.get("tip_force", 0.0))
        flags = [name for name in ("punctured", "tear", "out_of_workspace", "missed", "diverged") if info.get(name)]
        text = {
            "episode": (f"**{status.state}** · driver `{status.driver}` · seed {status.seed}  \n"
                        f"step {status.step} · t = {status.time:.3f} s · return {status.episode_return:+.3f}  \n"
                        f"stitch {info.get('stitch', 0)} · wound gap {1e3 * float(info.get('wound_gap', 0.0)):.2f} mm"
                        f" · {' '.join(flags) or 'not punctured'}"),
            "wrench": (f"F = {_vector(wrench[:3], 3)} N, |F| = **{force:.3f} N**  \n"
                       f"τ = {_vector(1e3 * wrench[3:], 2)} mN m (gauge: |F| / {self.force_span:g} N)"),
            "tip": f"**{tip:.3f} N** (puncture threshold {force_threshold:.2f} N)",
        }
        rows = [f"| {key[len('reward_'):]} | {float(value):+.4f} | {self.sums.get(key[len('reward_'):], 0.0):+.3f} |"
                for key, value in info.items() if key.startswith("reward_")]
        text["terms"] = "| term | step | episode |\n| --- | ---: | ---: |\n" + "\n".join(rows)
        self._episode.content = text["episode"]
        self._wrench.content = text["wrench"]
        self._tip.content = text["tip"]
        self._terms.content = text["terms"]
        self._gauge(self._wrench_gauge, force / self.force_span)
        self._gauge(self._tip_gauge, tip / (TIP_GAUGE_SPAN * force_threshold))
        self.text = text


class LiveView:
    """A viser server showing one env: :class:`LiveScene` and :class:`StatePanel`.

    Args:
        host: interface to serve on (``127.0.0.1``: this machine only).
        port: TCP port (0: any free port; a taken port makes viser try the next ones). :attr:`port` is the one
            bound.
        fps: most frames pushed per wall-clock second (:meth:`show` skips the others).
        force_span: the reaction gauge's full scale, N.
        label: the page's title.

    :attr:`pushes` and :attr:`push_seconds` count the frames pushed and the wall-clock time spent pushing them.
    """

    def __init__(self, host: str = "127.0.0.1", port: int = 8080, fps: float = 30.0, force_span: float = 5.0,
                 label: str = "suture_gym") -> None:
        if isinstance(port, bool) or not isinstance(port, int) or not 0 <= port <= 65535:
            raise ValueError(f"port must be an integer in [0, 65535], got {port!r}")
        if not (isinstance(fps, (int, float)) and math.isfinite(fps) and fps > 0.0):
            raise ValueError(f"fps must be a finite rate > 0 frames/s, got {fps!r}")
        viser = require_viser()
        # viser prints its address box on stdout whatever ``verbose`` says: keep stdout for the caller's output
        # (``--json`` scripts).
        with contextlib.redirect_stdout(sys.stderr):
            self.server = viser.ViserServer(host=host, port=port, label=label, verbose=False)
        self.host = host
        self.min_interval = 1.0 / float(fps)
        self.scene = LiveScene(self.server)
        self.panel = StatePanel(self.server.gui, force_span)
        self.pushes = 0
        self.push_seconds = 0.0
        self._last_push = -math.inf

    @property
    def port(self) -> int:
        """The TCP port the server is bound to."""
        return self.server.get_port()

    @property
    def url(self) -> str:
        """The page's address."""
        return f"http://{self.host}:{self.port}"

    def show(self, frame: RenderFrame, arcs: list[np.ndarray], grip: np.ndarray, info: dict, status: EpisodeStatus,
             force: bool = False) -> bool:
        """Push one frame unless the last push was less than ``1 / fps`` s ago (``force``: push anyway). Call it
        after every reset and step: the panel's episode sums of the reward terms count every step.

        Args:
            frame: the scene (:meth:`suture_gym.envs.base.SutureEnv.view_frame`).
            arcs: the planned arcs, (n, 3) polylines in m.
            grip: ``(3,)`` grip point, m (where the reaction arrow starts).
            info: the step's ``info`` (``haptic_wrench`` gives the arrow and the gauge).
            status: the episode panel's state.

        Returns:
            Whether the frame was pushed.
        """
        self.panel.count(info, status.step)
        now = time.perf_counter()
        if not force and now - self._last_push < self.min_interval:
            return False
        wrench = np.asarray(info.get("haptic_wrench", np.zeros(6)), dtype=np.float64)
        with self.server.atomic():
            self.scene.update(frame, arcs, grip, wrench[:3])
            self.panel.update(info, status, frame.force_threshold)
        self._last_push = time.perf_counter()
        self.pushes += 1
        self.push_seconds += self._last_push - now
        return True

    def close(self) -> None:
        """Stop the server (viser's goodbye goes to stderr too)."""
        with contextlib.redirect_stdout(sys.stderr):
            self.server.stop()
