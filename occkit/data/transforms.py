"""Training and test transforms: image augmentation, BEV augmentation and simulated sensor failures.

Every geometric augmentation is sampled as parameters and recorded as a matrix (docs/conventions.md):

- images: :class:`ImageAugParams` -> ``img_aug`` ``(3, 3)``, original to augmented pixels, built by
  :func:`occkit.geometry.image_aug_matrix`; :func:`augment_image` warps the pixels to match it exactly.
- BEV: ``occ_aug`` ``(4, 4)`` acts in the ego frame (occupancy labels), ``bev_aug = inv(lidar2ego) @ occ_aug @
  lidar2ego`` in the LiDAR frame (points, boxes), so both describe the same physical transform.

The values follow FlashOcc / BEVDet (images) and DAOcc (BEV flips); the sensor failures serve robustness evaluation.
Functions are pure: inputs are never modified.
"""

from __future__ import annotations

import functools
import math
import warnings
from collections.abc import Collection, Sequence
from dataclasses import dataclass

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from occkit.config import check_ranges
from occkit.geometry.camera import image_aug_matrix
from occkit.geometry.grid import VoxelGrid
from occkit.geometry.se3 import invert_transform, rotation_about_z, transform_points

__all__ = [
    "ImageAugConfig",
    "ImageAugParams",
    "sample_image_aug",
    "augment_image",
    "BevAugConfig",
    "sample_bev_aug",
    "lidar_frame_aug",
    "augment_points",
    "augment_boxes",
    "augment_occupancy",
    "augment_flow",
    "drop_cameras",
    "drop_lidar_beams",
    "drop_points",
    "sanitize_points",
]


def _check_range(values: tuple[float, float], name: str) -> None:
    if len(values) != 2 or values[0] > values[1]:
        raise ValueError(f"{name} must be (low, high) with low <= high, got {values!r}")


# --------------------------------------------------------------------------------------------- image augmentation
@dataclass(frozen=True)
class ImageAugConfig:
    """Random resize, crop, flip and rotation of camera images (BEVDet / FlashOcc ``data_config``)."""

    final_size: tuple[int, int] = (256, 704)
    """Network input size ``(H, W)`` in pixels; the crop has exactly this size."""
    resize_range: tuple[float, float] = (-0.06, 0.11)
    """Training offset added to the base resize ``final_W / image_W`` (0.44 for 1600 x 900 images), uniform."""
    bottom_crop: bool = True
    """Keep the bottom ``final_H`` rows of the resized image (cutting sky); otherwise a random (test: centred) band."""
    flip: bool = True
    """Flip images horizontally with probability 0.5 in training."""
    rotate_deg: tuple[float, float] = (-5.4, 5.4)
    """Training rotation range in degrees, uniform; positive is counter-clockwise on screen."""

    def __post_init__(self) -> None:
        if len(self.final_size) != 2 or any(int(n) != n or n <= 0 for n in self.final_size):
            raise ValueError(f"final_size must be two positive integers (H, W), got {self.final_size!r}")
        _check_range(self.resize_range, "resize_range")
        _check_range(self.rotate_deg, "rotate_deg")
        # A resize offset past +-1 scales an image to nothing or to many times the memory of the final size.
        check_ranges("image_aug", self, {"final_size": (1, 8192), "resize_range": (-0.9, 4.0),
                                         "rotate_deg": (-180.0, 180.0)})  # fmt: skip


@dataclass(frozen=True)
class ImageAugParams:
    """One sampled image augmentation, applied in the order resize, crop, flip, rotate."""

    resize: float
    """Scale factor from original to resized pixels."""
    crop: tuple[int, int, int, int]
    """``(left, top, right, bottom)`` in resized pixels; may reach past the resized image (filled with black)."""
    flip: bool
    """Horizontal flip of the cropped image."""
    rotate_deg: float
    """Rotation about the crop centre in degrees, counter-clockwise on screen."""

    @property
    def output_size(self) -> tuple[int, int]:
        """Augmented image size ``(H, W)``."""
        left, top, right, bottom = self.crop
        return bottom - top, right - left

    def matrix(self, device: torch.device | str | None = None, dtype: torch.dtype = torch.float32) -> Tensor:
        """``(3, 3)`` map from original to augmented pixels (``img_aug``)."""
        return image_aug_matrix(self.resize, self.crop, self.flip, self.rotate_deg, device=device, dtype=dtype)


