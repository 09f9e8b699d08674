import math
import warnings

import numpy as np
import pytest
import torch
from PIL import Image

from occkit.config import field_docs, from_dict
from occkit.data.lidar_maps import depth_map, height_map
from occkit.data.transforms import (
    BevAugConfig,
    ImageAugConfig,
    ImageAugParams,
    augment_boxes,
    augment_image,
    augment_occupancy,
    augment_points,
    drop_cameras,
    drop_lidar_beams,
    drop_points,
    lidar_frame_aug,
    sample_bev_aug,
    sample_image_aug,
    sanitize_points,
)
from occkit.geometry import OCC3D_GRID, VoxelGrid, apply_image_aug, image_aug_matrix, invert_image_aug
from occkit.geometry.se3 import make_transform, transform_points
from occkit.sim.rig import LIDAR_TOP, camera_rig

F64 = torch.float64
LIDAR2EGO = torch.from_numpy(LIDAR_TOP.lidar2ego)


# --------------------------------------------------------------------------------------------- image augmentation
def test_test_transform_1600x900_is_flashocc():
    params = sample_image_aug(ImageAugConfig(), (1600, 900), False, np.random.default_rng(0))
    assert params == ImageAugParams(0.44, (0, 140, 704, 396), False, 0.0)
    assert params.output_size == (256, 704)
    torch.testing.assert_close(params.matrix(dtype=F64), image_aug_matrix(0.44, (0, 140, 704, 396), dtype=F64))


def test_test_transform_800x450_uses_its_own_base_resize():
    params = sample_image_aug(ImageAugConfig(), (800, 450), False, np.random.default_rng(0))
    assert params == ImageAugParams(0.88, (0, 140, 704, 396), False, 0.0)
    assert augment_image(np.zeros((450, 800, 3), np.uint8), params).shape == (256, 704, 3)


def test_train_sampling_stays_in_the_flashocc_ranges():
    config, rng = ImageAugConfig(), np.random.default_rng(1)
    samples = [sample_image_aug(config, (1600, 900), True, rng) for _ in range(200)]
    for p in samples:
        new_w, new_h = int(1600 * p.resize + 1e-6), int(900 * p.resize + 1e-6)
        assert 0.44 - 0.06 <= p.resize <= 0.44 + 0.11
        assert -5.4 <= p.rotate_deg <= 5.4
        assert p.output_size == (256, 704)
        assert p.crop[3] == new_h  # bottom aligned
        assert 0 <= p.crop[0] <= max(0, new_w - 704)
    assert 50 < sum(p.flip for p in samples) < 150


def test_free_vertical_crop_is_random_in_training_and_centred_at_test():
    config = ImageAugConfig(bottom_crop=False)
    rng = np.random.default_rng(2)
    tops = {sample_image_aug(config, (1600, 900), True, rng).crop[1] for _ in range(50)}
    assert len(tops) > 5 and min(tops) >= 0
    assert sample_image_aug(config, (1600, 900), False, rng).crop == (0, 70, 704, 326)


def _blob_image(params: ImageAugParams, size_wh: tuple[int, int], rng: np.random.Generator):
    """An image with one 3x3 blob per colour channel, placed where the augmented image will show it."""
    width, height = size_wh
    matrix = params.matrix(dtype=F64)
    inverse = invert_image_aug(matrix)
    out_h, out_w = params.output_size
    image = np.zeros((height, width, 3), np.uint8)
    expected = []
    for channel in range(3):
        while True:
            target = torch.tensor([rng.uniform(20, out_w - 20), rng.uniform(20, out_h - 20)], dtype=F64)
            u, v = (int(c) for c in apply_image_aug(inverse, target))
            if 3 <= u < width - 3 and 3 <= v < height - 3:
                break
        image[v - 1 : v + 2, u - 1 : u + 2, channel] = 255
        expected.append(apply_image_aug(matrix, torch.tensor([u + 0.5, v + 0.5], dtype=F64)).numpy())
    return image, np.stack(expected)


