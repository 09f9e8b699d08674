"""Voxel confusion matrices and the occupancy benchmarks' IoU metrics.

Everything here agrees value for value with the CVPR 2023 occupancy challenge's ``Metric_mIoU`` (Occ3D-nuScenes):
a ``(K, K)`` int64 confusion matrix indexed ``[gt][pred]`` over the voxels a mask keeps, per-class IoU
``diag / (row + col - diag)`` with NaN for a class absent from both GT and prediction, and mIoU the nanmean over the
semantic classes 0..16 (17 = free is counted but not averaged). Also provided: the SparseOcc variant (NaN for every
class without GT voxels), geometry IoU (occupied vs free), the SurroundOcc protocol (0 = empty) and
distance-binned masks. DA-Occ's RT-mIoU@K is in :mod:`occkit.metrics.realtime`.

Counting is one pass of a compiled kernel over uint8 labels, so the 200 x 200 x 16 Occ3D frame never goes through
boolean-mask copies or int64 code arrays; CUDA tensors are counted on the device with ``torch.bincount``.
"""

from __future__ import annotations

import math
from collections.abc import Iterable, Sequence

import numpy as np
import torch
from numba import njit

from occkit.classes import IGNORE_INDEX, OCC3D, SURROUNDOCC
from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.label_space import LabelSpace

__all__ = [
    "confusion_matrix",
    "iou_from_confusion",
    "miou",
    "geometry_iou",
    "OccupancyMetric",
    "surroundocc_metrics",
    "distance_bins",
]

_MASK_MODES = ("camera", "lidar", None)

# Independent sub-tables the kernel rotates through: most Occ3D voxels fall in the same (free, free) cell, and
# incrementing one counter back to back serialises on the store-to-load latency.
_LANES = 4