def _resized_size(width: int, height: int, resize: float) -> tuple[int, int]:
    # BEVDet truncates with int(); the epsilon keeps e.g. 1600 * (704 / 1600) from truncating to 703.
    return math.floor(width * resize + 1e-6), math.floor(height * resize + 1e-6)


def sample_image_aug(
    config: ImageAugConfig, image_size: tuple[int, int], train: bool, rng: np.random.Generator
) -> ImageAugParams:
    """Sample the augmentation of one camera image (BEVDet ``sample_augmentation``).

    Args:
        config: augmentation ranges.
        image_size: original image size ``(W, H)``, the order of PIL's ``Image.size``.
        train: random parameters if true; otherwise the deterministic test transform (base resize, bottom or centred
            crop, horizontally centred, no flip or rotation).
        rng: random source, used only in training.

    Example:
        >>> sample_image_aug(ImageAugConfig(), (1600, 900), False, np.random.default_rng(0))
        ImageAugParams(resize=0.44, crop=(0, 140, 704, 396), flip=False, rotate_deg=0.0)
    """
    width, height = image_size
    final_h, final_w = config.final_size
    resize = final_w / width
    if train:
        resize += float(rng.uniform(*config.resize_range))
    new_w, new_h = _resized_size(width, height, resize)
    spare_w, spare_h = max(0, new_w - final_w), max(0, new_h - final_h)
    if config.bottom_crop:
        # Negative when the resized image is shorter than the crop: the band then starts above the image.
        top = new_h - final_h
    elif train:
        top = int(rng.uniform(0, spare_h))
    else:
        top = spare_h // 2
    left = int(rng.uniform(0, spare_w)) if train else spare_w // 2
    flip = bool(train and config.flip and rng.random() < 0.5)
    rotate = float(rng.uniform(*config.rotate_deg)) if train else 0.0
    return ImageAugParams(resize, (left, top, left + final_w, top + final_h), flip, rotate)


def augment_image(image: Image.Image | np.ndarray, params: ImageAugParams) -> np.ndarray:
    """Warp an RGB image exactly as ``params.matrix()`` maps its pixels (BEVDet ``img_transform_core``).

    PIL bilinear resize, crop, left-right transpose, then PIL ``rotate`` (nearest neighbour, as BEVDet) about the crop
    centre. BEVDet resizes to ``int(W * resize)`` pixels and so scales by slightly less than ``resize``; here the
    resize reads a source box of ``new_W / resize`` pixels, so the scale is exactly ``resize`` and pixels land where
    the matrix says.

    Args:
        image: PIL image (converted to RGB) or ``(H, W, 3)`` uint8 array.
        params: from :func:`sample_image_aug`.

    Returns:
        ``(H', W', 3)`` uint8 with ``(H', W') == params.output_size``; areas outside the source are black.
    """
    if isinstance(image, np.ndarray):
        if image.ndim != 3 or image.shape[2] != 3 or image.dtype != np.uint8:
            raise ValueError(f"image array must be (H, W, 3) uint8, got {image.shape} {image.dtype}")
        image = Image.fromarray(image)
    elif image.mode != "RGB":
        image = image.convert("RGB")
    new_w, new_h = _resized_size(*image.size, params.resize)
    box = (0.0, 0.0, new_w / params.resize, new_h / params.resize)
    image = image.resize((new_w, new_h), Image.Resampling.BILINEAR, box=box)
    image = image.crop(params.crop)
    if params.flip:
        image = image.transpose(Image.Transpose.FLIP_LEFT_RIGHT)
    if params.rotate_deg != 0.0:
        image = image.rotate(params.rotate_deg)
    return np.asarray(image)


# --------------------------------------------------------------------------------------------- BEV augmentation
@dataclass(frozen=True)
class BevAugConfig:
    """Random flips, rotation and scale of the bird's-eye-view frame (BEVDet ``bda_aug_conf``)."""

    flip_x: float = 0.5
    """Probability of flipping the ego x axis (x -> -x, occupancy array axis 0)."""
    flip_y: float = 0.5
    """Probability of flipping the ego y axis (y -> -y, occupancy array axis 1)."""
    rotate_deg: tuple[float, float] = (0.0, 0.0)
    """Rotation about the ego z axis in degrees, uniform; DAOcc and FlashOcc use none."""
    scale: tuple[float, float] = (1.0, 1.0)
    """Uniform scale factor range; DAOcc and FlashOcc use none."""

    def __post_init__(self) -> None:
        for name in ("flip_x", "flip_y"):
            if not 0.0 <= getattr(self, name) <= 1.0:
                raise ValueError(f"{name} is a probability in [0, 1], got {getattr(self, name)}")
        _check_range(self.rotate_deg, "rotate_deg")
        _check_range(self.scale, "scale")
        check_ranges("bev_aug", self, {"rotate_deg": (-180.0, 180.0), "scale": (0.0, 10.0)})
        if self.scale[0] <= 0:
            raise ValueError(f"scale must be positive, got {self.scale!r}")


