"""LiDAR targets for camera branches: per-camera depth and height maps at feature resolution.

Both project the key-frame LiDAR points into every augmented image and reduce per ``d x d`` feature cell:

- depth (BEVDet ``PointToMultiViewDepth`` + BEVDepth ``get_downsampled_gt_depth``): the minimum positive camera
  depth per cell, 0 where no point lands. The per-pixel nearest point of those codes does not change a cell minimum,
  so the cell minimum is taken over all points directly.
- height (DHD, github.com/yanzq95/DHD ``PointToMultiViewDepthandHeight`` + ``get_downsampled_gt_height``; the
  target of DA-Occ's HeightNet): per pixel the ego-frame height ``z`` of the *nearest* point, which is the surface the
  pixel sees, then the minimum of those heights per cell. DHD marks "no point" with height 0, which is also a valid
  ground height; here it is NaN.

Pixels follow docs/conventions.md: a point at ``(u, v)`` falls in pixel ``(floor(u), floor(v))`` (BEVDet rounds,
treating integer coordinates as pixel centres).
"""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor

from occkit.geometry.camera import project_points
from occkit.geometry.grid import OCC3D_GRID
from occkit.geometry.se3 import invert_transform

__all__ = ["depth_map", "height_map"]


def _project_to_pixels(
    points_ego: Tensor,
    cam2ego: Tensor,
    intrinsics: Tensor,
    img_aug: Tensor | None,
    image_size: Sequence[int],
    downsample: int,
    depth_range: tuple[float, float] | None,
) -> tuple[Tensor, Tensor, Tensor, tuple[int, int, int]]:
    """Projections that land in an image, as flat pixel indices over ``(N, H, W)``.

    Returns:
        pixel: ``(K,)`` int64 ``(camera * H + v) * W + u``.
        depth: ``(K,)`` camera-frame depth.
        height: ``(K,)`` ego-frame ``z`` of the projected point.
        map_shape: ``(N, H / d, W / d)``.
    """
    if points_ego.ndim != 2 or points_ego.shape[1] < 3:
        raise ValueError(f"points_ego must have shape (P, C >= 3), got {tuple(points_ego.shape)}")
    height, width = (int(n) for n in image_size)
    if height % downsample or width % downsample:
        raise ValueError(f"image_size {tuple(image_size)} is not divisible by downsample {downsample}")
    points = points_ego[:, :3]
    num_cameras = cam2ego.shape[0]
    ego2cam = invert_transform(cam2ego.to(points))
    aug = None if img_aug is None else img_aug.to(points)
    uv, depth, valid = project_points(points, ego2cam, intrinsics.to(points), aug, (height, width))  # (N, P, ...)
    if depth_range is not None:
        valid &= (depth >= depth_range[0]) & (depth < depth_range[1])
    camera = torch.arange(num_cameras, device=points.device)[:, None].expand_as(depth)
    pixel_uv = torch.floor(uv).long()
    pixel = (camera * height + pixel_uv[..., 1]) * width + pixel_uv[..., 0]
    point_z = points[:, 2].expand_as(depth)
    return pixel[valid], depth[valid], point_z[valid], (num_cameras, height // downsample, width // downsample)


def _cell_of_pixel(pixel: Tensor, image_size: Sequence[int], downsample: int) -> Tensor:
    """Flat feature-cell index over ``(N, H / d, W / d)`` of flat pixel indices over ``(N, H, W)``."""
    height, width = (int(n) for n in image_size)
    camera, within = pixel // (height * width), pixel % (height * width)
    row, column = within // width // downsample, within % width // downsample
    return (camera * (height // downsample) + row) * (width // downsample) + column


def _cell_minimum(values: Tensor, cell: Tensor, map_shape: tuple[int, int, int]) -> Tensor:
    """``map_shape`` float32 minimum of ``values`` per flat cell index, +inf where a cell receives nothing."""
    out = torch.full((map_shape[0] * map_shape[1] * map_shape[2],), torch.inf, device=values.device)
    out.scatter_reduce_(0, cell, values.to(torch.float32), reduce="amin", include_self=True)
    return out.reshape(map_shape)


def depth_map(
    points_ego: Tensor,
    cam2ego: Tensor,
    intrinsics: Tensor,
    img_aug: Tensor | None,
    image_size: Sequence[int],
    downsample: int,
    depth_range: tuple[float, float] | None = None,
) -> Tensor:
    """LiDAR depth per feature cell of every augmented image (BEVDepth-style supervision).

    Args:
        points_ego: ``(P, C >= 3)`` key-frame points in the ego frame before BEV augmentation (images are not
            BEV-augmented); only ``x, y, z`` are read.
        cam2ego: ``(N, 4, 4)`` camera to ego.
        intrinsics: ``(N, 3, 3)`` of the original images.
        img_aug: ``(N, 3, 3)`` original to augmented pixels, or None.
        image_size: augmented image ``(H, W)``, divisible by ``downsample``.
        downsample: feature stride ``d``.
        depth_range: keep only depths in ``[min, max)`` (BEVDet's ``grid_config['depth']``); None keeps every
            point in front of the camera.

    Returns:
        ``(N, H / d, W / d)`` float32 minimum camera depth per cell, 0 where no point projects.
    """
    pixel, depth, _, map_shape = _project_to_pixels(
        points_ego, cam2ego, intrinsics, img_aug, image_size, downsample, depth_range
    )
    cells = _cell_minimum(depth, _cell_of_pixel(pixel, image_size, downsample), map_shape)
    return torch.where(torch.isinf(cells), torch.zeros_like(cells), cells)


def height_map(
    points_ego: Tensor,
    cam2ego: Tensor,
    intrinsics: Tensor,
    img_aug: Tensor | None,
    image_size: Sequence[int],
    downsample: int,
    z_range: tuple[float, float] = (OCC3D_GRID.point_cloud_range[2], OCC3D_GRID.point_cloud_range[5]),
    depth_range: tuple[float, float] | None = None,
) -> Tensor:
    """Ego-frame height of the surface seen per feature cell of every augmented image (DHD's height target).

    Per pixel the height of the nearest point (smallest camera depth) projecting there; pixels whose nearest point
    lies outside ``z_range`` carry no height (the farther points behind it are occluded, so they do not stand in);
    per cell the minimum height over its pixels, as DHD.

    Args:
        points_ego, cam2ego, intrinsics, img_aug, image_size, downsample, depth_range: as :func:`depth_map`.
        z_range: valid heights ``[min, max]`` in metres (the Occ3D z range by default).

    Returns:
        ``(N, H / d, W / d)`` float32 minimum height per cell, NaN where no valid height.
    """
    pixel, depth, height, map_shape = _project_to_pixels(
        points_ego, cam2ego, intrinsics, img_aug, image_size, downsample, depth_range
    )
    # Sorting by depth, then stably by pixel, puts each pixel's nearest point first in its run.
    by_depth = torch.argsort(depth, stable=True)
    order = by_depth[torch.argsort(pixel[by_depth], stable=True)]
    pixel, height = pixel[order], height[order]
    nearest = torch.ones_like(pixel, dtype=torch.bool)
    nearest[1:] = pixel[1:] != pixel[:-1]
    keep = nearest & (height >= z_range[0]) & (height <= z_range[1])
    cells = _cell_minimum(height[keep], _cell_of_pixel(pixel[keep], image_size, downsample), map_shape)
    return torch.where(torch.isinf(cells), torch.full_like(cells, torch.nan), cells)
