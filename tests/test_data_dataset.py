"""The dataset on the synthetic world: samples, geometric consistency under augmentation, bad input."""

from __future__ import annotations

import dataclasses
import io
import json
import os
import shutil
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from PIL import Image, ImageFile

from occkit.classes import DETECTION_CLASSES
from occkit.data import dataset as dataset_module
from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset, SampleError
from occkit.data.index import (
    INDEX_FORMAT,
    IndexFormatError,
    OutdatedIndexError,
    load_index,
    read_index_header,
    save_index,
    tables_key,
)
from occkit.data.transforms import BevAugConfig, ImageAugConfig
from occkit.geometry.grid import OCC3D_GRID
from occkit.sim.generate import SimConfig, simulate_dataset

VERSION = "v1.0-synth"
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
    with pytest.raises(SampleError, match="not a multiple of 20"):
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


# ----------------------------------------------------------------------------------------------------- sensor files
@pytest.fixture()
def broken(root, tmp_path) -> Path:
    """A copy of the dataset to damage."""
    shutil.copytree(root, tmp_path / "broken")
    return tmp_path / "broken"


def _damage(path: Path, content: bytes | None) -> bytes:
    """Replace (None: delete) a file; returns the original bytes."""
    original = path.read_bytes()
    if content is None:
        path.unlink()
    else:
        path.write_bytes(content)
    return original