def sample_bev_aug(config: BevAugConfig, rng: np.random.Generator, train: bool) -> Tensor:
    """Sample ``occ_aug``, the BEV augmentation in the ego frame (identity at test time).

    ``occ_aug = flip @ (scale * rotation)``, the order of BEVDet's ``bev_transform``.

    Returns:
        ``(4, 4)`` float64 mapping ego-frame points to the augmented ego frame.
    """
    occ_aug = torch.eye(4, dtype=torch.float64)
    if not train:
        return occ_aug
    yaw = math.radians(float(rng.uniform(*config.rotate_deg)))
    scale = float(rng.uniform(*config.scale))
    flip = torch.ones(3, dtype=torch.float64)
    flip[0] = -1.0 if rng.random() < config.flip_x else 1.0
    flip[1] = -1.0 if rng.random() < config.flip_y else 1.0
    occ_aug[:3, :3] = flip[:, None] * (scale * rotation_about_z(torch.tensor(yaw, dtype=torch.float64)))
    return occ_aug


def lidar_frame_aug(occ_aug: Tensor, lidar2ego: Tensor) -> Tensor:
    """``bev_aug``: the ego-frame augmentation expressed in the LiDAR frame, ``inv(lidar2ego) @ occ_aug @ lidar2ego``.

    A flip about the ego origin is a flip about a line 0.94 m from the LiDAR on nuScenes, so ``bev_aug`` carries a
    translation; with it, points and boxes stay aligned with the flipped labels.

    Args:
        occ_aug: ``(4, 4)`` ego-frame augmentation.
        lidar2ego: ``(4, 4)`` rigid transform.

    Returns:
        ``(4, 4)`` float64.
    """
    lidar2ego = lidar2ego.to(torch.float64)
    return invert_transform(lidar2ego) @ occ_aug.to(torch.float64) @ lidar2ego


def augment_points(points: Tensor, bev_aug: Tensor) -> Tensor:
    """Apply ``bev_aug`` to the ``x, y, z`` columns of a point cloud; the other columns are kept.

    Args:
        points: ``(P, C)``, ``C >= 3``, in the LiDAR frame.
        bev_aug: ``(4, 4)``.

    Returns:
        ``(P, C)`` in the augmented LiDAR frame, same dtype.
    """
    if points.ndim != 2 or points.shape[1] < 3:
        raise ValueError(f"points must have shape (P, C >= 3), got {tuple(points.shape)}")
    xyz = transform_points(bev_aug.to(torch.float64), points[:, :3].to(torch.float64)).to(points.dtype)
    return torch.cat((xyz, points[:, 3:]), dim=1)


def augment_boxes(boxes: Tensor, bev_aug: Tensor) -> Tensor:
    """Apply ``bev_aug`` to 3D boxes ``[x, y, z, l, w, h, yaw, vx, vy]``.

    ``yaw`` is the heading of the length axis, counter-clockwise from +x about +z. The centre is transformed as a
    point; the heading and velocity as vectors, so a flip mirrors the yaw (x flip: ``pi - yaw``, y flip: ``-yaw``);
    sizes are multiplied by the scale ``|det(A)|^(1/3)`` of the 3x3 block ``A``.

    Args:
        boxes: ``(M, 9)`` in the LiDAR frame.
        bev_aug: ``(4, 4)``.

    Returns:
        ``(M, 9)`` in the augmented LiDAR frame, same dtype, yaw in ``[-pi, pi]``.
    """
    if boxes.ndim != 2 or boxes.shape[1] != 9:
        raise ValueError(f"boxes must have shape (M, 9) [x, y, z, l, w, h, yaw, vx, vy], got {tuple(boxes.shape)}")
    bev_aug = bev_aug.to(torch.float64)
    boxes64 = boxes.to(torch.float64)
    linear = bev_aug[:3, :3]
    centres = transform_points(bev_aug, boxes64[:, :3])
    scale = torch.linalg.det(linear).abs() ** (1.0 / 3.0)
    yaw = boxes64[:, 6]
    heading = torch.stack((torch.cos(yaw), torch.sin(yaw), torch.zeros_like(yaw)), dim=-1) @ linear.T
    velocity = torch.cat((boxes64[:, 7:9], torch.zeros_like(yaw)[:, None]), dim=-1) @ linear.T
    new_yaw = torch.atan2(heading[:, 1], heading[:, 0])
    out = torch.cat((centres, boxes64[:, 3:6] * scale, new_yaw[:, None], velocity[:, :2]), dim=-1)
    return out.to(boxes.dtype)


