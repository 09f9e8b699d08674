"""Occ3D's visibility masks of a key frame's labels: what the LiDAR rays and the cameras observe.

Both walk rays through the label grid with :func:`~occkit.geometry.raycast.traverse_rays`. The synthetic world
computes its exact masks with them, and ``occkit label`` computes the masks of the labels it builds from sensor
data with the same code, so the two can be compared voxel for voxel.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from occkit.classes import OCC3D
from occkit.geometry.grid import VoxelGrid
from occkit.geometry.raycast import traverse_rays

__all__ = ["lidar_visibility", "camera_visibility"]

#: Occ3D's free label, the default empty label of both masks.
FREE = OCC3D.empty_index


def _check_semantics(semantics: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    semantics = np.asarray(semantics)
    if semantics.shape != grid.shape:
        raise ValueError(f"semantics has shape {semantics.shape}, the grid {grid.shape}")
    return semantics


def lidar_visibility(
    semantics: np.ndarray, grid: VoxelGrid, sweeps: Sequence[tuple[np.ndarray, np.ndarray]], free: int = FREE
) -> np.ndarray:
    """Occ3D ``mask_lidar``: voxels observed by LiDAR rays, free space along them and the surfaces they hit.

    Each ray runs from its sweep's sensor origin to one return and marks every voxel it crosses, the return's
    voxel included. Rays are not stopped at occupied voxels (a return proves the way to it was clear).

    Args:
        semantics: ``(X, Y, Z)`` labels of the key frame (checked against the grid); ``free`` is empty space.
        grid: the label grid; its frame is the key frame's ego frame.
        sweeps: per sweep, ``(origin (3,), points (N, >=3))`` in that frame (the caller moves every sweep into the
            key frame); columns past ``x, y, z`` are ignored.

    Returns:
        ``(X, Y, Z)`` uint8, 1 where observed.
    """
    semantics = _check_semantics(semantics, grid)
    origins, ends = [], []
    for origin, points in sweeps:
        points = np.asarray(points, dtype=np.float64)
        if points.ndim != 2 or points.shape[1] < 3:
            raise ValueError(f"sweep points must have shape (N, >=3), got {points.shape}")
        ends.append(points[:, :3])
        origins.append(np.broadcast_to(np.asarray(origin, dtype=np.float64).reshape(3), ends[-1].shape))
    if not ends:
        return np.zeros(grid.shape, dtype=np.uint8)
    visited = traverse_rays(semantics != free, grid, np.concatenate(origins), np.concatenate(ends))
    return visited.astype(np.uint8)


def camera_visibility(
    semantics: np.ndarray,
    grid: VoxelGrid,
    cameras: Sequence[tuple[np.ndarray, np.ndarray, int, int]],
    min_depth: float = 0.1,
    free: int = FREE,
) -> np.ndarray:
    """Occ3D ``mask_camera``: occupied voxels the cameras see, and the free space in front of them.

    As Occ3D does, one ray goes from a camera's centre to every occupied voxel that projects into its image;
    the voxels it crosses, up to and including the first occupied one, are observed. The ray aims at the voxel's
    point nearest the camera (nudged into the voxel) rather than its centre: a ground voxel seen at a grazing
    angle would otherwise be hidden by its own neighbours in the ground layer.

    Args:
        semantics: ``(X, Y, Z)`` labels of the key frame; every label but ``free`` blocks the view.
        grid: the label grid; its frame is the cameras' ``ego``.
        cameras: per camera, ``(cam2ego (4, 4), K (3, 3), width, height)``.
        min_depth: voxel centres closer than this to a camera's image plane are not targets of that camera.

    Returns:
        ``(X, Y, Z)`` uint8, 1 where observed.
    """
    semantics = _check_semantics(semantics, grid)
    occupied = semantics != free
    index = np.argwhere(occupied)
    size = np.asarray(grid.voxel_size)
    low = np.asarray(grid.lower) + index * size
    centres = low + size / 2
    origins, ends = [], []
    for cam2ego, intrinsics, width, height in cameras:
        cam2ego = np.asarray(cam2ego, dtype=np.float64)
        ego2cam = np.linalg.inv(cam2ego)
        in_camera = centres @ ego2cam[:3, :3].T + ego2cam[:3, 3]
        depth = in_camera[:, 2]
        front = depth > min_depth
        uv = (
            in_camera[front, :2] / depth[front, None] @ np.asarray(intrinsics)[:2, :2].T + np.asarray(intrinsics)[:2, 2]
        )
        seen = np.flatnonzero(front)[(uv[:, 0] >= 0) & (uv[:, 0] < width) & (uv[:, 1] >= 0) & (uv[:, 1] < height)]
        eye = cam2ego[:3, 3]
        nearest = np.clip(eye, low[seen], low[seen] + size)
        # One percent of the way to the centre: inside the target, but still in front of its neighbours.
        ends.append(nearest + 0.01 * (centres[seen] - nearest))
        origins.append(np.broadcast_to(eye, ends[-1].shape))
    if not ends:
        return np.zeros(grid.shape, dtype=np.uint8)
    visited = traverse_rays(occupied, grid, np.concatenate(origins), np.concatenate(ends), True)
    return visited.astype(np.uint8)
