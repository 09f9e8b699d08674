"""Building an index from the nuScenes tables: one :class:`~occkit.data.index.records.FrameRecord` per key frame.

Frames and matrices follow docs/conventions.md: ``a2b`` maps points of frame ``a`` to frame ``b``; the key frame's
ego pose is the one at the LIDAR_TOP key-frame timestamp (the Occ3D label frame). Where the field's info files
(mmdetection3d's ``create_data``) and nuscenes-devkit define a quantity, the definition is theirs:

* sweeps follow ``sample_data.prev`` from the key LiDAR record, as mmdetection3d's ``obtain_sensor2top``;
* box velocities are nuscenes-devkit's ``box_velocity`` (global frame), rotated into the ego / LiDAR frame as
  ``get_sample_data`` rotates a box's velocity (mmdetection3d zeroes the global vz first; the two differ by the
  ego's pitch and roll times the vertical velocity, which is small on roads);
* box yaw is pyquaternion's ``yaw_pitch_roll[0]`` of the box rotation in the frame, as both take it;
* ``box_valid`` is mmdetection3d's ``valid_flag``, ``(num_lidar_pts + num_radar_pts) > 0``, which its
  ``use_valid_flag`` training keeps as targets.
"""

from __future__ import annotations

import math
import os
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from pathlib import Path

import numpy as np

from occkit.classes import detection_name
from occkit.data.index.checks import IndexFormatError, _is_number, _matrix, _show
from occkit.data.index.records import CameraRecord, FrameRecord, SweepRecord
from occkit.data.names import is_safe_name, is_safe_relative_path, safe_name, safe_relative_path
from occkit.data.tables import NuScenesTables, TableError, load_tables
from occkit.geometry.numpy_se3 import (
    MIN_QUATERNION_NORM,
    invert_transform,
    make_transform,
    quaternion_to_matrix,
    rotation_yaw,
    transform_points,
)
from occkit.nuscenes import CAMERA_ORDER, LIDAR_CHANNEL

#: nuscenes-devkit's ``box_velocity`` default: neighbours further apart than this (s) give no velocity; twice
#: this for a centred difference.
MAX_VELOCITY_TIME_DIFF = 1.5


def build_split_index(
    root: str | Path,
    version: str,
    split: str = "all",
    split_file: str | Path | None = None,
    max_sweeps: int = 10,
    progress: Callable[[int, int], None] | None = None,
) -> list[FrameRecord]:
    """:func:`build_index` of one split (``occkit index``): the scenes that ``split_file`` lists under ``split`` (all
    of them for ``all``), else the dataset's own split of that name (its ``splits.json``, or nuScenes' splits);
    ``all`` without a split file indexes every scene."""
    from occkit.data.splits import read_split_file, split_scenes

    if split_file is not None:
        scenes = read_split_file(split_file, None if split == "all" else split)
    else:
        scenes = None if split == "all" else split_scenes(root, version, split)
    return build_index(root, version, max_sweeps=max_sweeps, scenes=scenes, progress=progress)