def _pure_flip_axes(occ_aug: np.ndarray) -> list[int] | None:
    """Axes flipped by ``occ_aug`` if it is only a flip about the origin (no rotation, scale or translation)."""
    diagonal = np.diag(occ_aug[:3, :3])
    is_flip = (
        np.allclose(occ_aug[:3, :3], np.diag(diagonal), atol=1e-9)
        and np.allclose(np.abs(diagonal), 1.0, atol=1e-9)
        and np.allclose(occ_aug[:3, 3], 0.0, atol=1e-9)
    )
    return [axis for axis in range(3) if diagonal[axis] < 0] if is_flip else None


@functools.lru_cache(maxsize=2)
def _octant_sources(matrix_bytes: bytes, grid: VoxelGrid, device: str) -> tuple[Tensor, Tensor]:
    """Input voxel (flat index) under each of the 8 octant centres of every output voxel, and whether it is inside.

    Cached on the matrix: a sample's labels and both masks move with the same augmentation.
    """
    matrix = torch.from_numpy(np.frombuffer(matrix_bytes, dtype=np.float64).reshape(4, 4).copy()).to(device)
    offsets = torch.tensor([[dx, dy, dz] for dx in (-1, 1) for dy in (-1, 1) for dz in (-1, 1)], dtype=torch.float64)
    offsets = offsets * grid.size_tensor(dtype=torch.float64) / 4  # the centres of the voxel's eight octants
    centres = grid.centers(device=device, dtype=torch.float64).reshape(-1, 1, 3) + offsets.to(device)
    source, inside = grid.world_to_index(transform_points(torch.linalg.inv(matrix), centres))
    flat = grid.ravel_index(torch.where(inside[..., None], source, torch.zeros_like(source)))
    return flat, inside


def _octant_samples(values: Tensor, matrix: Tensor, grid: VoxelGrid, fill: int | bool) -> tuple[Tensor, ...]:
    """``values`` (``grid.shape``) read at the 8 octant centres of every output voxel, ``(X*Y*Z, 8)``, ``fill``
    where a centre maps from outside the grid; with the flat input voxels read and whether each is inside."""
    flat, inside = _octant_sources(matrix.numpy().tobytes(), grid, str(values.device))
    samples = values.reshape(-1)[flat]
    samples[~inside] = fill
    return samples, flat, inside


def _first_occupied(samples: Tensor, empty: int) -> Tensor:
    """``(N,)`` index of each row's first sample that is not ``empty`` (0 when all are): the label a resampled
    voxel takes."""
    occupied = samples != empty
    return torch.where(occupied.any(dim=1), occupied.to(torch.uint8).argmax(dim=1), 0)


