"""Live 3D view of an environment in the browser, with viser (``pip install 'suture_gym[viewer]'``).

* :class:`~suture_gym.viewer.scene.LiveView` (:mod:`.scene`): a viser server showing the tissue surface, needle,
  thread, entry/exit markers, planned arcs and the haptic reaction force, with read-out panels; the meshes are
  created once and then streamed as vertex updates. ``render_mode="human"`` of every env is one of these.
* :class:`~suture_gym.viewer.teleop.Teleop` (:mod:`.teleop`): keyboard and on-screen teleoperation (a haptic
  proxy the needle holder follows), and :class:`~suture_gym.viewer.teleop.DemoRecorder`, which writes teleoperated
  episodes as a Minari dataset.
* :mod:`.app`: ``python -m suture_gym.viewer --env ID``: the viewer application (policy playback, pause, single
  step, reset with a seed, speed, teleoperation, recording).

Like :mod:`suture_gym.render`, :mod:`.scene` takes plain arrays (a :class:`~suture_gym.render.RenderFrame`) and
never imports the simulator. viser is imported only when a view is made (:func:`require_viser`).
"""

from __future__ import annotations

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
