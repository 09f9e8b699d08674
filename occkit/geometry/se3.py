"""Rigid transforms (SE(3)) as batched 4x4 homogeneous matrices.

Quaternions are ``(w, x, y, z)``, the order nuScenes stores them in. A matrix named ``a2b`` maps points
expressed in frame ``a`` to frame ``b`` (``cam2ego``, ``ego2global``), so chains read right to left:
``a2c = b2c @ a2b == compose(b2c, a2b)``. Every function broadcasts over leading dimensions and keeps the
device and dtype of its inputs.
"""

from __future__ import annotations

from functools import reduce

import torch
from torch import Tensor

from occkit.geometry._shapes import check_shape

__all__ = [
    "quaternion_to_matrix",
    "matrix_to_quaternion",
    "make_transform",
    "transform_from_quaternion",
    "compose",
    "invert_transform",
    "transform_points",
    "rotation_about_z",
]


def quaternion_to_matrix(quaternion: Tensor) -> Tensor:
    """Rotation matrices of ``(w, x, y, z)`` quaternions.

    Args:
        quaternion: ``(..., 4)``, any non-zero norm; it is normalised first, so records rounded to a few
            decimals still give orthonormal matrices.

    Returns:
        ``(..., 3, 3)`` rotation matrices.
    """
    check_shape(quaternion, (4,), "quaternion")
    q = quaternion / torch.linalg.vector_norm(quaternion, dim=-1, keepdim=True)
    w, x, y, z = q.unbind(-1)
    rows = (
        (1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)),
        (2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)),
        (2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)),
    )
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)


def _sqrt_positive(x: Tensor) -> Tensor:
    # The inner where keeps sqrt away from 0, whose infinite gradient would turn into NaN through the clamp.
    positive = x > 0
    return torch.where(positive, torch.sqrt(torch.where(positive, x, torch.ones_like(x))), torch.zeros_like(x))


def matrix_to_quaternion(rotation: Tensor) -> Tensor:
    """Unit ``(w, x, y, z)`` quaternions of rotation matrices, with canonical sign ``w >= 0``.

    Each of ``|w|, |x|, |y|, |z|`` can be read off the diagonal, and the other three components follow from
    off-diagonal sums divided by it. Dividing by the largest of the four (Shepperd's method) keeps the
    result accurate for every rotation, including half turns where ``w`` is 0.

    Args:
        rotation: ``(..., 3, 3)`` rotation matrices.

    Returns:
        ``(..., 4)`` unit quaternions.
    """
    check_shape(rotation, (3, 3), "rotation")
    m00, m01, m02, m10, m11, m12, m20, m21, m22 = rotation.flatten(-2).unbind(-1)
    # 2 * |q_i| for i in (w, x, y, z).
    q_abs = _sqrt_positive(
        torch.stack(
            (
                1 + m00 + m11 + m22,
                1 + m00 - m11 - m22,
                1 - m00 + m11 - m22,
                1 - m00 - m11 + m22,
            ),
            dim=-1,
        )
    )
    # Row i holds 4 * q_i * q; dividing it by 4 * |q_i| gives q up to sign.
    candidates = torch.stack(
        (
            torch.stack((q_abs[..., 0] ** 2, m21 - m12, m02 - m20, m10 - m01), dim=-1),
            torch.stack((m21 - m12, q_abs[..., 1] ** 2, m10 + m01, m02 + m20), dim=-1),
            torch.stack((m02 - m20, m10 + m01, q_abs[..., 2] ** 2, m12 + m21), dim=-1),
            torch.stack((m10 - m01, m20 + m02, m21 + m12, q_abs[..., 3] ** 2), dim=-1),
        ),
        dim=-2,
    )
    # The largest |q_i| is at least 1/2 for a unit quaternion; the floor only guards the unused rows.
    candidates = candidates / (2 * q_abs.clamp(min=0.1)[..., None])
    best = q_abs.argmax(dim=-1)
    index = best[..., None, None].expand(*best.shape, 1, 4)
    q = candidates.gather(-2, index).squeeze(-2)
    q = torch.where(q[..., :1] < 0, -q, q)
    return q / torch.linalg.vector_norm(q, dim=-1, keepdim=True)