@njit(cache=True, nogil=True)
def _count_masked(gt, pred, mask, lut, width):
    """Histogram of ``(lut[gt], lut[pred])`` pairs where ``mask`` is 1; all arrays flat, uint8."""
    tables = np.zeros((_LANES, width * width), np.int64)
    n = gt.size
    whole = n - n % 8
    # Visibility masks come in large contiguous blocks of zeros: testing 8 mask bytes at once skips them quickly,
    # and the per-voxel branch that follows is well predicted for the same reason.
    words = mask[:whole].view(np.uint64)
    for w in range(whole // 8):
        if words[w]:
            base = w * 8
            for j in range(8):
                if mask[base + j]:
                    tables[j & (_LANES - 1), lut[gt[base + j]] * width + lut[pred[base + j]]] += 1
    for i in range(whole, n):
        if mask[i]:
            tables[0, lut[gt[i]] * width + lut[pred[i]]] += 1
    return tables.sum(axis=0).reshape(width, width)


@njit(cache=True, nogil=True)
def _count_all(gt, pred, lut, width):
    """Histogram of ``(lut[gt], lut[pred])`` pairs over every voxel; arrays flat, uint8."""
    tables = np.zeros((_LANES, width * width), np.int64)
    n = gt.size
    for i in range(n):
        tables[i & (_LANES - 1), lut[gt[i]] * width + lut[pred[i]]] += 1
    return tables.sum(axis=0).reshape(width, width)


def _as_array(x, name: str):
    """numpy array or torch tensor, unchanged; anything else through ``np.asarray``."""
    if isinstance(x, (np.ndarray, torch.Tensor)):
        return x
    if x is None:
        raise ValueError(f"{name} is None")
    return np.asarray(x)


def _check_labels(x, name: str) -> None:
    is_int = (
        (not x.dtype.is_floating_point and not x.dtype.is_complex and x.dtype != torch.bool)
        if isinstance(x, torch.Tensor)
        else np.issubdtype(x.dtype, np.integer)
    )
    if not is_int:
        raise ValueError(f"{name} must hold integer class ids, got dtype {x.dtype}")
    if x.ndim not in (3, 4):
        raise ValueError(f"{name} must be one frame (X, Y, Z) or a batch (B, X, Y, Z), got shape {tuple(x.shape)}")


def _mask_to_bool(mask, shape, like_torch: bool):
    """Mask as bool (numpy, or torch on CUDA); raises when it holds values other than 0/1 or has the wrong shape."""
    if tuple(mask.shape) != tuple(shape):
        raise ValueError(f"mask shape {tuple(mask.shape)} does not match the labels' shape {tuple(shape)}")
    if isinstance(mask, torch.Tensor) and not like_torch:
        mask = mask.detach().cpu().numpy()
    if isinstance(mask, torch.Tensor):
        if mask.dtype != torch.bool:
            if not bool(((mask == 0) | (mask == 1)).all()):
                bad = torch.unique(mask[(mask != 0) & (mask != 1)]).tolist()[:8]
                raise ValueError(f"mask must be 0/1 or bool, found values {bad}")
            mask = mask != 0
        return mask
    mask = np.asarray(mask)
    if mask.dtype == np.bool_:
        return mask
    # uint8 masks (how Occ3D stores them) only need a max check, which numpy vectorises.
    ok = mask.max(initial=0) <= 1 if mask.dtype == np.uint8 else bool(((mask == 0) | (mask == 1)).all())
    if not ok:
        bad = np.unique(mask[(mask != 0) & (mask != 1)])[:8].tolist()
        raise ValueError(f"mask must be 0/1 or bool, found values {bad}")
    return mask != 0


def _raise_out_of_range(values: Iterable[int], num_classes: int, ignore_index: int | None) -> None:
    values = sorted({int(v) for v in values})
    allowed = f"0..{num_classes - 1}" + (f" or ignore_index {ignore_index}" if ignore_index is not None else "")
    raise ValueError(f"labels outside {allowed}: found values {values[:16]}")


def _confusion_numpy(gt: np.ndarray, pred: np.ndarray, mask, num_classes: int, ignore_index: int | None):
    k = num_classes
    if gt.dtype == np.uint8 and pred.dtype == np.uint8 and k <= 256:
        # Lookup table: ids 0..K-1 keep their row, the ignore id lands in row K, any other value in row K + 1.
        lut = np.full(256, k + 1, np.int64)
        lut[:k] = np.arange(k)
        if ignore_index is not None and k <= ignore_index < 256:
            lut[ignore_index] = k
        gt_flat, pred_flat = gt.reshape(-1), pred.reshape(-1)
        if mask is None:
            table = _count_all(gt_flat, pred_flat, lut, k + 2)
        else:
            table = _count_masked(gt_flat, pred_flat, mask.reshape(-1).view(np.uint8), lut, k + 2)
        if table[k + 1].any() or table[:, k + 1].any():
            keep = slice(None) if mask is None else mask
            evaluated = np.concatenate([gt[keep].ravel(), pred[keep].ravel()]).astype(np.int64)
            bad = evaluated[evaluated >= k]
            if ignore_index is not None:
                bad = bad[bad != ignore_index]
            _raise_out_of_range(np.unique(bad), k, ignore_index)
        return np.ascontiguousarray(table[:k, :k])

    # Other integer dtypes: checked in int64, then counted with one bincount over the kept voxels.
    g = gt.astype(np.int64, copy=False)
    p = pred.astype(np.int64, copy=False)
    if mask is not None:
        g, p = g[mask], p[mask]
    g, p = g.ravel(), p.ravel()
    g_in = (g >= 0) & (g < k)
    p_in = (p >= 0) & (p < k)
    bad = np.concatenate([g[~g_in], p[~p_in]])
    if ignore_index is not None:
        bad = bad[bad != ignore_index]
    if bad.size:
        _raise_out_of_range(np.unique(bad), k, ignore_index)
    both = g_in & p_in
    if not both.all():
        g, p = g[both], p[both]
    return np.bincount(g * k + p, minlength=k * k).reshape(k, k).astype(np.int64, copy=False)


def _confusion_torch(gt: torch.Tensor, pred: torch.Tensor, mask, num_classes: int, ignore_index: int | None):
    """Device-side counting for tensors that live on an accelerator; returns a CPU int64 numpy matrix."""
    k = num_classes
    g = gt.reshape(-1).long()
    p = pred.reshape(-1).long()
    if mask is not None:
        keep = mask.reshape(-1)
        g, p = g[keep], p[keep]
    g_in = (g >= 0) & (g < k)
    p_in = (p >= 0) & (p < k)
    bad = torch.cat([g[~g_in], p[~p_in]])
    if ignore_index is not None:
        bad = bad[bad != ignore_index]
    if bad.numel():
        _raise_out_of_range(torch.unique(bad).tolist(), k, ignore_index)
    both = g_in & p_in
    # Voxels skipped by the ignore id go to one extra bin instead of being compacted out.
    codes = torch.where(both, g * k + p, torch.full_like(g, k * k))
    counts = torch.bincount(codes, minlength=k * k + 1)[: k * k]
    return counts.reshape(k, k).cpu().numpy().astype(np.int64, copy=False)


def confusion_matrix(gt, pred, mask=None, num_classes: int = 18, ignore_index: int | None = IGNORE_INDEX) -> np.ndarray:
    """Confusion matrix of voxel labels, indexed ``[gt][pred]``.

    Args:
        gt: ``(X, Y, Z)`` or ``(B, X, Y, Z)`` integer class ids, numpy or torch (uint8 is the fast path).
        pred: same shape as ``gt``.
        mask: optional, same shape; bool or any dtype holding only 0/1. Only voxels where it is true count.
        num_classes: K; ids must be ``0..K-1``.
        ignore_index: voxels whose gt or pred equals it are skipped; ``None`` makes every out-of-range id an error.

    Returns:
        ``(K, K)`` int64 numpy array.

    Raises:
        ValueError: float or bool labels, mismatched shapes, a mask with values other than 0/1, or ids outside
            ``0..K-1`` that are not ``ignore_index`` (the message lists them).
    """
    if num_classes < 1:
        raise ValueError(f"num_classes must be positive, got {num_classes}")
    gt, pred = _as_array(gt, "gt"), _as_array(pred, "pred")
    _check_labels(gt, "gt")
    _check_labels(pred, "pred")
    if tuple(gt.shape) != tuple(pred.shape):
        raise ValueError(f"shape mismatch: gt {tuple(gt.shape)} vs pred {tuple(pred.shape)}")
    on_device = any(isinstance(x, torch.Tensor) and x.device.type != "cpu" for x in (gt, pred))
    if on_device:
        device = gt.device if isinstance(gt, torch.Tensor) and gt.device.type != "cpu" else pred.device
        gt, pred = torch.as_tensor(gt, device=device), torch.as_tensor(pred, device=device)
        if mask is not None:
            mask = _mask_to_bool(torch.as_tensor(_as_array(mask, "mask"), device=device), gt.shape, True)
        return _confusion_torch(gt, pred, mask, num_classes, ignore_index)
    # CPU tensors share memory with their numpy view, so this costs nothing.
    gt = gt.detach().numpy() if isinstance(gt, torch.Tensor) else gt
    pred = pred.detach().numpy() if isinstance(pred, torch.Tensor) else pred
    if mask is not None:
        mask = np.ascontiguousarray(_mask_to_bool(_as_array(mask, "mask"), gt.shape, False))
    return _confusion_numpy(np.ascontiguousarray(gt), np.ascontiguousarray(pred), mask, num_classes, ignore_index)


def _check_square(cm) -> np.ndarray:
    cm = np.asarray(cm)
    if cm.ndim != 2 or cm.shape[0] != cm.shape[1]:
        raise ValueError(f"confusion matrix must be square (K, K), got shape {cm.shape}")
    return cm


def iou_from_confusion(cm, nan_without_gt: bool = False) -> np.ndarray:
    """Per-class IoU ``diag / (row + col - diag)`` of a ``[gt][pred]`` confusion matrix.

    Args:
        cm: ``(K, K)`` counts.
        nan_without_gt: SparseOcc's ``old_metrics`` variant: NaN for every class with no GT voxel, so a class that
            is only predicted is skipped instead of scoring 0.

    Returns:
        ``(K,)`` float64; NaN for a class absent from both GT and prediction (the official ``Metric_mIoU``), 0 for
        one that is only predicted (unless ``nan_without_gt``).
    """
    cm = _check_square(cm).astype(np.float64)
    tp = np.diag(cm)
    gt_count = cm.sum(axis=1)
    union = gt_count + cm.sum(axis=0) - tp
    with np.errstate(divide="ignore", invalid="ignore"):
        iou = tp / union
    iou[union == 0] = np.nan
    if nan_without_gt:
        iou[gt_count == 0] = np.nan
    return iou


def miou(cm, classes: Iterable[int] = OCC3D.semantic_ids, nan_without_gt: bool = False) -> float:
    """Mean IoU over ``classes`` (Occ3D: 0..16, free excluded), skipping NaN classes; NaN if all are NaN."""
    iou = iou_from_confusion(cm, nan_without_gt)[list(classes)]
    if np.isnan(iou).all():
        return math.nan
    return float(np.nanmean(iou))


def geometry_iou(cm, free_index: int = OCC3D.empty_index) -> float:
    """Occupied-vs-free IoU: every class but ``free_index`` counts as occupied.

    Equals SparseOcc's 2-class ``Metric_mIoU`` (labels < 17 -> occupied) on the same voxels. NaN if neither GT nor
    prediction has an occupied voxel.
    """
    cm = _check_square(cm).astype(np.int64)
    occupied = np.ones(cm.shape[0], dtype=bool)
    occupied[free_index] = False
    tp = cm[np.ix_(occupied, occupied)].sum()
    fn = cm[occupied, free_index].sum()
    fp = cm[free_index, occupied].sum()
    union = tp + fn + fp
    return float(tp / union) if union else math.nan


def surroundocc_metrics(cm17) -> dict:
    """SurroundOcc's protocol on a 17-class matrix (0 = empty, 1..16 semantic; build it with ``ignore_index=255``).

    Args:
        cm17: ``(17, 17)`` counts indexed ``[gt][pred]`` in SurroundOcc ids.

    Returns:
        ``iou``: occupied (1..16) vs empty (0) IoU; ``miou``: nanmean IoU over classes 1..16;
        ``per_class_iou``: ``(17,)`` float64 (index 0 = empty).
    """
    cm = _check_square(cm17)
    if cm.shape[0] != SURROUNDOCC.num_classes:
        raise ValueError(f"SurroundOcc uses {SURROUNDOCC.num_classes} classes ({SURROUNDOCC.empty_index} = empty), "
                         f"got a {cm.shape[0]}-class matrix")  # fmt: skip
    return {
        "iou": geometry_iou(cm, free_index=SURROUNDOCC.empty_index),
        "miou": miou(cm, classes=SURROUNDOCC.semantic_ids),
        "per_class_iou": iou_from_confusion(cm),
    }


def distance_bins(grid: VoxelGrid = OCC3D_GRID, edges: Sequence[float] = (0, 20, 40)) -> np.ndarray:
    """Masks of voxels by the horizontal distance of their centre from the ego origin.

    Args:
        grid: the voxel grid (Occ3D by default).
        edges: increasing bin edges in metres; bin ``i`` is ``edges[i] <= sqrt(x^2 + y^2) < edges[i + 1]``.

    Returns:
        ``(len(edges) - 1, X, Y, Z)`` bool; pass one slice as ``mask`` (and'ed with a camera mask) for binned mIoU.
    """
    edges = [float(e) for e in edges]
    if len(edges) < 2 or any(b <= a for a, b in zip(edges[:-1], edges[1:], strict=True)):
        raise ValueError(f"edges must be at least two increasing distances, got {edges}")
    xs = grid.axis_centers(0, dtype=torch.float64).numpy()
    ys = grid.axis_centers(1, dtype=torch.float64).numpy()
    radius = np.hypot(xs[:, None], ys[None, :])
    bins = np.stack([(radius >= lo) & (radius < hi) for lo, hi in zip(edges[:-1], edges[1:], strict=True)])
    # The distance is horizontal, so every height shares the (X, Y) pattern.
    return np.ascontiguousarray(np.broadcast_to(bins[..., None], bins.shape + (grid.shape[2],)))


class OccupancyMetric:
    """Accumulating Occ3D mIoU / IoU over frames, batches and ranks.

    Args:
        num_classes: K (Occ3D: 18, free last).
        free_index: the free class, counted in the matrix but excluded from mIoU.
        class_names: K names for ``per_class_iou``.
        mask: which visibility mask ``update`` applies: ``"camera"`` (the official setting), ``"lidar"`` or None.
        ignore_index: skipped label value.
    """

    def __init__(
        self,
        num_classes: int = OCC3D.num_classes,
        free_index: int = OCC3D.empty_index,
        class_names: Sequence[str] = OCC3D.classes,
        mask: str | None = "camera",
        ignore_index: int | None = IGNORE_INDEX,
    ) -> None:
        if mask not in _MASK_MODES:
            raise ValueError(f"mask must be one of {_MASK_MODES}, got {mask!r}")
        if len(class_names) != num_classes:
            raise ValueError(f"{len(class_names)} class names for {num_classes} classes")
        self.num_classes = num_classes
        self.free_index = free_index
        self.class_names = tuple(class_names)
        self.mask = mask
        self.ignore_index = ignore_index
        self.confusion = np.zeros((num_classes, num_classes), np.int64)

    @classmethod
    def for_space(cls, space: LabelSpace, mask: str | None = "default") -> OccupancyMetric:
        """The metric of a label space's protocol: its classes and free / empty id, under ``mask`` (``default``:
        the benchmark's own, the camera mask for Occ3D and every voxel for SurroundOcc)."""
        mask = space.check_mask(space.default_mask if mask == "default" else mask)
        return cls(space.num_classes, space.free_index, space.taxonomy.classes, mask, space.ignore_index)

    def reset(self) -> None:
        """Zero the accumulated matrix."""
        self.confusion[:] = 0

    def update(self, gt, pred, mask_camera=None, mask_lidar=None) -> None:
        """Add one frame ``(X, Y, Z)`` or a batch ``(B, X, Y, Z)``; the mask named at construction is required."""
        mask = {"camera": mask_camera, "lidar": mask_lidar, None: None}[self.mask]
        if self.mask is not None and mask is None:
            raise ValueError(f"OccupancyMetric(mask={self.mask!r}) needs mask_{self.mask} in update()")
        self.confusion += confusion_matrix(gt, pred, mask, self.num_classes, self.ignore_index)

    def merge(self, other: OccupancyMetric) -> OccupancyMetric:
        """Add another metric's counts (e.g. from a worker process); returns self."""
        if other.confusion.shape != self.confusion.shape:
            raise ValueError(f"cannot merge a {other.num_classes}-class metric into a {self.num_classes}-class one")
        self.confusion += other.confusion
        return self

    def all_reduce(self) -> None:
        """Sum the matrix over torch.distributed ranks; does nothing when no process group is initialised."""
        if not (torch.distributed.is_available() and torch.distributed.is_initialized()):
            return
        # NCCL only reduces device tensors; gloo takes CPU ones.
        device = "cuda" if torch.distributed.get_backend() == "nccl" else "cpu"
        counts = torch.from_numpy(self.confusion).to(device)
        torch.distributed.all_reduce(counts, op=torch.distributed.ReduceOp.SUM)
        self.confusion = counts.cpu().numpy().astype(np.int64)

    def compute(self) -> dict:
        """``miou`` (nanmean over non-free classes), ``iou`` (geometry), ``per_class_iou`` {name: float or None}."""
        iou = iou_from_confusion(self.confusion)
        semantic = [c for c in range(self.num_classes) if c != self.free_index]
        return {
            "miou": miou(self.confusion, semantic),
            "iou": geometry_iou(self.confusion, self.free_index),
            "per_class_iou": {
                name: None if np.isnan(value) else float(value)
                for name, value in zip(self.class_names, iou, strict=True)
            },
        }
