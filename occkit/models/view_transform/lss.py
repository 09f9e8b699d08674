"""Lift-Splat-Shoot view transform of BEVDet / FlashOcc, with the voxel pooling done in plain PyTorch.

Lift: every cell of the image feature map is a ray, cut into ``D`` depth bins; a 1x1 depth net predicts a
distribution over the bins and a context vector, and their outer product places ``D`` weighted copies of the
context along the ray. Splat: each copy is summed into the voxel of the target grid that contains its point.

The reference does the splat with a custom CUDA kernel (``bev_pool_v2``) fed with precomputed index lists. occkit
keeps the index lists (a :class:`PoolingPlan`) and replaces the kernel by one gather, one multiply and one
``index_add``, whose backward autograd derives; it exports to ONNX with standard operators (Gather, Mul and a
summing ScatterElements). For one rig the plan is computed once and reused (:mod:`occkit.models.base`), as the
reference measures its speed.

Pipeline, at FlashOcc's M0 size (one sample, six cameras)::

    features (1, 6, 256, 16, 44) -> depth net -> depth (1, 6, 44, 16, 44), context (1, 6, 64, 16, 44)
    frustum (44, 16, 44, 3) --lift_geometry--> points (1, 6, 44, 16, 44, 3) in the augmented ego frame
    points --make_pooling_plan--> PoolingPlan;  voxel_pool(depth, context, plan) -> (1, 64, Z=1, X=200, Y=200)
    fold_height -> BEV (1, 64, 200, 200)

Index order: BEVDet pools into ``(B, Z, Y, X, C)`` and hands ``(B, C, Y, X)`` to its BEV encoder. occkit pools
straight into ``(B, C, Z, X, Y)``, axes in :class:`~occkit.geometry.grid.VoxelGrid` order (dim ``-2`` is x, forward;
dim ``-1`` is y, left), so the conversion from the reference's layout happens here and nowhere else.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import ClassVar

import torch
from torch import Tensor, nn

from occkit.geometry.camera import invert_image_aug
from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.models.base import FIXED_CALIBRATION_RETIRED
from occkit.models.indexing import take

__all__ = [
    "LSSConfig",
    "PoolingPlan",
    "depth_bins",
    "frustum",
    "lift_geometry",
    "make_pooling_plan",
    "voxel_pool",
    "gather_point_weights",
    "fold_height",
    "LSSViewTransform",
]


@dataclass(frozen=True)
class LSSConfig:
    """LSS view transform (FlashOcc's ``LSSViewTransformer`` with its 1x1 depth net)."""

    #: Keys of older versions, skipped on load (see :func:`occkit.config.from_dict`).
    RETIRED_KEYS: ClassVar[dict[str, str]] = {"fixed_calibration": FIXED_CALIBRATION_RETIRED}

    image_size: tuple[int, int] = (256, 704)
    """``(H, W)`` of the augmented input images, pixels; the frustum is laid over this image."""
    feature_stride: int = 16
    """Image pixels per feature cell; the feature map is ``(H // stride, W // stride)``."""
    depth_range: tuple[float, float, float] = (1.0, 45.0, 1.0)
    """Depth bins ``(start, stop, step)`` in metres, as ``arange`` (stop excluded): M0 44 bins, M1 step 0.5 -> 88."""
    point_cloud_range: tuple[float, float, float, float, float, float] = OCC3D_GRID.point_cloud_range
    """Extent of the target grid in the (augmented) ego frame ``(x_min, y_min, z_min, x_max, y_max, z_max)``, m."""
    grid_size: tuple[int, int, int] = (*OCC3D_GRID.shape[:2], 1)
    """Voxels along x, y, z; the BEV comes out ``X x Y`` with ``Z * context_channels`` channels."""
    in_channels: int = 256
    """Channels of the image features."""
    context_channels: int = 64
    """Channels of the context vector splatted along each ray (the BEV feature width per height bin)."""
    truncate_indices: bool = False
    """False: voxel index ``floor((p - min) / size)`` (occkit's grid convention). True: the reference's
    ``.long()``, which truncates toward zero and so also keeps points up to one voxel below each lower bound in
    voxel 0 (for FlashOcc's single 6.4 m height bin: heights down to -7.4 m); for parity with reference weights."""

    @property
    def num_depth_bins(self) -> int:
        """``D``, the number of depth bins of :attr:`depth_range`."""
        return _num_depth_bins(self.depth_range)

    @property
    def feature_size(self) -> tuple[int, int]:
        """``(h, w)`` of the image feature map."""
        return self.image_size[0] // self.feature_stride, self.image_size[1] // self.feature_stride

    def voxel_grid(self) -> VoxelGrid:
        """The target grid: :attr:`point_cloud_range` cut into :attr:`grid_size` voxels."""
        return VoxelGrid.from_shape(self.point_cloud_range, self.grid_size)


@dataclass
class PoolingPlan:
    """Which frustum point feeds which voxel, for one batch's geometry; ``M`` points fall inside the grid.

    Each of the ``M`` entries says: multiply weight ``ranks_depth`` by context row ``ranks_feat`` and add the
    product to voxel row ``ranks_bev``. Entries are sorted by ``ranks_bev`` (ties keep frustum order), as the
    reference sorts them, so the scatter sees sorted indices.
    """

    ranks_depth: Tensor
    """``(M,)`` int64 flat index into the per-point weights ``(B, N, D, h, w)``."""
    ranks_feat: Tensor
    """``(M,)`` int64 flat index into the context rows ``(B, N, h, w)``."""
    ranks_bev: Tensor
    """``(M,)`` int64 flat index into the output rows ``(B, Z, X, Y)``."""
    point_shape: tuple[int, int, int, int, int]
    """``(B, N, D, h, w)``: the frustum the plan was made for."""
    grid_shape: tuple[int, int, int]
    """``(X, Y, Z)``: the target grid's :attr:`VoxelGrid.shape`."""

    @property
    def num_points(self) -> int:
        """``M``, the frustum points inside the grid."""
        return int(self.ranks_bev.shape[0])

    def to(self, device: torch.device | str) -> PoolingPlan:
        """The same plan with its index tensors on ``device``."""
        return PoolingPlan(
            self.ranks_depth.to(device), self.ranks_feat.to(device), self.ranks_bev.to(device),
            self.point_shape, self.grid_shape,
        )  # fmt: skip


# --------------------------------------------------------------------------- lift: frustum and its geometry
def _num_depth_bins(depth_range: Sequence[float]) -> int:
    start, stop, step = (float(v) for v in depth_range)
    if step <= 0 or stop <= start:
        raise ValueError(f"depth_range must be (start, stop, step) with stop > start and step > 0, got {depth_range}")
    # The length torch.arange gives on the CPU (computed in double), so the bins match the reference's.
    return math.ceil((stop - start) / step)


def depth_bins(
    depth_range: Sequence[float], *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """``(D,)`` depth-bin values ``start + i * step``, the reference's ``arange(start, stop, step)``.

    Built in float64 and rounded once, so every device gets the same count and values (a float32 ``arange``
    on CUDA may differ by one bin for some ranges).
    """
    start, _, step = (float(v) for v in depth_range)
    index = torch.arange(_num_depth_bins(depth_range), dtype=torch.float64)
    return (start + index * step).to(device=device, dtype=dtype)


def frustum(
    image_size: Sequence[int],
    feature_stride: int,
    depth_range: Sequence[float],
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """The frustum of an augmented image: one ``(u, v, d)`` per depth bin and feature cell.

    Pixel coordinates follow BEVDet, not pixel centres: ``u = linspace(0, W - 1, w)``, ``v = linspace(0, H - 1, h)``
    with ``h = H // stride``, ``w = W // stride``, so the first and last cells sit on the image's first and last
    pixel columns / rows. Kept as is, since trained depth nets learned against exactly these rays.

    Args:
        image_size: ``(H, W)`` of the augmented image, pixels.
        feature_stride: image pixels per feature cell.
        depth_range: ``(start, stop, step)`` metres, see :func:`depth_bins`.

    Returns:
        ``(D, h, w, 3)``: ``[..., 0]`` is ``u``, ``[..., 1]`` is ``v`` (augmented-image pixels), ``[..., 2]`` is the
        camera-frame depth ``z`` in metres.
    """
    height, width = (int(n) for n in image_size)
    h, w = height // feature_stride, width // feature_stride
    if h < 1 or w < 1:
        raise ValueError(f"image_size {tuple(image_size)} is smaller than one feature cell of stride {feature_stride}")
    depth = depth_bins(depth_range, device=device, dtype=dtype)
    u = torch.linspace(0, width - 1, w, device=device, dtype=dtype)
    v = torch.linspace(0, height - 1, h, device=device, dtype=dtype)
    d, vv, uu = torch.meshgrid(depth, v, u, indexing="ij")
    return torch.stack((uu, vv, d), dim=-1)


def lift_geometry(
    frustum_points: Tensor,
    intrinsics: Tensor,
    cam2ego: Tensor,
    img_aug: Tensor | None = None,
    occ_aug: Tensor | None = None,
) -> Tensor:
    """Where each frustum point lies in the (augmented) ego frame.

    For a frustum entry ``(u', v', d)`` of camera ``n``: undo the image augmentation
    (``[u, v, 1] = img_aug^-1 [u', v', 1]``), unproject at depth ``d`` (``p = d K^-1 [u, v, 1]``, the same point as
    :func:`occkit.geometry.camera.unproject`), map camera -> ego with ``cam2ego`` and apply ``occ_aug``. All of it is
    linear in ``(u' d, v' d, d)``, so it folds into one 3x3 matrix and one translation per camera, applied to every
    point at once (BEVDet's ``get_lidar_coor``, in one matrix product).

    Args:
        frustum_points: ``(..., 3)`` ``(u', v', d)`` in the augmented image, e.g. ``(D, h, w, 3)`` from
            :func:`frustum`; shared by all cameras.
        intrinsics: ``(B, N, 3, 3)`` pinhole matrices of the original images.
        cam2ego: ``(B, N, 4, 4)`` camera -> ego.
        img_aug: ``(B, N, 3, 3)`` original -> augmented pixels; None: no image augmentation.
        occ_aug: ``(B, 4, 4)`` ego -> augmented ego (BEVDet's ``bda``); None: identity.

    Returns:
        ``(B, N, ..., 3)`` points in the augmented ego frame, e.g. ``(B, N, D, h, w, 3)``.
    """
    batch, cameras = intrinsics.shape[:2]
    pixels_to_cam = torch.linalg.inv(intrinsics)  # (B, N, 3, 3)
    if img_aug is not None:
        # [u d, v d, d] = img_aug^-1 [u' d, v' d, d] because the affine map's last row is (0, 0, 1).
        pixels_to_cam = pixels_to_cam @ invert_image_aug(img_aug)
    rotation = cam2ego[..., :3, :3] @ pixels_to_cam  # (B, N, 3, 3)
    translation = cam2ego[..., :3, 3]  # (B, N, 3)
    if occ_aug is not None:
        aug_rotation = occ_aug[:, None, :3, :3]  # (B, 1, 3, 3)
        rotation = aug_rotation @ rotation
        translation = (aug_rotation @ translation[..., None])[..., 0] + occ_aug[:, None, :3, 3]
    shape = frustum_points.shape[:-1]
    flat = frustum_points.reshape(-1, 3).to(rotation.dtype)
    scaled = torch.cat((flat[:, :2] * flat[:, 2:], flat[:, 2:]), dim=1)  # (P, 3) = (u' d, v' d, d)
    # Row vectors: p @ R^T == (R p)^T, broadcast over (B, N).
    points = scaled @ rotation.transpose(-1, -2) + translation[:, :, None]  # (B, N, P, 3)
    return points.view(batch, cameras, *shape, 3)


# --------------------------------------------------------------------------- splat: pooling plan and pooling
def make_pooling_plan(
    points: Tensor,
    grid: VoxelGrid,
    camera_mask: Tensor | None = None,
    truncate_indices: bool = False,
) -> PoolingPlan:
    """Index lists of the voxel pooling for one batch's frustum geometry (BEVDet's ``voxel_pooling_prepare_v2``).

    Args:
        points: ``(B, N, D, h, w, 3)`` frustum points in the grid's frame, from :func:`lift_geometry`.
        grid: the target grid; the output rows are ``(B, Z, X, Y)`` over its :attr:`VoxelGrid.shape` ``(X, Y, Z)``.
        camera_mask: ``(B, N)`` bool, False for failed or absent cameras, whose points are dropped; None: all work.
        truncate_indices: see :attr:`LSSConfig.truncate_indices` (False: ``grid.world_to_index``, floor).

    Returns:
        The plan; points outside the grid (or of masked cameras) get no entry.
    """
    if points.ndim != 6 or points.shape[-1] != 3:
        raise ValueError(f"points must be (B, N, D, h, w, 3), got {tuple(points.shape)}")
    batch, cameras, bins, h, w = points.shape[:5]
    size_x, size_y, size_z = grid.shape
    index, inside = grid.world_to_index(points.detach())  # (B, N, D, h, w, 3), (B, N, D, h, w)
    if truncate_indices:
        # .long() truncates toward zero: coordinates in (-1, 0) voxels land in voxel 0 instead of -1.
        index = torch.where(index == -1, torch.zeros_like(index), index)
        upper = torch.tensor(grid.shape, device=index.device)
        inside = ((index >= 0) & (index < upper)).all(dim=-1)
    if camera_mask is not None:
        inside = inside & camera_mask.to(device=inside.device, dtype=torch.bool)[:, :, None, None, None]
    ranks_depth = inside.flatten().nonzero().squeeze(1)  # (M,) ascending
    # Flat point index ((b * N + n) * D + d) * h * w + pixel; the context row drops the depth bin.
    pixels = h * w
    ranks_feat = ranks_depth // (bins * pixels) * pixels + ranks_depth % pixels
    kept = index.view(-1, 3)[ranks_depth]  # (M, 3) voxel (x, y, z)
    sample = ranks_depth // (cameras * bins * pixels)
    ranks_bev = ((sample * size_z + kept[:, 2]) * size_x + kept[:, 0]) * size_y + kept[:, 1]
    # Stable, so ties stay in frustum order and the result is the same on every device.
    ranks_bev, order = torch.sort(ranks_bev, stable=True)
    return PoolingPlan(
        ranks_depth=ranks_depth[order], ranks_feat=ranks_feat[order], ranks_bev=ranks_bev,
        point_shape=(batch, cameras, bins, h, w), grid_shape=grid.shape,
    )  # fmt: skip


def voxel_pool(weights: Tensor, context: Tensor, plan: PoolingPlan, grid_shape: Sequence[int] | None = None) -> Tensor:
    """Sum pooling of weighted context copies into voxels: the pure-PyTorch ``bev_pool_v2``.

    Voxel ``(b, z, x, y)`` receives ``sum weights[b, n, d, i, j] * context[b, n, :, i, j]`` over the frustum points
    ``(b, n, d, i, j)`` inside it. ``weights`` can be any per-point weight with the frustum's shape:

    - LSS: the depth distribution ``softmax`` over ``D`` (FlashOcc, BEVDet, DA-Occ's depth branch);
    - a distribution over another axis, e.g. height probabilities ``(B, N, K, h, w)`` over ``K`` height bins:
      gather each point's bin with :func:`gather_point_weights` to get ``(B, N, D, h, w)`` (DA-Occ's height
      pooling); products of several such weights work the same way;
    - ``torch.ones(plan.point_shape)``: counts of points per voxel.

    Accumulates in float32 at least (the reference kernel casts both inputs to float32); gradients reach
    ``weights`` and ``context`` through autograd.

    Args:
        weights: ``(B, N, D, h, w)`` per-point weights, ``plan.point_shape``.
        context: ``(B, N, C, h, w)`` per-pixel features.
        plan: from :func:`make_pooling_plan`.
        grid_shape: ``(X, Y, Z)``, the grid's :attr:`VoxelGrid.shape`; None: the plan's, else checked against it.

    Returns:
        ``(B, C, Z, X, Y)``, contiguous, float32 (or wider when the inputs are).
    """
    if grid_shape is not None and tuple(grid_shape) != tuple(plan.grid_shape):
        raise ValueError(f"grid_shape {tuple(grid_shape)} differs from the plan's {plan.grid_shape}")
    batch, cameras, bins, h, w = plan.point_shape
    if tuple(weights.shape) != plan.point_shape:
        raise ValueError(f"weights must be (B, N, D, h, w) = {plan.point_shape}, got {tuple(weights.shape)}")
    if context.ndim != 5 or tuple(context.shape[:2]) != (batch, cameras) or tuple(context.shape[3:]) != (h, w):
        raise ValueError(f"context must be ({batch}, {cameras}, C, {h}, {w}), got {tuple(context.shape)}")
    size_x, size_y, size_z = plan.grid_shape
    channels = context.shape[2]
    dtype = torch.promote_types(torch.promote_types(weights.dtype, context.dtype), torch.float32)
    rows = context.to(dtype).permute(0, 1, 3, 4, 2).reshape(-1, channels)  # (B*N*h*w, C)
    # take rather than rows[...]: a context row feeds up to D points, and take's backward sums those gradients in a
    # fixed order on the CPU (see occkit.models.indexing).
    values = take(weights.to(dtype).reshape(-1), plan.ranks_depth)[:, None] * take(rows, plan.ranks_feat)  # (M, C)
    volume = _add_rows(rows.new_zeros(batch * size_z * size_x * size_y, channels), plan.ranks_bev, values)
    return volume.view(batch, size_z, size_x, size_y, channels).permute(0, 4, 1, 2, 3).contiguous()


def _add_rows(volume: Tensor, index: Tensor, values: Tensor) -> Tensor:
    """``volume[index[m]] += values[m]`` for every ``m``, repeated indices summed."""
    if torch.onnx.is_in_onnx_export():
        # The TorchScript exporter writes index_add as a ScatterElements without reduction, silently wrong for
        # repeated indices; scatter_add becomes ScatterElements(reduction="add") with either exporter.
        return volume.scatter_add(0, index[:, None].expand_as(values), values)
    # index_add in eager: sums in index order on the CPU, whatever the thread count, and
    # deterministic on CUDA under torch.use_deterministic_algorithms.
    return volume.index_add(0, index, values)


def gather_point_weights(probabilities: Tensor, bins: Tensor) -> Tensor:
    """Per-point weights from a per-pixel distribution over bins of another axis (height, say).

    Point ``(b, n, d, i, j)`` gets ``probabilities[b, n, bins[b, n, d, i, j], i, j]``. For height bins of a grid,
    ``bins = grid.world_to_index(points)[0][..., 2]``; bins outside ``[0, K)`` are clamped, which only matters for
    points that are outside that grid (and so dropped by its plan).

    Args:
        probabilities: ``(B, N, K, h, w)``.
        bins: ``(B, N, D, h, w)`` integer bin of every frustum point.

    Returns:
        ``(B, N, D, h, w)``, usable as ``weights`` of :func:`voxel_pool` (alone or multiplied with depth).
    """
    if probabilities.ndim != 5 or bins.ndim != 5:
        raise ValueError(f"probabilities and bins must be 5-D, got {tuple(probabilities.shape)}, {tuple(bins.shape)}")
    index = bins.long().clamp(0, probabilities.shape[2] - 1)
    return torch.gather(probabilities, 2, index)


def fold_height(volume: Tensor) -> Tensor:
    """``(B, C, Z, X, Y)`` -> BEV ``(B, Z * C, X, Y)``, channel ``z * C + c`` (BEVDet's ``cat(unbind(dim=2))``).

    For ``Z = 1`` this is ``(B, C, X, Y)``, a view.
    """
    batch, channels, size_z, size_x, size_y = volume.shape
    return volume.transpose(1, 2).reshape(batch, size_z * channels, size_x, size_y)


# --------------------------------------------------------------------------- module
class LSSViewTransform(nn.Module):
    """Image features ``(B, N, C_in, h, w)`` -> BEV ``(B, Z * C_ctx, X, Y)`` in the augmented ego frame.

    The depth net is FlashOcc's: one 1x1 convolution to ``D + C_ctx`` channels, softmax over the first ``D`` for
    depth, the rest is context.

    Example:
        >>> vt = LSSViewTransform(LSSConfig())
        >>> plan = vt.plan(batch.intrinsics, batch.cam2ego, batch.img_aug, batch.occ_aug)  # doctest: +SKIP
        >>> bev, depth = vt(features, plan)  # (B, 64, 200, 200), (B, 6, 44, 16, 44)  # doctest: +SKIP
    """

    def __init__(self, cfg: LSSConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.grid = cfg.voxel_grid()
        self.num_depth_bins = cfg.num_depth_bins
        self.depth_net = nn.Conv2d(cfg.in_channels, self.num_depth_bins + cfg.context_channels, kernel_size=1)
        self.out_channels = cfg.context_channels * cfg.grid_size[2]

    def plan(
        self,
        intrinsics: Tensor,
        cam2ego: Tensor,
        img_aug: Tensor | None,
        occ_aug: Tensor | None,
        image_size: Sequence[int] | None = None,
        camera_mask: Tensor | None = None,
    ) -> PoolingPlan:
        """The pooling plan for a batch's geometry.

        Args:
            intrinsics: ``(B, N, 3, 3)``; cam2ego: ``(B, N, 4, 4)``; img_aug: ``(B, N, 3, 3)`` or None;
            occ_aug: ``(B, 4, 4)`` or None; image_size: ``(H, W)`` of the augmented images (None: the config's);
            camera_mask: ``(B, N)`` bool or None, see :func:`make_pooling_plan`.
        """
        # Built per call rather than kept as a buffer: it is tiny, and a buffer would follow module.half() and lose
        # pixel precision.
        image_size = self.cfg.image_size if image_size is None else image_size
        points_uvd = frustum(image_size, self.cfg.feature_stride, self.cfg.depth_range, device=intrinsics.device)
        points = lift_geometry(points_uvd, intrinsics.float(), cam2ego.float(),
                               None if img_aug is None else img_aug.float(),
                               None if occ_aug is None else occ_aug.float())  # fmt: skip
        return make_pooling_plan(points, self.grid, camera_mask, self.cfg.truncate_indices)

    def forward(self, features: Tensor, plan: PoolingPlan) -> tuple[Tensor, Tensor]:
        """Lift and splat.

        Args:
            features: ``(B, N, C_in, h, w)`` image features.
            plan: from :meth:`plan`, for the same ``B``, ``N`` and feature size.

        Returns:
            bev: ``(B, Z * C_ctx, X, Y)``, float32 at least.
            depth: ``(B, N, D, h, w)`` depth distributions (softmax over ``D``).
        """
        batch, cameras, _, h, w = features.shape
        expected = (batch, cameras, self.num_depth_bins, h, w)
        if plan.point_shape != expected:
            raise ValueError(f"plan was made for points {plan.point_shape}, features need {expected}")
        x = self.depth_net(features.flatten(0, 1))  # (B*N, D + C_ctx, h, w)
        depth = x[:, : self.num_depth_bins].softmax(dim=1).view(expected)
        context = x[:, self.num_depth_bins :].view(batch, cameras, -1, h, w)
        volume = voxel_pool(depth, context, plan, self.grid.shape)  # (B, C_ctx, Z, X, Y)
        return fold_height(volume), depth
