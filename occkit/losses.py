"""Losses of the occupancy field, as pure functions of tensors.

Occupancy logits follow occkit's order ``(B, K, X, Y, Z)`` with labels ``(B, X, Y, Z)``; ``255`` is ignored everywhere.
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import Tensor

from occkit.classes import IGNORE_INDEX

__all__ = [
    "masked_cross_entropy",
    "drop_free_cross_entropy",
    "gaussian_focal_loss",
    "weighted_l1_loss",
]


def _check_logits_labels(logits: Tensor, labels: Tensor) -> None:
    if logits.dim() < 2 or logits.shape[:1] + logits.shape[2:] != labels.shape:
        raise ValueError(
            f"logits (B, K, ...) and labels (B, ...) disagree: {tuple(logits.shape)} vs {tuple(labels.shape)}"
        )


def masked_cross_entropy(
    logits: Tensor, labels: Tensor, mask: Tensor | None = None, class_weights: Tensor | None = None
) -> Tensor:
    """Cross-entropy averaged over the voxels of ``mask`` (FlashOcc, DAOcc: ``mask_camera``).

    As mmdet's ``CrossEntropyLoss`` with ``avg_factor``: the sum of per-voxel losses (times the class weight of the
    label) over masked, non-ignored voxels, divided by the mask's voxel count, or with ``class_weights`` by the sum of
    the masked voxels' class weights (BEVDet/FlashOcc's class balance).

    Args:
        logits: ``(B, K, ...)`` unnormalised scores.
        labels: ``(B, ...)`` integer class ids, ``255`` ignored.
        mask: ``(B, ...)`` bool or 0/1, voxels that count; None counts every voxel.
        class_weights: ``(K,)`` optional per-class weights.

    Returns:
        Scalar loss; zero (with a gradient path) when the mask is empty.
    """
    _check_logits_labels(logits, labels)
    labels = labels.long()
    weight = torch.ones_like(labels, dtype=logits.dtype) if mask is None else mask.to(logits.dtype)
    valid = labels != IGNORE_INDEX
    safe_labels = torch.where(valid, labels, torch.zeros_like(labels))
    per_voxel = F.cross_entropy(logits, safe_labels, reduction="none")  # (B, ...)
    weight = weight * valid.to(logits.dtype)
    if class_weights is not None:
        weight = weight * class_weights.to(logits)[safe_labels]
        normaliser = weight.sum()
    else:
        normaliser = (mask.to(logits.dtype).sum() if mask is not None else torch.tensor(float(labels.numel())))
    return (per_voxel * weight).sum() / normaliser.clamp_min(1.0)


def drop_free_cross_entropy(
    logits: Tensor,
    labels: Tensor,
    free_index: int,
    keep_free: float = 0.2,
    generator: torch.Generator | None = None,
) -> Tensor:
    """Cross-entropy over all voxels keeping each free voxel with probability ``keep_free`` (DAOcc without mask).

    Free voxels dominate an unmasked grid (about 90% in Occ3D); dropping most of them at random, differently at every
    step, keeps the loss from collapsing onto the free class. The loss is averaged over the kept voxels.

    Args:
        logits: ``(B, K, ...)``.
        labels: ``(B, ...)``, ``255`` ignored.
        free_index: class id of free space (Occ3D: 17; SurroundOcc: 0).
        keep_free: probability of keeping a free voxel.
        generator: random source for the drop (None: torch's global one).
    """
    if not 0.0 <= keep_free <= 1.0:
        raise ValueError(f"keep_free must be in [0, 1], got {keep_free}")
    draw = torch.rand(labels.shape, generator=generator, device="cpu").to(labels.device)
    keep = (labels.long() != free_index) | (draw < keep_free)
    _check_logits_labels(logits, labels)
    labels = torch.where(keep, labels.long(), torch.full_like(labels.long(), IGNORE_INDEX))
    kept = (labels != IGNORE_INDEX).to(logits.dtype)
    return masked_cross_entropy(logits, labels, kept)


def gaussian_focal_loss(
    probs: Tensor, target: Tensor, alpha: float = 2.0, gamma: float = 4.0, eps: float = 1e-12
) -> Tensor:
    """CenterNet's focal loss for Gaussian heatmaps, summed (divide by the number of objects).

    Positives (``target == 1``) weigh ``-log(p) (1 - p)^alpha``; the rest ``-log(1 - p) p^alpha (1 - target)^gamma``,
    so cells near an object's peak are penalised less (mmdet's ``GaussianFocalLoss``).

    Args:
        probs: ``(...)`` predicted probabilities in ``(0, 1)`` (sigmoid, clamped).
        target: ``(...)`` Gaussian targets in ``[0, 1]``, exactly 1 at object centres.
    """
    positive = target.eq(1).to(probs.dtype)
    negative_weight = (1 - target).pow(gamma)
    pos_loss = -(probs + eps).log() * (1 - probs).pow(alpha) * positive
    neg_loss = -(1 - probs + eps).log() * probs.pow(alpha) * negative_weight * (1 - positive)
    return (pos_loss + neg_loss).sum()


def weighted_l1_loss(pred: Tensor, target: Tensor, weight: Tensor) -> Tensor:
    """Sum of ``weight * |pred - target|`` (divide by the number of objects); ``nan`` targets must have weight 0."""
    target = torch.where(weight > 0, target, pred.detach())
    return (weight * (pred - target).abs()).sum()
