"""The dataset on the synthetic world: samples, geometric consistency under augmentation, bad input."""

from __future__ import annotations

import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset, SampleError
from occkit.data.transforms import BevAugConfig, ImageAugConfig
from occkit.geometry.grid import OCC3D_GRID
from occkit.sim.generate import SimConfig, simulate_dataset

CAMERAS = ("CAM_FRONT", "CAM_BACK")
IMAGE_AUG = ImageAugConfig(final_size=(96, 176))


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("data") / "synth"
    simulate_dataset(SimConfig(scenes=2, frames=2, seed=1, image_size=(352, 198), cameras=CAMERAS), root)
    return root


def _dataset(root: Path, **options) -> OccupancyDataset:
    defaults = {"root": str(root), "split": "all", "cameras": CAMERAS, "image_aug": IMAGE_AUG, "sweeps": 0}
    return OccupancyDataset(DatasetConfig(**{**defaults, **options}))


def test_sample_shapes_and_batch(root):
    dataset = _dataset(root, sweeps=9, depth_downsample=8)
    assert len(dataset) == 4
    batch = collate([dataset[1], dataset[3]])
    assert batch.images.shape == (2, 2, 3, 96, 176)
    assert batch.cam2ego.shape == (2, 2, 4, 4) and batch.img_aug.shape == (2, 2, 3, 3)
    assert batch.voxel_semantics.shape == (2, 200, 200, 16) and batch.mask_camera.dtype == torch.bool
    assert batch.points.shape[0] == 2 and batch.num_points.min() > 1000
    lags = batch.points[0, : batch.num_points[0], 4]
    assert lags.min() == 0 and 0.4 < lags.max() < 0.5  # the key frame and sweeps back to the previous key frame
    assert batch.depth_maps.shape == (2, 2, 12, 22) and (batch.depth_maps > 0).any()
    assert len(batch.boxes) == 2 and batch.boxes[0].shape[1] == 9
    splits = _dataset(root, split="train"), _dataset(root, split="val")
    assert (len(splits[0]), len(splits[1])) == (2, 2)


@pytest.mark.parametrize("epoch", range(2))
def test_points_stay_consistent_under_any_augmentation(root, epoch):
    plain = _dataset(root)
    augmented = _dataset(root, augment=True, bev_aug=BevAugConfig(flip_x=0.5, flip_y=0.5, rotate_deg=(-20.0, 20.0)))
    augmented.set_epoch(epoch)
    for index in range(len(plain)):
        reference, sample = plain[index], augmented[index]
        # Points in the augmented LiDAR frame land in occupied voxels of the augmented labels.
        ego = sample.points[:, :3] @ sample.lidar2ego[:3, :3].T + sample.lidar2ego[:3, 3]
        voxel, inside = OCC3D_GRID.world_to_index(ego)
        labels = sample.voxel_semantics[voxel[inside, 0], voxel[inside, 1], voxel[inside, 2]]
        occupied = ((labels != 17) & (labels != 255)).float().mean()
        assert occupied >= 0.95
        # Undoing the BEV augmentation gives the points back; they project to the same original pixels.
        undone = (
            sample.points[:, :3] @ torch.linalg.inv(sample.bev_aug)[:3, :3].T + torch.linalg.inv(sample.bev_aug)[:3, 3]
        )
        torch.testing.assert_close(undone, reference.points[:, :3], atol=2e-4, rtol=0)
        _assert_same_pixels(reference, sample)


