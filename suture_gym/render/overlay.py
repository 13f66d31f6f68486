"""2-D overlays drawn on the finished ``(H, W, 3) uint8`` image, in output pixels, and the built-in font.

Everything here is pure graphics on arrays; nothing imports the simulator. These run after
:func:`suture_gym.render.raster.shade_resolve` (see :mod:`suture_gym.render.raster` for the 3-D pipeline):

* :func:`blend_rect`: alpha-blend a solid rectangle (caption backgrounds).
* :func:`draw_gauge_bar`: a horizontal bar with a colour ramp and a threshold tick (the force gauge).
* :func:`draw_text`: stamp glyphs of the built-in 5x7 bitmap font (:data:`FONT_GLYPHS`, :data:`FONT_CHARS`);
  :func:`text_glyph_indices`, :func:`text_size` and :func:`text_bitmap` are the plain-Python helpers around it.

Coordinates are integer output pixels, ``x`` to the right and ``y`` down from the top-left corner; everything
is clipped to the image bounds. Colours are ``(3,) uint8`` RGB.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

# ----------------------------------------------------------------------------------------------------------
# Drawing primitives (output pixels)
# ----------------------------------------------------------------------------------------------------------


@njit(cache=True)
def blend_rect(x0, y0, x1, y1, color, alpha, image):
    """Blend the pixel rectangle ``[x0, x1) x [y0, y1)`` towards ``color`` (3,) uint8 with weight ``alpha``
    in [0, 1] (1 = opaque). Parts outside ``image`` (H,W,3) uint8 are ignored."""
    h, w = image.shape[0], image.shape[1]
    for y in range(max(y0, 0), min(y1, h)):
        for x in range(max(x0, 0), min(x1, w)):
            for c in range(3):
                v = (1.0 - alpha) * image[y, x, c] + alpha * color[c]
                image[y, x, c] = np.uint8(min(max(int(v + 0.5), 0), 255))


@njit(cache=True)
def _ramp_color(ramp_at, ramp_color, x, out):
    """Piecewise-linear colour ramp: ``ramp_at`` (R,) increasing keys, ``ramp_color`` (R,3) uint8."""
    if x <= ramp_at[0]:
        out[:] = ramp_color[0]
        return
    for r in range(1, ramp_at.shape[0]):
        if x <= ramp_at[r]:
            t = (x - ramp_at[r - 1]) / (ramp_at[r] - ramp_at[r - 1])
            for c in range(3):
                lo = float(ramp_color[r - 1, c])
                out[c] = np.uint8(int(lo + t * (float(ramp_color[r, c]) - lo) + 0.5))
            return
    out[:] = ramp_color[ramp_at.shape[0] - 1]


@njit(cache=True)
def draw_gauge_bar(
    x0, y0, width, height, fill, tick, ramp_at, ramp_color, empty_color, tick_color, tick_px, overhang_px, image
):
    """A horizontal gauge bar with a colour ramp and a threshold tick.

    Args:
        x0, y0, width, height: the bar rectangle in output pixels (top-left corner and size).
        fill: filled fraction in [0, 1]; non-finite draws an empty bar.
        tick: fraction in [0, 1] where the threshold tick sits.
        ramp_at: (R,) increasing keys in units of the threshold (bar position / tick position), and
            ramp_color (R,3) uint8 their colours: each filled column is coloured by its own position.
        empty_color, tick_color: (3,) uint8.
        tick_px: tick width, pixels; overhang_px: how far it sticks out above and below the bar.
        image: (H,W,3) uint8, drawn in place (clipped to its bounds).
    """
    h, w = image.shape[0], image.shape[1]
    col = np.empty(3, dtype=np.uint8)
    n_fill = int(round(fill * width)) if math.isfinite(fill) else 0
    for i in range(width):
        x = x0 + i
        if x < 0 or x >= w:
            continue
        if i < n_fill:
            _ramp_color(ramp_at, ramp_color, ((i + 0.5) / width) / tick, col)
        else:
            col[:] = empty_color
        for y in range(max(y0, 0), min(y0 + height, h)):
            image[y, x, :] = col
    xt = x0 + int(round(tick * width)) - tick_px // 2
    for y in range(max(y0 - overhang_px, 0), min(y0 + height + overhang_px, h)):
        for x in range(max(xt, 0), min(xt + tick_px, w)):
            image[y, x, :] = tick_color


@njit(cache=True)
def draw_text(glyph_index, glyphs, x0, y0, scale, color, image):
    """Stamp glyphs left to right from the top-left corner ``(x0, y0)`` (output pixels).

    glyph_index (n,) int indices into glyphs (G,7,5) bool; each glyph cell is ``scale x scale`` pixels and
    glyphs advance by 6 cells. color (3,) uint8; image (H,W,3) uint8, clipped to its bounds.
    """
    h, w = image.shape[0], image.shape[1]
    gh, gw = glyphs.shape[1], glyphs.shape[2]
    for n in range(glyph_index.shape[0]):
        g = glyph_index[n]
        gx = x0 + n * (gw + 1) * scale
        for r in range(gh):
            for c in range(gw):
                if not glyphs[g, r, c]:
                    continue
                for yy in range(y0 + r * scale, y0 + (r + 1) * scale):
                    if yy < 0 or yy >= h:
                        continue
                    for xx in range(gx + c * scale, gx + (c + 1) * scale):
                        if 0 <= xx < w:
                            image[yy, xx, :] = color


# ----------------------------------------------------------------------------------------------------------
# Built-in 5x7 bitmap font (drawn for this project): digits, A-Z and a little punctuation.
# ----------------------------------------------------------------------------------------------------------

_FONT_ROWS: dict[str, tuple[str, ...]] = {
    " ": (".....", ".....", ".....", ".....", ".....", ".....", "....."),
    "0": (".###.", "#...#", "#..##", "#.#.#", "##..#", "#...#", ".###."),
    "1": ("..#..", ".##..", "..#..", "..#..", "..#..", "..#..", ".###."),
    "2": (".###.", "#...#", "....#", "...#.", "..#..", ".#...", "#####"),
    "3": ("#####", "...#.", "..#..", "...#.", "....#", "#...#", ".###."),
    "4": ("...#.", "..##.", ".#.#.", "#..#.", "#####", "...#.", "...#."),
    "5": ("#####", "#....", "####.", "....#", "....#", "#...#", ".###."),
    "6": ("..##.", ".#...", "#....", "####.", "#...#", "#...#", ".###."),
    "7": ("#####", "....#", "...#.", "..#..", ".#...", ".#...", ".#..."),
    "8": (".###.", "#...#", "#...#", ".###.", "#...#", "#...#", ".###."),
    "9": (".###.", "#...#", "#...#", ".####", "....#", "...#.", ".##.."),
    "A": (".###.", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"),
    "B": ("####.", "#...#", "#...#", "####.", "#...#", "#...#", "####."),
    "C": (".###.", "#...#", "#....", "#....", "#....", "#...#", ".###."),
    "D": ("###..", "#..#.", "#...#", "#...#", "#...#", "#..#.", "###.."),
    "E": ("#####", "#....", "#....", "####.", "#....", "#....", "#####"),
    "F": ("#####", "#....", "#....", "####.", "#....", "#....", "#...."),
    "G": (".###.", "#...#", "#....", "#.###", "#...#", "#...#", ".####"),
    "H": ("#...#", "#...#", "#...#", "#####", "#...#", "#...#", "#...#"),
    "I": (".###.", "..#..", "..#..", "..#..", "..#..", "..#..", ".###."),
    "J": ("..###", "...#.", "...#.", "...#.", "...#.", "#..#.", ".##.."),
    "K": ("#...#", "#..#.", "#.#..", "##...", "#.#..", "#..#.", "#...#"),
    "L": ("#....", "#....", "#....", "#....", "#....", "#....", "#####"),
    "M": ("#...#", "##.##", "#.#.#", "#.#.#", "#...#", "#...#", "#...#"),
    "N": ("#...#", "#...#", "##..#", "#.#.#", "#..##", "#...#", "#...#"),
    "O": (".###.", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."),
    "P": ("####.", "#...#", "#...#", "####.", "#....", "#....", "#...."),
    "Q": (".###.", "#...#", "#...#", "#...#", "#.#.#", "#..#.", ".##.#"),
    "R": ("####.", "#...#", "#...#", "####.", "#.#..", "#..#.", "#...#"),
    "S": (".####", "#....", "#....", ".###.", "....#", "....#", "####."),
    "T": ("#####", "..#..", "..#..", "..#..", "..#..", "..#..", "..#.."),
    "U": ("#...#", "#...#", "#...#", "#...#", "#...#", "#...#", ".###."),
    "V": ("#...#", "#...#", "#...#", "#...#", "#...#", ".#.#.", "..#.."),
    "W": ("#...#", "#...#", "#...#", "#.#.#", "#.#.#", "#.#.#", ".#.#."),
    "X": ("#...#", "#...#", ".#.#.", "..#..", ".#.#.", "#...#", "#...#"),
    "Y": ("#...#", "#...#", ".#.#.", "..#..", "..#..", "..#..", "..#.."),
    "Z": ("#####", "....#", "...#.", "..#..", ".#...", "#....", "#####"),
    ".": (".....", ".....", ".....", ".....", ".....", ".##..", ".##.."),
    ",": (".....", ".....", ".....", ".....", ".##..", "..#..", ".#..."),
    ":": (".....", ".##..", ".##..", ".....", ".##..", ".##..", "....."),
    "-": (".....", ".....", ".....", "#####", ".....", ".....", "....."),
    "+": (".....", "..#..", "..#..", "#####", "..#..", "..#..", "....."),
    "=": (".....", ".....", "#####", ".....", "#####", ".....", "....."),
    "/": ("....#", "....#", "...#.", "..#..", ".#...", "#....", "#...."),
    "%": ("##..#", "##..#", "...#.", "..#..", ".#...", "#..##", "#..##"),
    "(": ("...#.", "..#..", ".#...", ".#...", ".#...", "..#..", "...#."),
    ")": (".#...", "..#..", "...#.", "...#.", "...#.", "..#..", ".#..."),
    "_": (".....", ".....", ".....", ".....", ".....", ".....", "#####"),
    "!": ("..#..", "..#..", "..#..", "..#..", "..#..", ".....", "..#.."),
    "?": (".###.", "#...#", "....#", "...#.", "..#..", ".....", "..#.."),
}

#: Characters of the built-in font, in glyph order.
FONT_CHARS: str = "".join(_FONT_ROWS)
#: (G,7,5) bool glyph bitmaps, row-major from the top; index with :func:`text_glyph_indices`.
FONT_GLYPHS: np.ndarray = np.array([[[ch == "#" for ch in row] for row in rows] for rows in _FONT_ROWS.values()])
FONT_GLYPHS.setflags(write=False)
_FONT_INDEX = {ch: i for i, ch in enumerate(FONT_CHARS)}
#: Glyph cell size (rows, columns) and horizontal advance, in font cells.
GLYPH_ROWS, GLYPH_COLUMNS, GLYPH_ADVANCE = 7, 5, 6


def text_glyph_indices(text: str) -> np.ndarray:
    """(n,) int32 glyph indices of ``text``: lower case is drawn as upper case, unknown characters as '?'."""
    unknown = _FONT_INDEX["?"]
    return np.array([_FONT_INDEX.get(ch, unknown) for ch in text.upper()], dtype=np.int32)


def text_size(text: str, scale: int = 1) -> tuple[int, int]:
    """``(width, height)`` in pixels of one line of ``text`` drawn with :func:`draw_text` at ``scale``."""
    n = len(text)
    return (max(GLYPH_ADVANCE * n - 1, 0) * scale, GLYPH_ROWS * scale)


def text_bitmap(text: str, scale: int = 1) -> np.ndarray:
    """(7 scale, (6 n - 1) scale) bool mask of the pixels :func:`draw_text` sets for one line of ``text``."""
    w, h = text_size(text, scale)
    canvas = np.zeros((h, w, 3), dtype=np.uint8)
    draw_text(text_glyph_indices(text), FONT_GLYPHS, 0, 0, scale, np.full(3, 255, dtype=np.uint8), canvas)
    return canvas[:, :, 0] == 255
