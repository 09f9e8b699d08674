"""Channel-to-height occupancy head (FlashOcc, DAOcc): a BEV ``(B, C, X, Y)`` -> logits ``(B, K, X, Y, Z)``.

conv3x3 + ReLU, then per BEV cell an MLP ``Linear(C, 2C) -> Softplus -> Linear(2C, Z * K)`` whose outputs are the
``Z`` voxels of the column, channel ``z * K + k`` as the references lay them out. The loss is the camera-masked
cross-entropy, or without the mask the drop-free cross-entropy (DAOcc), optionally class-balanced (BEVDet), plus an
optional Lovasz-softmax term over the same voxels.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from occkit.classes import OCC3D, OCC3D_TO_OPENOCC, OPENOCC
from occkit.geometry.grid import OCC3D_GRID
from occkit.losses import (
    CountedVoxels,
    class_weights_from_frequencies,
    counted_cross_entropy,
    counted_lovasz_softmax,
    drop_free_cross_entropy,
)
from occkit.types import OccPrediction

__all__ = ["OccupancyHeadConfig", "OccupancyHead", "OCC3D_CLASS_FREQUENCIES", "class_frequencies",
           "occupancy_prediction", "column_mlp"]

#: Voxel counts per Occ3D class (0..16, 17 = free) over the nuScenes train split, as BEVDet's class balance uses.
OCC3D_CLASS_FREQUENCIES = (
    944004, 1897170, 152386, 2391677, 16957802, 724139, 189027, 2074468, 413451, 2384460, 5916653, 175883646,
    4275424, 51393615, 61411620, 105975596, 116424404, 1892500630,
)  # fmt: skip


@dataclass(frozen=True)
class OccupancyHeadConfig:
    """Channel-to-height head and its loss."""

    in_channels: int = 128
    """Channels of the BEV."""
    hidden_channels: int = 128
    """Channels after the conv3x3; the MLP's hidden layer has twice as many."""
    height: int = OCC3D_GRID.shape[2]
    """Voxels per column (Z)."""
    num_classes: int = OCC3D.num_classes
    """Classes, free space included (Occ3D: 18, free = 17; SurroundOcc: 17, empty = 0)."""
    free_index: int = OCC3D.empty_index
    """Class id of free/empty space."""
    use_mask: bool = True
    """Cross-entropy over the camera-visible voxels only (``mask_camera``); False: drop-free CE over all voxels."""
    keep_free: float = 0.2
    """Without the mask: probability of keeping each free voxel in the loss."""
    class_balance: bool = False
    """Weight classes by 1 / ln(frequency + 0.001) with Occ3D's training frequencies (BEVDet), or their OpenOcc v2
    form (:func:`class_frequencies`)."""
    lovasz_weight: float = 0.0
    """Weight of a Lovasz-softmax term (the IoU surrogate of OccFormer and others) over the voxels the cross-entropy
    counts, masked or all; 0 (DAOcc, FlashOcc): cross-entropy only."""


def class_frequencies(num_classes: int, free_index: int) -> tuple[int, ...]:
    """The training voxel counts per class that ``class_balance`` weights by: Occ3D's (18 classes, free = 17), or
    the same voxels in OpenOcc v2's classes (17, free = 16; Occ3D's ``others`` counted as free, as the labels are
    converted). Other classes: ValueError."""
    if (num_classes, free_index) == (OCC3D.num_classes, OCC3D.empty_index):
        return OCC3D_CLASS_FREQUENCIES
    if (num_classes, free_index) == (OPENOCC.num_classes, OPENOCC.empty_index):
        counts = [0] * OPENOCC.num_classes
        for occ3d_id, count in enumerate(OCC3D_CLASS_FREQUENCIES):
            counts[OCC3D_TO_OPENOCC[occ3d_id]] += count
        return tuple(counts)
    raise ValueError(f"class_balance knows the class frequencies of Occ3D (18 classes, free = 17) and OpenOcc v2 (17, "
                     f"free = 16), not of {num_classes} classes with free / empty id {free_index}")  # fmt: skip


def occupancy_prediction(logits: Tensor) -> OccPrediction:
    """Class ids ``(B, X, Y, Z)`` uint8 from logits ``(B, K, X, Y, Z)``: what every model's ``predict`` returns."""
    return OccPrediction(semantics=logits.argmax(dim=1).to(torch.uint8))