def _channel_centroids(image: np.ndarray) -> np.ndarray:
    """``(3, 2)`` intensity-weighted ``(u, v)`` of each channel, with pixel centres at ``i + 0.5``."""
    rows, cols = np.mgrid[: image.shape[0], : image.shape[1]] + 0.5
    weights = image.astype(np.float64)
    total = weights.sum(axis=(0, 1))
    return np.stack(
        ((weights * cols[..., None]).sum((0, 1)) / total, (weights * rows[..., None]).sum((0, 1)) / total), 1
    )


@pytest.mark.parametrize("as_pil", [False, True])
@pytest.mark.parametrize("seed", range(4))
def test_augmented_landmarks_land_where_the_matrix_says(seed, as_pil):
    rng = np.random.default_rng(seed)
    params = sample_image_aug(ImageAugConfig(), (800, 450), True, rng)
    if seed == 0:  # make sure flip and a full-range rotation are both exercised
        params = ImageAugParams(params.resize, params.crop, True, 5.4)
    image, expected = _blob_image(params, (800, 450), rng)
    out = augment_image(Image.fromarray(image) if as_pil else image, params)
    assert out.shape == (256, 704, 3) and out.dtype == np.uint8
    np.testing.assert_allclose(_channel_centroids(out), expected, atol=1.0)


@pytest.mark.parametrize("flip", [False, True])
def test_resize_crop_flip_are_exact_without_rotation(flip):
    # 1600 * 0.4713 is not a whole number of pixels: a plain resize to int(W * r) would shift the far edge by ~1 px.
    params = ImageAugParams(0.4713, (30, 168, 734, 424), flip, 0.0)
    image, expected = _blob_image(params, (1600, 900), np.random.default_rng(5))
    np.testing.assert_allclose(_channel_centroids(augment_image(image, params)), expected, atol=0.05)


def test_pil_and_array_inputs_agree():
    rng = np.random.default_rng(3)
    image = rng.integers(0, 256, (450, 800, 3), dtype=np.uint8)
    params = sample_image_aug(ImageAugConfig(), (800, 450), True, rng)
    np.testing.assert_array_equal(augment_image(image, params), augment_image(Image.fromarray(image), params))
    with pytest.raises(ValueError, match="uint8"):
        augment_image(image.astype(np.float32), params)


def test_configs_load_from_plain_values_and_document_every_field():
    config = from_dict(ImageAugConfig, {"final_size": [128, 352], "rotate_deg": [0, 0]})
    assert config.final_size == (128, 352) and config.rotate_deg == (0.0, 0.0)
    assert from_dict(BevAugConfig, {"flip_x": 1}).flip_x == 1.0
    for cls in (ImageAugConfig, BevAugConfig, ImageAugParams):
        assert set(field_docs(cls)) == set(cls.__dataclass_fields__)
    with pytest.raises(ValueError, match="resize_range"):
        ImageAugConfig(resize_range=(0.1, -0.1))
    with pytest.raises(ValueError, match="flip_y"):
        BevAugConfig(flip_y=1.5)


# --------------------------------------------------------------------------------------------- BEV augmentation
def test_bev_aug_is_identity_at_test_time_and_flips_on_request():
    rng = np.random.default_rng(0)
    torch.testing.assert_close(
        sample_bev_aug(BevAugConfig(1.0, 1.0, (30.0, 30.0)), rng, False), torch.eye(4, dtype=F64)
    )
    flip_x = sample_bev_aug(BevAugConfig(flip_x=1.0, flip_y=0.0), rng, True)
    torch.testing.assert_close(flip_x, torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=F64)))
    flips = [sample_bev_aug(BevAugConfig(), rng, True).diagonal()[:2].tolist() for _ in range(200)]
    assert 60 < sum(f[0] < 0 for f in flips) < 140 and 60 < sum(f[1] < 0 for f in flips) < 140