def augment_occupancy(
    volume: np.ndarray | Tensor, occ_aug: Tensor, grid: VoxelGrid, fill: int | bool, empty: int | None = None
) -> np.ndarray | Tensor:
    """Move a voxel volume (labels or a mask) with the augmentation of its grid's frame.

    Pure flips on a grid symmetric about 0 on the flipped axes are exact array flips (the Occ3D case, where
    ``occ_aug`` is the ego-frame augmentation). Anything else (rotation, scale, translation) is resampled at 2 x 2 x 2
    points per output voxel, inverse-mapped into the input: a mask takes the largest value found (any observed
    sub-point), labels the first value that is not ``empty``. Plain nearest-neighbour sampling of the centre would
    thin surfaces, whose voxels are often only partly covered after a rotation; this keeps them at the cost of at
    most half a voxel of thickening. Sub-points mapped from outside the grid read ``fill``.

    Args:
        volume: ``(X, Y, Z)`` array or tensor of any dtype, ``grid.shape``.
        occ_aug: ``(4, 4)`` augmentation of the grid's frame.
        grid: the volume's grid.
        fill: value for voxels mapped from outside the grid: 255 (ignore) for semantics, 0 for masks.
        empty: the free-space label of a label volume (17 for Occ3D); None for masks.

    Returns:
        The augmented volume, same type, dtype and shape (a new, contiguous array).

    Raises:
        ValueError: a flip on an axis where the grid is not symmetric about 0 (the flipped grid would not be the grid).
    """
    if tuple(volume.shape) != grid.shape:
        raise ValueError(f"volume has shape {tuple(volume.shape)} but the grid {grid!r} has {grid.shape}")
    matrix = occ_aug.detach().cpu().to(torch.float64)
    flip_axes = _pure_flip_axes(matrix.numpy())
    if flip_axes is not None:
        for axis in flip_axes:
            low, high = grid.lower[axis], grid.upper[axis]
            if abs(low + high) > 1e-6 * max(abs(low), abs(high)):
                raise ValueError(
                    f"cannot flip {'xyz'[axis]}: the grid spans [{low:g}, {high:g}] on that axis, not symmetric "
                    "about 0, so the flipped volume would not lie on the grid"
                )
        if isinstance(volume, np.ndarray):
            return np.ascontiguousarray(np.flip(volume, axis=tuple(flip_axes)))
        return torch.flip(volume, dims=flip_axes).contiguous()
    is_numpy = isinstance(volume, np.ndarray)
    values = torch.from_numpy(np.ascontiguousarray(volume)) if is_numpy else volume
    samples, _, _ = _octant_samples(values, matrix, grid, fill)
    if empty is None:
        resampled = samples.max(dim=1).values
    else:
        resampled = samples.gather(1, _first_occupied(samples, empty)[:, None])[:, 0]
    resampled = resampled.reshape(grid.shape)
    return resampled.numpy() if is_numpy else resampled


def augment_flow(
    flow: np.ndarray, semantics: np.ndarray, occ_aug: Tensor, grid: VoxelGrid, fill: int, empty: int
) -> np.ndarray:
    """Move an occupancy flow volume with the augmentation of its grid's frame: positions as the labels, vectors
    with the augmentation's linear part.

    Each output voxel takes the flow of the input voxel its label came from (:func:`augment_occupancy`'s choice on
    ``semantics``; zero where that lies outside the grid), then the vector turns with ``occ_aug``'s upper-left
    ``2 x 2`` block: a flip of x negates ``vx``, a rotation turns the vector, a scale stretches it as it stretches the
    scene (a scene scaled by ``s`` moves ``s`` times as fast).

    Args:
        flow: ``(X, Y, Z, 2)`` float32 ``vx, vy`` (m/s).
        semantics: ``(X, Y, Z)`` the labels of the same frame, before the augmentation.
        occ_aug: ``(4, 4)`` augmentation of the grid's frame.
        grid: the volumes' grid.
        fill, empty: the label of voxels mapped from outside the grid and the free-space label, as given to
            :func:`augment_occupancy` for ``semantics``.

    Returns:
        ``(X, Y, Z, 2)`` float32, a new contiguous array.
    """
    if flow.shape != (*grid.shape, 2):
        raise ValueError(f"flow has shape {tuple(flow.shape)} but the grid {grid!r} needs {(*grid.shape, 2)}")
    matrix = occ_aug.detach().cpu().to(torch.float64)
    linear = matrix[:2, :2].numpy()
    flip_axes = _pure_flip_axes(matrix.numpy())
    if flip_axes is not None:
        moved = augment_occupancy(flow[..., 0], occ_aug, grid, 0), augment_occupancy(flow[..., 1], occ_aug, grid, 0)
        moved = np.stack(moved, axis=-1)
    else:
        source = _first_sources(np.ascontiguousarray(semantics), matrix, grid, fill, empty)
        flat = flow.reshape(-1, 2)
        moved = np.where(source[:, None] >= 0, flat[np.maximum(source, 0)], 0.0).reshape(*grid.shape, 2)
    # Vectors turn with the linear part, computed in float64 and rounded once (a flip is exact either way).
    return np.ascontiguousarray((moved.astype(np.float64) @ linear.T).astype(np.float32))


def _first_sources(semantics: np.ndarray, matrix: Tensor, grid: VoxelGrid, fill: int, empty: int) -> np.ndarray:
    """``(X*Y*Z,)`` int64 flat input voxel each output voxel's label comes from in :func:`augment_occupancy`'s
    resampling (the first octant sample that is not ``empty``, else the first), -1 where that sample is outside."""
    samples, flat, inside = _octant_samples(torch.from_numpy(semantics), matrix, grid, fill)
    first = _first_occupied(samples, empty)
    chosen = flat.gather(1, first[:, None])[:, 0]
    return torch.where(inside.gather(1, first[:, None])[:, 0], chosen, -1).numpy()


