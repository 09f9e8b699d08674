"""RayPQ: panoptic quality on the rays of the RayIoU protocol (SparseOcc, ``loaders/ray_pq.py`` and ``main_raypq``),
value for value.

The rays are RayIoU's (:func:`occkit.metrics.rayiou.cast_frame`): each ray reads the class, the instance id and
the depth of the voxel it stops in, in the prediction and in the ground truth, and only rays whose ground truth stops
on something other than free space count. Per depth threshold ``t`` (1, 2, 4 m) and class, segments are matched as
in panoptic segmentation, with the rays as pixels:

* the ground truth's segments: one per object of a *thing* class (:data:`THING_CLASSES`; the reference takes an
  instance's class from its rays, and an instance whose rays carry two classes counts as free space), and one per
  *stuff* class, all of its rays together;
* the prediction's segments: one per predicted instance id within a class (a stuff prediction, instance id 0, is
  one segment per class);
* a pair of segments of the same class matches (a true positive, TP) when their intersection over union exceeds 0.5,
  the intersection counting only rays whose depths differ by less than ``t``; unmatched ground-truth segments of at
  least 10 rays are false negatives (FN), unmatched predicted segments of at least 10 rays false positives (FP);
* summed over all frames, ``SQ = sum of matched IoUs / TP``, ``RQ = TP / (TP + FP / 2 + FN / 2)`` and
  ``PQ = SQ x RQ`` per class (NaN where a class has no TP, FP or FN); RayPQ@t is the mean over classes and RayPQ
  the mean over thresholds and classes.

Inputs are Occ3D grids ``(200, 200, 16)`` of class ids (17 = free) and of instance ids (0 = no instance).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from occkit.classes import THING_CLASSES
from occkit.label_space import OCC3D_SPACE
from occkit.metrics.rayiou import RAYIOU_THRESHOLDS, FrameRays, cast_frame

__all__ = ["THING_CLASSES", "MIN_SEGMENT_RAYS", "RayPQCounts", "raypq"]

#: An unmatched segment of fewer rays is neither a false negative nor a false positive.
MIN_SEGMENT_RAYS = 10
#: The reference's offset of its combined (ground truth, prediction) segment ids.
_ID_OFFSET = 2**16

_FREE = OCC3D_SPACE.free_index
_NUM_CLASSES = OCC3D_SPACE.num_classes
_THINGS = frozenset(OCC3D_SPACE.taxonomy.index(name) for name in THING_CLASSES)


class RayPQCounts:
    """TP, matched IoU, FP and FN per threshold and class, summed over the frames added."""

    def __init__(self, thresholds: Sequence[float] = RAYIOU_THRESHOLDS) -> None:
        self.thresholds = tuple(thresholds)
        shape = (len(self.thresholds), _NUM_CLASSES)
        self.tp = np.zeros(shape, dtype=np.int64)
        self.iou = np.zeros(shape, dtype=np.float64)
        self.fp = np.zeros(shape, dtype=np.int64)
        self.fn = np.zeros(shape, dtype=np.int64)

    def add_rays(self, sem_pred: np.ndarray, sem_gt: np.ndarray, inst_pred: np.ndarray, inst_gt: np.ndarray,
                 depth_error: np.ndarray) -> None:  # fmt: skip
        """One frame's rays (those whose ground truth is not free): ``(R,)`` class and instance ids of both sides and
        the absolute depth difference in metres."""
        gt_segments = _ground_truth_segments(sem_gt.astype(np.int64), inst_gt.astype(np.int64))
        pred_segments = inst_pred.astype(np.int64) + 1  # instance 0 (stuff) becomes a segment too
        for j, threshold in enumerate(self.thresholds):
            close = depth_error < threshold
            for cls in range(_NUM_CLASSES - 1):
                self._match(j, cls, np.where(sem_pred == cls, pred_segments, 0),
                            np.where(sem_gt == cls, gt_segments, 0), close)  # fmt: skip

    def _match(self, j: int, cls: int, pred: np.ndarray, gt: np.ndarray, close: np.ndarray) -> None:
        pred_ids, pred_areas = np.unique(pred[pred > 0], return_counts=True)
        gt_ids, gt_areas = np.unique(gt[gt > 0], return_counts=True)
        both = (pred > 0) & (gt > 0) & close
        pairs, intersections = np.unique(pred[both] + _ID_OFFSET * gt[both], return_counts=True)
        pair_gt, pair_pred = pairs // _ID_OFFSET, pairs % _ID_OFFSET
        gt_area = gt_areas[np.searchsorted(gt_ids, pair_gt)]
        pred_area = pred_areas[np.searchsorted(pred_ids, pair_pred)]
        ious = intersections / (gt_area + pred_area - intersections)
        matched = ious > 0.5
        self.tp[j, cls] += int(matched.sum())
        self.iou[j, cls] += float(ious[matched].sum())
        matched_gt = np.isin(gt_ids, pair_gt[matched])
        matched_pred = np.isin(pred_ids, pair_pred[matched])
        self.fn[j, cls] += int(((gt_areas >= MIN_SEGMENT_RAYS) & ~matched_gt).sum())
        self.fp[j, cls] += int(((pred_areas >= MIN_SEGMENT_RAYS) & ~matched_pred).sum())

    def add_frame(self, gt: np.ndarray, pred: np.ndarray, gt_instances: np.ndarray, pred_instances: np.ndarray,
                  origins: np.ndarray) -> None:  # fmt: skip
        """One frame's grids: cast the rays from ``origins`` through both and count the non-free ground-truth rays."""
        self.add_cast(cast_frame(gt, pred, origins), gt_instances, pred_instances)

    def add_cast(self, rays: FrameRays, gt_instances: np.ndarray, pred_instances: np.ndarray) -> None:
        """One frame's rays as :func:`~occkit.metrics.rayiou.cast_frame` cast them for RayIoU, with the frame's
        ``(200, 200, 16)`` ground-truth and predicted instance grids."""
        gt_id = np.asarray(gt_instances)[tuple(rays.gt_voxel.T)]
        pred_id = np.asarray(pred_instances)[tuple(rays.pred_voxel.T)]
        self.add_rays(rays.pred_label, rays.gt_label, pred_id, gt_id, rays.depth_error)

    def reduce(self, reduce: Callable[[np.ndarray], np.ndarray]) -> None:
        """Replace every count by ``reduce(count)``: a sum over distributed ranks, which every rank calls alike."""
        for name in ("tp", "iou", "fp", "fn"):
            setattr(self, name, np.asarray(reduce(getattr(self, name))).astype(getattr(self, name).dtype))

    def merge(self, other: RayPQCounts) -> None:
        """Add another set of counts (of other frames, same thresholds)."""
        if other.thresholds != self.thresholds:
            raise ValueError(f"cannot merge RayPQ counts of thresholds {other.thresholds} into {self.thresholds}")
        self.tp += other.tp
        self.iou += other.iou
        self.fp += other.fp
        self.fn += other.fn

    def compute(self) -> dict:
        """``raypq`` (mean over thresholds and classes), ``raypq@t`` per threshold, and ``per_class`` ``{t: list of
        17 floats}`` (NaN for a class without TP, FP or FN), the free class left out."""
        sq = self.iou / np.maximum(self.tp, 1e-5)
        rq = self.tp / np.maximum(self.tp + 0.5 * self.fp + 0.5 * self.fn, 1e-5)
        pq = sq * rq
        pq[(self.tp + self.fp + self.fn) == 0] = np.nan
        pq = pq[:, :_FREE]
        result = {"raypq": _nanmean(pq)}
        for j, threshold in enumerate(self.thresholds):
            result[f"raypq@{threshold:g}"] = _nanmean(pq[j])
        result["per_class"] = {int(t): pq[j].tolist() for j, t in enumerate(self.thresholds)}
        return result


