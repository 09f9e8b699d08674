"""Prediction against ground truth: the outcome of every voxel, a BEV error map and a side-by-side figure.

Voxel outcomes follow the Occ3D metric: only voxels the mask keeps and whose label is not ignored (255) are
evaluated; an evaluated voxel is a true free voxel, correct (same occupied class), a wrong class (both occupied,
classes differ), missed (occupied in the ground truth, predicted free) or a false positive (free in the ground
truth, predicted occupied). A column of the error map shows its most frequent error, so a single wrong voxel on top
of a correct ground is still seen; columns without errors are correct, or empty when they hold only free voxels.
"""

from __future__ import annotations

import math

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from occkit.classes import IGNORE_INDEX, OCC3D
from occkit.figure import new_figure
from occkit.label_space import OCC3D_SPACE, LabelSpace
from occkit.metrics.confusion import OccupancyMetric
from occkit.viz.bev import bev_image, bev_view, draw_bev, top_occupied
from occkit.viz.palette import EMPTY_COLOR, UNOBSERVED_COLOR, add_class_legend

__all__ = [
    "NOT_EVALUATED",
    "TRUE_FREE",
    "CORRECT",
    "WRONG_CLASS",
    "MISSED",
    "FALSE_POSITIVE",
    "OUTCOME_NAMES",
    "OUTCOME_COLORS",
    "voxel_outcomes",
    "column_outcomes",
    "error_image",
    "frame_scores",
    "format_scores",
    "comparison_figure",
]

NOT_EVALUATED, TRUE_FREE, CORRECT, WRONG_CLASS, MISSED, FALSE_POSITIVE = range(6)
#: Legend text per outcome code.
OUTCOME_NAMES = ("not observed", "free (no occupied voxel)", "correct", "wrong class", "missed (predicted free)",
                 "false positive (GT free)")  # fmt: skip
#: RGB per outcome code: errors in saturated colours (Okabe-Ito orange, vermillion-red and blue) over a grey that
#: marks correct columns.
OUTCOME_COLORS = (UNOBSERVED_COLOR, EMPTY_COLOR, (190, 190, 190), (230, 159, 0), (213, 40, 40), (0, 114, 178))
_ERRORS = (WRONG_CLASS, MISSED, FALSE_POSITIVE)


def voxel_outcomes(
    gt: np.ndarray, pred: np.ndarray, mask: np.ndarray | None = None, free_index: int = OCC3D.empty_index
) -> np.ndarray:
    """Outcome code of every voxel.

    Args:
        gt: ``(X, Y, Z)`` ground-truth labels (255 = ignore).
        pred: ``(X, Y, Z)`` predicted labels.
        mask: optional ``(X, Y, Z)`` visibility mask; voxels outside it are not evaluated.
        free_index: the free label.

    Returns:
        ``(X, Y, Z)`` uint8 codes :data:`NOT_EVALUATED`, :data:`TRUE_FREE`, :data:`CORRECT`, :data:`WRONG_CLASS`,
        :data:`MISSED` or :data:`FALSE_POSITIVE`.
    """
    gt, pred = np.asarray(gt), np.asarray(pred)
    if gt.shape != pred.shape or gt.ndim != 3:
        raise ValueError(f"gt and pred must both be (X, Y, Z), got shapes {gt.shape} and {pred.shape}")
    evaluated = gt != IGNORE_INDEX
    if mask is not None:
        if np.shape(mask) != gt.shape:
            raise ValueError(f"mask shape {np.shape(mask)} does not match the labels' shape {gt.shape}")
        evaluated &= np.asarray(mask, dtype=bool)
    gt_occupied, pred_occupied = gt != free_index, pred != free_index
    outcomes = np.full(gt.shape, TRUE_FREE, dtype=np.uint8)
    outcomes[gt_occupied & pred_occupied] = WRONG_CLASS
    outcomes[gt_occupied & pred_occupied & (gt == pred)] = CORRECT
    outcomes[gt_occupied & ~pred_occupied] = MISSED
    outcomes[~gt_occupied & pred_occupied] = FALSE_POSITIVE
    outcomes[~evaluated] = NOT_EVALUATED
    return outcomes


