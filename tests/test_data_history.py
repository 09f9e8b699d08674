"""History frames (``DatasetConfig.history``): earlier key frames of the scene for temporal models."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image

from occkit.data import dataset as dataset_module
from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset, SampleError
from occkit.data.transforms import BevAugConfig, ImageAugConfig, augment_image

CAMERAS = ("CAM_FRONT", "CAM_BACK")
IMAGE_AUG = ImageAugConfig(final_size=(64, 176))
TRAIN_AUG = {"augment": True, "bev_aug": BevAugConfig(flip_x=0.5, flip_y=0.5)}


@pytest.fixture(scope="module")
def world(synthetic_world) -> Path:
    """2 scenes x 3 key frames (scene-0001 trains, scene-0002 validates)."""
    return synthetic_world(scenes=2, frames=3, seed=0, image_size=(176, 99), cameras=CAMERAS)


def _dataset(root: Path, **options) -> OccupancyDataset:
    defaults = {"root": str(root), "split": "all", "cameras": CAMERAS, "image_aug": IMAGE_AUG, "sweeps": -1,
                "boxes": False, "occupancy": False}  # fmt: skip
    return OccupancyDataset(DatasetConfig(**{**defaults, **options}))


def _earlier(records, record, count: int) -> list:
    """The ``count`` frames before ``record`` in its scene by ``index_in_scene``, newest first (fewer at the start)."""
    scene = {r.index_in_scene: r for r in records if r.scene == record.scene}
    return [scene[i] for i in range(record.index_in_scene - 1, max(record.index_in_scene - count, 0) - 1, -1)]


def test_history_is_the_earlier_frames_newest_first_padded_at_the_scene_start(world):
    dataset, plain = _dataset(world, history=2), _dataset(world)
    records = dataset.records
    firsts = [i for i, r in enumerate(records) if r.index_in_scene == 0]
    thirds = [i for i, r in enumerate(records) if r.index_in_scene == 2]
    assert len(firsts) == len(thirds) == 2
    for index in firsts:
        sample = dataset[index]
        assert sample.history_tokens == (sample.token, sample.token)
        assert sample.history_padded.tolist() == [True, True] and sample.history_padded.dtype == torch.bool
        assert sample.history_images.shape == (2, 2, 3, 64, 176) and sample.history_images.dtype == torch.float32
        for k in range(2):
            assert torch.equal(sample.history_images[k], sample.images)
            assert torch.equal(sample.history_intrinsics[k], sample.intrinsics)
            assert torch.equal(sample.history_cam2ego[k], sample.cam2ego)
            assert torch.equal(sample.history_ego2global[k], sample.ego2global)
    for index in thirds:
        record, sample = records[index], dataset[index]
        earlier = _earlier(records, record, 2)
        assert [r.token for r in earlier] == [record.prev, earlier[0].prev]  # the index's prev chain agrees
        assert sample.history_tokens == tuple(r.token for r in earlier)
        assert sample.history_padded.tolist() == [False, False]
        assert sample.history_ego2global.dtype == torch.float64
        assert torch.equal(sample.history_ego2global, torch.from_numpy(np.stack([r.ego2global for r in earlier])))
        for k, previous in enumerate(earlier):
            # Without augmentation each history slot is that frame as a sample of its own would show it.
            reference = plain[records.index(previous)]
            assert torch.equal(sample.history_images[k], reference.images)
            assert torch.equal(sample.history_intrinsics[k], reference.intrinsics)
            assert torch.equal(sample.history_cam2ego[k], reference.cam2ego)
            assert torch.equal(sample.history_img_aug[k], reference.img_aug)
    # The second frame: one earlier frame, then a padded slot.
    second = dataset[firsts[0] + 1]
    assert second.history_tokens == (records[firsts[0]].token, second.token)
    assert second.history_padded.tolist() == [False, True]
    assert torch.equal(second.history_images[1], second.images)


def test_history_shares_the_augmentation_and_leaves_the_current_frame_as_it_was(world, monkeypatch):
    options = {**TRAIN_AUG, "occupancy": True, "sweeps": 0, "camera_dropout": 0.3, "point_dropout": 0.2}
    without, with_history = _dataset(world, **options), _dataset(world, history=2, **options)
    for dataset in (without, with_history):
        dataset.set_epoch(1)
    flipped = 0
    for index in range(len(without)):
        before, sample = without[index], with_history[index]
        assert before.history_images is None and before.history_tokens is None
        for name in ("images", "img_aug", "camera_mask", "occ_aug", "bev_aug", "points", "voxel_semantics",
                     "mask_camera"):  # fmt: skip
            assert torch.equal(getattr(sample, name), getattr(before, name)), name
        for k in range(2):
            assert torch.equal(sample.history_img_aug[k], sample.img_aug)
        assert sample.occ_aug.shape == (4, 4)  # one BEV augmentation for the whole sequence
        flipped += not torch.equal(sample.occ_aug, torch.eye(4))
    assert flipped  # the draws did augment
    # Each history image is that frame's image under the current frame's draws for the camera, and the history
    # draws nothing: sample_image_aug runs once per camera.
    augmented = _dataset(world, history=2, **TRAIN_AUG)
    drawn = []

    def recording(*args, **kwargs):
        drawn.append(original(*args, **kwargs))
        return drawn[-1]

    original = dataset_module.sample_image_aug
    monkeypatch.setattr(dataset_module, "sample_image_aug", recording)
    index = next(i for i, r in enumerate(augmented.records) if r.index_in_scene == 2)
    sample = augmented[index]
    assert len(drawn) == len(CAMERAS) and any(params.flip or params.rotate_deg for params in drawn)
    mean = torch.tensor([123.675, 116.28, 103.53]).view(3, 1, 1)
    std = torch.tensor([58.395, 57.12, 57.375]).view(3, 1, 1)
    for k, previous in enumerate(_earlier(augmented.records, augmented.records[index], 2)):
        for n, name in enumerate(CAMERAS):
            with Image.open(world / previous.cameras[name].path) as image:
                pixels = np.array(augment_image(image.convert("RGB"), drawn[n]))
            expected = (torch.from_numpy(pixels).permute(2, 0, 1).float() - mean) / std
            assert torch.equal(sample.history_images[k, n], expected)
            assert torch.equal(sample.history_img_aug[k, n], drawn[n].matrix())


def test_history_collates_and_moves(world):
    dataset = _dataset(world, history=2)
    samples = [dataset[0], dataset[2]]
    batch = collate(samples)
    assert batch.history_images.shape == (2, 2, 2, 3, 64, 176)
    assert batch.history_intrinsics.shape == (2, 2, 2, 3, 3) and batch.history_img_aug.shape == (2, 2, 2, 3, 3)
    assert batch.history_cam2ego.shape == (2, 2, 2, 4, 4)
    assert batch.history_ego2global.shape == (2, 2, 4, 4) and batch.history_ego2global.dtype == torch.float64
    assert batch.history_padded.tolist() == [[True, True], [False, False]]
    assert batch.history_tokens == [s.history_tokens for s in samples]
    moved = batch.to("cpu")
    assert moved.history_tokens == batch.history_tokens and isinstance(moved.history_tokens[0], tuple)
    assert moved.history_ego2global.dtype == torch.float64 and torch.equal(moved.history_images, batch.history_images)
    plain = collate([_dataset(world)[0]])
    assert plain.history_tokens is None and plain.history_images is None and plain.history_padded is None


@pytest.mark.parametrize("split", ["train", "val"])
def test_history_never_crosses_scenes(world, split):
    scene_of = {r.token: r.scene for r in _dataset(world).records}
    dataset = _dataset(world, split=split, history=3)  # more than a scene's 3 frames hold
    for sample in dataset:
        earlier = [t for t, padded in zip(sample.history_tokens, sample.history_padded.tolist(), strict=True)
                   if not padded]  # fmt: skip
        assert all(scene_of[token] == sample.scene for token in earlier)
        assert sample.history_padded[-1]  # no frame of a 3-frame scene has 3 earlier ones
        assert len(set(earlier)) == len(earlier) and sample.token not in earlier


def test_failed_cameras_fail_in_every_history_frame(world):
    index = next(i for i, r in enumerate(_dataset(world).records) if r.index_in_scene == 2)
    full = _dataset(world, history=2)[index]
    failed = _dataset(world, history=2, drop_cameras=("CAM_BACK",))[index]
    assert failed.camera_mask.tolist() == [True, False]
    assert (failed.history_images[:, 1] == 0).all() and (full.history_images[:, 1] != 0).any()
    assert torch.equal(failed.history_images[:, 0], full.history_images[:, 0])
    # Random failures: the key frame's draw, the same cameras in the history frames.
    dropout = _dataset(world, history=2, camera_dropout=0.5)
    masks = set()
    for sample in dropout:
        dead = (sample.history_images == 0).flatten(2).all(-1)  # (K, N)
        assert torch.equal(dead, ~sample.camera_mask.expand(2, -1))
        masks.add(tuple(sample.camera_mask.tolist()))
    assert len(masks) > 1  # the seeds give some variety


def test_a_broken_history_image_names_the_file_and_both_tokens(world, tmp_path):
    root = tmp_path / "broken"
    shutil.copytree(world, root)
    dataset = _dataset(root, history=1)
    index = next(i for i, r in enumerate(dataset.records) if r.index_in_scene == 1)
    record, previous = dataset.records[index], dataset.records[index - 1]
    assert record.prev == previous.token
    path = root / previous.cameras["CAM_BACK"].path
    path.write_bytes(path.read_bytes()[:-600])  # a truncated JPEG
    message = rf"^sample {previous.token} \(history of {record.token}\): cannot read image .*{path.name}: .*truncated"
    with pytest.raises(SampleError, match=message):
        dataset[index]
    assert _dataset(root)[index] is not None  # the frame itself is fine without its history
    assert _dataset(root, history=1, on_error="skip")[index] is None


def test_history_settings_are_checked(world):
    for history in (-1, True, 1.5):
        with pytest.raises(ValueError, match="history must be (an integer >= 0|between 0 and 100)"):
            _dataset(world, history=history)
    with pytest.raises(ValueError, match="history=2 needs cameras"):
        _dataset(world, history=2, cameras=())