def column_mlp(channels: int, outputs: int) -> nn.Sequential:
    """The per-BEV-cell MLP of a channel-to-height head, ``Linear(C, 2C) -> Softplus -> Linear(2C, outputs)``
    (``outputs`` = the column's voxels x values per voxel)."""
    return nn.Sequential(nn.Linear(channels, 2 * channels), nn.Softplus(), nn.Linear(2 * channels, outputs))


class OccupancyHead(nn.Module):
    """``forward(bev (B, C, X, Y)) -> logits (B, K, X, Y, Z)``; ``loss(logits, labels, mask)``."""

    def __init__(self, cfg: OccupancyHeadConfig) -> None:
        super().__init__()
        self.conv = nn.Sequential(nn.Conv2d(cfg.in_channels, cfg.hidden_channels, 3, padding=1), nn.ReLU(inplace=True))
        self.predictor = column_mlp(cfg.hidden_channels, cfg.height * cfg.num_classes)
        if cfg.class_balance:
            weights = class_weights_from_frequencies(class_frequencies(cfg.num_classes, cfg.free_index))
            self.register_buffer("class_weights", weights, persistent=False)
        else:
            self.class_weights = None
        self.cfg = cfg

    def forward(self, bev: Tensor) -> Tensor:
        return self.logits(self.columns(bev))

    def columns(self, bev: Tensor) -> Tensor:
        """The per-cell features ``(B, X, Y, C_hidden)`` after the conv3x3 (what a flow head reads too)."""
        return self.conv(bev).permute(0, 2, 3, 1)

    def logits(self, columns: Tensor) -> Tensor:
        """Logits ``(B, K, X, Y, Z)`` of the per-cell features ``(B, X, Y, C_hidden)``.

        Under bf16 autocast the last projection runs in float32: bf16 keeps 8 significant bits, so logits rounded to it
        tie where fp32's differ by less than 0.4% and the arg-max flips there (fp16's 11 bits do not need it).
        """
        batch, x, y, _ = columns.shape
        hidden, last = self.predictor[:-1](columns), self.predictor[-1]
        device = columns.device.type
        bf16 = torch.amp.is_autocast_available(device) and torch.is_autocast_enabled(device)
        if bf16 and torch.get_autocast_dtype(device) == torch.bfloat16:
            with torch.autocast(device, enabled=False):
                flat = last(hidden.float())
        else:
            flat = last(hidden)
        logits = flat.view(batch, x, y, self.cfg.height, self.cfg.num_classes)  # (B, X, Y, Z, K)
        return logits.permute(0, 4, 1, 2, 3)

    def loss(
        self, logits: Tensor, labels: Tensor, mask_camera: Tensor | None, voxels: CountedVoxels | None = None
    ) -> dict[str, Tensor]:
        """Loss terms of ``logits (B, K, X, Y, Z)`` against ``labels (B, X, Y, Z)``: ``occupancy`` (cross-entropy)
        and, with ``lovasz_weight``, ``lovasz`` (already weighted).

        ``voxels``: the counted voxels of these logits (:meth:`counted_voxels`), when the caller gathered them for
        terms of its own; gathered here otherwise.
        """
        if voxels is None and (self.cfg.use_mask or self.cfg.lovasz_weight > 0):
            voxels = self.counted_voxels(logits, labels, mask_camera)
        if self.cfg.use_mask:
            losses = {"occupancy": counted_cross_entropy(voxels, self.class_weights)}
        else:
            losses = {"occupancy": drop_free_cross_entropy(logits, labels, self.cfg.free_index, self.cfg.keep_free)}
        if self.cfg.lovasz_weight > 0:
            losses["lovasz"] = self.cfg.lovasz_weight * counted_lovasz_softmax(voxels)
        return losses

    def counted_voxels(self, logits: Tensor, labels: Tensor, mask_camera: Tensor | None) -> CountedVoxels:
        """The voxels this head's loss counts: the camera-visible ones with ``use_mask``, else every voxel."""
        if self.cfg.use_mask and mask_camera is None:
            raise ValueError("the occupancy loss uses mask_camera (use_mask=True) but the batch has none")
        return CountedVoxels(logits, labels, mask_camera.bool() if self.cfg.use_mask else None)
