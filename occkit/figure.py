"""Headless matplotlib figures: Agg canvases that need no display and leave pyplot's global state alone.

Every figure of occkit (reports, training curves, visualisations) is made and saved here."""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np
from matplotlib.backends.backend_agg import FigureCanvasAgg
from matplotlib.figure import Figure
from PIL import Image

from occkit.classes import EMPTY_COLOR, IGNORE_COLOR, OCC3D_COLORS, UNOBSERVED_COLOR

__all__ = ["MIN_PALETTE_COLORS", "new_figure", "save_figure"]

#: ``(K, 3)`` uint8 colours that palette PNGs keep exactly (sorted rows): classes, map markers and white.
_MARKERS = [UNOBSERVED_COLOR, EMPTY_COLOR, IGNORE_COLOR, (255, 255, 255)]
_EXACT_COLORS = np.unique(np.concatenate((OCC3D_COLORS, _MARKERS)), axis=0).astype(np.uint8)
#: Fewest palette colours :func:`save_figure` accepts: the exact ones and a few for everything else.
MIN_PALETTE_COLORS = len(_EXACT_COLORS) + 8


def new_figure(width: float, height: float, dpi: float = 100, layout: str | None = None) -> Figure:
    """A figure of ``width x height`` inches drawn by the Agg canvas.

    Unlike ``pyplot.figure`` it is not registered with pyplot, so it is freed with its last reference and never
    opens a window, whatever backend an interactive session has selected. ``layout`` is matplotlib's layout engine
    (``"constrained"`` keeps legends outside the axes in the figure), or None for fixed axes positions.
    """
    figure = Figure(figsize=(width, height), dpi=dpi, layout=layout)
    FigureCanvasAgg(figure)
    return figure


def save_figure(
    figure: Figure, path: str | Path, dpi: float | None = None, colors: int | None = None, tight: bool = False
) -> Path:
    """Write ``figure`` as a PNG (parent folders created) and return the path.

    Args:
        figure: the figure.
        path: PNG file.
        dpi: resolution (default: the figure's).
        colors: if given, store the PNG with a palette of this many colours (at most 256), which makes renders over
            camera photographs several times smaller (for pages and documentation). Pixels of the class and marker
            colours of :mod:`occkit.classes` (and white) keep their exact colour; the rest of the palette adapts
            to the image, with dithering.
        tight: crop the page to what is drawn (matplotlib's ``bbox_inches="tight"``).
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    dpi = dpi if dpi is not None else figure.dpi
    options = {"dpi": dpi, "facecolor": "white", "bbox_inches": "tight" if tight else None}
    if colors is None:
        figure.savefig(path, **options)
        return path
    if not MIN_PALETTE_COLORS <= colors <= 256:
        raise ValueError(f"colors must lie in {MIN_PALETTE_COLORS}..256, got {colors}")
    exact = _EXACT_COLORS
    buffer = io.BytesIO()
    figure.savefig(buffer, format="png", **options)
    with Image.open(buffer) as opened:
        image = opened.convert("RGB")
    # Median cut picks the colours, Floyd-Steinberg dithering maps the image onto them (smooth photographs and colour
    # maps instead of bands); flat colours are snapped back to their exact entries below.
    quantized = image.quantize(palette=image.quantize(colors - len(exact)), dither=Image.Dither.FLOYDSTEINBERG)
    adaptive = quantized.getpalette()  # fewer entries than asked for when the image has fewer colours
    indices = np.asarray(quantized).copy()  # (H, W) palette indices
    # Pixels that hold one of the exact colours get its own palette entry, so legends and maps keep their colours.
    code = _rgb_code(np.asarray(image))  # (H, W)
    exact_code = _rgb_code(exact)  # (K,), sorted because ``exact`` is
    position = np.clip(np.searchsorted(exact_code, code), 0, len(exact) - 1)
    is_exact = exact_code[position] == code
    indices[is_exact] = len(adaptive) // 3 + position[is_exact]
    palette = adaptive + exact.reshape(-1).tolist()
    result = Image.fromarray(indices, mode="P")
    result.putpalette(palette)
    result.save(path, optimize=True)
    return path


def _rgb_code(rgb: np.ndarray) -> np.ndarray:
    """``(..., 3)`` uint8 -> ``(...)`` int64 ``r * 65536 + g * 256 + b`` (sorted like the rows of ``np.unique``)."""
    rgb = rgb.astype(np.int64)
    return rgb[..., 0] * 65536 + rgb[..., 1] * 256 + rgb[..., 2]
