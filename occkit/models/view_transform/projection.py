"""DAOcc's projection-and-sampling view transform: voxel centres -> cameras -> bilinear samples -> BEV.

Paper V1 (DAOcc sec. 3.2): the centres of a ``X x Y x Z`` voxel grid in the (augmented) LiDAR frame are projected
into every camera through the batch's own matrices (BEV augmentation undone, LiDAR -> ego -> camera, intrinsics,
image augmentation applied), kept where in front of the camera and inside the augmented image, sampled bilinearly
from the image features and averaged over the cameras that see them; height is folded into channels, giving
``(B, Z * C, X, Y)``. V2 (the public code's later variant) takes only the first camera that sees a point.

The sampling is a :class:`SamplingPlan`: which (sample, camera) sees which voxel and where. For one rig it is
computed once and reused (:mod:`occkit.models.base`), like the precomputed ranks of LSS.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar, Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.geometry.grid import VoxelGrid
from occkit.geometry.se3 import invert_transform
from occkit.models.base import FIXED_CALIBRATION_RETIRED

__all__ = ["ProjectionConfig", "SamplingPlan", "projection_matrices", "make_sampling_plan", "ProjectionViewTransform"]


@dataclass(frozen=True)
class ProjectionConfig:
    """Voxel-centre projection view transform."""

    #: Keys of older versions, skipped on load (see :func:`occkit.config.from_dict`).
    RETIRED_KEYS: ClassVar[dict[str, str]] = {"fixed_calibration": FIXED_CALIBRATION_RETIRED}

    point_cloud_range: tuple[float, float, float, float, float, float] = (-54.0, -54.0, -5.0, 54.0, 54.0, 3.0)
    """Extent of the sampled volume in the LiDAR frame (x_min, y_min, z_min, x_max, y_max, z_max), metres."""
    grid_size: tuple[int, int, int] = (180, 180, 10)
    """Voxels along x, y, z; the BEV comes out ``X x Y`` with ``Z * out_channels`` channels."""
    in_channels: int = 256
    """Channels of the image features."""
    out_channels: int = 128
    """Channels after the 1x1 reduction applied before sampling."""
    mode: Literal["average", "first"] = "average"
    """``average``: mean over the cameras that see a voxel (paper V1); ``first``: the first such camera (code V2)."""
    align_corners: bool = False
    """False: occkit's continuous pixel convention (docs/conventions.md), the image's edges at the feature map's
    edges. True: the public code's V2 (``BEVTransformV2``), which samples with ``align_corners=True``, so that the
    image's edges fall on the centres of the first and last feature cells; weights trained by that code expect it."""


@dataclass
class SamplingPlan:
    """Where each (sample, camera) samples its image features, flattened over the visible voxels.

    ``L`` is the most voxels any one (sample, camera) sees; shorter lists are padded and point at a dummy row.
    """

    grid: Tensor
    """``(B * N, L, 1, 2)`` image coordinates normalised by the image size (-1 and 1 at its edges), for
    ``grid_sample`` with the config's ``align_corners``."""
    target: Tensor
    """``(B * N, L)`` int64 flat row ``b * P + p`` of the voxel each sample feeds; ``B * P`` for padding."""
    weight: Tensor
    """``(B * N, L)`` 1 / number of cameras averaged at the voxel (0 for padding)."""
    num_voxels: int
    """``P = X * Y * Z``."""


def projection_matrices(
    intrinsics: Tensor, cam2ego: Tensor, img_aug: Tensor, lidar2ego: Tensor, bev_aug: Tensor
) -> Tensor:
    """``(B, N, 3, 4)`` maps augmented-LiDAR points to homogeneous augmented-image pixels ``w * (u', v', 1)``.

    ``img_aug @ K @ ego2cam @ lidar2ego @ inverse(bev_aug)``; ``img_aug`` is affine, so it commutes with the
    perspective division.

    Args:
        intrinsics: ``(B, N, 3, 3)``; cam2ego: ``(B, N, 4, 4)``; img_aug: ``(B, N, 3, 3)``;
        lidar2ego, bev_aug: ``(B, 4, 4)``.
    """
    aug_lidar2ego = lidar2ego @ invert_transform(bev_aug)  # (B, 4, 4)
    lidar2cam = invert_transform(cam2ego) @ aug_lidar2ego[:, None]  # (B, N, 4, 4)
    return img_aug @ intrinsics @ lidar2cam[..., :3, :]


