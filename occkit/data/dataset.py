"""The occupancy dataset: index records -> typed :class:`~occkit.types.Sample` with every transform as a matrix.

Works on any nuScenes + Occ3D layout (the real datasets and occkit's synthetic world). The index is built from the
nuScenes tables on first use and cached (an index file, :func:`~occkit.data.index.save_index`) beside the tables (or
in ``~/.cache/occkit`` when the dataset is read-only), so there is no separate data-preparation step. The cache is
keyed on the tables' content (:func:`~occkit.data.index.tables_key`): a changed table rebuilds it, whatever its
modification time.

Augmentation draws are seeded by ``(seed, epoch, index)``: a run is reproducible whatever the number of workers.
"""

from __future__ import annotations

import contextlib
import itertools
import logging
import os
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Literal

import numpy as np
import torch
from PIL import Image
from torch import Tensor

from occkit.classes import DETECTION_CLASSES
from occkit.config import check_ranges
from occkit.data.corruptions import SampleCorruption
from occkit.data.index import (
    FrameRecord,
    OutdatedIndexError,
    build_index,
    load_index,
    read_index_header,
    save_index,
    tables_key,
)
from occkit.data.labels import LabelError, label_file, read_labels
from occkit.data.lidar_maps import depth_map, height_map
from occkit.data.splits import split_scenes
from occkit.data.transforms import (
    BevAugConfig,
    ImageAugConfig,
    ImageAugParams,
    augment_boxes,
    augment_flow,
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
from occkit.errors import InputError
from occkit.geometry.se3 import invert_transform
from occkit.label_space import label_space
from occkit.nuscenes import CAMERAS
from occkit.types import Sample

__all__ = ["DatasetConfig", "OccupancyDataset", "SampleError", "read_points"]

log = logging.getLogger(__name__)

_IMAGENET_MEAN = (123.675, 116.28, 103.53)
_IMAGENET_STD = (58.395, 57.12, 57.375)


class SampleError(InputError, RuntimeError):
    """A sample cannot be loaded; the message names the sample token and the file."""


#: Inclusive bounds of the dataset's numeric settings (nuScenes has 10 sweeps per key frame and 32 LiDAR beams).
_DATASET_RANGES = {"sweeps": (-1, 100), "history": (0, 100), "camera_dropout": (0.0, 1.0),
                   "lidar_beams_every": (1, 64), "point_dropout": (0.0, 1.0), "corruption_severity": (1, 100),
                   "depth_downsample": (0, 256), "seed": (0, 2**63 - 1)}  # fmt: skip


@dataclass(frozen=True)
class DatasetConfig:
    """Where the data is and what a sample holds."""

    root: str = "data/synth"
    """Dataset root (the folder holding the version folder, samples/, sweeps/ and gts/)."""
    version: str = "v1.0-synth"
    """Table folder: v1.0-trainval, v1.0-mini, v1.0-test, or a synthetic version."""
    split: str = "train"
    """Scene split: train, val, test, mini_train, mini_val, all, or a path to a JSON list of scene names."""
    index: str | None = None
    """Prebuilt index file (``occkit index``); None builds and caches one on first use."""
    cameras: tuple[str, ...] = CAMERAS
    """Cameras to load, in this order; empty for LiDAR-only models."""
    sweeps: int = 9
    """Previous LiDAR sweeps added to the key frame (DAOcc: 9, i.e. 10 sweeps); -1 for no LiDAR at all."""
    history: int = 0
    """Earlier key frames of the same scene each sample carries (temporal models: BEVDet4D-style history), newest
    first; 0 for none. At the start of a scene the missing frames repeat the current one and are flagged padded
    (BEVDet4D's choice). Only their cameras are loaded, with the sample's own image augmentation and failed cameras;
    the one BEV augmentation of the sample moves the whole sequence (``Sample.history_*``)."""
    occupancy: bool = True
    """Load the occupancy labels (and, for Occ3D, the visibility masks)."""
    flow: bool = False
    """Also load the occupancy flow (``Sample.voxel_flow``): the ``flow`` array of each ``labels.npz``, as the CVPR
    2024 challenge's OpenOcc v2 files carry it (the synthetic world writes it in its Occ3D files too). Needs
    ``occupancy``."""
    instances: bool = False
    """Also load each voxel's panoptic instance id (``Sample.voxel_instances``): the ``instances`` array of the
    synthetic world's Occ3D ``labels.npz``, which RayPQ scores against. Needs ``occupancy``."""
    label_space: str = "occ3d"
    """Which benchmark's ground truth: ``occ3d``, ``surroundocc`` or ``openocc`` (grid, frame, classes, files; see
    :mod:`occkit.label_space`). It must be the one the model's occupancy head predicts."""
    label_root: str | None = None
    """Folder of the label files; None: the label space's folder under ``root`` (``gts``, ``surroundocc``,
    ``openocc_v2``)."""
    boxes: bool = True
    """Load the 3D boxes of the detection classes."""
    box_frame: str = "lidar"
    """The frame of the boxes: ``lidar`` (DAOcc's detection head, on the LiDAR BEV) or ``ego`` (BEVDet's boxes, as
    Panoptic-FlashOcc's centre head on the ego-frame BEV reads them); augmented with the sample's BEV augmentation."""
    valid_boxes_only: bool = False
    """Keep only boxes with at least one LiDAR or radar point as targets, as mmdet3d's use_valid_flag (DAOcc,
    FlashOcc). It applies to the boxes of a sample and to :meth:`OccupancyDataset.sample_classes` (CBGS)."""
    augment: bool = False
    """Random image and BEV augmentation (training); off gives the deterministic test transform."""
    image_aug: ImageAugConfig = field(default_factory=ImageAugConfig)
    """Image resize / crop / flip / rotation."""
    bev_aug: BevAugConfig = field(default_factory=BevAugConfig)
    """BEV flips (and optional rotation / scale) of points, boxes and labels."""
    drop_cameras: tuple[str, ...] = ()
    """Robustness evaluation: these cameras are treated as failed (their images zeroed, i.e. the mean colour)."""
    camera_dropout: float = 0.0
    """Robustness evaluation: probability that each camera has failed in a sample."""
    lidar_beams_every: int = 1
    """Robustness evaluation: keep every k-th LiDAR beam (2: 32 -> 16 beams, 4: 8 beams)."""
    point_dropout: float = 0.0
    """Robustness evaluation: fraction of LiDAR points dropped at random, per sweep."""
    corruption: str | None = None
    """Robustness evaluation: the name of a corruption (``occkit robustness --list``) applied to every sample, after
    the settings above; None for none."""
    corruption_severity: int = 1
    """The corruption's level, 1 to its number of levels."""
    depth_downsample: int = 0
    """Return LiDAR depth and height maps at this feature stride (e.g. 16); 0 for none."""
    on_error: Literal["raise", "skip"] = "raise"
    """A broken sample raises, or is skipped (logged and counted): returned as None, which :func:`collate` leaves
    out, or replaced by the next sample that loads where the dataset's ``refill`` is set (training)."""
    seed: int = 0
    """Seed of the augmentation draws."""

    def __post_init__(self) -> None:
        check_ranges("data", self, _DATASET_RANGES)
        for key in ("flow", "instances"):
            if getattr(self, key) and not self.occupancy:
                raise ValueError(f"{key} = true needs occupancy = true: it is read from the occupancy label files")
        if self.box_frame not in ("lidar", "ego"):
            raise ValueError(f"box_frame must be lidar or ego, got {self.box_frame!r}")
        if self.depth_downsample and self.sweeps < 0:
            raise ValueError(f"depth_downsample = {self.depth_downsample} needs the LiDAR key frame, but sweeps = "
                             f"{self.sweeps} loads no LiDAR: set sweeps to 0 (the key frame) or more")


#: Bytes per point of a nuScenes ``.pcd.bin``: five float32 (x, y, z, intensity, ring index).
POINT_BYTES = 20


def read_points(path: Path, token: str) -> np.ndarray:
    """``(N, 5)`` float32 points; the file's byte size must be a whole number of points (``np.fromfile`` alone
    would drop a partial point at the end without a word)."""
    try:
        with open(path, "rb") as stream:
            size = os.fstat(stream.fileno()).st_size
            if size % POINT_BYTES:
                raise SampleError(
                    f"sample {token}: {path} holds {size} bytes, not a multiple of {POINT_BYTES} (5 float32 per "
                    "point: x, y, z, intensity, ring); the file is truncated or not a nuScenes .pcd.bin"
                )
            raw = np.fromfile(stream, dtype=np.float32)
    except FileNotFoundError:
        raise SampleError(f"sample {token}: point file not found: {path}") from None
    except OSError as error:
        raise SampleError(f"sample {token}: cannot read points {path}: {error.strerror or error}") from error
    if raw.size * 4 != size:
        raise SampleError(f"sample {token}: {path} changed while it was read ({size} bytes, then {raw.size * 4})")
    return raw.reshape(-1, 5)


def _read_image(path: Path, token: str, size: tuple[int, int]) -> Image.Image:
    """The RGB image, decoded in full here (a truncated file is an error, never a partly grey image), of ``size``
    (width, height) as the calibration says: intrinsics hold for that size only."""
    try:
        with Image.open(path) as image:
            if image.size != size:
                raise SampleError(
                    f"sample {token}: {path} is {image.size[0]}x{image.size[1]} pixels but its calibration "
                    f"(sample_data width and height) says {size[0]}x{size[1]}"
                )
            image.load()  # PIL decodes lazily: decoding errors of a truncated file surface here
            return image.convert("RGB")
    except FileNotFoundError:
        raise SampleError(f"sample {token}: image not found: {path}") from None
    # UnidentifiedImageError (empty or not an image) and "image file is truncated" are OSErrors; PIL raises
    # SyntaxError or ValueError for some malformed headers, DecompressionBombError for absurd sizes.
    except (OSError, SyntaxError, ValueError, Image.DecompressionBombError) as error:
        raise SampleError(f"sample {token}: cannot read image {path}: {error}") from error


def _matrix(values, dtype=torch.float32) -> Tensor:
    return torch.tensor(np.asarray(values, dtype=np.float64), dtype=dtype)


_MEAN = torch.tensor(_IMAGENET_MEAN).view(3, 1, 1)
_STD = torch.tensor(_IMAGENET_STD).view(3, 1, 1)


def _normalised(image: Image.Image, params: ImageAugParams) -> Tensor:
    """``(3, H, W)`` float32: the image augmented with ``params``, ImageNet-normalised."""
    pixels = torch.from_numpy(np.array(augment_image(image, params))).permute(2, 0, 1).float()
    return (pixels - _MEAN) / _STD


class OccupancyDataset(torch.utils.data.Dataset):
    """Key frames of one split as :class:`Sample`; see :class:`DatasetConfig`."""

    def __init__(self, config: DatasetConfig) -> None:
        self.config = config
        if isinstance(config.history, bool) or not isinstance(config.history, int) or config.history < 0:
            raise ValueError(f"history must be an integer >= 0 (earlier key frames per sample), got {config.history!r}")
        if config.history and not config.cameras:
            raise ValueError(f"history={config.history} needs cameras (history frames are camera frames); cameras is "
                             "empty")  # fmt: skip
        self.space = label_space(config.label_space)
        self.corruption = None if config.corruption is None else \
            SampleCorruption(config.corruption, config.corruption_severity, config.seed)  # fmt: skip
        self.root = Path(config.root)
        records = self._load_records()
        if config.split != "all":
            scenes = set(split_scenes(self.root, config.version, config.split))
            records = [r for r in records if r.scene in scenes]
        if not records:
            raise ValueError(f"{self.root}: split {config.split!r} of {config.version} has no key frames")
        missing = [c for c in (*config.cameras, *config.drop_cameras) if c not in records[0].cameras]
        if missing:
            raise ValueError(f"{self.root}: cameras {missing} not in the data; it has {sorted(records[0].cameras)}")
        self.records = records
        # Token -> record, to follow `prev` links to the history frames. The split's records suffice: a split is a
        # list of scenes and `prev` never leaves the scene.
        self._by_token = {r.token: r for r in records} if config.history else {}
        self.epoch = 0
        self.skipped = 0
        """Samples that failed to load and were skipped, in this process (each DataLoader worker counts its own)."""
        self.refill = False
        """With ``on_error="skip"``: replace a sample that fails by the next index of the split that loads, with the
        augmentation draws of the index it stands in for, so batches stay full and a run stays a pure function of
        (seed, epoch, index). Training sets it; evaluation must not (a frame would be scored twice)."""
        self.replaced = 0
        """Samples replaced so far under ``refill``, in this process."""

    def _load_records(self) -> Sequence[FrameRecord]:
        if self.config.index is not None:
            return load_index(self.config.index)[0]
        max_sweeps = max(self.config.sweeps, 0)
        if self.corruption is not None and self.config.sweeps >= 0:
            max_sweeps += self.corruption.lidar_delay  # the older sweeps a delayed LiDAR reads
        name = f"occkit-index-{self.config.version}-{max_sweeps}.npz"
        caches = (self.root / ".occkit" / name, Path.home() / ".cache" / "occkit" / _slug(self.root) / name)
        key = tables_key(self.root, self.config.version, max_sweeps)
        for cache in caches:
            records = _read_cache(cache, key)
            if records is not None:
                return records
        records = build_index(self.root, self.config.version, max_sweeps=max_sweeps)
        meta = {"version": self.config.version, "root": str(self.root), "max_sweeps": max_sweeps, "tables_key": key}
        for cache in caches:
            try:
                save_index(records, cache, meta)
            except OSError:
                continue
            with contextlib.suppress(OSError):  # the JSON cache of an older occkit, never read again: up to a GB
                cache.with_suffix(".json").unlink(missing_ok=True)
            break
        return records

    def scene_indices(self) -> list[list[int]]:
        """The sample indices of each scene, in time order (``index_in_scene``), the scenes in the split's order:
        the streams a temporal model runs over (evaluation, streamed training, the benchmark)."""
        scenes: dict[str, list[int]] = {}
        for index, record in enumerate(self.records):
            scenes.setdefault(record.scene, []).append(index)
        return [sorted(indices, key=lambda i: self.records[i].index_in_scene) for indices in scenes.values()]

    def sample_classes(self) -> list[frozenset[str]]:
        """The detection classes (:data:`~occkit.classes.DETECTION_CLASSES`) among each sample's boxes, as
        mmdetection3d's ``NuScenesDataset.get_cat_ids``: with ``valid_boxes_only``, of the boxes with a LiDAR or
        radar point only (its ``use_valid_flag``). What CBGS balances (:func:`occkit.data.sampling.cbgs_indices`).

        Read from the index records alone, no sensor or label file: about 0.1 s for 28,130 samples of 40 boxes
        (trainval's training split).

        Returns:
            ``len(self)`` sets, in sample order; empty for a sample without a box of a detection class.
        """
        valid_only = self.config.valid_boxes_only
        classes = []
        for record in self.records:
            names = record.box_detection_names
            if valid_only:
                names = itertools.compress(names, record.box_valid.tolist())
            classes.append(frozenset(names).difference((None,)))  # None: a category that is no detection target
        return classes

    def set_epoch(self, epoch: int) -> None:
        """Change the augmentation draws (call once per epoch, as with a DistributedSampler)."""
        self.epoch = epoch

    def __len__(self) -> int:
        return len(self.records)

    def __getitem__(self, index: int) -> Sample | None:
        sample = self._try(index, index)
        if sample is not None or not self.refill:
            return sample
        for offset in range(1, len(self.records)):
            other = (index + offset) % len(self.records)
            sample = self._try(other, index)
            if sample is not None:
                self.replaced += 1
                log.warning("sample %s (index %d) replaced by sample %s (index %d); %d replaced so far",
                            self.records[index].token, index, sample.token, other, self.replaced)  # fmt: skip
                return sample
        raise SampleError(f"{self.root}: no sample of split {self.config.split!r} loads (on_error=skip)")

    def _try(self, index: int, draws: int) -> Sample | None:
        """Sample ``index`` with the augmentation draws of index ``draws``; None if it fails and errors are skipped."""
        try:
            return self._load(self.records[index], np.random.default_rng([self.config.seed, self.epoch, draws]))
        except SampleError as error:
            if self.config.on_error == "raise":
                raise
            self.skipped += 1
            log.warning("skipping %s (%d skipped so far)", error, self.skipped)
            return None

    # ---------------------------------------------------------------------------------------------------- loading
    def _load(self, record: FrameRecord, rng: np.random.Generator) -> Sample:
        config = self.config
        lidar2ego = _matrix(record.lidar2ego)
        # The BEV augmentation is drawn in the labels' frame, where a flip is an exact flip of the label array;
        # occ_aug is its ego-frame form (the camera geometry's), bev_aug its LiDAR-frame form (points, boxes).
        label_aug = sample_bev_aug(config.bev_aug, rng, config.augment)
        if self.space.frame == "ego":
            occ_aug, bev_aug = label_aug, lidar_frame_aug(label_aug, lidar2ego.double())
        else:
            occ_aug, bev_aug = lidar_frame_aug(label_aug, invert_transform(lidar2ego.double())), label_aug
        sample = Sample(
            token=record.token,
            scene=record.scene,
            lidar2ego=lidar2ego,
            ego2global=_matrix(record.ego2global, torch.float64),
            bev_aug=bev_aug.float(),
            occ_aug=occ_aug.float(),
        )
        if config.cameras:
            augs = self._load_cameras(record, sample, rng)
            if config.history:
                self._load_history(record, sample, augs)
        key_points = None
        if config.sweeps >= 0:
            key_points = self._load_points(record, sample, rng)
        if config.boxes:
            self._load_boxes(record, sample)
        if config.occupancy:
            self._load_occupancy(record, sample, label_aug)
        if config.depth_downsample and config.cameras and key_points is not None:
            ego_points = key_points[:, :3] @ lidar2ego[:3, :3].T + lidar2ego[:3, 3]
            size = sample.images.shape[-2:]
            args = (ego_points, sample.cam2ego, sample.intrinsics, sample.img_aug, tuple(size), config.depth_downsample)
            sample.depth_maps = depth_map(*args)
            sample.height_maps = height_map(*args)
        return sample

    def _load_cameras(self, record: FrameRecord, sample: Sample, rng: np.random.Generator) -> list[ImageAugParams]:
        """The cameras of the key frame; returns each camera's augmentation, which its history frames share."""
        images, intrinsics, cam2ego, img_aug, augs = [], [], [], [], []
        for name in self.config.cameras:
            camera = record.cameras[name]
            image = self._read_camera(record, name, record.token)
            params = sample_image_aug(self.config.image_aug, image.size, self.config.augment, rng)
            images.append(_normalised(image, params))
            intrinsics.append(_matrix(camera.intrinsics))
            cam2ego.append(self._cam2ego(record, name))
            img_aug.append(params.matrix())
            augs.append(params)
        sample.images = torch.stack(images)
        sample.camera_mask = torch.ones(len(images), dtype=torch.bool)
        failed = set(self.config.drop_cameras)
        if self.corruption is not None:
            failed |= self.corruption.failed_cameras(record.token, self.config.cameras)
        failed = [i for i, name in enumerate(self.config.cameras) if name in failed]
        if failed:
            sample.images, kept = drop_cameras(sample.images, failed)
            sample.camera_mask &= kept
        if self.config.camera_dropout > 0:
            sample.images, kept = drop_cameras(sample.images, self.config.camera_dropout, rng)
            sample.camera_mask &= kept
        sample.intrinsics = torch.stack(intrinsics)
        sample.cam2ego = torch.stack(cam2ego)
        sample.img_aug = torch.stack(img_aug)
        return augs

    def _read_camera(self, record: FrameRecord, name: str, where: str) -> Image.Image:
        """A camera's image of a key frame as read (corrupted when the dataset has an image corruption)."""
        camera = record.cameras[name]
        image = _read_image(self.root / camera.path, where, (camera.width, camera.height))
        if self.corruption is not None and self.corruption.family == "images":
            image = Image.fromarray(self.corruption.image(np.asarray(image), record.token, name))
        return image

    def _cam2ego(self, record: FrameRecord, name: str) -> Tensor:
        """A camera's extrinsics as the model is given them (perturbed under ``camera_extrinsics``)."""
        matrix = record.cameras[name].cam2keyego
        if self.corruption is not None:
            matrix = self.corruption.cam2ego(matrix, record.token, name)
        return _matrix(matrix)

    def _history_records(self, record: FrameRecord) -> list[FrameRecord]:
        """Up to ``history`` earlier key frames of the record's scene, newest first, following ``prev``."""
        frames: list[FrameRecord] = []
        current = record
        while len(frames) < self.config.history and current.prev:
            # A `prev` outside the records: an index file that holds part of a scene (e.g. saved from a subset of
            # the records); the history then ends there, as at the start of the scene. Indexes built here never link
            # across scenes; the scene check keeps an edited index from doing so.
            current = self._by_token.get(current.prev)
            if current is None or current.scene != record.scene:
                break
            frames.append(current)
        return frames

    def _load_history(self, record: FrameRecord, sample: Sample, augs: list[ImageAugParams]) -> None:
        """The cameras of the earlier key frames (``sample.history_*``), after :meth:`_load_cameras`.

        Each camera's image gets the key frame's augmentation ``augs`` (no new draws: the sample's own draws stay
        those of a run without history), and the cameras that failed in the key frame are failed in every frame (one
        rig). Slots beyond the start of the scene repeat the key frame and are flagged padded.
        """
        frames = self._history_records(record)
        failed = (~sample.camera_mask).nonzero().flatten().tolist()
        images, intrinsics, cam2ego, ego2global = [], [], [], []
        for frame in frames:
            where = f"{frame.token} (history of {record.token})"
            pixels = []
            for name, params in zip(self.config.cameras, augs, strict=True):
                pixels.append(_normalised(self._read_camera(frame, name, where), params))
            frame_images = torch.stack(pixels)
            if failed:
                frame_images = drop_cameras(frame_images, failed)[0]
            images.append(frame_images)
            intrinsics.append(torch.stack([_matrix(frame.cameras[name].intrinsics) for name in self.config.cameras]))
            cam2ego.append(torch.stack([self._cam2ego(frame, name) for name in self.config.cameras]))
            ego2global.append(_matrix(frame.ego2global, torch.float64))
        padding = self.config.history - len(frames)
        # BEVDet4D's data pipeline also fills the slots before the scene's first frame with the current frame.
        images += [sample.images] * padding
        intrinsics += [sample.intrinsics] * padding
        cam2ego += [sample.cam2ego] * padding
        ego2global += [sample.ego2global] * padding
        sample.history_tokens = tuple(f.token for f in frames) + (record.token,) * padding
        sample.history_images = torch.stack(images)
        sample.history_intrinsics = torch.stack(intrinsics)
        sample.history_cam2ego = torch.stack(cam2ego)
        sample.history_img_aug = sample.img_aug.expand(self.config.history, -1, -1, -1).clone()
        sample.history_ego2global = torch.stack(ego2global)
        sample.history_padded = torch.arange(self.config.history) >= len(frames)

    def _degrade(self, points: Tensor, rng: np.random.Generator, token: str, sweep: int, lidar2ego) -> Tensor:
        """Fewer beams and points, for robustness evaluation; raw rows still hold the ring index in column 4.
        ``sweep`` numbers the sweep (0: the key frame), a stream of the corruption's draws."""
        if self.config.lidar_beams_every > 1:
            points = drop_lidar_beams(points, keep_every=self.config.lidar_beams_every)
        if self.config.point_dropout > 0:
            points = drop_points(points, self.config.point_dropout, rng)
        if self.corruption is not None:
            points = self.corruption.points(points, token, sweep, lidar2ego)
        return points

    def _load_points(self, record: FrameRecord, sample: Sample, rng: np.random.Generator) -> Tensor:
        """Key frame plus sweeps in the key LiDAR frame, ``(x, y, z, intensity, time lag)``; returns the key points.

        Under ``lidar_delay`` the sweep ``k`` before the key frame stands in for it, in the key frame's place (the
        model cannot tell), with the sweeps before it (at a scene's start, the oldest sweep there is). Under
        ``no_lidar`` the cloud is empty."""
        corruption = self.corruption
        if corruption is not None and corruption.lidar_missing:
            sample.points = torch.zeros((0, 5), dtype=torch.float32)
            return sample.points
        sweeps = record.sweeps
        wanted = self.config.sweeps if corruption is None else corruption.sweeps(self.config.sweeps)
        delay = 0 if corruption is None else min(corruption.lidar_delay, len(sweeps))
        path, to_key, lag = self.root / record.lidar_path, np.eye(4), 0.0
        if delay:
            stand_in = sweeps[delay - 1]
            path, to_key, lag = self.root / stand_in.path, np.linalg.inv(stand_in.sweep2lidar), stand_in.time_lag
        raw = read_points(path, record.token)
        if len(raw) == 0:
            # A LiDAR key frame always has returns; an empty file is a failed copy, and scoring it skews the metrics.
            raise SampleError(f"sample {record.token}: {path} is empty (0 points)")
        key = self._degrade(sanitize_points(torch.from_numpy(raw.copy()), str(path)), rng, record.token, 0,
                            record.lidar2ego)  # fmt: skip
        key[:, 4] = 0.0  # the ring column becomes the time lag
        clouds = [key]
        for index, sweep in enumerate(sweeps[delay : delay + wanted], start=1):
            sweep_path = self.root / sweep.path
            raw = read_points(sweep_path, record.token)
            if len(raw) == 0:
                # Sweeps only densify the key frame: an empty one leaves the frame usable, so it is named, not fatal.
                warnings.warn(f"sample {record.token}: sweep {sweep_path} is empty (0 points)", stacklevel=2)
            points = sanitize_points(torch.from_numpy(raw.copy()), str(sweep_path))
            points = self._degrade(points, rng, record.token, index, record.lidar2ego)
            transform = _matrix(to_key @ sweep.sweep2lidar)
            points[:, :3] = points[:, :3] @ transform[:3, :3].T + transform[:3, 3]
            points[:, 4] = sweep.time_lag - lag
            clouds.append(points)
        sample.points = augment_points(torch.cat(clouds), sample.bev_aug)
        return key

    def _load_boxes(self, record: FrameRecord, sample: Sample) -> None:
        """``sample.boxes`` ``(M, 9)`` in the augmented LiDAR (or ego, ``box_frame``) frame and ``sample.box_labels``
        ``(M,)``: the boxes of detection classes (with ``valid_boxes_only``, those with a LiDAR or radar point)."""
        names, valid = record.box_detection_names, record.box_valid
        only_valid = self.config.valid_boxes_only
        keep = [i for i, name in enumerate(names) if name is not None and (valid[i] or not only_valid)]
        source, aug = (record.boxes_ego, sample.occ_aug) if self.config.box_frame == "ego" else \
            (record.boxes_lidar, sample.bev_aug)  # fmt: skip
        boxes = torch.from_numpy(np.asarray(source, dtype=np.float32)[keep].reshape(-1, 9))
        sample.boxes = augment_boxes(boxes, aug)
        sample.box_labels = torch.tensor(
            [DETECTION_CLASSES.index(record.box_detection_names[i]) for i in keep], dtype=torch.int64
        )

    def label_path(self, record: FrameRecord) -> Path:
        """The ground-truth file of a key frame in this dataset's label space."""
        folder = Path(self.config.label_root) if self.config.label_root is not None else self.root / \
            self.space.label_folder  # fmt: skip
        return label_file(self.space, folder, record.scene, record.token, record.lidar_path)

    def _load_occupancy(self, record: FrameRecord, sample: Sample, label_aug: Tensor) -> None:
        """Labels (and masks) moved with ``label_aug``, the BEV augmentation in the labels' frame."""
        space = self.space
        try:
            labels = read_labels(space, self.label_path(record), record.token, flow=self.config.flow,
                                 instances=self.config.instances)  # fmt: skip
        except LabelError as error:  # one error type for every file of a sample (its message names both)
            raise SampleError(str(error)) from error
        sample.voxel_semantics = torch.from_numpy(
            augment_occupancy(labels.semantics, label_aug, space.grid, space.ignore_index, empty=space.free_index)
        )
        if labels.instances is not None:
            sample.voxel_instances = torch.from_numpy(augment_occupancy(labels.instances, label_aug, space.grid, 0,
                                                                        empty=0))  # fmt: skip
        if labels.flow is not None:
            sample.voxel_flow = torch.from_numpy(
                augment_flow(labels.flow, labels.semantics, label_aug, space.grid, space.ignore_index, space.free_index)
            )
        for name in ("mask_camera", "mask_lidar"):
            mask = getattr(labels, name)
            if mask is not None:
                setattr(sample, name, torch.from_numpy(augment_occupancy(mask, label_aug, space.grid, False)))


def _slug(path: Path) -> str:
    return str(path.resolve()).strip(os.sep).replace(os.sep, "_")


def _read_cache(path: Path, key: str) -> Sequence[FrameRecord] | None:
    """The records of an index cache built from tables with ``key``; None if there is none, it is of other tables
    (or parameters) or of an older occkit's format, or it is unreadable (then with a warning naming the file): the
    caller rebuilds it."""
    try:
        if read_index_header(path).get("tables_key") != key:
            log.info("%s: built from other tables or settings; rebuilding it", path)
            return None
        return load_index(path)[0]
    except FileNotFoundError:
        return None
    except OutdatedIndexError:  # an older occkit's cache: expected after an upgrade, nothing is wrong with it
        log.info("%s: an index of an older occkit's format; rebuilding it", path)
        return None
    except (OSError, ValueError) as error:  # IndexFormatError is a ValueError
        warnings.warn(f"{path}: unreadable index cache, rebuilding it ({error})", stacklevel=3)
        return None