def test_images_must_match_the_calibration_and_decode_in_full(broken):
    assert ImageFile.LOAD_TRUNCATED_IMAGES is False  # nothing in occkit turns PIL's truncation error off
    dataset = _dataset(broken)
    record = dataset.records[1]
    camera = record.cameras["CAM_BACK"]
    path = broken / camera.path
    small = io.BytesIO()
    Image.new("RGB", (50, 40)).save(small, "JPEG")
    jpeg = path.read_bytes()
    cases = [
        (small.getvalue(), rf"{path.name} is 50x40 pixels but its calibration .* says {camera.width}x{camera.height}"),
        (jpeg[: len(jpeg) // 2], rf"cannot read image .*{path.name}: image file is truncated"),
        (b"", rf"cannot read image .*{path.name}: cannot identify image file"),
        (None, rf"image not found: .*{path.name}"),
    ]
    for content, message in cases:
        original = _damage(path, content)
        with pytest.raises(SampleError, match=rf"^sample {record.token}: .*{message}"):
            dataset[1]
        path.write_bytes(original)
    assert dataset[1] is not None


def test_point_files_must_hold_whole_points(broken):
    dataset = _dataset(broken, cameras=(), sweeps=9)
    record = dataset.records[1]
    key, sweep = broken / record.lidar_path, broken / record.sweeps[0].path
    points = key.read_bytes()
    cases = [
        (key, points[:22], rf"{key.name} holds 22 bytes, not a multiple of 20"),
        (key, points[:-4], rf"{key.name} holds {len(points) - 4} bytes, not a multiple of 20"),
        (key, b"", rf"{key.name} is empty \(0 points\)"),
        (key, None, rf"point file not found: .*{key.name}"),
        (sweep, points[:-3], rf"{sweep.name} holds {len(points) - 3} bytes"),
        (sweep, None, rf"point file not found: .*{sweep.name}"),
    ]
    for path, content, message in cases:
        original = _damage(path, content)
        with pytest.raises(SampleError, match=rf"^sample {record.token}: .*{message}"):
            dataset[1]
        path.write_bytes(original)
    # An empty sweep leaves the frame usable: a warning names it, the other sweeps load.
    full = dataset[1].points
    original = _damage(sweep, b"")
    with pytest.warns(UserWarning, match=rf"sample {record.token}: sweep .*{sweep.name} is empty \(0 points\)"):
        fewer = dataset[1].points
    assert 0 < len(fewer) < len(full)
    sweep.write_bytes(original)


def test_a_missing_or_corrupt_label_file_is_a_sample_error(broken):
    dataset = _dataset(broken, cameras=(), sweeps=-1)
    record = dataset.records[0]
    path = broken / record.occ_path
    _damage(path, b"PK\x03\x04 not a zip")
    with pytest.raises(SampleError, match=rf"^sample {record.token}: .*labels\.npz: cannot read labels"):
        dataset[0]
    path.unlink()
    with pytest.raises(SampleError, match=rf"^sample {record.token}: .*labels\.npz: label file not found"):
        dataset[0]


# ----------------------------------------------------------------------------------------------------- valid boxes
BOXES_ONLY = {"cameras": (), "sweeps": -1, "occupancy": False}


def test_valid_boxes_only_keeps_the_boxes_with_points(root):
    every, valid = _dataset(root, **BOXES_ONLY), _dataset(root, valid_boxes_only=True, **BOXES_ONLY)
    dropped = 0
    for index, record in enumerate(every.records):
        detection = [i for i, name in enumerate(record.box_detection_names) if name is not None]
        kept = [k for k, i in enumerate(detection) if record.box_valid[i]]  # rows of the detection boxes
        all_boxes, valid_boxes = every[index], valid[index]
        assert len(all_boxes.boxes) == len(detection) and len(valid_boxes.boxes) == len(kept)
        torch.testing.assert_close(valid_boxes.boxes, all_boxes.boxes[kept], rtol=0, atol=0)
        assert valid_boxes.box_labels.tolist() == all_boxes.box_labels[kept].tolist()
        dropped += len(detection) - len(kept)
    assert dropped > 0  # the world has boxes that a camera saw and the LiDAR did not


def _classes(record, valid_only: bool) -> set[str]:
    """The detection classes of a record's boxes (with a point only, where ``valid_only``)."""
    return {n for n, v in zip(record.box_detection_names, record.box_valid, strict=True) if n and (v or not valid_only)}


def test_sample_classes_follow_the_boxes_and_their_valid_flags(root, tmp_path):
    every = _dataset(root, **BOXES_ONLY)
    expected = [_classes(record, valid_only=False) for record in every.records]
    assert every.sample_classes() == expected and set().union(*expected) <= set(DETECTION_CLASSES)
    # An index in which no box of one class of sample 0 has a point: the class leaves that sample with
    # valid_boxes_only, and only then.
    record = every.records[0]
    name = next(n for n, v in zip(record.box_detection_names, record.box_valid, strict=True) if n and v)
    flags = record.box_valid & (np.array(record.box_detection_names, dtype=object) != name)
    path = tmp_path / "index.npz"
    save_index([dataclasses.replace(record, box_valid=flags), *every.records[1:]], path,
               {"version": VERSION, "root": str(root), "max_sweeps": 0})  # fmt: skip
    plain = _dataset(root, index=str(path), **BOXES_ONLY)
    valid = _dataset(root, index=str(path), valid_boxes_only=True, **BOXES_ONLY)
    assert plain.sample_classes() == expected
    valid_expected = [_classes(r, valid_only=True) for r in plain.records]
    assert valid.sample_classes() == valid_expected
    assert name in expected[0] and name not in valid_expected[0]
    assert valid_expected[1:] == [_classes(r, valid_only=True) for r in every.records[1:]]
    assert len(valid[0].boxes) == int(flags[[n is not None for n in record.box_detection_names]].sum())


# ----------------------------------------------------------------------------------------------------- index cache
def test_index_cache_follows_the_tables_content_not_their_modification_time(root, tmp_path, monkeypatch):
    data = tmp_path / "tables"
    shutil.copytree(root / VERSION, data / VERSION)
    first = _dataset(data, cameras=())
    cache = data / ".occkit" / f"occkit-index-{VERSION}-0.npz"
    assert read_index_header(cache)["tables_key"] == tables_key(data, VERSION, 0)
    with monkeypatch.context() as patch:  # unchanged tables: the cache is read, nothing is rebuilt
        patch.setattr(dataset_module, "build_index", None)
        assert _dataset(data, cameras=()).records == first.records
    # A table edited in place, same size, its old modification time put back (older than the cache).
    path = data / VERSION / "scene.json"
    stat = path.stat()
    path.write_text(path.read_text().replace("scene-0002", "scene-0003"))
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and cache.stat().st_mtime_ns > path.stat().st_mtime_ns
    again = _dataset(data, cameras=())
    assert sorted({r.scene for r in again.records}) == ["scene-0001", "scene-0003"]
    assert read_index_header(cache)["tables_key"] == tables_key(data, VERSION, 0)


def _unsafe_token(cache: Path, token: str) -> None:
    """Rewrite the cache's string ``token`` (a sample token) as ``../../escape_tok``; its header is unchanged."""
    with np.load(cache) as npz:
        arrays = {name: npz[name] for name in npz.files}
    raw, offsets = arrays["strings"].tobytes(), arrays["strings.offsets"]
    strings = [raw[a:b].decode() for a, b in zip(offsets[:-1], offsets[1:], strict=True)]
    encoded = [("../../escape_tok" if text == token else text).encode() for text in strings]
    arrays["strings"] = np.frombuffer(b"".join(encoded), dtype=np.uint8)
    arrays["strings.offsets"] = np.cumsum([0] + [len(text) for text in encoded])
    with open(cache, "wb") as stream:
        np.savez(stream, **arrays)


def test_a_corrupt_or_unsafe_index_cache_is_rebuilt_with_a_warning(root, tmp_path):
    data = tmp_path / "tables"
    shutil.copytree(root / VERSION, data / VERSION)
    records = _dataset(data, cameras=()).records
    cache = data / ".occkit" / f"occkit-index-{VERSION}-0.npz"
    good = cache.read_bytes()
    _unsafe_token(cache, records[0].token)  # the header's key still matches
    unsafe = cache.read_bytes()
    for content in (b"{not json", good[: len(good) // 2], unsafe, b"\x00\xff", b""):
        cache.write_bytes(content)
        with pytest.warns(UserWarning, match=rf"{cache.name}: unreadable index cache, rebuilding it"):
            assert _dataset(data, cameras=()).records == records
        assert load_index(cache)[0] == records
    header = read_index_header(cache)
    del header["tables_key"]
    save_index(records, cache, header)  # no key (an older occkit): rebuilt quietly
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _dataset(data, cameras=()).records == records
    assert "tables_key" in read_index_header(cache)


def test_a_cache_of_the_previous_format_is_rebuilt_quietly(root, tmp_path):
    data = tmp_path / "tables"
    shutil.copytree(root / VERSION, data / VERSION)
    records = _dataset(data, cameras=()).records
    cache = data / ".occkit" / f"occkit-index-{VERSION}-0.npz"
    with np.load(cache) as npz:
        arrays = {name: npz[name] for name in npz.files if name != "box_valid"}
    header = json.loads(str(arrays["header"])) | {"format": "occkit-index/2"}  # its tables_key matched then
    with open(cache, "wb") as stream:
        np.savez(stream, **(arrays | {"header": np.array(json.dumps(header))}))
    # Named explicitly, it is one line of error that says how to rebuild it.
    with pytest.raises(OutdatedIndexError, match=r"occkit-index/2\); this occkit reads .* rebuild it with `occkit"):
        _dataset(data, cameras=(), index=str(cache))
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert _dataset(data, cameras=()).records == records
    assert read_index_header(cache)["format"] == INDEX_FORMAT


def test_the_json_cache_of_an_older_occkit_is_replaced(root, tmp_path):
    data = tmp_path / "tables"
    shutil.copytree(root / VERSION, data / VERSION)
    old = data / ".occkit" / f"occkit-index-{VERSION}-0.json"
    old.parent.mkdir()
    old.write_text('{"format": "occkit-index/1", "version": "v1.0-synth", "tables_key": "sha256:0", "records": [\n]}\n')
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        records = _dataset(data, cameras=()).records
    cache = old.with_suffix(".npz")
    assert list(old.parent.iterdir()) == [cache]
    assert _dataset(data, cameras=(), index=str(cache)).records == records
    # Named explicitly, a JSON index is one line of error that says how to rebuild it.
    old.write_text('{"format": "occkit-index/1", "version": "v1.0-synth", "root": "r", "records": [\n]}\n')
    with pytest.raises(IndexFormatError, match=r"0\.json: a JSON index of an older occkit .* rebuild it with `occkit"):
        _dataset(data, cameras=(), index=str(old))


def test_depth_maps_without_lidar_are_refused_when_configured():
    from occkit.data.dataset import DatasetConfig

    with pytest.raises(ValueError, match="depth_downsample = 16 needs the LiDAR key frame, but sweeps = -1"):
        DatasetConfig(sweeps=-1, depth_downsample=16)
