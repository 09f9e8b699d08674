"""Bird's-eye-view semantic maps: the class of the top-most occupied voxel of each column, in the class palette.

Orientation (checked by tests): Occ3D labels are indexed ``[x, y, z]`` in the ego frame, x forward, y left, z up
(docs/conventions.md). A BEV image shows the scene as a driver expects it on a map held in the direction of travel:
**forward (+x) points up** and **left (+y) is on the left**. Image row ``r`` holds ``x`` index ``X - 1 - r`` and
image column ``c`` holds ``y`` index ``Y - 1 - c``, i.e. the image is ``columns[::-1, ::-1]``
(:func:`bev_view`). Drawn with :func:`draw_bev`, the axes are labelled in metres with the same orientation.
Labels of a label space in the LiDAR frame (SurroundOcc) are drawn in that frame's axes, named on the axes, with the
sensor's origin marked instead of the ego car.
"""

from __future__ import annotations

import numpy as np
from matplotlib.axes import Axes
from matplotlib.figure import Figure
from matplotlib.patches import Rectangle

from occkit.classes import IGNORE_INDEX, OCC3D, Taxonomy
from occkit.figure import new_figure
from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.label_space import OCC3D_SPACE, LabelSpace
from occkit.viz.palette import EMPTY_COLOR, UNOBSERVED_COLOR, add_class_legend, class_colors

__all__ = ["EGO_BOX", "top_occupied", "bev_view", "bev_image", "bev_extent", "draw_bev", "draw_ego", "bev_figure"]

#: The ego car in its own frame (nuScenes' Renault Zoe, origin at the rear axle on the ground), metres:
#: ``(x_min, y_min, z_min, x_max, y_max, z_max)``.
EGO_BOX = (-0.7, -0.87, 0.0, 3.4, 0.87, 1.56)


def top_occupied(
    semantics: np.ndarray, mask: np.ndarray | None = None, free_index: int = OCC3D.empty_index
) -> tuple[np.ndarray, np.ndarray]:
    """Class and height index of the highest occupied voxel of every column.

    Occupied means neither free nor ignored (255); with a mask, only voxels the mask keeps count, as in the Occ3D
    metric.

    Args:
        semantics: ``(X, Y, Z)`` integer labels.
        mask: optional ``(X, Y, Z)`` visibility mask (e.g. ``mask_camera``).
        free_index: label of free space.

    Returns:
        top_class: ``(X, Y)`` uint8, ``free_index`` in columns without an occupied voxel.
        top_z: ``(X, Y)`` int64 z index, -1 in columns without an occupied voxel.
    """
    semantics = np.asarray(semantics)
    if semantics.ndim != 3:
        raise ValueError(f"semantics must be (X, Y, Z), got shape {semantics.shape}")
    occupied = (semantics != free_index) & (semantics != IGNORE_INDEX)
    if mask is not None:
        if np.shape(mask) != semantics.shape:
            raise ValueError(f"mask shape {np.shape(mask)} does not match semantics shape {semantics.shape}")
        occupied &= np.asarray(mask, dtype=bool)
    depth = semantics.shape[2]
    top_z = depth - 1 - np.argmax(occupied[:, :, ::-1], axis=2)  # (X, Y): argmax finds the first True from the top
    has_any = occupied.any(axis=2)
    top_class = np.take_along_axis(semantics, top_z[:, :, None], axis=2)[:, :, 0].astype(np.uint8)
    top_class[~has_any] = free_index
    top_z[~has_any] = -1
    return top_class, top_z


def bev_view(columns: np.ndarray) -> np.ndarray:
    """Per-column values ``(X, Y, ...)`` laid out as an image ``(X, Y, ...)``: forward (+x) up, left (+y) left."""
    return np.ascontiguousarray(columns[::-1, ::-1])


