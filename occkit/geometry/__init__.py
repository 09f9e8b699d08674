"""Geometry core: voxel grids, rigid transforms, cameras and voxelization, as pure functions of tensors.

Shapes are in every docstring; everything is differentiable where that makes sense and runs on any device.
Frames, index orders and matrix conventions: docs/conventions.md.
"""

from occkit.geometry.camera import (
    apply_image_aug,
    crop_matrix,
    flip_matrix,
    image_aug_matrix,
    image_aug_to_post_rot_tran,
    in_image_mask,
    invert_image_aug,
    post_rot_tran_to_image_aug,
    project,
    project_points,
    resize_matrix,
    rotate_matrix,
    unproject,
)
from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid
from occkit.geometry.se3 import (
    compose,
    invert_transform,
    make_transform,
    matrix_to_quaternion,
    quaternion_to_matrix,
    rotation_about_z,
    transform_from_quaternion,
    transform_points,
)
from occkit.geometry.voxelize import Voxels, hard_voxelize, voxelize_batch

__all__ = [
    "VoxelGrid",
    "OCC3D_GRID",
    "SURROUNDOCC_GRID",
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "make_transform",
    "transform_from_quaternion",
    "compose",
    "invert_transform",
    "transform_points",
    "rotation_about_z",
    "project",
    "unproject",
    "in_image_mask",
    "project_points",
    "resize_matrix",
    "crop_matrix",
    "flip_matrix",
    "rotate_matrix",
    "image_aug_matrix",
    "apply_image_aug",
    "invert_image_aug",
    "image_aug_to_post_rot_tran",
    "post_rot_tran_to_image_aug",
    "Voxels",
    "hard_voxelize",
    "voxelize_batch",
]