def build_index(
    root: str | Path,
    version: str,
    max_sweeps: int = 10,
    scenes: Iterable[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[FrameRecord]:
    """Index the key frames of ``root/version``, in scene order (scene.json's) and then time order.

    Args:
        root: dataset root.
        version: table folder, e.g. ``v1.0-trainval``.
        max_sweeps: earlier LiDAR sweeps to record per key frame (DAOcc loads the key frame and 9 of them).
        scenes: scene names to index (see :mod:`occkit.data.splits`); None for all.
        progress: called as ``progress(done, total)`` in key frames, first with ``done = 0``.

    Raises:
        FileNotFoundError, TableError: see :func:`occkit.data.tables.load_tables`; TableError also for records
            that refer to missing tokens, a sample without a LIDAR_TOP key frame, or unknown scene names.
    """
    return index_tables(load_tables(root, version), max_sweeps, scenes, progress)


def index_tables(
    tables: NuScenesTables,
    max_sweeps: int = 10,
    scenes: Iterable[str] | None = None,
    progress: Callable[[int, int], None] | None = None,
) -> list[FrameRecord]:
    """:func:`build_index` on tables already loaded."""
    if max_sweeps < 0:
        raise ValueError(f"max_sweeps must be >= 0, got {max_sweeps}")
    builder = _IndexBuilder(tables, max_sweeps)
    selected = builder.scenes(scenes)
    total = sum(len(samples) for _, samples in selected)
    if progress is not None:
        progress(0, total)
    records: list[FrameRecord] = []
    for scene, samples in selected:
        labelled = builder.labelled_samples(scene["name"])
        for index, sample in enumerate(samples):
            records.append(builder.frame(scene, sample, index, sample["token"] in labelled))
            if progress is not None:
                progress(len(records), total)
    return records


class _IndexBuilder:
    """The reverse lookups that the tables lack (sample -> its key-frame sample_data and annotations), built in
    one pass over each large table, and the per-frame assembly.

    Every table field that goes into a record is checked where it is read (the ``_integer``, ``_name``, ``_path``,
    ``_vectors`` and ``_rotations`` helpers): a wrong type, size or reference is a :class:`TableError` naming the
    table file, the record's token and the field, so no index holds a value its own reader would refuse.
    """

    def __init__(self, tables: NuScenesTables, max_sweeps: int) -> None:
        self.tables = tables
        self.max_sweeps = max_sweeps
        self.sensors: dict[str, dict] = {}
        self.key_data: dict[str, dict[str, dict]] = defaultdict(dict)
        samples = tables.tokens["sample"]
        for sd in tables["sample_data"]:
            if sd["sample_token"] not in samples:
                self._reference("sample_data", sd, "sample_token", "sample")  # raises
            if sd["is_key_frame"]:
                sensor = self._sensor(sd)
                if sensor["modality"] == "camera" or sensor["channel"] == LIDAR_CHANNEL:
                    self.key_data[sd["sample_token"]][sensor["channel"]] = sd
        self.annotations: dict[str, list[dict]] = defaultdict(list)
        for annotation in tables["sample_annotation"]:
            if annotation["sample_token"] not in samples:
                self._reference("sample_annotation", annotation, "sample_token", "sample")  # raises
            self.annotations[annotation["sample_token"]].append(annotation)
        self.calibrations: dict[str, np.ndarray] = {}
        self.intrinsics: dict[str, np.ndarray] = {}
        self.categories: dict[str, str] = {}

    # ------------------------------------------------------------------------------------------- field checks
    def _where(self, table: str, record: Mapping, field: str | None = None) -> str:
        token = record["token"]
        where = f"{self.tables.file(table)}: record {token if is_safe_name(token) else _show(token)}"
        return where if field is None else f"{where}.{field}"

    def _error(self, table: str, record: Mapping, field: str, message: str) -> TableError:
        return TableError(f"{self._where(table, record, field)}: {message}")

    def _reference(self, table: str, record: Mapping, field: str, target: str) -> dict:
        """The ``target`` record that ``record[field]`` names."""
        try:
            return self.tables.tokens[target][record[field]]
        except (KeyError, TypeError):
            return self.tables.get(target, record[field], self._where(table, record, field))  # raises

    def _integer(self, table: str, record: Mapping, field: str) -> int:
        value = record[field]
        if type(value) is not int:
            raise self._error(table, record, field, f"expected an integer, got {_show(value)}")
        return value

    def _text(self, table: str, record: Mapping, field: str) -> str:
        value = record[field]
        if type(value) is not str:
            raise self._error(table, record, field, f"expected a string, got {_show(value)}")
        return value

    def _name(self, table: str, record: Mapping, field: str) -> str:
        value = record[field]
        return value if is_safe_name(value) else safe_name(value, self._where(table, record, field), TableError)

    def _path(self, table: str, record: Mapping, field: str) -> str:
        value = record[field]
        if is_safe_relative_path(value):
            return value
        return safe_relative_path(value, self._where(table, record, field), TableError)

    def _vectors(self, table: str, records: Sequence[Mapping], field: str, size: int) -> np.ndarray:
        """``(M, size)`` float64 of the records' ``field``, each a list of ``size`` finite numbers."""
        values = [record[field] for record in records]
        try:
            # numpy parses numbers in strings ("1.5") too: harmless, the index holds the floats.
            array = np.array(values, dtype=np.float64)
        except (ValueError, TypeError):  # ragged, or not numbers
            array = None
        if array is not None and array.shape == (len(values), size) and np.isfinite(array).all():
            return array
        for record, value in zip(records, values, strict=True):
            if not (
                isinstance(value, list)
                and len(value) == size
                and all(_is_number(x) and math.isfinite(x) for x in value)
            ):
                raise self._error(table, record, field, f"expected a list of {size} finite numbers, got {_show(value)}")
        return np.array(values, dtype=np.float64).reshape(len(values), size)

    def _rotations(self, table: str, records: Sequence[Mapping]) -> np.ndarray:
        """``(M, 3, 3)`` rotations of the records' ``rotation`` quaternions (w, x, y, z)."""
        quaternions = self._vectors(table, records, "rotation", 4)
        try:
            return quaternion_to_matrix(quaternions)
        except ValueError:  # a norm below MIN_QUATERNION_NORM (the values are finite)
            norms = np.linalg.norm(quaternions, axis=1)
            i = int(np.argmax(norms < MIN_QUATERNION_NORM))
            raise self._error(
                table, records[i], "rotation", f"{_show(records[i]['rotation'])} has norm {norms[i]:.3g}: not a "
                "rotation quaternion (w, x, y, z)"
            ) from None  # fmt: skip

    def _transforms(self, table: str, records: Sequence[Mapping]) -> np.ndarray:
        """``(M, 4, 4)`` float64 from records with ``translation`` (3) and ``rotation`` (w, x, y, z)."""
        return make_transform(self._rotations(table, records), self._vectors(table, records, "translation", 3))

    # ------------------------------------------------------------------------------------------- lookups
    def _sensor(self, sd: dict) -> dict:
        token = sd["calibrated_sensor_token"]
        if token not in self.sensors:
            calibration = self._reference("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
            sensor = self._reference("calibrated_sensor", calibration, "sensor_token", "sensor")
            self._text("sensor", sensor, "channel")
            self.sensors[token] = sensor
        return self.sensors[token]

    def _pose(self, sd: dict) -> dict:
        return self._reference("sample_data", sd, "ego_pose_token", "ego_pose")

    def _calibration(self, sd: dict) -> np.ndarray:
        token = sd["calibrated_sensor_token"]
        if token not in self.calibrations:
            record = self._reference("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
            self.calibrations[token] = self._transforms("calibrated_sensor", [record])[0]
        return self.calibrations[token]

    def _intrinsics(self, sd: dict) -> np.ndarray:
        token = sd["calibrated_sensor_token"]
        if token not in self.intrinsics:
            record = self._reference("sample_data", sd, "calibrated_sensor_token", "calibrated_sensor")
            where = self._where("calibrated_sensor", record, "camera_intrinsic")
            try:
                self.intrinsics[token] = _matrix(record["camera_intrinsic"], 3, 3, where)
            except IndexFormatError as error:
                raise TableError(str(error)) from None
        return self.intrinsics[token]

    def _category(self, annotation: dict) -> str:
        token = annotation["instance_token"]
        if token not in self.categories:
            instance = self._reference("sample_annotation", annotation, "instance_token", "instance")
            category = self._reference("instance", instance, "category_token", "category")
            self.categories[token] = self._text("category", category, "name")
        return self.categories[token]

    def scenes(self, names: Iterable[str] | None) -> list[tuple[dict, list[dict]]]:
        """Selected scenes in table order, each with its samples in time order.

        Checks every scene and sample record: names, a known scene for each sample, prev / next samples that exist.
        """
        table = self.tables["scene"]
        for scene in table:
            self._name("scene", scene, "token")
            self._name("scene", scene, "name")
        if names is not None:
            wanted = set(names)
            missing = sorted(wanted - {scene["name"] for scene in table})
            if missing:
                shown = ", ".join(missing[:5]) + (f" and {len(missing) - 5} more" if len(missing) > 5 else "")
                raise TableError(f"{len(missing)} scene(s) are not in {self.tables.file('scene')}: {shown}")
            table = [scene for scene in table if scene["name"] in wanted]
        scenes, known = self.tables.tokens["scene"], self.tables.tokens["sample"]
        samples: dict[str, list[dict]] = defaultdict(list)
        for sample in self.tables["sample"]:
            self._name("sample", sample, "token")
            self._integer("sample", sample, "timestamp")
            if sample["scene_token"] not in scenes:
                self._reference("sample", sample, "scene_token", "scene")  # raises
            for field in ("prev", "next"):
                if sample[field] != "" and sample[field] not in known:
                    self._reference("sample", sample, field, "sample")  # raises
            samples[sample["scene_token"]].append(sample)
        return [(scene, sorted(samples[scene["token"]], key=lambda s: s["timestamp"])) for scene in table]

    def labelled_samples(self, scene: str) -> set[str]:
        """Sample tokens of ``scene`` with an Occ3D ``labels.npz``: one directory listing per scene, one stat per
        sample directory found (the index reads no other file). ``scene`` is a checked name (see :meth:`scenes`)."""
        return _labelled_tokens(Path(self.tables.root) / "gts" / scene)

    # ------------------------------------------------------------------------------------------- one frame
    def frame(self, scene: dict, sample: dict, index: int, labelled: bool) -> FrameRecord:
        try:
            return self._frame(scene, sample, index, labelled)
        except TableError:
            raise
        except ValueError as error:  # a record refused a value that no check above caught
            raise TableError(f"{self._where('sample', sample)}: {error}") from None

    def _frame(self, scene: dict, sample: dict, index: int, labelled: bool) -> FrameRecord:
        key = self.key_data.get(sample["token"], {})
        if LIDAR_CHANNEL not in key:
            raise TableError(
                f"{self.tables.file('sample_data')} has no {LIDAR_CHANNEL} key frame for sample {sample['token']}"
            )
        lidar = key[LIDAR_CHANNEL]
        cameras = sorted(
            (channel for channel in key if channel != LIDAR_CHANNEL),
            key=lambda c: (CAMERA_ORDER.index(c) if c in CAMERA_ORDER else len(CAMERA_ORDER), c),
        )
        sweeps = self._sweep_chain(lidar, scene["token"])
        data = [lidar, *sweeps, *(key[c] for c in cameras)]
        for sd in data:
            self._path("sample_data", sd, "filename")
            self._integer("sample_data", sd, "timestamp")
        # All ego poses of the frame in one batch: key LiDAR, sweeps, cameras.
        poses = self._transforms("ego_pose", [self._pose(sd) for sd in data])
        ego2global, sweep_poses, camera_poses = poses[0], poses[1 : 1 + len(sweeps)], poses[1 + len(sweeps) :]
        global2ego = invert_transform(ego2global)
        lidar2ego = self._calibration(lidar)
        ego2lidar = invert_transform(lidar2ego)
        global2lidar = ego2lidar @ global2ego
        sweep_records = tuple(
            SweepRecord(
                path=sd["filename"],
                timestamp=sd["timestamp"],
                sweep2lidar=global2lidar @ pose @ self._calibration(sd),
                time_lag=(lidar["timestamp"] - sd["timestamp"]) / 1e6,
            )
            for sd, pose in zip(sweeps, sweep_poses, strict=True)
        )
        camera_records = {}
        for channel, pose in zip(cameras, camera_poses, strict=True):
            sd = key[channel]
            cam2ego = self._calibration(sd)
            camera_records[channel] = CameraRecord(
                path=sd["filename"],
                timestamp=sd["timestamp"],
                width=self._integer("sample_data", sd, "width"),
                height=self._integer("sample_data", sd, "height"),
                intrinsics=self._intrinsics(sd),
                cam2ego=cam2ego,
                ego2global=pose,
                cam2keyego=global2ego @ pose @ cam2ego,
            )
        annotations = self.annotations.get(sample["token"], [])
        for annotation in annotations:
            self._text("sample_annotation", annotation, "instance_token")
            self._text("sample_annotation", annotation, "visibility_token")
            for field in ("num_lidar_pts", "num_radar_pts"):
                if (count := self._integer("sample_annotation", annotation, field)) < 0:
                    raise self._error("sample_annotation", annotation, field, f"expected a count >= 0, got {count}")
        boxes_ego, boxes_lidar, valid = self._boxes(annotations, global2ego, ego2lidar)
        categories = tuple(self._category(a) for a in annotations)
        return FrameRecord(
            token=sample["token"],
            scene=scene["name"],
            scene_token=scene["token"],
            timestamp=sample["timestamp"],
            prev=sample["prev"],
            next=sample["next"],
            index_in_scene=index,
            ego2global=ego2global,
            lidar_path=lidar["filename"],
            lidar2ego=lidar2ego,
            sweeps=sweep_records,
            cameras=camera_records,
            boxes_ego=boxes_ego,
            boxes_lidar=boxes_lidar,
            velocity_valid=valid,
            box_categories=categories,
            box_detection_names=tuple(self._detection_name(c) for c in categories),
            box_instances=tuple(a["instance_token"] for a in annotations),
            box_num_lidar_pts=[a["num_lidar_pts"] for a in annotations],
            # mmdetection3d's valid_flag (create_nuscenes_infos): a box that some LiDAR or radar return hit.
            box_valid=[a["num_lidar_pts"] + a["num_radar_pts"] > 0 for a in annotations],
            box_visibility=tuple(a["visibility_token"] for a in annotations),
            occ_path=f"gts/{scene['name']}/{sample['token']}/labels.npz" if labelled else None,
        )

    def _detection_name(self, category: str) -> str | None:
        try:
            return detection_name(category)
        except KeyError:
            raise TableError(f"{self.tables.file('category')}: {category!r} is not a nuScenes category") from None

    def _sweep_chain(self, lidar: dict, scene_token: str) -> list[dict]:
        """Up to ``max_sweeps`` sample_data records before ``lidar`` (newest first), within its scene."""
        chain: list[dict] = []
        record = lidar
        while len(chain) < self.max_sweeps and record["prev"]:
            record = self._reference("sample_data", record, "prev", "sample_data")
            sample = self._reference("sample_data", record, "sample_token", "sample")
            if sample["scene_token"] != scene_token:
                break
            chain.append(record)
        return chain

    def _boxes(
        self, annotations: list[dict], global2ego: np.ndarray, ego2lidar: np.ndarray
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``(N, 9)`` boxes in the ego and LiDAR frames and the ``(N,)`` velocity-valid flags."""
        if not annotations:
            return np.zeros((0, 9)), np.zeros((0, 9)), np.zeros(0, dtype=bool)
        centres = self._vectors("sample_annotation", annotations, "translation", 3)
        sizes = self._vectors("sample_annotation", annotations, "size", 3)
        rotations = self._rotations("sample_annotation", annotations)
        velocities, valid = self._velocities(annotations)
        lengths_widths_heights = sizes[:, [1, 0, 2]]  # nuScenes size is (w, l, h)
        boxes = []
        for transform in (global2ego, ego2lidar @ global2ego):
            rotation = transform[:3, :3]
            boxes.append(
                np.concatenate(
                    (
                        transform_points(transform, centres),
                        lengths_widths_heights,
                        rotation_yaw(rotation @ rotations)[:, None],
                        (velocities @ rotation.T)[:, :2],  # rotated, not translated
                    ),
                    axis=1,
                )
            )
        return boxes[0], boxes[1], valid

    def _velocities(self, annotations: list[dict]) -> tuple[np.ndarray, np.ndarray]:
        """nuscenes-devkit ``box_velocity`` of each annotation: ``(N, 3)`` global m/s (0 where invalid), ``(N,)``."""
        samples = self.tables.tokens["sample"]  # every annotation's sample exists: checked in __init__
        first, last, limits = [], [], []
        for annotation in annotations:
            has_prev, has_next = annotation["prev"] != "", annotation["next"] != ""
            table = "sample_annotation"
            first.append(self._reference(table, annotation, "prev", table) if has_prev else annotation)
            last.append(self._reference(table, annotation, "next", table) if has_next else annotation)
            # No neighbour: no estimate. A centred difference may span twice the one-sided limit.
            limits.append(0.0 if not (has_prev or has_next) else MAX_VELOCITY_TIME_DIFF * (1 + (has_prev and has_next)))
        times = [
            (samples[b["sample_token"]]["timestamp"] - samples[a["sample_token"]]["timestamp"]) / 1e6
            for a, b in zip(first, last, strict=True)
        ]
        time_diff = np.array(times, dtype=np.float64)
        valid = (time_diff > 0) & (time_diff <= np.array(limits))
        difference = self._vectors("sample_annotation", last, "translation", 3) - self._vectors(
            "sample_annotation", first, "translation", 3
        )
        velocities = np.where(valid[:, None], difference / np.where(valid, time_diff, 1.0)[:, None], 0.0)
        return velocities, valid


def _labelled_tokens(folder: Path) -> set[str]:
    """Names of the sample folders in an Occ3D scene folder (``gts/<scene>``) that hold a ``labels.npz``: what a
    record's ``occ_path`` says. One directory listing, one stat per sample folder; none for a missing folder."""
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return set()
    return {entry.name for entry in entries if os.path.isfile(os.path.join(entry.path, "labels.npz"))}