def test_lidar_frame_aug_is_the_same_physical_transform():
    rng = np.random.default_rng(4)
    occ_aug = sample_bev_aug(BevAugConfig(rotate_deg=(-30, 30), scale=(0.9, 1.1)), rng, True)
    bev_aug = lidar_frame_aug(occ_aug, LIDAR2EGO)
    points = torch.from_numpy(rng.uniform(-30, 30, (100, 3)))
    torch.testing.assert_close(
        transform_points(LIDAR2EGO, augment_points(points, bev_aug)),
        transform_points(occ_aug, transform_points(LIDAR2EGO, points)),
    )
    # nuScenes LIDAR_TOP: ego x = lidar y + 0.94 m, so an ego x flip is a lidar y flip about y = -0.94 m.
    ego_flip_x = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=F64))
    expected = torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0], dtype=F64))
    expected[1, 3] = -2 * LIDAR_TOP.translation[0]
    torch.testing.assert_close(lidar_frame_aug(ego_flip_x, LIDAR2EGO), expected)


def _box_scene(rng: np.random.Generator):
    """A car box in the LiDAR frame, points on its surface, and the Occ3D volume those points occupy."""
    box = torch.tensor([[8.0, 5.0, -0.8, 4.5, 1.9, 1.6, 0.3, 3.0, -1.0]], dtype=F64)
    local = rng.uniform(-0.5, 0.5, (400, 3))
    face = rng.integers(0, 3, 400)
    local[np.arange(400), face] = np.sign(local[np.arange(400), face]) * 0.5
    local = torch.from_numpy(local) * box[0, 3:6] * 0.98
    cos, sin = math.cos(0.3), math.sin(0.3)
    rotation = torch.tensor([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]], dtype=F64)
    points = local @ rotation.T + box[0, :3]
    volume = np.full(OCC3D_GRID.shape, 17, np.uint8)
    index, inside = OCC3D_GRID.world_to_index(transform_points(LIDAR2EGO, points))
    assert inside.all()
    volume[tuple(index.T.numpy())] = 4
    return box, points, volume