def column_outcomes(outcomes: np.ndarray) -> np.ndarray:
    """One outcome per column of :func:`voxel_outcomes`.

    The most frequent error of the column (ties: wrong class, then missed, then false positive); without errors
    :data:`CORRECT` if the column has a correct voxel, :data:`TRUE_FREE` if all its evaluated voxels are free, and
    :data:`NOT_EVALUATED` if none is evaluated.

    Args:
        outcomes: ``(X, Y, Z)`` uint8 codes.

    Returns:
        ``(X, Y)`` uint8 codes.
    """
    counts = np.stack([(outcomes == code).sum(axis=2) for code in range(len(OUTCOME_NAMES))], axis=-1)  # (X, Y, 6)
    columns = np.full(outcomes.shape[:2], NOT_EVALUATED, dtype=np.uint8)
    columns[counts[..., TRUE_FREE] > 0] = TRUE_FREE
    columns[counts[..., CORRECT] > 0] = CORRECT
    errors = counts[..., list(_ERRORS)]  # (X, Y, 3)
    worst = np.array(_ERRORS, dtype=np.uint8)[np.argmax(errors, axis=-1)]  # argmax keeps the first of equal counts
    has_error = errors.sum(axis=-1) > 0
    columns[has_error] = worst[has_error]
    return columns


def error_image(columns: np.ndarray) -> np.ndarray:
    """``(X, Y)`` column outcomes -> ``(X, Y, 3)`` uint8 image, forward up and left on the left (as BEV maps)."""
    return bev_view(np.array(OUTCOME_COLORS, dtype=np.uint8)[columns])


def frame_scores(
    gt: np.ndarray, pred: np.ndarray, mask: np.ndarray | None = None, space: LabelSpace = OCC3D_SPACE
) -> dict[str, float | None]:
    """``miou`` and ``iou`` of one frame with the metric of ``space``, under the camera ``mask`` when given; None
    where undefined."""
    metric = OccupancyMetric.for_space(space, mask="camera" if mask is not None else None)
    metric.update(gt, pred, mask_camera=mask)
    scores = metric.compute()
    return {key: None if math.isnan(scores[key]) else float(scores[key]) for key in ("miou", "iou")}


def format_scores(scores: dict[str, float | None]) -> str:
    """``"mIoU 41.2, IoU 60.3"`` from :func:`frame_scores` (``-`` where undefined)."""
    shown = {key: "-" if value is None else f"{100 * value:.1f}" for key, value in scores.items()}
    return f"mIoU {shown['miou']}, IoU {shown['iou']}"


def comparison_figure(
    gt: np.ndarray,
    pred: np.ndarray,
    mask: np.ndarray | None = None,
    space: LabelSpace = OCC3D_SPACE,
    title: str = "",
    pred_name: str = "prediction",
    shade: float = 0.25,
) -> Figure:
    """Ground truth, prediction and the error map side by side, with the frame's mIoU and IoU in the title.

    Args:
        gt: ``(X, Y, Z)`` ground-truth labels.
        pred: ``(X, Y, Z)`` predicted labels.
        mask: optional ``(X, Y, Z)`` mask (``mask_camera``: the official Occ3D setting); the BEV maps, the error map
            and the scores all use it.
        space: the label space of both (grid extents in metres, frame, classes, colours, metric).
        title: first line of the title (e.g. the sample token).
        pred_name: caption of the prediction panel.
        shade: see :func:`~occkit.viz.bev.bev_image`.
    """
    scores = frame_scores(gt, pred, mask, space)
    free = space.free_index
    figure = new_figure(13.0, 4.3, layout="constrained")
    axes = figure.subplots(1, 3)
    draw_bev(axes[0], bev_image(gt, mask, space.taxonomy, shade), space, "ground truth")
    draw_bev(axes[1], bev_image(pred, mask, space.taxonomy, shade), space, pred_name)
    errors = error_image(column_outcomes(voxel_outcomes(gt, pred, mask, free)))
    draw_bev(axes[2], errors, space, "errors (per column)")
    error_handles = [Patch(facecolor=np.array(OUTCOME_COLORS[code]) / 255, edgecolor="0.4", linewidth=0.5,
                           label=OUTCOME_NAMES[code])
                     for code in (CORRECT, WRONG_CLASS, MISSED, FALSE_POSITIVE, TRUE_FREE, NOT_EVALUATED)]  # fmt: skip
    axes[2].legend(handles=error_handles, loc="upper left", bbox_to_anchor=(1.02, 1.0), fontsize=7, frameon=False,
                   handlelength=1.2, borderaxespad=0.0)  # fmt: skip
    classes = np.union1d(np.unique(top_occupied(gt, mask, free)[0]), np.unique(top_occupied(pred, mask, free)[0]))
    add_class_legend(axes[1], classes, taxonomy=space.taxonomy, loc="upper center", bbox_to_anchor=(0.5, -0.16),
                     ncol=5)  # fmt: skip
    setting = "camera mask" if mask is not None else "no mask"
    figure.suptitle(f"{title + ': ' if title else ''}{format_scores(scores)} (this frame, {setting})", fontsize=9)
    return figure
