"""What ``occkit label`` reads: one scene's LiDAR sweeps, lidarseg labels, boxes, poses and cameras.

:func:`plan_scenes` turns the nuScenes tables (with the nuScenes-lidarseg extension) into one :class:`ScenePlan`
per scene: small, picklable records of every LiDAR sweep in time order with its poses and the boxes at its instant,
and of every key frame's cameras. Worker processes then read the point and label files of their scene with
:func:`read_sweep` and never touch the tables.

Boxes of a sweep between two key frames are interpolated as nuscenes-devkit's ``get_boxes`` does: a sweep belongs to
the next key frame's sample; an object annotated in that sample and in the previous one gets its centre linearly
and its rotation spherically interpolated at the sweep's timestamp; an object annotated in the sample alone keeps
that annotation; an object annotated in the previous sample alone has no box.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from occkit.classes import NUSCENES_TO_OCC3D, occ3d_id
from occkit.data.dataset import SampleError, read_points
from occkit.data.names import path_under
from occkit.data.tables import NuScenesTables, TableError
from occkit.geometry.numpy_se3 import quaternion_to_matrix, transform_from_quaternion
from occkit.nuscenes import LIDAR_CHANNEL, LIDARSEG_TABLE

__all__ = ["LidarsegMissingError", "Boxes", "SweepPlan", "KeyFramePlan", "ScenePlan", "plan_scenes",
           "lidarseg_to_occ3d", "read_sweep"]


class LidarsegMissingError(FileNotFoundError):
    """The dataset has no nuScenes-lidarseg labels (the table, a category's index or a label file)."""


@dataclass(frozen=True)
class Boxes:
    """The annotated boxes at one instant, global frame.

    Attributes:
        instance: ``(B,)`` int32 scene-local instance id (index into :attr:`ScenePlan.instances`).
        label: ``(B,)`` uint8 Occ3D class of the box's category.
        center: ``(B, 3)`` float64 box centres.
        size: ``(B, 3)`` float64 nuScenes ``(width, length, height)``.
        rotation: ``(B, 3, 3)`` float64 box to global rotation (the box's x axis runs along its length).
    """

    instance: np.ndarray
    label: np.ndarray
    center: np.ndarray
    size: np.ndarray
    rotation: np.ndarray

    def __len__(self) -> int:
        return int(self.instance.shape[0])

    def box2global(self) -> np.ndarray:
        """``(B, 4, 4)`` float64 box to global transforms."""
        transform = np.tile(np.eye(4), (len(self), 1, 1))
        transform[:, :3, :3] = self.rotation
        transform[:, :3, 3] = self.center
        return transform


@dataclass(frozen=True)
class SweepPlan:
    """One LiDAR sweep of a scene.

    Attributes:
        token: its sample_data token (the lidarseg token of a key frame).
        filename: the point file, relative to the dataset root.
        timestamp: microseconds.
        key: whether it is a key frame (only key frames have lidarseg labels).
        lidarseg: the lidarseg file of a key frame, relative to the root; "" for a sweep.
        ego2global, lidar2ego: ``(4, 4)`` float64 poses.
        boxes: the boxes at its timestamp.
    """

    token: str
    filename: str
    timestamp: int
    key: bool
    lidarseg: str
    ego2global: np.ndarray
    lidar2ego: np.ndarray
    boxes: Boxes


@dataclass(frozen=True)
class KeyFramePlan:
    """What the output of one key frame needs besides the aggregated points.

    Attributes:
        sample_token: the sample's token (the Occ3D label folder's name).
        sweep: index of its LiDAR sweep in :attr:`ScenePlan.sweeps`.
        cameras: per camera, ``(cam2ego (4, 4), K (3, 3), width, height)`` as calibrated at the key frame.
    """

    sample_token: str
    sweep: int
    cameras: tuple[tuple[np.ndarray, np.ndarray, int, int], ...]


@dataclass(frozen=True)
class ScenePlan:
    """One scene: its sweeps in time order, its key frames and its objects.

    Attributes:
        name: the scene's name (``scene-0061``).
        root: the dataset root.
        sweeps: every LiDAR sweep used, key frames included, in time order.
        key_frames: the key frames in time order.
        instances: the instance token of each scene-local instance id.
    """

    name: str
    root: Path
    sweeps: tuple[SweepPlan, ...]
    key_frames: tuple[KeyFramePlan, ...]
    instances: tuple[str, ...]


def _lidarseg_files(tables: NuScenesTables) -> dict[str, str]:
    """sample_data token -> lidarseg file; :class:`LidarsegMissingError` names what the dataset lacks."""
    table = tables.root / tables.version / f"{LIDARSEG_TABLE}.json"
    if not table.is_file():
        raise LidarsegMissingError(
            f"occkit label needs nuScenes-lidarseg: {table} not found. Per-point semantics come from it (boxes "
            f"alone do not label the ground, buildings or vegetation). Extract the lidarseg archive of "
            f"{tables.version} (nuScenes-lidarseg-all-v1.0.tar.bz2, or nuScenes-lidarseg-mini-v1.0.tar.bz2 for "
            f"v1.0-mini) into {tables.root}: it adds lidarseg/{tables.version}/*.bin and {tables.version}/lidarseg.json"
        )
    import json

    try:
        rows = json.loads(table.read_text())
        files = {row["sample_data_token"]: row["filename"] for row in rows}
    except (ValueError, TypeError, KeyError) as error:
        raise TableError(f"{tables.version}/{LIDARSEG_TABLE}.json: not a lidarseg table ({error!r})") from None
    missing_index = [row["name"] for row in tables["category"] if "index" not in row]
    if missing_index:
        raise LidarsegMissingError(
            f"{tables.file('category')}: categories {', '.join(missing_index[:4])} have no lidarseg 'index' field; "
            "the lidarseg extension's category.json replaces the one without it"
        )
    return files


def lidarseg_to_occ3d(tables: NuScenesTables) -> np.ndarray:
    """``(256,)`` uint8 lookup from the dataset's lidarseg indices (category ``index`` field) to Occ3D ids."""
    lookup = np.full(256, 255, np.uint8)
    for row in tables["category"]:
        name = row["name"]
        if name not in NUSCENES_TO_OCC3D:
            raise TableError(f"{tables.file('category')}: unknown category {name!r}")
        lookup[int(row["index"])] = NUSCENES_TO_OCC3D[name]
    return lookup


def _slerp(q0: np.ndarray, q1: np.ndarray, amount: float) -> np.ndarray:
    """Spherical interpolation of (w, x, y, z) unit quaternions, along the shorter arc."""
    q0, q1 = q0 / np.linalg.norm(q0), q1 / np.linalg.norm(q1)
    dot = float(q0 @ q1)
    if dot < 0.0:
        q1, dot = -q1, -dot
    if dot > 0.9995:  # nearly parallel: linear interpolation is exact to rounding
        q = q0 + amount * (q1 - q0)
        return q / np.linalg.norm(q)
    theta = np.arccos(dot)
    return (np.sin((1 - amount) * theta) * q0 + np.sin(amount * theta) * q1) / np.sin(theta)


class _Planner:
    """Indexes the tables once and builds each scene's plan."""

    def __init__(self, tables: NuScenesTables, sweeps_per_interval: int | None) -> None:
        self.tables = tables
        self.sweeps_per_interval = sweeps_per_interval
        self.lidarseg = _lidarseg_files(tables)
        self.channel = {
            row["token"]: tables.get("sensor", row["sensor_token"], tables.file("calibrated_sensor"))["channel"]
            for row in tables["calibrated_sensor"]
        }
        self.data_of_sample: dict[str, list[dict]] = defaultdict(list)
        for row in tables["sample_data"]:
            self.data_of_sample[row["sample_token"]].append(row)
        self.annotations_of_sample: dict[str, list[dict]] = defaultdict(list)
        for row in tables["sample_annotation"]:
            self.annotations_of_sample[row["sample_token"]].append(row)
        self.label_of_instance = {}
        for row in tables["instance"]:
            category = tables.get("category", row["category_token"], f"{tables.file('instance')}: {row['token']}")
            self.label_of_instance[row["token"]] = occ3d_id(category["name"])

    def _pose(self, record: dict, table: str) -> np.ndarray:
        row = self.tables.get(table, record[f"{table}_token"], f"{self.tables.file('sample_data')}: {record['token']}")
        return transform_from_quaternion(np.asarray(row["rotation"], float), np.asarray(row["translation"], float))

    def _boxes(self, annotations: list[dict], instances: dict[str, int]) -> Boxes:
        ids = [instances.setdefault(a["instance_token"], len(instances)) for a in annotations]
        quaternions = np.array([a["rotation"] for a in annotations], float).reshape(-1, 4)
        return Boxes(
            instance=np.array(ids, np.int32),
            label=np.array([self.label_of_instance[a["instance_token"]] for a in annotations], np.uint8),
            center=np.array([a["translation"] for a in annotations], float).reshape(-1, 3),
            size=np.array([a["size"] for a in annotations], float).reshape(-1, 3),
            rotation=quaternion_to_matrix(quaternions) if len(annotations) else np.zeros((0, 3, 3)),
        )

    def _sweep_boxes(self, sample: dict, timestamp: int, key: bool, instances: dict[str, int]) -> Boxes:
        current = self.annotations_of_sample[sample["token"]]
        if key or not sample["prev"]:
            return self._boxes(current, instances)
        previous_sample = self.tables.get("sample", sample["prev"], self.tables.file("sample"))
        previous = {a["instance_token"]: a for a in self.annotations_of_sample[previous_sample["token"]]}
        t0, t1 = previous_sample["timestamp"], sample["timestamp"]
        amount = (min(max(timestamp, t0), t1) - t0) / (t1 - t0) if t1 > t0 else 1.0
        interpolated = []
        for annotation in current:
            before = previous.get(annotation["instance_token"])
            if before is not None:
                centre = np.asarray(before["translation"]) + amount * (
                    np.asarray(annotation["translation"]) - np.asarray(before["translation"])
                )
                rotation = _slerp(np.asarray(before["rotation"], float), np.asarray(annotation["rotation"], float),
                                  amount)  # fmt: skip
                annotation = {**annotation, "translation": centre.tolist(), "rotation": rotation.tolist()}
            interpolated.append(annotation)
        return self._boxes(interpolated, instances)

    def _kept(self, rows: list[dict]) -> list[dict]:
        """The sweeps of one key-frame interval that are used: all, or ``sweeps_per_interval`` evenly spread."""
        wanted = self.sweeps_per_interval
        if wanted is None or wanted >= len(rows):
            return rows
        return [rows[int((j + 0.5) * len(rows) / wanted)] for j in range(wanted)]

    def plan(self, scene: dict) -> ScenePlan:
        tables = self.tables
        samples, token = [], scene["first_sample_token"]
        while token:
            samples.append(tables.get("sample", token, f"{tables.file('scene')}: {scene['name']}"))
            token = samples[-1]["next"]
        instances: dict[str, int] = {}
        sweeps: list[SweepPlan] = []
        key_frames: list[KeyFramePlan] = []
        for sample in samples:
            rows = sorted(
                (r for r in self.data_of_sample[sample["token"]] if self.channel[r["calibrated_sensor_token"]]
                 == LIDAR_CHANNEL), key=lambda r: r["timestamp"])  # fmt: skip
            keys = [r for r in rows if r["is_key_frame"]]
            if len(keys) != 1:
                raise TableError(f"sample {sample['token']} of {scene['name']}: {len(keys)} key-frame "
                                 f"{LIDAR_CHANNEL} sample_data records, expected 1")  # fmt: skip
            between = self._kept([r for r in rows if not r["is_key_frame"]])
            for row in (*between, keys[0]):
                key = row["is_key_frame"]
                if key and row["token"] not in self.lidarseg:
                    raise LidarsegMissingError(
                        f"sample {sample['token']} of {scene['name']}: {tables.version}/{LIDARSEG_TABLE}.json has no "
                        f"labels for its {LIDAR_CHANNEL} sample_data {row['token']}"
                    )
                sweeps.append(SweepPlan(
                    token=row["token"], filename=row["filename"], timestamp=int(row["timestamp"]), key=key,
                    lidarseg=self.lidarseg[row["token"]] if key else "",
                    ego2global=self._pose(row, "ego_pose"), lidar2ego=self._pose(row, "calibrated_sensor"),
                    boxes=self._sweep_boxes(sample, int(row["timestamp"]), key, instances),
                ))  # fmt: skip
            cameras = []
            for row in self.data_of_sample[sample["token"]]:
                calibration = tables.get("calibrated_sensor", row["calibrated_sensor_token"],
                                         tables.file("sample_data"))  # fmt: skip
                if row["is_key_frame"] and calibration.get("camera_intrinsic"):
                    cameras.append((self.channel[row["calibrated_sensor_token"]], self._pose(row, "calibrated_sensor"),
                                    np.asarray(calibration["camera_intrinsic"], float), int(row["width"]),
                                    int(row["height"])))  # fmt: skip
            cameras.sort(key=lambda c: c[0])
            key_frames.append(KeyFramePlan(sample["token"], len(sweeps) - 1, tuple(c[1:] for c in cameras)))
        return ScenePlan(scene["name"], tables.root, tuple(sweeps), tuple(key_frames), tuple(instances))


def plan_scenes(
    tables: NuScenesTables, scenes: list[str] | None = None, sweeps_per_interval: int | None = None
) -> list[ScenePlan]:
    """One plan per scene of ``tables`` (or of the named ``scenes``, in table order).

    Args:
        tables: the dataset's tables.
        scenes: scene names to plan; None for all. An unknown name is a ValueError listing the known ones.
        sweeps_per_interval: non-key sweeps used between consecutive key frames, evenly spread (nuScenes and the
            synthetic world have 9 or 10); None for all, 0 for key frames only.

    Raises:
        LidarsegMissingError: the dataset has no lidarseg labels, or a key frame has none.
    """
    if sweeps_per_interval is not None and sweeps_per_interval < 0:
        raise ValueError(f"sweeps per key-frame interval must be >= 0 or None (all), got {sweeps_per_interval}")
    planner = _Planner(tables, sweeps_per_interval)
    chosen = tables["scene"]
    if scenes is not None:
        known = {row["name"] for row in chosen}
        unknown = [name for name in scenes if name not in known]
        if unknown:
            raise ValueError(f"no scene {', '.join(unknown)} in {tables.file('scene')}; scenes: "
                             f"{', '.join(sorted(known)[:10])}{' ...' if len(known) > 10 else ''}")  # fmt: skip
        chosen = [row for row in chosen if row["name"] in set(scenes)]
    return [planner.plan(scene) for scene in chosen]


def read_sweep(plan: ScenePlan, sweep: SweepPlan, lookup: np.ndarray) -> tuple[np.ndarray, np.ndarray | None]:
    """The sweep's points and, for a key frame, their Occ3D labels.

    Args:
        plan: the scene (for its root and name in messages).
        sweep: the sweep.
        lookup: ``(256,)`` lidarseg index -> Occ3D id (:func:`lidarseg_to_occ3d`).

    Returns:
        ``(N, 3)`` float64 points in the LiDAR frame, and ``(N,)`` uint8 Occ3D labels or None for a non-key sweep.
    """
    where = f"{plan.name}: {LIDAR_CHANNEL} sample_data {sweep.token}"
    points = read_points(path_under(plan.root, sweep.filename, where), sweep.token)[:, :3].astype(np.float64)
    if not sweep.key:
        return points, None
    path = path_under(plan.root, sweep.lidarseg, where)
    try:
        labels = np.fromfile(path, dtype=np.uint8)
    except FileNotFoundError:
        raise LidarsegMissingError(f"{where}: lidarseg file {path} not found") from None
    if labels.shape[0] != points.shape[0]:
        raise SampleError(f"{where}: {path} holds {labels.shape[0]} labels for {points.shape[0]} points")
    return points, lookup[labels]