def _inside_box(points: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    offset = points - box[:3]
    cos, sin = torch.cos(box[6]), torch.sin(box[6])
    local = torch.stack(
        (cos * offset[:, 0] + sin * offset[:, 1], -sin * offset[:, 0] + cos * offset[:, 1], offset[:, 2])
    )
    return (local.abs().T - box[3:6] / 2 <= 1e-6).all(dim=1)


def _occupied_neighbourhood(volume: np.ndarray, index: torch.Tensor, reach: int) -> np.ndarray:
    """Whether any voxel within ``reach`` voxels in x and y of each index is labelled 4."""
    hits = np.zeros(len(index), bool)
    for di in range(-reach, reach + 1):
        for dj in range(-reach, reach + 1):
            i = np.clip(index[:, 0].numpy() + di, 0, volume.shape[0] - 1)
            j = np.clip(index[:, 1].numpy() + dj, 0, volume.shape[1] - 1)
            hits |= volume[i, j, index[:, 2].numpy()] == 4
    return hits


@pytest.mark.parametrize(
    ("flip_x", "flip_y", "rotate"),
    [(1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (1.0, 1.0, 0.0), (0.0, 0.0, 90.0), (1.0, 0.0, 90.0), (0.5, 0.5, 30.0)],
)  # fmt: skip
def test_points_box_and_labels_stay_together(flip_x, flip_y, rotate):
    # Flips and quarter turns move whole voxels; other angles resample and may thicken the shell by half a voxel.
    rng = np.random.default_rng(7)
    box, points, volume = _box_scene(rng)
    occ_aug = sample_bev_aug(BevAugConfig(flip_x, flip_y, (rotate, rotate)), rng, True)
    bev_aug = lidar_frame_aug(occ_aug, LIDAR2EGO)
    new_points, new_box = augment_points(points, bev_aug), augment_boxes(box, bev_aug)[0]
    new_volume = augment_occupancy(volume, occ_aug, OCC3D_GRID, fill=255, empty=17)
    new_mask = augment_occupancy(volume == 4, occ_aug, OCC3D_GRID, fill=0)
    assert _inside_box(new_points, new_box).all()
    index, inside = OCC3D_GRID.world_to_index(transform_points(LIDAR2EGO, new_points))
    assert inside.all()
    # Resampling samples each voxel at 8 points, so a point grazing a voxel's corner may land one voxel off.
    assert _occupied_neighbourhood(new_volume, index, 0 if rotate % 90 == 0 else 1).all()
    np.testing.assert_array_equal(new_mask, new_volume == 4)
    before, after = (volume == 4).sum(), (new_volume == 4).sum()
    assert after == before if rotate % 90 == 0 else before <= after <= 1.7 * before


def test_scaled_boxes_keep_their_points():
    rng = np.random.default_rng(8)
    box, points, _ = _box_scene(rng)
    bev_aug = lidar_frame_aug(
        sample_bev_aug(BevAugConfig(rotate_deg=(-45, 45), scale=(1.2, 1.2)), rng, True), LIDAR2EGO
    )
    new_box = augment_boxes(box, bev_aug)[0]
    torch.testing.assert_close(new_box[3:6], box[0, 3:6] * 1.2)
    torch.testing.assert_close(new_box[7:9].norm(), box[0, 7:9].norm() * 1.2)
    assert _inside_box(augment_points(points, bev_aug), new_box).all()


@pytest.mark.parametrize(
    ("flips", "yaw", "velocity"),
    [((-1, 1), math.pi - 0.5, (-2.0, 1.0)), ((1, -1), -0.5, (2.0, -1.0)), ((-1, -1), 0.5 - math.pi, (-2.0, -1.0))],
)
def test_box_yaw_and_velocity_mirror_under_flips(flips, yaw, velocity):
    bev_aug = torch.diag(torch.tensor([flips[0], flips[1], 1.0, 1.0], dtype=F64))
    box = torch.tensor([[1.0, 2.0, 0.5, 4.0, 2.0, 1.5, 0.5, 2.0, 1.0]])
    out = augment_boxes(box, bev_aug)[0]
    assert out.dtype == torch.float32
    torch.testing.assert_close(out[:6], torch.tensor([flips[0] * 1.0, flips[1] * 2.0, 0.5, 4.0, 2.0, 1.5]))
    assert math.remainder(out[6].item() - yaw, 2 * math.pi) == pytest.approx(0.0, abs=1e-6)
    torch.testing.assert_close(out[7:], torch.tensor(velocity))


def test_flip_on_a_grid_not_symmetric_about_zero_raises():
    grid = VoxelGrid((0.0, -4.0, -1.0, 8.0, 4.0, 0.6), 0.4)
    volume = np.zeros(grid.shape, np.uint8)
    with pytest.raises(ValueError, match="cannot flip x"):
        augment_occupancy(volume, torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0])), grid, fill=255)
    flipped_y = augment_occupancy(volume, torch.diag(torch.tensor([1.0, -1.0, 1.0, 1.0])), grid, fill=255)
    assert flipped_y.shape == grid.shape


