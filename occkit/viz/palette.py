"""Occ3D class colours as arrays, and class legends.

The colours are :data:`occkit.classes.OCC3D_COLORS`, the palette of the field's Occ3D visualisers; two more colours
mark what is not a class: columns no camera observes, and observed columns that hold only free space.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from matplotlib.axes import Axes
from matplotlib.patches import Patch

from occkit.classes import IGNORE_INDEX, OCC3D, OCC3D_CLASSES, OCC3D_COLORS

__all__ = ["PALETTE", "UNOBSERVED_COLOR", "EMPTY_COLOR", "IGNORE_COLOR", "class_colors", "add_class_legend"]

#: ``(18, 3)`` uint8 RGB per Occ3D id (17 = free).
PALETTE = np.array(OCC3D_COLORS, dtype=np.uint8)
#: Columns that no camera observes (outside the camera mask): dark, so observed content stands out.
UNOBSERVED_COLOR = (30, 30, 30)
#: Observed columns that hold no occupied voxel: a grey lighter than unobserved columns and darker than any class
#: but ``others`` (the palette's white is free space, too close to ``manmade`` to read as "nothing here").
EMPTY_COLOR = (75, 75, 75)
#: Voxels labelled 255 (ignored by losses and metrics).
IGNORE_COLOR = (128, 128, 128)


def class_colors(labels: np.ndarray) -> np.ndarray:
    """RGB of class ids.

    Args:
        labels: integer array of any shape ``S`` with Occ3D ids 0..17 or 255.

    Returns:
        ``(*S, 3)`` uint8; ignored voxels get :data:`IGNORE_COLOR`.
    """
    labels = np.asarray(labels)
    bad = (labels < 0) | ((labels >= len(PALETTE)) & (labels != IGNORE_INDEX))
    if bad.any():
        values = np.unique(labels[bad])[:8].tolist()
        raise ValueError(f"class ids must lie in 0..{len(PALETTE) - 1} or be {IGNORE_INDEX}, found {values}")
    table = np.tile(np.array(IGNORE_COLOR, np.uint8), (256, 1))  # (256, 3): every uint8 id, ignore included
    table[: len(PALETTE)] = PALETTE
    return table[labels.astype(np.uint8)]


def add_class_legend(axis: Axes, class_ids: Iterable[int], extra: Iterable[tuple[str, tuple[int, int, int]]] = (),
                     **legend_kwargs) -> None:
    """A legend of coloured patches, one per class id (in id order), then ``extra`` ``(label, rgb)`` entries.

    Free space and ignored ids among ``class_ids`` are left out: they are never drawn as a class colour.
    Keyword arguments go to ``Axes.legend`` (default: outside the axes, to the right, small font).
    """
    ids = sorted({int(i) for i in class_ids if 0 <= int(i) < OCC3D.empty_index})
    entries = [(OCC3D_CLASSES[i], tuple(int(c) for c in PALETTE[i])) for i in ids] + list(extra)
    handles = [Patch(facecolor=np.array(rgb) / 255, edgecolor="0.4", linewidth=0.5, label=name)
               for name, rgb in entries]  # fmt: skip
    options = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "fontsize": 7, "frameon": False,
               "handlelength": 1.2, "borderaxespad": 0.0}  # fmt: skip
    axis.legend(handles=handles, **{**options, **legend_kwargs})
