"""Pinhole cameras and 2D image augmentation.

Camera frame: x right, y down, z forward. Pixel coordinates are continuous, ``u`` right and ``v`` down:
pixel ``(i, j)`` covers ``[i, i + 1) x [j, j + 1)``, so its centre is ``(i + 0.5, j + 0.5)``, and an image
of height ``H`` and width ``W`` holds ``u`` in ``[0, W)`` and ``v`` in ``[0, H)``.

Image augmentation (resize, crop, flip, rotate) is a 3x3 homogeneous affine matrix ``A`` with
``[u', v', 1]^T = A [u, v, 1]^T``, mapping original-image pixels to augmented-image pixels.
BEVDet-family code stores the same map as ``post_rot`` / ``post_tran``; converters to and from that form
are at the end of this module.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
import torch.nn.functional as F
from torch import Tensor

from occkit.geometry._shapes import check_shape
from occkit.geometry.se3 import transform_points

__all__ = [
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
]


def _check_image_size(image_size: Sequence[int]) -> tuple[int, int]:
    size = tuple(image_size)
    if len(size) != 2 or any(int(n) != n or n <= 0 for n in size):
        raise ValueError(f"image_size must be two positive integers (H, W), got {image_size!r}")
    return int(size[0]), int(size[1])


def _affine(linear: Tensor, offset: Tensor) -> Tensor:
    """``(..., 3, 3)`` matrices ``[[M, t], [0, 0, 1]]`` from ``(..., 2, 2)`` and ``(..., 2)``, broadcast."""
    batch = torch.broadcast_shapes(linear.shape[:-2], offset.shape[:-1])
    top = torch.cat((linear.expand(*batch, 2, 2), offset.expand(*batch, 2)[..., None]), dim=-1)
    bottom = torch.tensor((0.0, 0.0, 1.0), device=top.device, dtype=top.dtype)
    return torch.cat((top, bottom.expand(*batch, 1, 3)), dim=-2)


# --------------------------------------------------------------------------- projection
def project(points_cam: Tensor, intrinsics: Tensor, eps: float = 1e-5) -> tuple[Tensor, Tensor]:
    """Pinhole projection of camera-frame points to pixels.

    ``u = fx x / z + s y / z + cx`` and ``v = fy y / z + cy``, read from the full intrinsic matrix (skew
    allowed; its last row is taken to be ``(0, 0, 1)``). ``z`` is clamped to ``eps`` in magnitude, keeping
    its sign, before dividing, so points on or behind the image plane give large but finite pixels; use
    ``depth`` (or :func:`in_image_mask`) to discard them.

    Args:
        points_cam: ``(..., 3)`` points in the camera frame.
        intrinsics: ``(..., 3, 3)``; leading dimensions broadcast with those of ``points_cam``.
        eps: smallest ``|z|`` divided by.

    Returns:
        uv: ``(..., 2)`` continuous pixel coordinates.
        depth: ``(...)`` the unclamped ``z``.
    """
    check_shape(points_cam, (3,), "points_cam")
    check_shape(intrinsics, (3, 3), "intrinsics")
    z = points_cam[..., 2]
    floor = torch.full_like(z, eps)
    z_safe = torch.where(z.abs() >= eps, z, torch.where(z < 0, -floor, floor))
    normalised = points_cam[..., :2] / z_safe[..., None]
    uv = (intrinsics[..., :2, :2] @ normalised[..., None])[..., 0] + intrinsics[..., :2, 2]
    return uv, z.expand(uv.shape[:-1])


def unproject(uv: Tensor, depth: Tensor, intrinsics: Tensor) -> Tensor:
    """Camera-frame points seen at pixels ``uv`` with depth ``depth``: the inverse of :func:`project`.

    Args:
        uv: ``(..., 2)`` pixel coordinates.
        depth: ``(...)`` camera-frame ``z`` (positive in front of the camera).
        intrinsics: ``(..., 3, 3)``.

    Returns:
        ``(..., 3)`` points with ``z == depth``.
    """
    check_shape(uv, (2,), "uv")
    check_shape(intrinsics, (3, 3), "intrinsics")
    homogeneous = F.pad(uv, (0, 1), value=1.0)
    rays = torch.linalg.solve(intrinsics, homogeneous[..., None])[..., 0]
    return rays * depth[..., None]


def in_image_mask(uv: Tensor, depth: Tensor, image_size: Sequence[int], min_depth: float = 1e-5) -> Tensor:
    """Which projections land inside an image, in front of the camera.

    Args:
        uv: ``(..., 2)`` pixel coordinates.
        depth: ``(...)`` camera-frame ``z``.
        image_size: ``(H, W)`` in pixels.
        min_depth: depths at or below this are invalid.

    Returns:
        ``(...)`` bool: ``depth > min_depth`` and ``0 <= u < W`` and ``0 <= v < H``.
    """
    check_shape(uv, (2,), "uv")
    height, width = _check_image_size(image_size)
    u, v = uv.unbind(-1)
    return (depth > min_depth) & (u >= 0) & (u < width) & (v >= 0) & (v < height)


def project_points(
    points: Tensor,
    frame2cam: Tensor,
    intrinsics: Tensor,
    image_aug: Tensor | None,
    image_size: Sequence[int],
    eps: float = 1e-5,
    min_depth: float = 1e-5,
) -> tuple[Tensor, Tensor, Tensor]:
    """Project points of any frame into (augmented) camera images.

    Chain: rigid transform into the camera, pinhole projection, image augmentation, then the in-image
    test against the augmented image size.

    Args:
        points: ``(..., N, 3)`` points in the source frame (ego, lidar, ...).
        frame2cam: ``(..., 4, 4)`` source frame to camera.
        intrinsics: ``(..., 3, 3)``.
        image_aug: ``(..., 3, 3)`` original-to-augmented pixel map, or ``None`` for no augmentation.
        image_size: ``(H, W)`` of the augmented image.
        eps: see :func:`project`.
        min_depth: see :func:`in_image_mask`.

    Leading dimensions of all tensors broadcast, e.g. points ``(B, 1, N, 3)`` with per-camera matrices
    ``(B, C, 4, 4)`` and ``(B, C, 3, 3)``.

    Returns:
        uv: ``(..., N, 2)`` augmented-image pixel coordinates.
        depth: ``(..., N)`` camera-frame ``z``.
        valid: ``(..., N)`` bool, see :func:`in_image_mask`.
    """
    check_shape(intrinsics, (3, 3), "intrinsics")
    if image_aug is not None:
        check_shape(image_aug, (3, 3), "image_aug")
    points_cam = transform_points(frame2cam, points)
    # The extra axis lines the per-camera matrices up against the N points.
    uv, depth = project(points_cam, intrinsics[..., None, :, :], eps)
    if image_aug is not None:
        uv = apply_image_aug(image_aug[..., None, :, :], uv)
    return uv, depth, in_image_mask(uv, depth, image_size, min_depth)


# --------------------------------------------------------------------------- image augmentation
def resize_matrix(
    scale: float | tuple[float, float], *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """``(3, 3)`` map of a resize: ``u' = sx u``, ``v' = sy v``.

    Args:
        scale: one factor for both axes, or ``(sx, sy)``.
    """
    sx, sy = (scale, scale) if isinstance(scale, (int, float)) else scale
    return torch.tensor(((sx, 0.0, 0.0), (0.0, sy, 0.0), (0.0, 0.0, 1.0)), device=device, dtype=dtype)


def crop_matrix(
    left: float, top: float, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """``(3, 3)`` map of a crop whose top-left corner is ``(left, top)``: ``u' = u - left``, ``v' = v - top``."""
    return torch.tensor(((1.0, 0.0, -left), (0.0, 1.0, -top), (0.0, 0.0, 1.0)), device=device, dtype=dtype)


def flip_matrix(
    width: float, *, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32
) -> Tensor:
    """``(3, 3)`` map of a horizontal flip of an image ``width`` pixels wide: ``u' = width - u``, ``v' = v``.

    With continuous pixels this sends pixel column ``i`` to column ``width - 1 - i``.
    """
    return torch.tensor(((-1.0, 0.0, width), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0)), device=device, dtype=dtype)


def rotate_matrix(
    angle_deg: float,
    center: tuple[float, float],
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """``(3, 3)`` map of an image rotation by ``angle_deg`` about ``center = (cu, cv)``.

    ``u' = R (u - c) + c`` with ``R = [[cos a, sin a], [-sin a, cos a]]``: counter-clockwise on screen for
    positive angles (``v`` points down), as PIL ``Image.rotate(angle_deg)`` and BEVDet's ``get_rot``.
    """
    radians = math.radians(angle_deg)
    cos, sin = math.cos(radians), math.sin(radians)
    cu, cv = center
    return torch.tensor(
        (
            (cos, sin, cu - (cos * cu + sin * cv)),
            (-sin, cos, cv - (-sin * cu + cos * cv)),
            (0.0, 0.0, 1.0),
        ),
        device=device,
        dtype=dtype,
    )


def image_aug_matrix(
    resize: float | tuple[float, float],
    crop: tuple[float, float, float, float],
    flip: bool = False,
    rotate_deg: float = 0.0,
    *,
    device: torch.device | str | None = None,
    dtype: torch.dtype = torch.float32,
) -> Tensor:
    """``(3, 3)`` map of the BEVDet / FlashOcc ``img_transform`` augmentation.

    Order: resize, crop ``(left, top, right, bottom)`` (in resized pixels), flip about the crop width, then
    rotate about the crop centre. The output image is ``(bottom - top, right - left)`` pixels.

    Example:
        >>> A = image_aug_matrix(0.44, (0, 140, 704, 396))
        >>> apply_image_aug(A, torch.tensor([800.0, 450.0]))
        tensor([352.,  58.])
    """
    left, top, right, bottom = crop
    width, height = right - left, bottom - top
    # Composed in float64 so the float32 result is a single rounding of the exact map.
    f64 = torch.float64
    matrix = crop_matrix(left, top, dtype=f64) @ resize_matrix(resize, dtype=f64)
    if flip:
        matrix = flip_matrix(width, dtype=f64) @ matrix
    matrix = rotate_matrix(rotate_deg, (width / 2, height / 2), dtype=f64) @ matrix
    return matrix.to(device=device, dtype=dtype)


def apply_image_aug(image_aug: Tensor, uv: Tensor) -> Tensor:
    """Map pixel coordinates through affine image augmentations.

    Args:
        image_aug: ``(..., 3, 3)`` with last row ``(0, 0, 1)``.
        uv: ``(..., 2)``; leading dimensions broadcast with those of ``image_aug``.

    Returns:
        ``(..., 2)`` augmented-image pixel coordinates.
    """
    check_shape(image_aug, (3, 3), "image_aug")
    check_shape(uv, (2,), "uv")
    return (image_aug[..., :2, :2] @ uv[..., None])[..., 0] + image_aug[..., :2, 2]


def invert_image_aug(image_aug: Tensor) -> Tensor:
    """Inverse affine maps (augmented-image pixels back to original pixels).

    Args:
        image_aug: ``(..., 3, 3)`` with last row ``(0, 0, 1)`` and an invertible 2x2 block.

    Returns:
        ``(..., 3, 3)``.
    """
    check_shape(image_aug, (3, 3), "image_aug")
    a, b = image_aug[..., 0, 0], image_aug[..., 0, 1]
    c, d = image_aug[..., 1, 0], image_aug[..., 1, 1]
    det = a * d - b * c
    inverse = torch.stack((torch.stack((d, -b), dim=-1), torch.stack((-c, a), dim=-1)), dim=-2) / det[..., None, None]
    return _affine(inverse, -(inverse @ image_aug[..., :2, 2:])[..., 0])


def image_aug_to_post_rot_tran(image_aug: Tensor) -> tuple[Tensor, Tensor]:
    """Split affine maps into BEVDet's ``post_rot`` / ``post_tran``.

    Args:
        image_aug: ``(..., 3, 3)``.

    Returns:
        post_rot: ``(..., 3, 3)`` with the 2x2 block top-left and 1 at ``[2, 2]``.
        post_tran: ``(..., 3)`` with 0 as third entry.
    """
    check_shape(image_aug, (3, 3), "image_aug")
    linear = image_aug[..., :2, :2]
    post_rot = _affine(linear, linear.new_zeros(2))
    post_tran = F.pad(image_aug[..., :2, 2], (0, 1))
    return post_rot, post_tran


def post_rot_tran_to_image_aug(post_rot: Tensor, post_tran: Tensor) -> Tensor:
    """Affine maps from BEVDet's ``post_rot`` / ``post_tran`` (their third row and entry are ignored).

    Args:
        post_rot: ``(..., 3, 3)``.
        post_tran: ``(..., 3)``; leading dimensions broadcast with those of ``post_rot``.

    Returns:
        ``(..., 3, 3)``.
    """
    check_shape(post_rot, (3, 3), "post_rot")
    check_shape(post_tran, (3,), "post_tran")
    return _affine(post_rot[..., :2, :2], post_tran[..., :2])