def _project(sample, camera: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Key-frame points in augmented pixels of one camera, and which are in front and inside."""
    lidar = sample.points[:, :3] @ torch.linalg.inv(sample.bev_aug)[:3, :3].T + torch.linalg.inv(sample.bev_aug)[:3, 3]
    ego = lidar @ sample.lidar2ego[:3, :3].T + sample.lidar2ego[:3, 3]
    ego2cam = torch.linalg.inv(sample.cam2ego[camera])
    cam = ego @ ego2cam[:3, :3].T + ego2cam[:3, 3]
    pixels = cam @ sample.intrinsics[camera].T
    uv = pixels[:, :2] / pixels[:, 2:3].clamp(min=1e-6)
    uv = uv @ sample.img_aug[camera][:2, :2].T + sample.img_aug[camera][:2, 2]
    height, width = sample.images.shape[-2:]
    valid = (cam[:, 2] > 1.0) & (uv[:, 0] >= 1) & (uv[:, 0] < width - 1) & (uv[:, 1] >= 1) & (uv[:, 1] < height - 1)
    return uv, valid


def _assert_same_pixels(reference, sample) -> None:
    """What the augmented image shows at a point's augmented pixel is what the original shows at its pixel."""
    for camera in range(sample.images.shape[0]):
        uv_aug, valid_aug = _project(sample, camera)
        uv_ref, valid_ref = _project(reference, camera)
        both = valid_aug & valid_ref
        if both.sum() < 50:
            continue
        mapped = uv_aug[both] - sample.img_aug[camera][:2, 2]
        back = torch.linalg.solve(sample.img_aug[camera][:2, :2], mapped.T).T
        original = back @ reference.img_aug[camera][:2, :2].T + reference.img_aug[camera][:2, 2]
        assert (original - uv_ref[both]).abs().max() < 1e-2
        colour_aug = sample.images[camera][:, uv_aug[both, 1].long(), uv_aug[both, 0].long()]
        colour_ref = reference.images[camera][:, uv_ref[both, 1].long(), uv_ref[both, 0].long()]
        # Within one pixel at the augmented scale: most points sample the same colour (texture edges aside).
        assert ((colour_aug - colour_ref).abs().amax(0) < 0.35).float().mean() > 0.8


def test_bad_files_name_sample_and_file_and_can_be_skipped(root, tmp_path, caplog):
    broken = tmp_path / "broken"
    shutil.copytree(root, broken)
    dataset = _dataset(broken)
    record = dataset.records[0]
    image = broken / record.cameras["CAM_FRONT"].path
    image.write_bytes(b"not a jpeg")
    with pytest.raises(SampleError, match=f"sample {record.token}: cannot read image .*{image.name}"):
        dataset[0]
    (broken / record.cameras["CAM_FRONT"].path).unlink()
    with pytest.raises(SampleError, match=f"sample {record.token}: image not found: .*{image.name}"):
        dataset[0]
    skipping = _dataset(broken, on_error="skip")
    assert skipping[0] is None and skipping.skipped == 1
    batch = collate([skipping[0], skipping[1]])
    assert len(batch) == 1 and batch.tokens == [skipping.records[1].token]
    points = broken / skipping.records[1].lidar_path
    points.write_bytes(points.read_bytes()[:-4])
    with pytest.raises(SampleError, match="not a multiple of 5"):
        _dataset(broken)[1]


def test_nan_points_are_dropped_with_a_warning(root, tmp_path):
    copy = tmp_path / "nan"
    shutil.copytree(root, copy)
    dataset = _dataset(copy, cameras=())
    path = copy / dataset.records[0].lidar_path
    points = np.fromfile(path, dtype=np.float32).reshape(-1, 5)
    points[:3, 0] = np.nan
    points.tofile(path)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        sample = dataset[0]
    assert sample.points.shape[0] == points.shape[0] - 3 and torch.isfinite(sample.points).all()
    assert any("dropped 3 of" in str(w.message) for w in caught)


def test_unknown_split_and_camera_are_errors(root):
    with pytest.raises(ValueError, match="CAM_TOP"):
        _dataset(root, cameras=("CAM_TOP",))
    with pytest.raises(ValueError, match="split"):
        _dataset(root, split="holdout")


def test_images_are_normalised_rgb(root):
    sample = _dataset(root)[0]
    record = _dataset(root).records[0]
    with Image.open(root / record.cameras["CAM_FRONT"].path) as image:
        assert image.size == (352, 198)
    assert -2.2 < sample.images.min() < 0 < sample.images.max() < 2.7


def test_sensor_failure_options(root):
    full = _dataset(root, sweeps=0)[0]
    failed = _dataset(root, sweeps=0, drop_cameras=("CAM_BACK",), lidar_beams_every=4, point_dropout=0.5)[0]
    assert (failed.images[1] == 0).all() and torch.equal(failed.images[0], full.images[0])
    # 8 of 32 beams, then half of those points.
    assert 0.05 * len(full.points) < len(failed.points) < 0.2 * len(full.points)
    with pytest.raises(ValueError, match="CAM_SIDE"):
        _dataset(root, drop_cameras=("CAM_SIDE",))
