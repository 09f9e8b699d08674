"""BEV view range extension (BVRE, DAOcc sec. 3.3): a wide LiDAR-frame BEV resampled onto the occupancy grid.

The BEV is computed over +-54 m in the (augmented) LiDAR frame, wider than the +-40 m Occ3D grid, so objects near
the grid's edge keep their context. BVRE reduces its channels with a 1x1 conv and samples it bilinearly (zeros
outside, align_corners=False) at the centres of the output grid's columns, mapped into the BEV frame by
``bev_aug @ inverse(lidar2ego) @ inverse(occ_aug)`` (Occ3D, ego-frame labels) or used as they are (SurroundOcc,
labels in the augmented LiDAR frame).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.geometry.grid import VoxelGrid
from occkit.geometry.se3 import invert_transform, transform_points

__all__ = ["RangeExtensionConfig", "RangeExtension", "occupancy_to_bev_frame"]


@dataclass(frozen=True)
class RangeExtensionConfig:
    """Where the BEV lies and which grid it is resampled onto."""

    bev_range: tuple[float, float, float, float] = (-54.0, -54.0, 54.0, 54.0)
    """Extent of the input BEV in the augmented LiDAR frame: x_min, y_min, x_max, y_max (m)."""
    in_channels: int = 512
    """Channels of the input BEV."""
    out_channels: int = 128
    """Channels after the 1x1 reduction."""
    label_frame: Literal["ego", "lidar"] = "ego"
    """Frame of the occupancy grid: ``ego`` (Occ3D) or ``lidar`` (SurroundOcc)."""


def occupancy_to_bev_frame(lidar2ego: Tensor, bev_aug: Tensor, occ_aug: Tensor, label_frame: str) -> Tensor:
    """``(B, 4, 4)`` map from the augmented occupancy frame to the augmented LiDAR (BEV) frame."""
    if label_frame == "lidar":
        return torch.eye(4, dtype=bev_aug.dtype, device=bev_aug.device).expand_as(bev_aug)
    if label_frame != "ego":
        raise ValueError(f"label_frame must be 'ego' or 'lidar', got {label_frame!r}")
    return bev_aug @ invert_transform(lidar2ego) @ invert_transform(occ_aug)


class RangeExtension(nn.Module):
    """``(B, C_in, X_bev, Y_bev)`` BEV -> ``(B, C_out, X, Y)`` on the occupancy grid's columns.

    Args:
        cfg: BEV extent and channels.
        grid: the occupancy grid; its column centres at height 0 are the sampling points.
    """

    def __init__(self, cfg: RangeExtensionConfig, grid: VoxelGrid) -> None:
        super().__init__()
        self.reduce = nn.Conv2d(cfg.in_channels, cfg.out_channels, 1) if cfg.in_channels != cfg.out_channels else None
        xs, ys = grid.axis_centers(0), grid.axis_centers(1)
        columns = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1)  # (X, Y, 2)
        columns = torch.cat([columns, torch.zeros_like(columns[..., :1])], dim=-1)  # (X, Y, 3), z = 0
        self.register_buffer("columns", columns, persistent=False)
        self.cfg = cfg
        self.out_channels = cfg.out_channels

    def to_bev_frame(self, lidar2ego: Tensor, bev_aug: Tensor, occ_aug: Tensor) -> Tensor:
        """``(B, 4, 4)`` map from the augmented occupancy frame to the augmented LiDAR (BEV) frame."""
        return occupancy_to_bev_frame(lidar2ego, bev_aug, occ_aug, self.cfg.label_frame).to(self.columns.dtype)

    def sampling_grid(self, to_bev: Tensor) -> Tensor:
        """``(B, X, Y, 2)`` ``grid_sample`` coordinates of the occupancy columns in the BEV, given the
        ``to_bev (B, 4, 4)`` of :meth:`to_bev_frame`.

        The BEV is ``(X_bev, Y_bev)``-ordered, so ``grid_sample``'s first coordinate (width) is y and its second
        (height) is x.
        """
        points = transform_points(to_bev[:, None], self.columns[None])  # (B, X, Y, 3)
        x_min, y_min, x_max, y_max = self.cfg.bev_range
        norm_x = (points[..., 0] - x_min) / (x_max - x_min) * 2 - 1
        norm_y = (points[..., 1] - y_min) / (y_max - y_min) * 2 - 1
        return torch.stack([norm_y, norm_x], dim=-1)

    def forward(self, bev: Tensor, grid: Tensor) -> Tensor:
        """``bev (B, C_in, X_bev, Y_bev)`` sampled at ``grid`` (from :meth:`sampling_grid`) -> ``(B, C_out, X, Y)``."""
        if self.reduce is not None:
            bev = self.reduce(bev)
        return F.grid_sample(bev, grid.to(bev.dtype), mode="bilinear", padding_mode="zeros", align_corners=False)
