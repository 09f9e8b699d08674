"""Hard voxelization of point clouds, vectorised in pure torch.

Semantics are those of mmdetection3d's hard voxelization (the ``hard_voxelize`` CPU kernel) followed by its mean
voxel feature encoder (``HardSimpleVFE``), the LiDAR front end of BEVFusion and DAOcc:

* points are visited in input order and points outside the grid are skipped;
* a voxel gets the next slot the first time one of its points is seen, unless ``max_voxels`` slots are taken, in
  which case the voxel and all its points are dropped;
* a voxel keeps its first ``max_points_per_voxel`` points, later ones are dropped;
* the voxel feature is the mean of its kept points, all channels.

Voxels therefore come out ordered by first appearance, exactly as mmdet3d orders them. The result is
deterministic on every device: the only float reduction is a sum over a dense ``(V, M, C)`` tensor.

Coordinates are occkit voxel indices ``(x, y, z)``. mmdet3d returns ``(z, y, x)`` and spconv wants
``(batch, d0, d1, d2)``; callers convert in one place, ``occkit.models.sparse.sparse_tensor_from_voxels``.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

from occkit.geometry.grid import VoxelGrid

__all__ = ["Voxels", "hard_voxelize", "voxelize_batch"]


@dataclass(frozen=True)
class Voxels:
    """Result of :func:`hard_voxelize`, ``V`` voxels ordered by first appearance.

    Attributes:
        features: ``(V, C)`` mean of the kept points of each voxel, in the points' dtype.
        coords: ``(V, 3)`` int64 voxel indices ``(x, y, z)`` (mmdet3d returns ``(z, y, x)``; see module docstring).
        counts: ``(V,)`` int64 number of kept points, in ``[1, max_points_per_voxel]``.
        points: ``(V, M, C)`` kept points in input order, zero padded, or ``None`` unless requested.
    """

    features: Tensor
    coords: Tensor
    counts: Tensor
    points: Tensor | None = None


def _check_inputs(points: Tensor, max_points_per_voxel: int, max_voxels: int) -> None:
    if points.dim() != 2 or points.shape[1] < 3:
        raise ValueError(f"points must have shape (N, >=3), got {tuple(points.shape)}")
    if not points.is_floating_point():
        raise TypeError(f"points must be a floating point tensor, got {points.dtype}")
    if max_points_per_voxel < 1:
        raise ValueError(f"max_points_per_voxel must be >= 1, got {max_points_per_voxel}")
    if max_voxels < 1:
        raise ValueError(f"max_voxels must be >= 1, got {max_voxels}")


def _slots_and_ranks(flat: Tensor) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Order voxels by first appearance and points by arrival within their voxel.

    Args:
        flat: ``(P,)`` int64 flat voxel index of each in-grid point, in input order.

    Returns:
        perm: ``(P,)`` positions into ``flat`` grouped by voxel, input order within a voxel.
        slot: ``(P,)`` first-appearance rank of the voxel of ``flat[perm]``.
        rank: ``(P,)`` arrival rank of ``flat[perm]`` within its voxel.
        voxel_flat: ``(U,)`` flat index of the voxel holding each slot.
        population: ``(U,)`` number of points of the voxel holding each slot.
    """
    unique_flat, inverse, sizes = torch.unique(flat, return_inverse=True, return_counts=True)
    # A stable sort keeps input order inside each voxel, so the head of each group is the voxel's first point.
    sorted_voxel, perm = torch.sort(inverse, stable=True)
    starts = torch.cumsum(sizes, 0) - sizes
    first_seen = perm[starts]
    order = torch.argsort(first_seen)
    slot_of_voxel = torch.empty_like(order)
    slot_of_voxel[order] = torch.arange(order.numel(), device=flat.device)
    rank = torch.arange(flat.numel(), device=flat.device) - starts[sorted_voxel]
    return perm, slot_of_voxel[sorted_voxel], rank, unique_flat[order], sizes[order]


def hard_voxelize(
    points: Tensor,
    grid: VoxelGrid,
    max_points_per_voxel: int,
    max_voxels: int,
    return_points: bool = False,
) -> Voxels:
    """Group points into at most ``max_voxels`` voxels of at most ``max_points_per_voxel`` points each.

    Args:
        points: ``(N, C)`` floating point, ``C >= 3``, metric ``(x, y, z)`` first, then any extra channels.
        grid: voxel grid; points outside ``[lower, upper)`` are skipped.
        max_points_per_voxel: ``M``, points kept per voxel (the first ``M`` in input order).
        max_voxels: voxels kept (the first ``max_voxels`` to appear).
        return_points: also return the zero-padded ``(V, M, C)`` kept points.

    Returns:
        :class:`Voxels` with ``V <= max_voxels`` voxels ordered by first appearance; ``features`` is
        differentiable with respect to ``points``.
    """
    _check_inputs(points, max_points_per_voxel, max_voxels)
    num_points, channels = points.shape
    index, inside = grid.world_to_index(points[:, :3].detach())
    in_grid = torch.nonzero(inside).squeeze(1)
    perm, slot, rank, voxel_flat, population = _slots_and_ranks(grid.ravel_index(index[in_grid]))

    num_voxels = min(voxel_flat.numel(), max_voxels)
    kept = (rank < max_points_per_voxel) & (slot < num_voxels)
    # Every (slot, rank) cell is written at most once, so this integer scatter is deterministic; empty cells point
    # at a zero row appended to the points, which keeps the gather differentiable and the padding exact zeros.
    cell_source = torch.full((num_voxels * max_points_per_voxel,), num_points, dtype=torch.long, device=points.device)
    cell_source[slot[kept] * max_points_per_voxel + rank[kept]] = in_grid[perm[kept]]
    padded_source = torch.cat((points, points.new_zeros(1, channels)))
    voxel_points = padded_source[cell_source].view(num_voxels, max_points_per_voxel, channels)

    counts = population[:num_voxels].clamp(max=max_points_per_voxel)
    features = voxel_points.sum(dim=1) / counts.to(points.dtype).unsqueeze(1)
    coords = grid.unravel_index(voxel_flat[:num_voxels])
    return Voxels(features, coords, counts, voxel_points if return_points else None)


def voxelize_batch(
    point_clouds: list[Tensor] | tuple[Tensor, ...],
    grid: VoxelGrid,
    max_points_per_voxel: int,
    max_voxels: int,
) -> tuple[Tensor, Tensor, Tensor]:
    """Voxelize each cloud independently and concatenate, the input form of a sparse encoder.

    Args:
        point_clouds: ``B`` tensors ``(N_i, C)`` with the same ``C``, dtype and device.
        grid, max_points_per_voxel, max_voxels: as in :func:`hard_voxelize`, limits applied per cloud.

    Returns:
        features: ``(V, C)`` mean point of each voxel.
        coords: ``(V, 4)`` int64 ``(batch, x, y, z)``.
        counts: ``(V,)`` int64 kept points per voxel.
    """
    if len(point_clouds) == 0:
        raise ValueError("point_clouds must hold at least one (N, C) tensor, got an empty sequence")
    results = [hard_voxelize(p, grid, max_points_per_voxel, max_voxels) for p in point_clouds]
    channels = [r.features.shape[1] for r in results]
    if len(set(channels)) != 1:
        raise ValueError(f"point_clouds must share one channel count C, got {channels}")
    coords = torch.cat([torch.nn.functional.pad(r.coords, (1, 0), value=b) for b, r in enumerate(results)])
    features = torch.cat([r.features for r in results])
    counts = torch.cat([r.counts for r in results])
    return features, coords, counts
