"""Collating samples into a :class:`~occkit.types.Batch`: stack what has one shape, pad points, list boxes."""

from __future__ import annotations

import torch
from torch import Tensor

from occkit.types import Batch, Sample

__all__ = ["collate"]

_STACKED = (
    "images",
    "intrinsics",
    "cam2ego",
    "img_aug",
    "camera_mask",
    "lidar2ego",
    "ego2global",
    "bev_aug",
    "occ_aug",
    "voxel_semantics",
    "mask_camera",
    "mask_lidar",
    "voxel_flow",
    "voxel_instances",
    "depth_maps",
    "height_maps",
    "history_images",
    "history_intrinsics",
    "history_cam2ego",
    "history_img_aug",
    "history_ego2global",
    "history_padded",
)


def _values(samples: list[Sample], name: str) -> list | None:
    """Every sample's ``name``; None when none has it (a mix is an error: the batch would be ragged)."""
    values = [getattr(s, name) for s in samples]
    if all(v is None for v in values):
        return None
    if any(v is None for v in values):
        missing = [s.token for s, v in zip(samples, values, strict=True) if v is None]
        raise ValueError(f"cannot collate {name}: samples {', '.join(missing)} have none")
    return values


def _stack(samples: list[Sample], name: str) -> Tensor | None:
    values = _values(samples, name)
    return None if values is None else torch.stack(values)


def collate(samples: list[Sample | None]) -> Batch:
    """Batch samples; ``None`` entries (samples skipped by ``on_error="skip"``) are left out.

    When every sample was skipped the batch is empty (``len(batch) == 0``, no tensors): evaluation and prediction
    loops pass over it. Points are padded to the longest cloud with zeros and their counts kept in ``num_points``.
    """
    kept = [s for s in samples if s is not None]
    batch = Batch(tokens=[s.token for s in kept], scenes=[s.scene for s in kept])
    if not kept:
        return batch
    for name in _STACKED:
        setattr(batch, name, _stack(kept, name))
    batch.history_tokens = _values(kept, "history_tokens")
    if any(s.points is not None for s in kept):
        clouds = [s.points if s.points is not None else torch.zeros(0, 5) for s in kept]
        batch.num_points = torch.tensor([c.shape[0] for c in clouds], dtype=torch.int64)
        batch.points = torch.nn.utils.rnn.pad_sequence(clouds, batch_first=True)
    if any(s.boxes is not None for s in kept):
        batch.boxes = [s.boxes if s.boxes is not None else torch.zeros(0, 9) for s in kept]
        batch.box_labels = [
            s.box_labels if s.box_labels is not None else torch.zeros(0, dtype=torch.int64) for s in kept
        ]
    return batch
