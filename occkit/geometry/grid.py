"""Axis-aligned voxel grids: the single home of grid arithmetic in occkit.

A grid is a range ``[x_min, y_min, z_min, x_max, y_max, z_max]`` (metres) cut into voxels of
``voxel_size`` metres. Voxel ``(i, j, k)`` covers ``[min + idx * size, min + (idx + 1) * size)`` on each axis,
its centre is ``min + (idx + 0.5) * size``, and indices run in Occ3D order ``(x, y, z)``.
Dataset readers, view transforms, heads, metrics and the synthetic world all take the same object.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["VoxelGrid", "OCC3D_GRID", "SURROUNDOCC_GRID"]


def _as_triple(value: float | tuple[float, ...] | list[float], name: str) -> tuple[float, float, float]:
    if isinstance(value, (int, float)):
        return (float(value),) * 3
    values = tuple(float(v) for v in value)
    if len(values) != 3:
        raise ValueError(f"{name} must be one number or three (x, y, z), got {value!r}")
    return values  # type: ignore[return-value]


@dataclass(frozen=True)
class VoxelGrid:
    """A regular 3D grid over a metric range.

    Args:
        point_cloud_range: ``(x_min, y_min, z_min, x_max, y_max, z_max)`` in metres.
        voxel_size: edge length in metres, one number or ``(sx, sy, sz)``.

    Example:
        >>> VoxelGrid((-40, -40, -1, 40, 40, 5.4), 0.4).shape
        (200, 200, 16)
    """

    point_cloud_range: tuple[float, float, float, float, float, float]
    voxel_size: tuple[float, float, float]

    def __init__(self, point_cloud_range, voxel_size) -> None:
        bounds = tuple(float(v) for v in point_cloud_range)
        if len(bounds) != 6:
            raise ValueError(f"point_cloud_range must have 6 numbers (min xyz, max xyz), got {point_cloud_range!r}")
        size = _as_triple(voxel_size, "voxel_size")
        if any(s <= 0 for s in size):
            raise ValueError(f"voxel_size must be positive, got {size}")
        for axis, name in enumerate("xyz"):
            extent = bounds[axis + 3] - bounds[axis]
            if extent <= 0:
                raise ValueError(f"point_cloud_range has {name}_max <= {name}_min: {bounds}")
            cells = extent / size[axis]
            # A range that is not a whole number of voxels would make shape and centres disagree.
            if abs(cells - round(cells)) > 1e-4:
                raise ValueError(
                    f"{name} extent {extent:g} m is not a whole number of {size[axis]:g} m voxels ({cells:.4f})"
                )
        object.__setattr__(self, "point_cloud_range", bounds)
        object.__setattr__(self, "voxel_size", size)

    @classmethod
    def from_shape(cls, point_cloud_range, shape) -> VoxelGrid:
        """The grid that cuts ``point_cloud_range`` into ``shape = (X, Y, Z)`` voxels."""
        bounds = tuple(float(v) for v in point_cloud_range)
        if len(bounds) != 6 or len(shape) != 3 or any(int(n) < 1 for n in shape):
            raise ValueError(f"need a 6-number range and 3 positive voxel counts, got {point_cloud_range!r}, {shape!r}")
        grid = cls(bounds, [(bounds[i + 3] - bounds[i]) / int(shape[i]) for i in range(3)])
        if grid.shape != tuple(int(n) for n in shape):
            raise ValueError(f"{tuple(shape)} voxels do not divide range {bounds} evenly")
        return grid

    # ------------------------------------------------------------------ sizes
    @property
    def lower(self) -> tuple[float, float, float]:
        """Minimum corner ``(x_min, y_min, z_min)`` in metres."""
        return self.point_cloud_range[:3]  # type: ignore[return-value]

    @property
    def upper(self) -> tuple[float, float, float]:
        """Maximum corner ``(x_max, y_max, z_max)`` in metres."""
        return self.point_cloud_range[3:]  # type: ignore[return-value]

    @property
    def shape(self) -> tuple[int, int, int]:
        """Number of voxels ``(X, Y, Z)``."""
        return tuple(int(round((self.upper[a] - self.lower[a]) / self.voxel_size[a])) for a in range(3))  # type: ignore[return-value]

    @property
    def num_voxels(self) -> int:
        return math.prod(self.shape)

    # ------------------------------------------------------------- tensors
    def lower_tensor(self, device=None, dtype=torch.float32) -> Tensor:
        """``(3,)`` minimum corner."""
        return torch.tensor(self.lower, device=device, dtype=dtype)

    def size_tensor(self, device=None, dtype=torch.float32) -> Tensor:
        """``(3,)`` voxel edge lengths."""
        return torch.tensor(self.voxel_size, device=device, dtype=dtype)

    def axis_centers(self, axis: int, device=None, dtype=torch.float32) -> Tensor:
        """``(shape[axis],)`` centre coordinates along one axis (0 = x, 1 = y, 2 = z)."""
        idx = torch.arange(self.shape[axis], device=device, dtype=dtype)
        return (idx + 0.5) * self.voxel_size[axis] + self.lower[axis]

    def centers(self, device=None, dtype=torch.float32) -> Tensor:
        """``(X, Y, Z, 3)`` metric centres of every voxel, indexed ``[i, j, k]``."""
        xs, ys, zs = (self.axis_centers(a, device, dtype) for a in range(3))
        return torch.stack(torch.meshgrid(xs, ys, zs, indexing="ij"), dim=-1)

    # ---------------------------------------------------------- conversions
    def world_to_index(self, points: Tensor) -> tuple[Tensor, Tensor]:
        """Voxel index of metric points.

        Args:
            points: ``(..., 3)`` metric ``(x, y, z)``.

        Returns:
            index: ``(..., 3)`` int64 ``floor((p - lower) / size)``; meaningful only where ``inside``.
            inside: ``(..., )`` bool, true where the point lies in ``[lower, upper)`` on every axis.
        """
        lower = self.lower_tensor(points.device, points.dtype)
        size = self.size_tensor(points.device, points.dtype)
        index = torch.floor((points - lower) / size).long()
        shape = torch.tensor(self.shape, device=points.device)
        inside = ((index >= 0) & (index < shape)).all(dim=-1)
        return index, inside

    def index_to_world(self, index: Tensor, dtype=torch.float32) -> Tensor:
        """Metric centres ``(..., 3)`` of integer voxel indices ``(..., 3)``."""
        lower = self.lower_tensor(index.device, dtype)
        size = self.size_tensor(index.device, dtype)
        return (index.to(dtype) + 0.5) * size + lower

    def ravel_index(self, index: Tensor) -> Tensor:
        """Flat index ``(...,)`` int64 of ``(..., 3)`` voxel indices in C order over ``(X, Y, Z)``."""
        _, ny, nz = self.shape
        return (index[..., 0] * ny + index[..., 1]) * nz + index[..., 2]

    def unravel_index(self, flat: Tensor) -> Tensor:
        """Inverse of :meth:`ravel_index`: ``(...,)`` int64 -> ``(..., 3)`` int64."""
        _, ny, nz = self.shape
        return torch.stack((flat // (ny * nz), (flat // nz) % ny, flat % nz), dim=-1)

    def to_dict(self) -> dict:
        return {"point_cloud_range": list(self.point_cloud_range), "voxel_size": list(self.voxel_size)}

    def __repr__(self) -> str:
        return (
            f"VoxelGrid(range={list(self.point_cloud_range)}, voxel_size={list(self.voxel_size)}, shape={self.shape})"
        )


#: Occ3D-nuScenes: ego frame, 200 x 200 x 16 voxels of 0.4 m.
OCC3D_GRID = VoxelGrid((-40.0, -40.0, -1.0, 40.0, 40.0, 5.4), 0.4)
#: SurroundOcc (nuScenes): LiDAR frame, 200 x 200 x 16 voxels of 0.5 m.
SURROUNDOCC_GRID = VoxelGrid((-50.0, -50.0, -5.0, 50.0, 50.0, 3.0), 0.5)
