"""Live 3D view of an environment in the browser, with viser (``pip install 'suture_gym[viewer]'``).

* :class:`~suture_gym.render.live.LiveView` (:mod:`suture_gym.render.live`): a viser server showing the tissue
  surface, needle, thread, entry/exit markers, planned arcs and the haptic reaction force, with read-out panels; the
  meshes are created once and then streamed as vertex updates. ``render_mode="human"`` of every env is one of these.
* :class:`~suture_gym.viewer.teleop.Teleop` (:mod:`.teleop`): keyboard and on-screen teleoperation (a haptic
  proxy the needle holder follows), and :class:`~suture_gym.viewer.teleop.DemoRecorder`, which writes teleoperated
  episodes as a Minari dataset.
* :mod:`.app`: ``python -m suture_gym.viewer --env ID``: the viewer application (policy playback, pause, single
  step, reset with a seed, speed, teleoperation, recording).

viser is imported only when a view is made (:func:`suture_gym.render.live.require_viser`).
"""

from suture_gym.render.live import INSTALL_HINT, require_viser

__all__ = ["INSTALL_HINT", "require_viser"]
