"""Panoptic occupancy from semantic occupancy and object centres: Panoptic-FlashOcc's post-processing.

Every voxel predicted as a thing class (:data:`~occkit.classes.THING_CLASSES`) takes the instance of the nearest
predicted centre of the same class, the distance measured between voxel indices (the centre's index truncated
towards zero, as the reference's ``.int()``; ties go to the first centre, the higher-scoring). A thing voxel whose class
has no centre keeps instance 0, which RayPQ reads as one segment of its class (the reference leaves it its class id,
the same segment). Stuff and free voxels: 0. Instance ids are 1 + the centre's place in the sample's list, so they
are unique within a frame (not tracked over time).
"""

from __future__ import annotations

import torch
from torch import Tensor

from occkit.classes import DETECTION_CLASSES, OCC3D, THING_CLASSES, Taxonomy
from occkit.geometry.grid import VoxelGrid

__all__ = ["assign_instances"]

#: Voxels measured against the centres at once: bounds the ``(voxels, centres)`` distance matrix to a few MB.
_CHUNK = 16384


@torch.no_grad()
def assign_instances(semantics: Tensor, centres: list[Tensor], labels: list[Tensor], grid: VoxelGrid,
                     taxonomy: Taxonomy = OCC3D) -> Tensor:  # fmt: skip
    """Instance ids of a batch of semantic grids.

    Args:
        semantics: ``(B, X, Y, Z)`` class ids of ``taxonomy`` on ``grid``.
        centres: ``B`` tensors ``(M_b, 3)`` object centres (x, y, z in the grid's frame, metres).
        labels: ``B`` tensors ``(M_b,)`` their DETECTION_CLASSES indices.
        grid: the grid of ``semantics``.
        taxonomy: the classes of ``semantics``.

    Returns:
        ``(B, X, Y, Z)`` int32 instance ids (0: stuff, free, or a thing without a centre of its class).
    """
    if semantics.dim() != 4 or tuple(semantics.shape[1:]) != grid.shape:
        raise ValueError(f"semantics must be (B, {', '.join(map(str, grid.shape))}), got {tuple(semantics.shape)}")
    if not len(centres) == len(labels) == semantics.shape[0]:
        raise ValueError(f"{len(centres)} centre and {len(labels)} label tensors for a batch of {semantics.shape[0]}")
    device = semantics.device
    lower = torch.tensor(grid.lower, dtype=torch.float32, device=device)
    voxel = torch.tensor(grid.voxel_size, dtype=torch.float32, device=device)
    things = [(taxonomy.index(name), DETECTION_CLASSES.index(name)) for name in THING_CLASSES]
    instances = torch.zeros(semantics.shape, dtype=torch.int32, device=device)
    for b, (sample_centres, sample_labels) in enumerate(zip(centres, labels, strict=True)):
        if sample_centres.shape[0] == 0:
            continue
        centre_index = ((sample_centres.to(device).float() - lower) / voxel).int().float()  # (M, 3), truncated
        sample_labels = sample_labels.to(device)
        for occ_id, det_id in things:
            owners = (sample_labels == det_id).nonzero()[:, 0]  # this class's centres, in list order
            if owners.numel() == 0:
                continue
            voxels = (semantics[b] == occ_id).nonzero()  # (N, 3)
            for start in range(0, voxels.shape[0], _CHUNK):
                chunk = voxels[start:start + _CHUNK]
                distance = ((chunk[:, None, :].float() - centre_index[owners][None]) ** 2).sum(-1)  # (n, m)
                nearest = owners[distance.argmin(dim=1)]
                instances[b, chunk[:, 0], chunk[:, 1], chunk[:, 2]] = (nearest + 1).int()
    return instances
