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
from occkit.models.indexing import take

__all__ = [
    "ProjectionConfig",
    "SamplingPlan",
    "projection_matrices",
    "make_sampling_plan",
    "bilinear_taps",
    "weighted_rows",
    "ProjectionViewTransform",
]


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
    """Which (sample, camera) views each voxel samples, and where: voxel-major, ``M`` view slots per voxel.

    ``M`` is the most cameras that see any one voxel (1 in ``first`` mode); a voxel seen by fewer cameras has padded
    slots of weight 0. Only the geometry is here: the bilinear taps depend on the feature map's size as well and are
    derived from it at each forward pass (:func:`bilinear_taps`), which costs a few elementwise operations.
    """

    grid: Tensor
    """``(B * P, M, 2)`` image coordinates normalised by the image size (-1 and 1 at its edges), ``grid_sample``'s
    convention with the config's ``align_corners``; voxel row ``b * P + p``."""
    view: Tensor
    """``(B * P, M)`` int64 flat index ``b * N + n`` of the (sample, camera) of each slot."""
    weight: Tensor
    """``(B * P, M)`` 1 / number of cameras averaged at the voxel; 0 for padded slots."""
    num_voxels: int
    """``P = X * Y * Z``."""
    num_views: int
    """``B * N``, the feature maps the plan samples."""


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
        The plan; a voxel seen by no camera has only padded slots (its feature stays zero).
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
    counts = visible.sum(dim=1)  # (B, P)
    slots = max(int(counts.max()) if counts.numel() else 0, 1)
    # Each visible (sample, camera, voxel) gets the slot of its camera's rank among the voxel's cameras, so a voxel's
    # views are summed in camera order.
    rank = visible.cumsum(dim=1) - 1  # (B, N, P)
    b, n, p = visible.nonzero(as_tuple=True)
    num_voxels = centers.shape[0]
    row, slot = b * num_voxels + p, rank[b, n, p]
    grid = uv.new_zeros(batch * num_voxels, slots, 2)
    grid[row, slot] = uv[b, n, p] / uv.new_tensor([width, height]) * 2 - 1
    view = torch.zeros(batch * num_voxels, slots, dtype=torch.int64, device=uv.device)
    view[row, slot] = b * cameras + n
    weight = uv.new_zeros(batch * num_voxels, slots)
    weight[row, slot] = 1.0 / counts[b, p].to(uv.dtype)
    return SamplingPlan(grid=grid, view=view, weight=weight, num_voxels=num_voxels, num_views=batch * cameras)


def bilinear_taps(plan: SamplingPlan, size: tuple[int, int], align_corners: bool) -> tuple[Tensor, Tensor]:
    """The plan's samples as weighted rows of the feature maps: ``grid_sample``'s bilinear taps, zero padding.

    Args:
        plan: the sampling plan.
        size: ``(h, w)`` of the feature maps.
        align_corners: ``grid_sample``'s convention for the plan's normalised coordinates.

    Returns:
        index: ``(B * P, 4 * M)`` int64 rows of the features flattened to ``(B * N * h * w + 1, C)``, pixel
        ``(b * N + n, y, x)`` at row ``((b * N + n) * h + y) * w + x``; taps outside the map and padded slots point at
        the last row, which holds zeros.
        weight: ``(B * P, 4 * M)`` bilinear weight times the slot's weight; 0 where the index is the zero row.
    """
    height, width = size
    u, v = plan.grid.unbind(-1)
    if align_corners:
        x, y = (u + 1) / 2 * (width - 1), (v + 1) / 2 * (height - 1)
    else:
        x, y = ((u + 1) * width - 1) / 2, ((v + 1) * height - 1) / 2
    x0, y0 = x.floor(), y.floor()
    zero_row = plan.num_views * height * width
    indices, weights = [], []
    for dy in (0, 1):
        for dx in (0, 1):
            xi, yi = x0 + dx, y0 + dy
            tap = (1 - (x - xi).abs()) * (1 - (y - yi).abs()) * plan.weight  # (B * P, M)
            inside = (xi >= 0) & (xi <= width - 1) & (yi >= 0) & (yi <= height - 1) & (plan.weight > 0)
            pixel = (plan.view * height + yi.clamp(0, height - 1).long()) * width + xi.clamp(0, width - 1).long()
            indices.append(torch.where(inside, pixel, torch.full_like(pixel, zero_row)))
            weights.append(torch.where(inside, tap, torch.zeros_like(tap)))
    return torch.cat(indices, dim=1), torch.cat(weights, dim=1)


def weighted_rows(rows: Tensor, index: Tensor, weight: Tensor) -> Tensor:
    """``out[i] = sum_j weight[i, j] * rows[index[i, j]]``: ``(R, C)`` rows, ``(P, T)`` index and weight -> ``(P, C)``.

    In eager mode one ``embedding_bag``, which sums each row's taps in a fused kernel on the CPU and the GPU. An
    exported graph (``torch.export``) would turn ``embedding_bag`` into a loop over the rows; there the taps are
    added one column at a time: ``T`` gathers of ``(P, C)``, still without a scatter.
    """
    weight = weight.to(rows.dtype)
    if torch.compiler.is_exporting():
        out = rows.new_zeros(index.shape[0], rows.shape[1])
        for tap in range(index.shape[1]):
            out = out + weight[:, tap, None] * take(rows, index[:, tap])
        return out
    return F.embedding_bag(index, rows, per_sample_weights=weight, mode="sum")


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

        Every voxel gathers its bilinear taps from the cameras that see it (:func:`weighted_rows`): no scatter, so
        no atomic additions on the GPU and no race in an exported graph, and the views are summed in camera order.
        """
        batch = features.shape[0]
        flat = features.flatten(0, 1)  # (B*N, C_in, h, w)
        if self.reduce is not None:
            flat = self.reduce(flat)
        channels, height, width = flat.shape[1:]
        rows = torch.cat((flat.permute(0, 2, 3, 1).reshape(-1, channels), flat.new_zeros(1, channels)))
        index, weight = bilinear_taps(plan, (height, width), self.cfg.align_corners)
        volume = weighted_rows(rows, index, weight)  # (B * P, C)
        x, y, z = self.cfg.grid_size
        volume = volume.view(batch, x, y, z, channels)
        # (B, X, Y, Z, C) -> (B, Z, C, X, Y) -> (B, Z*C, X, Y): channel z * C + c, as the reference folds height.
        return volume.permute(0, 3, 4, 1, 2).reshape(batch, z * channels, x, y)
