"""Software rendering for the environments: a numba z-buffer rasteriser, no GPU, display or system GL needed.

* :class:`Camera`, :func:`frame_box` (:mod:`.camera`): look-at perspective camera, world -> pixel projection.
* :class:`SceneRenderer`, :class:`RenderFrame`, :class:`SceneStyle`, :class:`Material` (:mod:`.scene`):
  tissue surface, needle, suture, markers, force gauge and caption -> ``(H, W, 3) uint8``.
* :func:`write_video`, :func:`save_png` (:mod:`.video`): need the optional ``render`` extra (imageio,
  imageio-ffmpeg), imported only when called.

The renderer takes plain arrays and never imports the simulator.
"""

from suture_gym.render.camera import Camera, frame_box
from suture_gym.render.scene import Material, RenderFrame, SceneRenderer, SceneStyle
from suture_gym.render.video import save_png, write_video

__all__ = ["Camera", "Material", "RenderFrame", "SceneRenderer", "SceneStyle", "frame_box", "save_png", "write_video"]
