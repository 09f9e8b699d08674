"""Class colours as arrays, and class legends, for a label space's taxonomy.

The colours are the taxonomy's (:data:`occkit.classes.OCC3D_COLORS`, the palette of the field's Occ3D visualisers;
SurroundOcc's ids 1..16 take the same colours); two more colours mark what is not a class: columns no camera
observes, and observed columns that hold only free space.
"""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from matplotlib.axes import Axes
from matplotlib.colors import hsv_to_rgb
from matplotlib.patches import Patch

from occkit.classes import EMPTY_COLOR, IGNORE_COLOR, IGNORE_INDEX, OCC3D, OCC3D_COLORS, UNOBSERVED_COLOR, Taxonomy

__all__ = ["PALETTE", "UNOBSERVED_COLOR", "EMPTY_COLOR", "IGNORE_COLOR", "class_colors", "instance_colors",
           "add_class_legend"]

#: ``(18, 3)`` uint8 RGB per Occ3D id (17 = free).
PALETTE = np.array(OCC3D_COLORS, dtype=np.uint8)


def class_colors(labels: np.ndarray, taxonomy: Taxonomy = OCC3D) -> np.ndarray:
    """RGB of class ids.

    Args:
        labels: integer array of any shape ``S`` with ids of ``taxonomy`` (Occ3D: 0..17) or 255.
        taxonomy: the label set whose colours to use.

    Returns:
        ``(*S, 3)`` uint8; ignored voxels get :data:`IGNORE_COLOR`.
    """
    labels = np.asarray(labels)
    palette = np.array(taxonomy.colors, dtype=np.uint8)
    bad = (labels < 0) | ((labels >= len(palette)) & (labels != IGNORE_INDEX))
    if bad.any():
        values = np.unique(labels[bad])[:8].tolist()
        raise ValueError(f"{taxonomy.name} class ids must lie in 0..{len(palette) - 1} or be {IGNORE_INDEX}, "
                         f"found {values}")  # fmt: skip
    table = np.tile(np.array(IGNORE_COLOR, np.uint8), (256, 1))  # (256, 3): every uint8 id, ignore included
    table[: len(palette)] = palette
    return table[labels.astype(np.uint8)]


def instance_colors(labels: np.ndarray, instances: np.ndarray, taxonomy: Taxonomy = OCC3D) -> np.ndarray:
    """RGB of panoptic voxels: each object instance its own colour, stuff its class colour.

    An instance's colour is a hue stepped by the golden ratio from its id (so neighbouring ids differ strongly), at
    high saturation and brightness: the same object has the same colour in every frame that gives it the same id
    (the synthetic world's ids hold over time), and no class colour decides it.

    Args:
        labels: integer class ids of ``taxonomy``, any shape ``S``.
        instances: integer instance ids of the same shape (0: stuff, coloured by class).
        taxonomy: the label set of ``labels``.

    Returns:
        ``(*S, 3)`` uint8.
    """
    labels, instances = np.asarray(labels), np.asarray(instances)
    if labels.shape != instances.shape:
        raise ValueError(f"labels {labels.shape} and instances {instances.shape} differ in shape")
    colors = class_colors(labels, taxonomy)
    objects = instances > 0
    if objects.any():
        hue = (instances[objects].astype(np.float64) * 0.6180339887498949) % 1.0
        hsv = np.stack([hue, np.full_like(hue, 0.75), np.full_like(hue, 0.95)], axis=-1)
        colors[objects] = np.round(255 * hsv_to_rgb(hsv)).astype(np.uint8)
    return colors


def add_class_legend(axis: Axes, class_ids: Iterable[int], extra: Iterable[tuple[str, tuple[int, int, int]]] = (),
                     taxonomy: Taxonomy = OCC3D, **legend_kwargs) -> None:
    """A legend of coloured patches, one per class id of ``taxonomy`` (in id order), then ``extra`` ``(label, rgb)``
    entries.

    Free space and ignored ids among ``class_ids`` are left out: they are never drawn as a class colour.
    Keyword arguments go to ``Axes.legend`` (default: outside the axes, to the right, small font).
    """
    ids = sorted({int(i) for i in class_ids} & set(taxonomy.semantic_ids))
    entries = [(taxonomy.classes[i], tuple(int(c) for c in taxonomy.colors[i])) for i in ids] + list(extra)
    handles = [Patch(facecolor=np.array(rgb) / 255, edgecolor="0.4", linewidth=0.5, label=name)
               for name, rgb in entries]  # fmt: skip
    options = {"loc": "upper left", "bbox_to_anchor": (1.01, 1.0), "fontsize": 7, "frameon": False,
               "handlelength": 1.2, "borderaxespad": 0.0}  # fmt: skip
    axis.legend(handles=handles, **{**options, **legend_kwargs})
