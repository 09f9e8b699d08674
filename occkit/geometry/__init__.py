"""Geometry core: voxel grids, rigid transforms, cameras and voxelization, as pure functions of tensors.

Shapes are in every docstring; everything is differentiable where that makes sense and runs on any device.
Frames, index orders and matrix conventions: docs/conventions.md.
"""

from __future__ import annotations

import importlib
from typing import Any

#: Public name -> the submodule that defines it; each is imported on first use, so that the numpy-only
#: ``occkit.geometry.numpy_se3`` (the index builder's) loads without torch.
_SOURCES = {
    "VoxelGrid": "grid",
    "OCC3D_GRID": "grid",
    "SURROUNDOCC_GRID": "grid",
    "quaternion_to_matrix": "se3",
    "matrix_to_quaternion": "se3",
    "make_transform": "se3",
    "transform_from_quaternion": "se3",
    "compose": "se3",
    "invert_transform": "se3",
    "transform_points": "se3",
    "rotation_about_z": "se3",
    "project": "camera",
    "unproject": "camera",
    "in_image_mask": "camera",
    "project_points": "camera",
    "resize_matrix": "camera",
    "crop_matrix": "camera",
    "flip_matrix": "camera",
    "rotate_matrix": "camera",
    "image_aug_matrix": "camera",
    "apply_image_aug": "camera",
    "invert_image_aug": "camera",
    "image_aug_to_post_rot_tran": "camera",
    "post_rot_tran_to_image_aug": "camera",
    "Voxels": "voxelize",
    "hard_voxelize": "voxelize",
    "voxelize_batch": "voxelize",
    "lidar_visibility": "visibility",
    "camera_visibility": "visibility",
}

__all__ = list(_SOURCES)


def __getattr__(name: str) -> Any:
    if name not in _SOURCES:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_SOURCES[name]}"), name)
    globals()[name] = value
    return value


def __dir__() -> list[str]:
    return sorted(set(globals()) | set(_SOURCES))