def make_sampling_plan(
    centers: Tensor,
    projection: Tensor,
    image_size: tuple[int, int],
    camera_mask: Tensor | None = None,
    mode: str = "average",
    eps: float = 1e-5,
) -> SamplingPlan:
    """Project voxel centres into every camera and list the visible ones.

    Args:
        centers: ``(P, 3)`` voxel centres in the augmented LiDAR frame.
        projection: ``(B, N, 3, 4)`` from :func:`projection_matrices`.
        image_size: ``(H, W)`` of the augmented images, pixels.
        camera_mask: ``(B, N)`` bool, False for failed or absent cameras; None: all work.
        mode: ``average`` or ``first``.

    Returns:
        The plan; a voxel seen by no camera gets no entry (its feature stays zero).
    """
    batch, cameras = projection.shape[:2]
    height, width = image_size
    homogeneous = torch.cat([centers, centers.new_ones(centers.shape[0], 1)], dim=1)  # (P, 4)
    pixels = torch.einsum("bnij,pj->bnpi", projection, homogeneous)  # (B, N, P, 3)
    depth = pixels[..., 2]
    uv = pixels[..., :2] / depth.clamp_min(eps)[..., None]
    visible = (depth > eps) & (uv[..., 0] > 0) & (uv[..., 0] < width) & (uv[..., 1] > 0) & (uv[..., 1] < height)
    if camera_mask is not None:
        visible &= camera_mask.to(torch.bool)[..., None]
    if mode == "first":
        visible &= visible.cumsum(dim=1) == 1
    elif mode != "average":
        raise ValueError(f"projection mode must be 'average' or 'first', got {mode!r}")
    counts = visible.sum(dim=1, keepdim=True).clamp_min(1)  # (B, 1, P)
    visible = visible.flatten(0, 1)  # (B*N, P)
    lengths = visible.sum(dim=1)
    longest = int(lengths.max()) if lengths.numel() else 0
    # Stable sort puts the visible voxels of each (sample, camera) first, in voxel order.
    order = torch.argsort((~visible).to(torch.uint8), dim=1, stable=True)[:, :longest]  # (B*N, L)
    valid = torch.arange(longest, device=visible.device)[None] < lengths[:, None]
    normalised = uv.flatten(0, 1) / uv.new_tensor([width, height]) * 2 - 1  # (B*N, P, 2)
    grid = torch.gather(normalised, 1, order[..., None].expand(-1, -1, 2))
    grid = torch.where(valid[..., None], grid, torch.zeros_like(grid))
    num_voxels = centers.shape[0]
    sample_offset = torch.arange(batch, device=order.device).repeat_interleave(cameras)[:, None] * num_voxels
    target = torch.where(valid, order + sample_offset, torch.full_like(order, batch * num_voxels))
    weight = torch.gather((1.0 / counts).expand(-1, cameras, -1).flatten(0, 1), 1, order)
    weight = torch.where(valid, weight, torch.zeros_like(weight))
    return SamplingPlan(grid=grid[:, :, None], target=target, weight=weight, num_voxels=num_voxels)


class ProjectionViewTransform(nn.Module):
    """Image features ``(B, N, C_in, h, w)`` -> BEV ``(B, Z * C_out, X, Y)`` in the augmented LiDAR frame."""

    def __init__(self, cfg: ProjectionConfig) -> None:
        super().__init__()
        self.grid = VoxelGrid.from_shape(cfg.point_cloud_range, cfg.grid_size)
        self.register_buffer("centers", self.grid.centers().reshape(-1, 3), persistent=False)  # (X*Y*Z, 3)
        self.reduce = nn.Conv2d(cfg.in_channels, cfg.out_channels, 1) if cfg.in_channels != cfg.out_channels else None
        self.cfg = cfg
        self.out_channels = cfg.out_channels * cfg.grid_size[2]

    def plan(
        self,
        intrinsics: Tensor,
        cam2ego: Tensor,
        img_aug: Tensor,
        lidar2ego: Tensor,
        bev_aug: Tensor,
        image_size: tuple[int, int],
        camera_mask: Tensor | None = None,
    ) -> SamplingPlan:
        """The sampling plan for a batch's geometry (shapes as in :func:`projection_matrices`)."""
        projection = projection_matrices(intrinsics, cam2ego, img_aug, lidar2ego, bev_aug)
        return make_sampling_plan(self.centers, projection.float(), image_size, camera_mask, self.cfg.mode)

    def forward(self, features: Tensor, plan: SamplingPlan) -> Tensor:
        """Sample and average. ``features (B, N, C_in, h, w)`` -> ``(B, Z * C_out, X, Y)``.

        The samples are added camera by camera: within one (sample, camera) every voxel is hit once (padding aside),
        but a voxel seen by two cameras is hit twice, and one ``index_add`` over all cameras exports to a
        ScatterND(reduction="add") that onnxruntime spreads over threads without guarding repeated rows. On a CPU
        the order of the additions, and so the result, is the same as one ``index_add``.
        """
        batch = features.shape[0]
        flat = features.flatten(0, 1)  # (B*N, C_in, h, w)
        if self.reduce is not None:
            flat = self.reduce(flat)
        channels = flat.shape[1]
        sampled = F.grid_sample(flat, plan.grid.to(flat.dtype), mode="bilinear", padding_mode="zeros",
                                align_corners=self.cfg.align_corners)  # (B*N, C, L, 1)
        sampled = sampled[..., 0].transpose(1, 2) * plan.weight[..., None].to(flat.dtype)  # (B*N, L, C)
        volume = flat.new_zeros(batch * plan.num_voxels + 1, channels)  # last row absorbs padding
        for camera in range(sampled.shape[0]):
            volume.index_add_(0, plan.target[camera], sampled[camera])
        x, y, z = self.cfg.grid_size
        volume = volume[:-1].view(batch, x, y, z, channels)
        # (B, X, Y, Z, C) -> (B, Z, C, X, Y) -> (B, Z*C, X, Y): channel z * C + c, as the reference folds height.
        return volume.permute(0, 3, 4, 1, 2).reshape(batch, z * channels, x, y)