def test_occupancy_flips_and_resampling_keep_type_and_fill_the_outside():
    grid = VoxelGrid((-2.0, -2.0, 0.0, 2.0, 2.0, 0.8), 0.4)
    volume = np.arange(grid.num_voxels, dtype=np.uint8).reshape(grid.shape)
    flip_xy = torch.diag(torch.tensor([-1.0, -1.0, 1.0, 1.0], dtype=F64))
    flipped = augment_occupancy(volume, flip_xy, grid, fill=255)
    np.testing.assert_array_equal(flipped, volume[::-1, ::-1])
    assert flipped.flags.c_contiguous and flipped.dtype == np.uint8
    as_tensor = augment_occupancy(torch.from_numpy(volume), flip_xy, grid, fill=255)
    assert isinstance(as_tensor, torch.Tensor) and torch.equal(as_tensor, torch.from_numpy(flipped))
    identity = augment_occupancy(volume, torch.eye(4, dtype=F64), grid, fill=255)
    np.testing.assert_array_equal(identity, volume)
    rotate_shift = make_transform(_yaw(37.0), torch.tensor([0.31, -0.47, 0.0], dtype=F64))  # off voxel faces
    labels = np.random.default_rng(3).choice(np.array([17, 3, 5], dtype=np.uint8), size=grid.shape, p=[0.8, 0.1, 0.1])
    as_mask = augment_occupancy(volume, rotate_shift, grid, fill=0)
    as_labels = augment_occupancy(labels, rotate_shift, grid, fill=255, empty=17)
    inverse = np.linalg.inv(rotate_shift.numpy())
    octants = np.array([[dx, dy, dz] for dx in (-1, 1) for dy in (-1, 1) for dz in (-1, 1)]) * 0.1
    for index in np.ndindex(grid.shape):
        centre = np.array(grid.lower) + (np.array(index) + 0.5) * 0.4
        points = centre + octants
        source = np.floor((points @ inverse[:3, :3].T + inverse[:3, 3] - grid.lower) / 0.4).astype(int)
        inside = (source >= 0).all(axis=1) & (source < grid.shape).all(axis=1)
        mask_values = [volume[tuple(src)] if ok else 0 for src, ok in zip(source, inside, strict=True)]
        label_values = [labels[tuple(src)] if ok else 255 for src, ok in zip(source, inside, strict=True)]
        assert as_mask[index] == max(mask_values)  # a mask keeps any sub-point's value (largest)
        occupied = [v for v in label_values if v != 17]
        assert as_labels[index] == (occupied[0] if occupied else label_values[0])  # labels keep the first non-free
    assert (as_labels == 255).sum() > 10 and (as_mask == 0).sum() > 10
    with pytest.raises(ValueError, match="shape"):
        augment_occupancy(volume[:-1], flip_xy, grid, fill=255)


def _yaw(degrees: float) -> torch.Tensor:
    cos, sin = math.cos(math.radians(degrees)), math.sin(math.radians(degrees))
    return torch.tensor([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]], dtype=F64)


# --------------------------------------------------------------------------------------------- sensor failures
def test_drop_cameras_by_index_and_probability():
    images = torch.ones(6, 3, 4, 8)
    dropped, kept = drop_cameras(images, [1, 4])
    assert kept.tolist() == [True, False, True, True, False, True]
    assert dropped[kept].eq(1).all() and dropped[~kept].eq(0).all() and images.eq(1).all()
    dropped, kept = drop_cameras(images, 0.5, np.random.default_rng(0))
    assert dropped[~kept].eq(0).all() and dropped[kept].eq(1).all()
    assert drop_cameras(images, 1.0, np.random.default_rng(0))[1].sum() == 0
    with pytest.raises(ValueError, match="rng"):
        drop_cameras(images, 0.5)
    with pytest.raises(TypeError, match="sequence"):
        drop_cameras(images, 1)
    with pytest.raises(ValueError, match="out of range"):
        drop_cameras(images, [6])


def test_drop_lidar_beams_keeps_every_kth_ring_or_a_set():
    rings = torch.arange(32, dtype=torch.float32).repeat(10)
    points = torch.cat((torch.randn(320, 4), rings[:, None]), dim=1)
    assert drop_lidar_beams(points, keep_every=2)[:, 4].unique().tolist() == list(range(0, 32, 2))
    assert len(drop_lidar_beams(points, keep_every=4)) == 80
    assert drop_lidar_beams(points, keep_rings={3, 7})[:, 4].unique().tolist() == [3.0, 7.0]
    with pytest.raises(ValueError, match="exactly one"):
        drop_lidar_beams(points, keep_every=2, keep_rings={1})
    with pytest.raises(ValueError, match="ring"):
        drop_lidar_beams(points[:, :4], keep_every=2)


def test_drop_points_keeps_an_ordered_subset():
    points = torch.arange(1000, dtype=torch.float32)[:, None].repeat(1, 5)
    kept = drop_points(points, 0.25, np.random.default_rng(0))
    assert kept.shape == (750, 5)
    assert (kept[1:, 0] > kept[:-1, 0]).all()
    assert len(drop_points(points, 0.0, np.random.default_rng(0))) == 1000