def bev_image(
    semantics: np.ndarray,
    mask: np.ndarray | None = None,
    taxonomy: Taxonomy = OCC3D,
    shade: float = 0.4,
) -> np.ndarray:
    """Top-down colour image of occupancy labels: the class colour of the highest occupied voxel in each column.

    Args:
        semantics: ``(X, Y, Z)`` uint8 labels of ``taxonomy``, indexed ``[x, y, z]`` (ego: x forward, y left).
        mask: optional ``(X, Y, Z)`` visibility mask: only the voxels it keeps count, and columns in which it keeps
            no voxel at all are drawn :data:`~occkit.viz.palette.UNOBSERVED_COLOR` (dark).
        taxonomy: the classes and colours; observed columns without a voxel other than its free / empty class are
            drawn :data:`~occkit.viz.palette.EMPTY_COLOR`.
        shade: darkening of low voxels, so that objects stand out from the ground: a voxel at z index ``k`` of
            ``Z`` is scaled by ``1 - shade * (1 - k / (Z - 1))``; 0 gives the exact palette colours.

    Returns:
        ``(X, Y, 3)`` uint8 image with forward (+x) up and left (+y) on the left (see the module docstring).
    """
    if not 0.0 <= shade <= 1.0:
        raise ValueError(f"shade must lie in [0, 1], got {shade}")
    top_class, top_z = top_occupied(semantics, mask, taxonomy.empty_index)
    image = class_colors(top_class, taxonomy).astype(np.float32)  # (X, Y, 3)
    depth = np.asarray(semantics).shape[2]
    brightness = 1.0 - shade * (1.0 - np.clip(top_z, 0, None) / max(depth - 1, 1))
    image *= brightness[:, :, None]
    image[top_z < 0] = EMPTY_COLOR
    if mask is not None:
        image[~np.asarray(mask, dtype=bool).any(axis=2)] = UNOBSERVED_COLOR
    return bev_view(np.round(image).astype(np.uint8))


def bev_extent(grid: VoxelGrid = OCC3D_GRID) -> tuple[float, float, float, float]:
    """``imshow`` extent ``(left, right, bottom, top)`` in metres of a :func:`bev_view` image: y from +y_max on the
    left to y_min on the right, x from x_min at the bottom to x_max at the top."""
    (x_min, y_min, _), (x_max, y_max, _) = grid.lower, grid.upper
    return (y_max, y_min, x_min, x_max)


def draw_ego(axis: Axes, color: str = "black") -> None:
    """The ego car's footprint on a BEV axis drawn with :func:`bev_extent` (horizontal: y, vertical: x)."""
    x_min, y_min, _, x_max, y_max, _ = EGO_BOX
    # The horizontal data axis runs from +y (left) to -y (right), so the rectangle starts at y_min.
    axis.add_patch(Rectangle((y_min, x_min), y_max - y_min, x_max - x_min, facecolor=color, edgecolor="white",
                             linewidth=0.6, zorder=3))  # fmt: skip
    axis.annotate("", xy=(0.0, x_max + 3.0), xytext=(0.0, x_max), zorder=3,
                  arrowprops={"arrowstyle": "-|>", "color": color, "linewidth": 0.8})  # fmt: skip


def draw_bev(axis: Axes, image: np.ndarray, space: LabelSpace = OCC3D_SPACE, title: str | None = None) -> None:
    """Show a :func:`bev_view` image of ``space``'s grid in metres: in the ego frame forward up, left on the left,
    the ego car marked; in the LiDAR frame its +x up, its +y on the left, the sensor's origin marked."""
    frame = space.frame
    axis.imshow(image, extent=bev_extent(space.grid), interpolation="nearest")
    if frame == "ego":
        draw_ego(axis)
        axis.set_xlabel("y (m), left +", fontsize=7)
        axis.set_ylabel("x (m), forward +", fontsize=7)
    else:
        axis.plot([0.0], [0.0], marker="+", color="black", markersize=8, zorder=3)
        axis.set_xlabel(f"{frame} y (m)", fontsize=7)
        axis.set_ylabel(f"{frame} x (m)", fontsize=7)
    axis.tick_params(labelsize=6)
    if title:
        axis.set_title(title, fontsize=8)


def bev_figure(
    semantics: np.ndarray,
    mask: np.ndarray | None = None,
    space: LabelSpace = OCC3D_SPACE,
    title: str = "",
    shade: float = 0.25,
) -> Figure:
    """BEV semantic map of one frame: all labels and, with a mask, the columns it observes; a class legend.

    Args:
        semantics: ``(X, Y, Z)`` labels of ``space``.
        mask: optional ``(X, Y, Z)`` visibility mask (``mask_camera``) for a second panel.
        space: the label space of ``semantics`` (grid extents in metres, frame, classes and colours).
        title: figure title.
        shade: see :func:`bev_image`.
    """
    panels = [("all labels", None)] + ([("camera-visible voxels (mask_camera)", mask)] if mask is not None else [])
    figure = new_figure(3.6 * len(panels) + 1.6, 3.9, layout="constrained")
    axes = figure.subplots(1, len(panels), squeeze=False)[0]
    for axis, (name, panel_mask) in zip(axes, panels, strict=True):
        draw_bev(axis, bev_image(semantics, panel_mask, space.taxonomy, shade), space, name)
    present = np.unique(top_occupied(semantics, free_index=space.free_index)[0])
    extra = [("no occupied voxel", EMPTY_COLOR)] + ([("not observed", UNOBSERVED_COLOR)] if mask is not None else [])
    add_class_legend(axes[-1], present, extra, space.taxonomy)
    if title:
        figure.suptitle(title, fontsize=9)
    return figure