# --------------------------------------------------------------------------------------------- sensor failures
def drop_cameras(
    images: Tensor, drop: Sequence[int] | float, rng: np.random.Generator | None = None
) -> tuple[Tensor, Tensor]:
    """Simulate failed cameras by zeroing their images (for normalised images, zero is the mean colour).

    Args:
        images: ``(N, 3, H, W)``.
        drop: camera indices to drop, or the probability of dropping each camera independently.
        rng: random source, required when ``drop`` is a probability.

    Returns:
        images: ``(N, 3, H, W)`` copy with the dropped cameras zeroed.
        kept: ``(N,)`` bool, true for cameras still working.
    """
    if images.ndim != 4:
        raise ValueError(f"images must have shape (N, 3, H, W), got {tuple(images.shape)}")
    num_cameras = images.shape[0]
    if isinstance(drop, (bool, int)):
        raise TypeError(f"drop must be a sequence of camera indices or a float probability, got {drop!r}")
    if isinstance(drop, float):
        if rng is None:
            raise ValueError("drop_cameras needs rng when drop is a probability")
        if not 0.0 <= drop <= 1.0:
            raise ValueError(f"camera drop probability must be in [0, 1], got {drop}")
        kept = torch.from_numpy(rng.random(num_cameras) >= drop)
    else:
        indices = list(drop)
        if any(not 0 <= i < num_cameras for i in indices):
            raise ValueError(f"camera indices {indices} out of range for {num_cameras} cameras")
        kept = torch.ones(num_cameras, dtype=torch.bool)
        kept[indices] = False
    kept = kept.to(images.device)
    return images.masked_fill(~kept[:, None, None, None], 0), kept


def drop_lidar_beams(
    points: Tensor, *, keep_every: int | None = None, keep_rings: Collection[int] | None = None
) -> Tensor:
    """Simulate a sparser LiDAR by keeping only some beams (rings), e.g. 32 -> 16 (``keep_every=2``) or 8 (4).

    Args:
        points: ``(P, 5)`` raw ``.pcd.bin`` rows ``x, y, z, intensity, ring``.
        keep_every: keep rings whose index is a multiple of this.
        keep_rings: keep exactly these ring indices. Give one of the two.

    Returns:
        ``(P', 5)`` the kept rows, in order.
    """
    if (keep_every is None) == (keep_rings is None):
        raise ValueError("give exactly one of keep_every and keep_rings")
    if points.ndim != 2 or points.shape[1] != 5:
        raise ValueError(f"points must be raw (P, 5) rows with the ring index in column 4, got {tuple(points.shape)}")
    rings = points[:, 4].round().long()
    if keep_every is not None:
        if keep_every < 1:
            raise ValueError(f"keep_every must be >= 1, got {keep_every}")
        keep = rings % keep_every == 0
    else:
        keep = torch.isin(rings, torch.tensor(sorted(keep_rings), dtype=torch.long, device=points.device))
    return points[keep]


def drop_points(points: Tensor, fraction: float, rng: np.random.Generator) -> Tensor:
    """Drop a random ``fraction`` of the points (``round(fraction * P)`` rows), keeping the order of the rest.

    Args:
        points: ``(P, C)``.
        fraction: in ``[0, 1]``.
        rng: random source.

    Returns:
        ``(P - round(fraction * P), C)``.
    """
    if not 0.0 <= fraction <= 1.0:
        raise ValueError(f"fraction must be in [0, 1], got {fraction}")
    total = points.shape[0]
    kept = np.sort(rng.choice(total, size=total - round(fraction * total), replace=False))
    return points[torch.from_numpy(kept).to(points.device)]


def sanitize_points(points: Tensor, source: str) -> Tensor:
    """Remove rows holding NaN or infinite values, warning with their count and the file they came from.

    Args:
        points: ``(P, C)``.
        source: where the points were read from (file name), quoted in the warning.

    Returns:
        ``(P', C)`` the finite rows, in order (``points`` itself when all are finite).
    """
    finite = torch.isfinite(points).all(dim=1)
    dropped = int((~finite).sum())
    if dropped == 0:
        return points
    warnings.warn(f"{source}: dropped {dropped} of {points.shape[0]} points with NaN or infinite values", stacklevel=2)
    return points[finite]