def test_sanitize_points_drops_non_finite_rows_and_names_the_file():
    points = torch.randn(10, 5)
    points[2, 0], points[7, 3] = torch.nan, torch.inf
    with pytest.warns(UserWarning, match=r"n015-lidar\.pcd\.bin: dropped 2 of 10 points"):
        clean = sanitize_points(points, "n015-lidar.pcd.bin")
    torch.testing.assert_close(clean, points[[0, 1, 3, 4, 5, 6, 8, 9]])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert sanitize_points(clean, "x.pcd.bin") is clean


# --------------------------------------------------------------------------------------------- depth and height maps
# A 16 x 8 image from a camera 3 m above the ground looking along ego +x (camera x right = ego -y, y down = ego -z).
CAM2EGO = make_transform(
    torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]]), torch.tensor([0.0, 0.0, 3.0])
)[None]
K = torch.tensor([[[8.0, 0.0, 8.0], [0.0, 8.0, 4.0], [0.0, 0.0, 1.0]]])
NO_AUG = torch.eye(3)[None]


def _seen_at(u: float, v: float, depth: float) -> list[float]:
    """Ego point projecting to pixel coordinate ``(u, v)`` at camera depth ``depth``."""
    x, y = (u - 8.0) * depth / 8.0, (v - 4.0) * depth / 8.0
    return [depth, -x, 3.0 - y]


def _maps(points, downsample, **kwargs):
    points = torch.tensor(points)
    depth = depth_map(points, CAM2EGO, K, NO_AUG, (8, 16), downsample, **kwargs.get("depth", {}))
    return depth, height_map(points, CAM2EGO, K, NO_AUG, (8, 16), downsample, **kwargs.get("height", {}))


def test_nearest_point_wins_its_pixel_and_cells_take_the_minimum():
    points = [
        _seen_at(2.5, 6.5, 5.0),  # height 1.44, nearest at pixel (2, 6)
        _seen_at(2.5, 6.5, 10.0),  # height -0.125, lower but hidden behind the first
        _seen_at(3.5, 5.5, 3.0),  # height 2.44, pixel (3, 5): same 4x4 cell as pixel (2, 6)
        _seen_at(10.5, 5.5, 2.0),  # height 2.625, pixel (10, 5)
        _seen_at(10.5, 5.5, 8.0),  # height 1.5, hidden
        [-5.0, 0.0, 3.0],  # behind the camera
        _seen_at(20.0, 5.5, 4.0),  # right of the image
    ]
    depth, height = _maps(points, 4)
    assert depth.shape == height.shape == (1, 2, 4) and depth.dtype == height.dtype == torch.float32
    torch.testing.assert_close(depth[0], torch.tensor([[0.0, 0.0, 0.0, 0.0], [3.0, 0.0, 2.0, 0.0]]))
    nan = math.nan
    expected = torch.tensor([[nan, nan, nan, nan], [3.0 - 2.5 * 5 / 8, nan, 3.0 - 1.5 * 2 / 8, nan]])
    torch.testing.assert_close(height[0], expected, equal_nan=True)

    depth, height = _maps(points, 1)
    assert depth[0, 6, 2] == 5.0 and depth[0, 5, 3] == 3.0 and (depth > 0).sum() == 3
    assert height[0, 6, 2] == pytest.approx(3.0 - 2.5 * 5 / 8) and torch.isnan(height).sum() == 8 * 16 - 3


def test_out_of_range_nearest_point_hides_the_pixel_and_depth_range_filters():
    points = [_seen_at(10.5, 5.5, 2.0), _seen_at(10.5, 5.5, 8.0)]  # heights 2.625 (nearest) and 1.5
    _, height = _maps(points, 4, height={"z_range": (-1.0, 2.0)})
    assert torch.isnan(height).all()
    depth, height = _maps(points, 4, depth={"depth_range": (3.0, 45.0)}, height={"depth_range": (3.0, 45.0)})
    assert depth[0, 1, 2] == 8.0 and height[0, 1, 2] == pytest.approx(1.5)


