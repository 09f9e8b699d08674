"""Numpy twins of :mod:`occkit.geometry.se3`, for code that reads datasets and needs no tensors (the index, info
files).

The same conventions: quaternions ``(w, x, y, z)``, ``a2b`` maps points of frame ``a`` to frame ``b``, every function
broadcasts over leading dimensions, float64 in and out. Two differences, both for data read from files: a
quaternion whose norm is below :data:`MIN_QUATERNION_NORM` (or not finite) is an error instead of a NaN matrix, and
:func:`rotation_yaw` reads a heading back the way nuscenes-devkit does. ``tests/test_se3.py`` checks each twin against
the torch function on random inputs.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "MIN_QUATERNION_NORM",
    "quaternion_to_matrix",
    "make_transform",
    "transform_from_quaternion",
    "invert_transform",
    "transform_points",
    "rotation_about_z",
    "rotation_yaw",
]

#: Quaternions with a smaller norm (or a non-finite one) are no rotation: an error, not a NaN matrix. Others are
#: normalised, as nuscenes-devkit (pyquaternion) does.
MIN_QUATERNION_NORM = 1e-6


def quaternion_to_matrix(quaternion: np.ndarray) -> np.ndarray:
    """Rotation matrices of ``(..., 4)`` (w, x, y, z) quaternions, normalised first.

    Returns:
        ``(..., 3, 3)``.

    Raises:
        ValueError: a quaternion's norm is below :data:`MIN_QUATERNION_NORM` or not finite; the message gives its
            row in the flattened batch.
    """
    quaternion = np.asarray(quaternion, dtype=np.float64)
    norms = np.linalg.norm(quaternion, axis=-1, keepdims=True)
    bad = ~((norms[..., 0] >= MIN_QUATERNION_NORM) & np.isfinite(norms[..., 0]))
    if bad.any():
        row = int(np.flatnonzero(bad.reshape(-1))[0])
        raise ValueError(
            f"quaternion {row} {quaternion.reshape(-1, 4)[row].tolist()} is no rotation (norm "
            f"{float(norms.reshape(-1)[row]):.3g}; expected (w, x, y, z) of norm 1)"
        )
    w, x, y, z = np.moveaxis(quaternion / norms, -1, 0)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def make_transform(rotation: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """Homogeneous transforms ``[[R, t], [0, 1]]`` of ``(..., 3, 3)`` rotations and ``(..., 3)`` translations
    (leading dimensions broadcast); ``(..., 4, 4)``."""
    rotation, translation = np.asarray(rotation, dtype=np.float64), np.asarray(translation, dtype=np.float64)
    batch = np.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    transform = np.zeros((*batch, 4, 4))
    transform[..., :3, :3] = rotation
    transform[..., :3, 3] = translation
    transform[..., 3, 3] = 1.0
    return transform


def transform_from_quaternion(quaternion: np.ndarray, translation: np.ndarray) -> np.ndarray:
    """``(..., 4, 4)`` from ``(..., 4)`` (w, x, y, z) rotations and ``(..., 3)`` translations: the form of nuScenes
    ``calibrated_sensor`` and ``ego_pose`` records. Raises as :func:`quaternion_to_matrix`."""
    return make_transform(quaternion_to_matrix(quaternion), translation)


def invert_transform(transform: np.ndarray) -> np.ndarray:
    """Inverse of ``(..., 4, 4)`` rigid transforms, ``[[R^T, -R^T t], [0, 1]]`` (valid only when the 3x3 block is a
    rotation)."""
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    return make_transform(rotation_t, -(rotation_t @ transform[..., :3, 3:])[..., 0])


def transform_points(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``R p + t`` of ``(..., N, 3)`` points under ``(..., 4, 4)`` transforms (leading dimensions broadcast)."""
    # Row vectors: p @ R^T == (R p)^T, which lets matmul broadcast the batch dimensions.
    return points @ np.swapaxes(transform[..., :3, :3], -1, -2) + transform[..., None, :3, 3]


def rotation_about_z(yaw: np.ndarray) -> np.ndarray:
    """``(..., 3, 3)`` rotations by ``(...)`` yaw angles (rad) about +z, counter-clockwise seen from above."""
    yaw = np.asarray(yaw, dtype=np.float64)
    cos, sin, zero, one = np.cos(yaw), np.sin(yaw), np.zeros_like(yaw), np.ones_like(yaw)
    rows = ((cos, -sin, zero), (sin, cos, zero), (zero, zero, one))
    return np.stack([np.stack(row, axis=-1) for row in rows], axis=-2)


def rotation_yaw(rotation: np.ndarray) -> np.ndarray:
    """Yaw of ``(..., 3, 3)`` rotations as pyquaternion's ``yaw_pitch_roll[0]`` (``R = R_x R_y R_z(yaw)``); ``(...)``.

    nuscenes-devkit and mmdetection3d's info files take a box's yaw this way. For a rotation about z alone it is the
    heading of the box's x axis, ``atan2(R[1, 0], R[0, 0])``, and inverts :func:`rotation_about_z`; with the ego's
    pitch and roll folded in, the two differ by about pitch * roll (1e-4 rad).
    """
    return np.arctan2(-rotation[..., 0, 1], rotation[..., 0, 0])
