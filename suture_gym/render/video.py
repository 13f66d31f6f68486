"""Write rendered frames to disk: MP4 videos through imageio-ffmpeg and PNG images through imageio.

Both libraries belong to the optional ``render`` extra (``pip install 'suture_gym[render]'``) and are
imported only when a function here is called. imageio-ffmpeg ships its own ffmpeg binary, so no system
library is needed.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np

_EXTRA_HINT = "install the optional 'render' extra: pip install 'suture_gym[render]'"


def _check_image(image, name: str, channels: tuple[int, ...] = (3,)) -> np.ndarray:
    if not isinstance(image, np.ndarray) or image.dtype != np.uint8:
        kind = image.dtype if isinstance(image, np.ndarray) else type(image).__name__
        raise ValueError(f"{name} must be a uint8 numpy array, got {kind}")
    if image.ndim != 3 or image.shape[2] not in channels or image.shape[0] == 0 or image.shape[1] == 0:
        raise ValueError(f"{name} must have shape (H, W, {' or '.join(map(str, channels))}), got {image.shape}")
    return image


def write_video(frames: Iterable[np.ndarray], path: str | os.PathLike, fps: float = 30.0, quality: float = 7.0) -> int:
    """Encode ``frames`` ((H,W,3) uint8 RGB, all the same size) into a video file at ``path``.

    Args:
        frames: any iterable (consumed once, frame by frame, so a generator need not fit in memory).
        path: output file; the container follows the extension (``.mp4`` -> H.264, yuv420p).
        fps: frames per second, finite and > 0.
        quality: imageio-ffmpeg's quality in [0, 10] (10 is best).

    Returns the number of frames written. Raises ValueError for a bad ``fps`` or ``quality``, an empty
    ``frames``, a frame that is not (H,W,3) uint8, a size differing from the first frame's, or an odd width or
    height (yuv420p needs even sizes; frames are never silently resized); a partly written file is removed.
    Raises ImportError with an install hint when imageio-ffmpeg is missing.
    """
    if isinstance(fps, bool) or not isinstance(fps, (int, float)) or not math.isfinite(fps) or fps <= 0:
        raise ValueError(f"fps must be a finite number > 0, got {fps!r}")
    if isinstance(quality, bool) or not isinstance(quality, (int, float)) or not (0.0 <= quality <= 10.0):
        raise ValueError(f"quality must be a number in [0, 10], got {quality!r}")
    try:
        import imageio_ffmpeg
    except ImportError as err:
        raise ImportError(f"write_video needs imageio-ffmpeg; {_EXTRA_HINT}") from err
    path = Path(path)
    writer = None
    shape = None
    count = 0
    try:
        for i, frame in enumerate(frames):
            image = _check_image(frame, f"frames[{i}]")
            if shape is None:
                shape = image.shape
                height, width = shape[0], shape[1]
                if width % 2 or height % 2:
                    raise ValueError(f"frames must have an even width and height for H.264/yuv420p, got {shape}")
                writer = imageio_ffmpeg.write_frames(
                    str(path),
                    (width, height),
                    fps=float(fps),
                    quality=float(quality),
                    macro_block_size=2,
                    ffmpeg_log_level="error",
                )
                writer.send(None)
            elif image.shape != shape:
                raise ValueError(f"frames[{i}] has shape {image.shape}, but the first frame has {shape}")
            writer.send(np.ascontiguousarray(image))
            count += 1
    except BaseException:
        if writer is not None:
            writer.close()
            path.unlink(missing_ok=True)
        raise
    if writer is None:
        raise ValueError("frames is empty: there is nothing to write")
    writer.close()
    return count


def save_png(image: np.ndarray, path: str | os.PathLike) -> None:
    """Write an (H,W,3) RGB or (H,W,4) RGBA uint8 ``image`` to ``path`` as PNG (whatever the extension)."""
    _check_image(image, "image", channels=(3, 4))
    try:
        import imageio.v3 as iio
    except ImportError as err:
        raise ImportError(f"save_png needs imageio; {_EXTRA_HINT}") from err
    iio.imwrite(Path(path), image, extension=".png")