def _brute_force_maps(points, cam2ego, intrinsics, img_aug, image_size, downsample):
    height_px, width_px = image_size
    shape = (len(cam2ego), height_px // downsample, width_px // downsample)
    depth_out, height_out, all_heights = np.full(shape, np.inf), np.full(shape, np.inf), np.full(shape, np.inf)
    for camera in range(len(cam2ego)):
        ego2cam = np.linalg.inv(cam2ego[camera])
        nearest = {}
        for point in points:
            p_cam = ego2cam[:3, :3] @ point + ego2cam[:3, 3]
            if p_cam[2] <= 1e-5:
                continue
            uv1 = img_aug[camera] @ intrinsics[camera] @ (p_cam / p_cam[2])
            u, v = math.floor(uv1[0]), math.floor(uv1[1])
            if not (0 <= u < width_px and 0 <= v < height_px):
                continue
            if -1.0 <= point[2] <= 5.4:
                cell = (camera, v // downsample, u // downsample)
                all_heights[cell] = min(all_heights[cell], point[2])
            if p_cam[2] < nearest.get((u, v), (np.inf,))[0]:
                nearest[(u, v)] = (p_cam[2], point[2])
        for (u, v), (depth, z) in nearest.items():
            cell = (camera, v // downsample, u // downsample)
            depth_out[cell] = min(depth_out[cell], depth)
            if -1.0 <= z <= 5.4:
                height_out[cell] = min(height_out[cell], z)
    return (
        np.where(np.isinf(depth_out), 0.0, depth_out),
        np.where(np.isinf(height_out), np.nan, height_out),
        np.where(np.isinf(all_heights), np.nan, all_heights),
    )


def test_maps_match_a_per_point_loop_on_augmented_cameras():
    rng = np.random.default_rng(11)
    cameras = camera_rig(800, 450)[:2]
    cam2ego = np.stack([c.cam2ego for c in cameras])
    intrinsics = np.stack([c.K for c in cameras])
    params = [sample_image_aug(ImageAugConfig(), (800, 450), True, rng) for _ in cameras]
    img_aug = np.stack([ImageAugParams(p.resize, p.crop, True, p.rotate_deg).matrix(dtype=F64).numpy() for p in params])
    points = np.concatenate((rng.uniform(-25, 25, (3000, 2)), rng.uniform(-1.5, 6.0, (3000, 1))), axis=1)
    # Triples on rays from camera 0 share a pixel, so the nearest-point choice decides the heights there.
    centre = cam2ego[0, :3, 3]
    on_rays = centre + (points[:500, None] - centre) * np.array([0.5, 1.0, 2.0])[:, None]  # (500, 3, 3)
    points = np.concatenate((points, on_rays.reshape(-1, 3)))
    args = [torch.from_numpy(a) for a in (points, cam2ego, intrinsics, img_aug)]
    depth = depth_map(*args, (256, 704), 16)
    height = height_map(*args, (256, 704), 16)
    expected_depth, expected_height, expected_all_heights = _brute_force_maps(
        points, cam2ego, intrinsics, img_aug, (256, 704), 16
    )
    assert (expected_depth > 0).sum() > 50
    assert (expected_height > expected_all_heights).any()  # lower points hidden behind nearer ones are ignored
    torch.testing.assert_close(depth, torch.from_numpy(expected_depth).float())
    torch.testing.assert_close(height, torch.from_numpy(expected_height).float(), equal_nan=True)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA device")
def test_maps_agree_between_cpu_and_cuda():
    rng = np.random.default_rng(12)
    cameras = camera_rig(800, 450)
    tensors = [
        torch.from_numpy(rng.uniform(-25, 25, (20000, 3))).float(),
        torch.from_numpy(np.stack([c.cam2ego for c in cameras])).float(),
        torch.from_numpy(np.stack([c.K for c in cameras])).float(),
        torch.stack([sample_image_aug(ImageAugConfig(), (800, 450), True, rng).matrix() for _ in cameras]),
    ]
    for build in (depth_map, height_map):
        cpu = build(*tensors, (256, 704), 16)
        cuda = build(*[t.cuda() for t in tensors], (256, 704), 16)
        torch.testing.assert_close(cuda.cpu(), cpu, equal_nan=True)
