"""Ray origins of the RayIoU protocol: where the scene's LiDAR was, seen from the evaluated key frame.

SparseOcc casts RayIoU rays from the LiDAR positions of every key frame of the scene that lie within 39 m (in x and y)
of the evaluated frame, at most 8 of them spread evenly in time. Each position is expressed in the evaluated frame's
LiDAR coordinates, rounded to float32 as the reference does, then mapped into its ego coordinates.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

__all__ = ["PoseRecord", "ray_origins", "records_ray_origins", "MAX_ORIGINS", "ORIGIN_RANGE"]

MAX_ORIGINS = 8
ORIGIN_RANGE = 39.0


@dataclass(frozen=True)
class PoseRecord:
    """One key frame's poses: ``lidar2ego`` and ``ego2global`` are ``(4, 4)`` float64."""

    token: str
    scene: str
    lidar2ego: np.ndarray
    ego2global: np.ndarray


def _origins_of(reference: PoseRecord, frames: Sequence[PoseRecord]) -> np.ndarray:
    """``(T, 3)`` float64 origins for one evaluated frame from the key frames of its scene (time order)."""
    global_from_reference = reference.ego2global @ reference.lidar2ego
    reference_from_global = np.linalg.inv(global_from_reference)
    origins = []
    for frame in frames:
        if frame is reference:
            in_lidar = np.zeros(3, dtype=np.float32)
        else:
            relative = reference_from_global @ (frame.ego2global @ frame.lidar2ego)
            in_lidar = relative[:3, 3].astype(np.float32)  # the reference rounds here
        origin = reference.lidar2ego[:3, :3] @ in_lidar.astype(np.float64) + reference.lidar2ego[:3, 3]
        if abs(origin[0]) < ORIGIN_RANGE and abs(origin[1]) < ORIGIN_RANGE:
            origins.append(origin)
    if len(origins) > MAX_ORIGINS:
        keep = np.round(np.linspace(0, len(origins) - 1, MAX_ORIGINS)).astype(np.int64)
        origins = [origins[i] for i in keep]
    return np.stack(origins)


def ray_origins(frames: Sequence[PoseRecord]) -> dict[str, np.ndarray]:
    """Token -> ``(T, 3)`` float64 ray origins in that frame's ego coordinates, for every frame given.

    Args:
        frames: key frames of one or more scenes; within a scene, in time order.
    """
    scenes: dict[str, list[PoseRecord]] = {}
    for frame in frames:
        scenes.setdefault(frame.scene, []).append(frame)
    return {frame.token: _origins_of(frame, scenes[frame.scene]) for frame in frames}


def records_ray_origins(records) -> dict[str, np.ndarray]:
    """:func:`ray_origins` of index records (anything with ``token``, ``scene``, ``lidar2ego`` and ``ego2global``: a
    dataset's key frames, or those of a dataset's nuScenes tables)."""
    return ray_origins([PoseRecord(r.token, r.scene, r.lidar2ego, r.ego2global) for r in records])