def make_transform(rotation: Tensor, translation: Tensor) -> Tensor:
    """Homogeneous transforms ``[[R, t], [0, 1]]``.

    Args:
        rotation: ``(..., 3, 3)``.
        translation: ``(..., 3)``; its leading dimensions broadcast with those of ``rotation``.

    Returns:
        ``(..., 4, 4)``.
    """
    check_shape(rotation, (3, 3), "rotation")
    check_shape(translation, (3,), "translation")
    batch = torch.broadcast_shapes(rotation.shape[:-2], translation.shape[:-1])
    top = torch.cat((rotation.expand(*batch, 3, 3), translation.expand(*batch, 3)[..., None]), dim=-1)
    bottom = torch.tensor((0.0, 0.0, 0.0, 1.0), device=top.device, dtype=top.dtype)
    return torch.cat((top, bottom.expand(*batch, 1, 4)), dim=-2)


def transform_from_quaternion(quaternion: Tensor, translation: Tensor) -> Tensor:
    """Homogeneous transforms from a ``(w, x, y, z)`` rotation and a translation.

    This is the form of nuScenes ``calibrated_sensor`` (sensor2ego) and ``ego_pose`` (ego2global) records.

    Args:
        quaternion: ``(..., 4)``, normalised internally.
        translation: ``(..., 3)``.

    Returns:
        ``(..., 4, 4)``.
    """
    return make_transform(quaternion_to_matrix(quaternion), translation)


def compose(*transforms: Tensor) -> Tensor:
    """Matrix product of transforms, leftmost applied last: ``compose(b2c, a2b) == b2c @ a2b``.

    Args:
        *transforms: one or more ``(..., 4, 4)`` tensors whose leading dimensions broadcast together.

    Returns:
        ``(..., 4, 4)``.
    """
    if not transforms:
        raise ValueError("compose needs at least one transform, got none")
    for i, transform in enumerate(transforms):
        check_shape(transform, (4, 4), f"transforms[{i}]")
    return reduce(torch.matmul, transforms)


def invert_transform(transform: Tensor) -> Tensor:
    """Inverse of rigid transforms, ``[[R^T, -R^T t], [0, 1]]``.

    Exact and cheaper than a general inverse, but only valid when the 3x3 block is a rotation.

    Args:
        transform: ``(..., 4, 4)`` rigid transforms.

    Returns:
        ``(..., 4, 4)``.
    """
    check_shape(transform, (4, 4), "transform")
    rotation_t = transform[..., :3, :3].transpose(-1, -2)
    translation = transform[..., :3, 3:]
    return make_transform(rotation_t, -(rotation_t @ translation)[..., 0])


def transform_points(transform: Tensor, points: Tensor) -> Tensor:
    """Apply transforms to point sets: ``R p + t``.

    Args:
        transform: ``(..., 4, 4)``.
        points: ``(..., N, 3)``; the leading dimensions broadcast with those of ``transform``, e.g. points
            ``(B, 1, N, 3)`` with per-camera transforms ``(B, C, 4, 4)`` give ``(B, C, N, 3)``.

    Returns:
        ``(..., N, 3)``.
    """
    check_shape(transform, (4, 4), "transform")
    if points.ndim < 2:
        raise ValueError(f"points must have shape (..., N, 3), got {tuple(points.shape)}")
    check_shape(points, (3,), "points")
    # Row vectors: p @ R^T == (R p)^T, which lets matmul broadcast the batch dimensions.
    return points @ transform[..., :3, :3].transpose(-1, -2) + transform[..., None, :3, 3]


def rotation_about_z(yaw: Tensor) -> Tensor:
    """Rotations by ``yaw`` radians about +z (counter-clockwise seen from above, x towards y).

    Args:
        yaw: ``(...)`` angles in radians.

    Returns:
        ``(..., 3, 3)``.
    """
    cos, sin = torch.cos(yaw), torch.sin(yaw)
    zero, one = torch.zeros_like(yaw), torch.ones_like(yaw)
    rows = ((cos, -sin, zero), (sin, cos, zero), (zero, zero, one))
    return torch.stack([torch.stack(row, dim=-1) for row in rows], dim=-2)