def _ground_truth_segments(sem_gt: np.ndarray, inst_gt: np.ndarray) -> np.ndarray:
    """The reference's ground-truth segment of each ray (0: none): every instance of a thing class its own segment,
    every stuff class one; segments numbered from 1 in the order of their class, then of their instance id, and then
    shifted by one as the reference does."""
    # An instance's class: the one class its rays carry; two classes make it free space (no segment).
    instance_class = np.full(int(inst_gt.max(initial=0)) + 1, _FREE, dtype=np.int64)
    for instance in range(1, instance_class.shape[0]):
        classes = np.unique(sem_gt[inst_gt == instance])
        if classes.shape[0] == 1:
            instance_class[instance] = classes[0]
    segments = np.zeros_like(inst_gt)
    count = 1
    for cls in range(_NUM_CLASSES - 1):
        if not np.any(sem_gt == cls):
            continue
        if cls in _THINGS:
            for instance in np.flatnonzero(instance_class == cls):
                segments[inst_gt == instance] = count
                count += 1
        else:
            segments[sem_gt == cls] = count
            count += 1
    return segments + 1


def _nanmean(values: np.ndarray) -> float:
    finite = values[~np.isnan(values)]
    return float(finite.mean()) if finite.size else float("nan")


def raypq(gts: Sequence[np.ndarray], preds: Sequence[np.ndarray], gt_instances: Sequence[np.ndarray],
          pred_instances: Sequence[np.ndarray], origins: Sequence[np.ndarray]) -> dict:  # fmt: skip
    """RayPQ over a set of frames, as SparseOcc's ``main_raypq``.

    Args:
        gts, preds: ``(200, 200, 16)`` uint8 Occ3D class grids per frame (17 = free).
        gt_instances, pred_instances: ``(200, 200, 16)`` integer instance ids per frame (0 = no instance).
        origins: ``(T, 3)`` ray origins per frame, ego metres.

    Returns:
        :meth:`RayPQCounts.compute`'s scores.
    """
    if not len(gts) == len(preds) == len(gt_instances) == len(pred_instances) == len(origins):
        raise ValueError("gts, preds, their instances and origins must have one entry per frame")
    counts = RayPQCounts()
    for gt, pred, gt_inst, pred_inst, org in zip(gts, preds, gt_instances, pred_instances, origins, strict=True):
        counts.add_frame(gt, pred, gt_inst, pred_inst, org)
    return counts.compute()
