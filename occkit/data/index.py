"""A plain index of key frames built from the nuScenes tables, saved as JSON (never pickle).

One :class:`FrameRecord` per sample holds everything a data pipeline needs without the tables: file paths
(relative to the dataset root), calibrations and poses as 4x4 matrices, the LiDAR sweeps before the key frame with
their transforms into the key frame's LiDAR frame, each camera's geometry relative to the key frame's ego pose, and
the sample's boxes in the ego and LiDAR frames.

Frames and matrices follow docs/conventions.md: ``a2b`` maps points of frame ``a`` to frame ``b``; the key frame's
ego pose is the one at the LIDAR_TOP key-frame timestamp (the Occ3D label frame). Where the field's info files
(mmdetection3d's ``create_data``) and nuscenes-devkit define a quantity, the definition is theirs:

* sweeps follow ``sample_data.prev`` from the key LiDAR record, as mmdetection3d's ``obtain_sensor2top``;
* box velocities are nuscenes-devkit's ``box_velocity`` (global frame), rotated into the ego / LiDAR frame as
  ``get_sample_data`` rotates a box's velocity (mmdetection3d zeroes the global vz first; the two differ by the
  ego's pitch and roll times the vertical velocity, which is small on roads);
* box yaw is pyquaternion's ``yaw_pitch_roll[0]`` of the box rotation in the frame, as both take it.

The JSON file is ``{"format": "occkit-index/1", "version", "root", "max_sweeps", "created_by", "frames",
"records": [...]}`` with the header on the first line and one record per line.

Names from the tables become file paths (``gts/<scene>/<token>/labels.npz``, ``<out>/<token>.npz``): sample tokens,
scene names and scene tokens must be safe names and every file path a relative path that stays under the root
(:mod:`occkit.data.names`), checked when an index is built and again when one is read.
"""

from __future__ import annotations

import abc
import hashlib
import json
import math
import os
from collections import defaultdict
from collections.abc import Callable, Iterable, Mapping, Sequence
from dataclasses import dataclass, fields
from pathlib import Path
from typing import Any

import numpy as np

from occkit import __version__
from occkit.classes import detection_name
from occkit.data.names import is_safe_name, is_safe_relative_path, safe_name, safe_relative_path
from occkit.data.tables import NuScenesTables, TableError, load_tables
from occkit.nuscenes import CAMERA_ORDER, LIDAR_CHANNEL, TABLE_NAMES

__all__ = [
    "INDEX_FORMAT",
    "BOX_COLUMNS",
    "IndexFormatError",
    "SweepRecord",
    "CameraRecord",
    "FrameRecord",
    "build_index",
    "index_tables",
    "save_index",
    "load_index",
    "read_index_header",
    "tables_key",
    "MIN_QUATERNION_NORM",
]

#: Value of the ``format`` key of index files.
INDEX_FORMAT = "occkit-index/1"

#: nuscenes-devkit's ``box_velocity`` default: neighbours further apart than this (s) give no velocity; twice
#: this for a centred difference.
MAX_VELOCITY_TIME_DIFF = 1.5

#: Columns of a box row: centre (m), size (m, length along the heading), yaw (rad), velocity (m/s).
BOX_COLUMNS = ("x", "y", "z", "l", "w", "h", "yaw", "vx", "vy")


class IndexFormatError(ValueError):
    """An index file or record dict is malformed; the message names the file, record and field."""


# ----------------------------------------------------------------------------------------------------- records
class _Record(abc.ABC):
    """Equality through :meth:`to_dict`: the dataclass-generated one cannot compare numpy arrays."""

    @abc.abstractmethod
    def to_dict(self) -> dict[str, Any]:
        """The record as JSON-ready nested lists and scalars."""

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return self.to_dict() == other.to_dict()  # type: ignore[attr-defined]

    __hash__ = None  # type: ignore[assignment]


def _frozen(record: object, name: str, shape: tuple[int, ...], dtype: type) -> None:
    """Replace field ``name`` of a frozen dataclass by a read-only array of ``dtype`` and check its shape."""
    array = np.array(getattr(record, name), dtype=dtype)
    if array.ndim != len(shape) or any(n not in (-1, m) for n, m in zip(shape, array.shape, strict=True)):
        wanted = "(" + ", ".join("N" if n == -1 else str(n) for n in shape) + ")"
        raise ValueError(f"{type(record).__name__}.{name} must have shape {wanted}, got {array.shape}")
    array.setflags(write=False)
    object.__setattr__(record, name, array)


@dataclass(frozen=True, eq=False)
class SweepRecord(_Record):
    """One LiDAR sweep before a key frame."""

    path: str
    """Point file, relative to the dataset root."""
    timestamp: int
    """Microseconds."""
    sweep2lidar: np.ndarray
    """``(4, 4)`` float64: points of this sweep's LiDAR frame -> the key frame's LiDAR frame (through both ego
    poses and the global frame)."""
    time_lag: float
    """Seconds from this sweep to the key frame, ``(key timestamp - timestamp) / 1e6``; >= 0."""

    def __post_init__(self) -> None:
        _frozen(self, "sweep2lidar", (4, 4), np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "timestamp": self.timestamp,
            "sweep2lidar": self.sweep2lidar.tolist(),
            "time_lag": self.time_lag,
        }

    @classmethod
    def from_dict(cls, data: Any, where: str = "sweep") -> SweepRecord:
        """Inverse of :meth:`to_dict`; :class:`IndexFormatError` names ``where`` and the field on bad input."""
        fields_ = _fields(cls, data, where)
        return cls(
            path=_path(fields_["path"], f"{where}.path"),
            timestamp=_integer(fields_["timestamp"], f"{where}.timestamp"),
            sweep2lidar=_matrix(fields_["sweep2lidar"], 4, 4, f"{where}.sweep2lidar"),
            time_lag=_number(fields_["time_lag"], f"{where}.time_lag"),
        )


@dataclass(frozen=True, eq=False)
class CameraRecord(_Record):
    """The key-frame image of one camera."""

    path: str
    """Image file, relative to the dataset root."""
    timestamp: int
    """Microseconds; the camera fires a little after the LiDAR key-frame timestamp."""
    width: int
    """Image width (pixels)."""
    height: int
    """Image height (pixels)."""
    intrinsics: np.ndarray
    """``(3, 3)`` float64 pinhole matrix."""
    cam2ego: np.ndarray
    """``(4, 4)`` float64 calibration: camera -> ego."""
    ego2global: np.ndarray
    """``(4, 4)`` float64 ego pose at the camera's own timestamp."""
    cam2keyego: np.ndarray
    """``(4, 4)`` float64 camera -> ego at the key frame: ``inv(key ego2global) @ ego2global @ cam2ego``."""

    def __post_init__(self) -> None:
        _frozen(self, "intrinsics", (3, 3), np.float64)
        for name in ("cam2ego", "ego2global", "cam2keyego"):
            _frozen(self, name, (4, 4), np.float64)

    def to_dict(self) -> dict[str, Any]:
        return {
            "path": self.path,
            "timestamp": self.timestamp,
            "width": self.width,
            "height": self.height,
            "intrinsics": self.intrinsics.tolist(),
            "cam2ego": self.cam2ego.tolist(),
            "ego2global": self.ego2global.tolist(),
            "cam2keyego": self.cam2keyego.tolist(),
        }

    @classmethod
    def from_dict(cls, data: Any, where: str = "camera") -> CameraRecord:
        """Inverse of :meth:`to_dict`; :class:`IndexFormatError` names ``where`` and the field on bad input."""
        fields_ = _fields(cls, data, where)
        return cls(
            path=_path(fields_["path"], f"{where}.path"),
            timestamp=_integer(fields_["timestamp"], f"{where}.timestamp"),
            width=_integer(fields_["width"], f"{where}.width"),
            height=_integer(fields_["height"], f"{where}.height"),
            intrinsics=_matrix(fields_["intrinsics"], 3, 3, f"{where}.intrinsics"),
            cam2ego=_matrix(fields_["cam2ego"], 4, 4, f"{where}.cam2ego"),
            ego2global=_matrix(fields_["ego2global"], 4, 4, f"{where}.ego2global"),
            cam2keyego=_matrix(fields_["cam2keyego"], 4, 4, f"{where}.cam2keyego"),
        )


@dataclass(frozen=True, eq=False)
class FrameRecord(_Record):
    """One key frame (nuScenes sample): paths, poses, sensor geometry and boxes.

    Box fields are parallel: row / item ``i`` of each describes the sample's ``i``-th annotation.
    Box rows are ``(x, y, z, l, w, h, yaw, vx, vy)`` (:data:`BOX_COLUMNS`): the box centre (m), its length along
    the heading, width and height (m; nuScenes stores ``size`` as w, l, h), the heading angle about +z (rad, 0 along
    +x), and the velocity (m/s) in the same frame.
    """

    token: str
    """Sample token (a safe name: :mod:`occkit.data.names`)."""
    scene: str
    """Scene name, e.g. ``scene-0061`` (a safe name; ``""`` for frames of info files without one)."""
    scene_token: str
    """Scene token (a safe name or ``""``)."""
    timestamp: int
    """Sample timestamp, microseconds (the LIDAR_TOP key-frame timestamp)."""
    prev: str
    """Previous sample token, ``""`` at the start of the scene."""
    next: str
    """Next sample token, ``""`` at the end of the scene."""
    index_in_scene: int
    """Position of the sample in its scene, from 0."""
    ego2global: np.ndarray
    """``(4, 4)`` float64 ego pose at the LiDAR key-frame timestamp."""
    lidar_path: str
    """Key-frame LiDAR point file, relative to the dataset root."""
    lidar2ego: np.ndarray
    """``(4, 4)`` float64 LIDAR_TOP calibration."""
    sweeps: tuple[SweepRecord, ...]
    """Earlier sweeps, newest first, within the scene; at most the ``max_sweeps`` the index was built with."""
    cameras: dict[str, CameraRecord]
    """Channel -> key-frame image, in :data:`CAMERA_ORDER`. Treat as read-only."""
    boxes_ego: np.ndarray
    """``(N, 9)`` float64 boxes in the key frame's ego frame."""
    boxes_lidar: np.ndarray
    """``(N, 9)`` float64 boxes in the key frame's LiDAR frame."""
    velocity_valid: np.ndarray
    """``(N,)`` bool: False where nuscenes-devkit's velocity is NaN (no neighbour annotation within reach); the
    velocity columns hold 0 there."""
    box_categories: tuple[str, ...]
    """nuScenes category names, e.g. ``vehicle.car``."""
    box_detection_names: tuple[str | None, ...]
    """Detection class (:data:`occkit.classes.DETECTION_CLASSES`) or None for categories that are not targets."""
    box_instances: tuple[str, ...]
    """Instance tokens (the same object across samples)."""
    box_num_lidar_pts: np.ndarray
    """``(N,)`` int64 LiDAR points inside each box."""
    box_visibility: tuple[str, ...]
    """nuScenes visibility tokens, ``"1"`` (0-40% visible) to ``"4"`` (80-100%)."""
    occ_path: str | None
    """``gts/<scene>/<token>/labels.npz`` (Occ3D labels) if that file exists under the root, else None."""

    def __post_init__(self) -> None:
        for name in ("ego2global", "lidar2ego"):
            _frozen(self, name, (4, 4), np.float64)
        _frozen(self, "boxes_ego", (-1, 9), np.float64)
        _frozen(self, "boxes_lidar", (-1, 9), np.float64)
        _frozen(self, "velocity_valid", (-1,), np.bool_)
        _frozen(self, "box_num_lidar_pts", (-1,), np.int64)
        object.__setattr__(self, "sweeps", tuple(self.sweeps))
        for name in ("box_categories", "box_detection_names", "box_instances", "box_visibility"):
            object.__setattr__(self, name, tuple(getattr(self, name)))
        counts = {name: len(getattr(self, name)) for name in _BOX_FIELDS}
        if len(set(counts.values())) > 1:
            raise ValueError(f"FrameRecord box fields must have one length each, got {counts}")

    @property
    def num_boxes(self) -> int:
        return len(self.box_instances)

    def __repr__(self) -> str:
        # The generated repr prints every matrix and box: thousands of numbers per frame.
        return (
            f"FrameRecord(token={self.token!r}, scene={self.scene!r}, index_in_scene={self.index_in_scene}, "
            f"sweeps={len(self.sweeps)}, cameras={list(self.cameras)}, boxes={self.num_boxes}, "
            f"occ_path={self.occ_path!r})"
        )

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: matrices and boxes as nested lists of floats, sub-records as dicts."""
        return {
            "token": self.token,
            "scene": self.scene,
            "scene_token": self.scene_token,
            "timestamp": self.timestamp,
            "prev": self.prev,
            "next": self.next,
            "index_in_scene": self.index_in_scene,
            "ego2global": self.ego2global.tolist(),
            "lidar_path": self.lidar_path,
            "lidar2ego": self.lidar2ego.tolist(),
            "sweeps": [sweep.to_dict() for sweep in self.sweeps],
            "cameras": {channel: camera.to_dict() for channel, camera in self.cameras.items()},
            "boxes_ego": self.boxes_ego.tolist(),
            "boxes_lidar": self.boxes_lidar.tolist(),
            "velocity_valid": self.velocity_valid.tolist(),
            "box_categories": list(self.box_categories),
            "box_detection_names": list(self.box_detection_names),
            "box_instances": list(self.box_instances),
            "box_num_lidar_pts": self.box_num_lidar_pts.tolist(),
            "box_visibility": list(self.box_visibility),
            "occ_path": self.occ_path,
        }

    @classmethod
    def from_dict(cls, data: Any, where: str = "record") -> FrameRecord:
        """Inverse of :meth:`to_dict`.

        Raises:
            IndexFormatError: ``data`` is not such a dict; the message names ``where`` and the field, e.g.
                ``index.json: record 12.boxes_ego[3]: expected a list of 9 numbers, got [1.0, 'a', ...]``.
        """
        f = _fields(cls, data, where)
        sweeps = _list(f["sweeps"], f"{where}.sweeps")
        cameras = f["cameras"]
        if not isinstance(cameras, dict):
            raise IndexFormatError(f"{where}.cameras: expected an object of channel -> camera, got {_show(cameras)}")
        values = {
            "token": _name(f["token"], f"{where}.token"),
            "scene": _name(f["scene"], f"{where}.scene", empty=True),
            "scene_token": _name(f["scene_token"], f"{where}.scene_token", empty=True),
            "timestamp": _integer(f["timestamp"], f"{where}.timestamp"),
            "prev": _name(f["prev"], f"{where}.prev", empty=True),
            "next": _name(f["next"], f"{where}.next", empty=True),
            "index_in_scene": _integer(f["index_in_scene"], f"{where}.index_in_scene"),
            "ego2global": _matrix(f["ego2global"], 4, 4, f"{where}.ego2global"),
            "lidar_path": _path(f["lidar_path"], f"{where}.lidar_path"),
            "lidar2ego": _matrix(f["lidar2ego"], 4, 4, f"{where}.lidar2ego"),
            "sweeps": tuple(SweepRecord.from_dict(s, f"{where}.sweeps[{i}]") for i, s in enumerate(sweeps)),
            "cameras": {
                channel: CameraRecord.from_dict(camera, f"{where}.cameras.{channel}")
                for channel, camera in cameras.items()
            },
            "boxes_ego": _matrix(f["boxes_ego"], None, 9, f"{where}.boxes_ego"),
            "boxes_lidar": _matrix(f["boxes_lidar"], None, 9, f"{where}.boxes_lidar"),
            "velocity_valid": _typed_list(f["velocity_valid"], (bool,), "booleans", f"{where}.velocity_valid"),
            "box_categories": _typed_list(f["box_categories"], (str,), "strings", f"{where}.box_categories"),
            "box_detection_names": _typed_list(
                f["box_detection_names"], (str, type(None)), "strings or nulls", f"{where}.box_detection_names"
            ),
            "box_instances": _typed_list(f["box_instances"], (str,), "strings", f"{where}.box_instances"),
            "box_num_lidar_pts": _counts(f["box_num_lidar_pts"], f"{where}.box_num_lidar_pts"),
            "box_visibility": _typed_list(f["box_visibility"], (str,), "strings", f"{where}.box_visibility"),
            "occ_path": None if f["occ_path"] is None else _path(f["occ_path"], f"{where}.occ_path"),
        }
        try:
            return cls(**values)
        except ValueError as error:  # box fields of different lengths
            raise IndexFormatError(f"{where}: {error}") from None


_BOX_FIELDS = (
    "boxes_ego",
    "boxes_lidar",
    "velocity_valid",
    "box_categories",
    "box_detection_names",
    "box_instances",
    "box_num_lidar_pts",
    "box_visibility",
)


# ----------------------------------------------------------------------------------------------------- validation
def _show(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 4] + " ..."


def _fields(cls: type, data: Any, where: str) -> dict[str, Any]:
    """``data`` as a dict with exactly the dataclass's fields."""
    if not isinstance(data, dict):
        raise IndexFormatError(f"{where}: expected an object of {cls.__name__} fields, got {_show(data)}")
    names = [f.name for f in fields(cls)]
    missing = [name for name in names if name not in data]
    if missing:
        raise IndexFormatError(f"{where}: missing {', '.join(missing)}")
    unknown = [str(key) for key in data if key not in names]
    if unknown:
        raise IndexFormatError(f"{where}: unknown key(s) {', '.join(unknown)}")
    return data


def _string(value: Any, where: str) -> str:
    if not isinstance(value, str):
        raise IndexFormatError(f"{where}: expected a string, got {_show(value)}")
    return value


def _name(value: Any, where: str, empty: bool = False) -> str:
    """A sample token or scene name / token (:func:`~occkit.data.names.safe_name`); ``""`` too where ``empty``."""
    if empty and value == "":
        return value
    return safe_name(_string(value, where), where, IndexFormatError)


def _path(value: Any, where: str) -> str:
    """A file path relative to the dataset root (:func:`~occkit.data.names.safe_relative_path`)."""
    return safe_relative_path(_string(value, where), where, IndexFormatError)


def _integer(value: Any, where: str) -> int:
    if type(value) is not int:
        raise IndexFormatError(f"{where}: expected an integer, got {_show(value)}")
    return value


def _number(value: Any, where: str) -> float:
    if not _is_number(value):
        raise IndexFormatError(f"{where}: expected a finite number, got {_show(value)}")
    return float(value)


def _list(value: Any, where: str) -> list:
    if not isinstance(value, list):
        raise IndexFormatError(f"{where}: expected a list, got {_show(value)}")
    return value


def _typed_list(value: Any, types: tuple[type, ...], what: str, where: str) -> list:
    # Exact types: JSON true must not pass as the integer 1, nor 1 as true.
    for i, item in enumerate(_list(value, where)):
        if type(item) not in types:
            raise IndexFormatError(f"{where}[{i}]: expected {what}, got {_show(item)}")
    return value


def _counts(value: Any, where: str) -> list[int]:
    _typed_list(value, (int,), "integers", where)
    for i, item in enumerate(value):
        if not 0 <= item < 2**63:
            raise IndexFormatError(f"{where}[{i}]: expected a count (0 <= n < 2**63), got {_show(item)}")
    return value


def _is_number(x: Any) -> bool:
    # Integers only where float64 holds them exactly; a hand-edited 1e400 as an integer is no coordinate.
    return (type(x) is float and math.isfinite(x)) or (type(x) is int and abs(x) <= 2**53)


def _matrix(value: Any, rows: int | None, columns: int, where: str) -> np.ndarray:
    """A ``(rows, columns)`` list of lists of finite numbers as float64 (``rows`` None: any number of rows)."""
    if not isinstance(value, list) or (rows is not None and len(value) != rows):
        shape = f"{rows} lists" if rows is not None else "a list of lists"
        raise IndexFormatError(f"{where}: expected {shape} of {columns} numbers, got {_show(value)}")
    for i, row in enumerate(value):
        # Files written by save_index hold floats only: the first test is the fast path of large indexes.
        if not (
            isinstance(row, list)
            and len(row) == columns
            and (all(type(x) is float for x in row) or all(_is_number(x) for x in row))
        ):
            raise IndexFormatError(f"{where}[{i}]: expected a list of {columns} finite numbers, got {_show(row)}")
    array = np.array(value, dtype=np.float64).reshape(len(value), columns)
    finite = np.isfinite(array).all(axis=1)
    if not finite.all():
        i = int(np.argmin(finite))
        raise IndexFormatError(f"{where}[{i}]: expected a list of {columns} finite numbers, got {_show(value[i])}")
    return array


# ----------------------------------------------------------------------------------------------------- geometry
#: Quaternions with a smaller norm (or a non-finite one) are no rotation: an error, not a NaN matrix. Others are
#: normalised, as nuscenes-devkit (pyquaternion) does.
MIN_QUATERNION_NORM = 1e-6


def quaternions_to_rotations(quaternions: np.ndarray) -> np.ndarray:
    """``(M, 3, 3)`` rotation matrices of ``(M, 4)`` (w, x, y, z) quaternions, normalised first (as
    :func:`occkit.geometry.se3.quaternion_to_matrix`, in numpy: the index needs no torch).

    Raises:
        ValueError: a quaternion's norm is below :data:`MIN_QUATERNION_NORM` or not finite; the message gives its row.
    """
    norms = np.linalg.norm(quaternions, axis=-1, keepdims=True)
    bad = ~((norms[..., 0] >= MIN_QUATERNION_NORM) & np.isfinite(norms[..., 0]))
    if bad.any():
        row = int(np.flatnonzero(bad.reshape(-1))[0])
        raise ValueError(
            f"quaternion {row} {quaternions.reshape(-1, 4)[row].tolist()} is no rotation (norm "
            f"{float(norms.reshape(-1)[row]):.3g}; expected (w, x, y, z) of norm 1)"
        )
    q = quaternions / norms
    w, x, y, z = q.T
    return np.stack(
        (
            1 - 2 * (y * y + z * z),
            2 * (x * y - w * z),
            2 * (x * z + w * y),
            2 * (x * y + w * z),
            1 - 2 * (x * x + z * z),
            2 * (y * z - w * x),
            2 * (x * z - w * y),
            2 * (y * z + w * x),
            1 - 2 * (x * x + y * y),
        ),
        axis=-1,
    ).reshape(-1, 3, 3)


def invert_rigid(transform: np.ndarray) -> np.ndarray:
    """Inverse of rigid ``(..., 4, 4)`` transforms."""
    inverse = np.zeros_like(transform)
    rotation_t = np.swapaxes(transform[..., :3, :3], -1, -2)
    inverse[..., :3, :3] = rotation_t
    inverse[..., :3, 3] = -(rotation_t @ transform[..., :3, 3:])[..., 0]
    inverse[..., 3, 3] = 1.0
    return inverse


def rotation_yaw(rotation: np.ndarray) -> np.ndarray:
    """Yaw of ``(N, 3, 3)`` rotations as pyquaternion's ``yaw_pitch_roll[0]`` (``R = R_x R_y R_z(yaw)``).

    nuscenes-devkit and mmdetection3d's info files take a box's yaw this way. For a rotation about z alone it is the
    heading of the box's x axis, ``atan2(R[1, 0], R[0, 0])``; with the ego's pitch and roll folded in, the two
    differ by about pitch * roll (1e-4 rad).
    """
    return np.arctan2(-rotation[:, 0, 1], rotation[:, 0, 0])


# ----------------------------------------------------------------------------------------------------- building
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
            return quaternions_to_rotations(quaternions)
        except ValueError:  # a norm below MIN_QUATERNION_NORM (the values are finite)
            norms = np.linalg.norm(quaternions, axis=1)
            i = int(np.argmax(norms < MIN_QUATERNION_NORM))
            raise self._error(
                table, records[i], "rotation", f"{_show(records[i]['rotation'])} has norm {norms[i]:.3g}: not a "
                "rotation quaternion (w, x, y, z)"
            ) from None  # fmt: skip

    def _transforms(self, table: str, records: Sequence[Mapping]) -> np.ndarray:
        """``(M, 4, 4)`` float64 from records with ``translation`` (3) and ``rotation`` (w, x, y, z)."""
        matrices = np.zeros((len(records), 4, 4))
        matrices[:, :3, :3] = self._rotations(table, records)
        matrices[:, :3, 3] = self._vectors(table, records, "translation", 3)
        matrices[:, 3, 3] = 1.0
        return matrices

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
        folder = self.tables.root / "gts" / scene
        try:
            entries = list(os.scandir(folder))
        except (FileNotFoundError, NotADirectoryError):
            return set()
        return {entry.name for entry in entries if os.path.isfile(os.path.join(entry.path, "labels.npz"))}

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
        global2ego = invert_rigid(ego2global)
        lidar2ego = self._calibration(lidar)
        ego2lidar = invert_rigid(lidar2ego)
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
            if (count := self._integer("sample_annotation", annotation, "num_lidar_pts")) < 0:
                message = f"expected a count >= 0, got {count}"
                raise self._error("sample_annotation", annotation, "num_lidar_pts", message)
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
                        centres @ rotation.T + transform[:3, 3],
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


# ----------------------------------------------------------------------------------------------------- files
_REQUIRED_META = ("version", "root", "max_sweeps")


def save_index(records: Sequence[FrameRecord], path: str | Path, meta: Mapping[str, Any]) -> Path:
    """Write ``records`` as an index JSON file (one record per line), atomically.

    Args:
        records: the frames, e.g. from :func:`build_index`.
        path: the file to write; parent folders are created.
        meta: at least ``version``, ``root`` and ``max_sweeps`` of the build; other JSON values (``split``, ...)
            are kept too. ``format``, ``created_by`` and ``frames`` are set here.
    """
    path = Path(path)
    missing = [key for key in _REQUIRED_META if key not in meta]
    if missing:
        raise ValueError(f"index meta needs {', '.join(missing)}; got keys {', '.join(meta) or 'none'}")
    if "records" in meta:
        raise ValueError("index meta may not have a 'records' key: it holds the frames")
    header = {
        "format": INDEX_FORMAT,
        "created_by": f"occkit {__version__}",
        **{key: value for key, value in meta.items() if key not in ("format", "created_by", "frames")},
        "frames": len(records),
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    # A per-process name: ranks of one torchrun job may build the same cache at the same moment.
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    with open(partial, "w", encoding="utf-8") as stream:
        # The header first, so `head` shows what a file is; json.dumps per record keeps memory flat.
        stream.write(json.dumps(header)[:-1] + ', "records": [\n')
        for i, record in enumerate(records):
            try:  # strict JSON: a NaN written here would be refused by load_index
                line = json.dumps(record.to_dict(), allow_nan=False)
            except ValueError:
                stream.close()
                partial.unlink()
                raise ValueError(f"{path}: record {i} (sample {record.token}) holds NaN or infinite values") from None
            stream.write(("" if i == 0 else ",\n") + line)
        stream.write("\n]}\n")
    os.replace(partial, path)
    return path


def load_index(path: str | Path) -> tuple[list[FrameRecord], dict[str, Any]]:
    """Read an index file written by :func:`save_index`.

    Returns:
        The records and the header (``format``, ``version``, ``root``, ``max_sweeps``, ``created_by``, ``frames``
        and any other meta saved).

    Raises:
        FileNotFoundError: no such file.
        IndexFormatError: not JSON, not an occkit index (the ``format`` key), or a malformed record (an unsafe
            name or path among them, see :mod:`occkit.data.names`); the message names the file, record and field.
    """
    path = Path(path)
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise FileNotFoundError(f"index file {path} does not exist") from None
    except (json.JSONDecodeError, UnicodeDecodeError) as error:
        raise IndexFormatError(f"{path}: not valid JSON ({error})") from None
    found = data.get("format") if isinstance(data, dict) else None
    if found != INDEX_FORMAT:
        raise IndexFormatError(f"{path}: not an occkit index (format {found!r}, expected {INDEX_FORMAT!r})")
    items = data.pop("records", None)
    if not isinstance(items, list):
        raise IndexFormatError(f"{path}: 'records' must be a list, got {_show(items)}")
    records = [FrameRecord.from_dict(item, f"{path}: record {i}") for i, item in enumerate(items)]
    return records, data


#: The end of an index file's first line (see :func:`save_index`).
_HEADER_END = ', "records": ['


def read_index_header(path: str | Path) -> dict[str, Any]:
    """The header of an index file written by :func:`save_index` (what :func:`load_index` returns second), read
    from its first line only: cheap for any size of index.

    Raises:
        FileNotFoundError: no such file.
        IndexFormatError: the first line is no occkit index header.
    """
    path = Path(path)
    with open(path, "rb") as stream:
        line = stream.readline(1 << 20).rstrip(b"\r\n")
    try:
        text = line.decode("utf-8")
        header = json.loads(text[: -len(_HEADER_END)] + "}") if text.endswith(_HEADER_END) else None
    except (json.JSONDecodeError, UnicodeDecodeError):
        header = None
    if not isinstance(header, dict) or header.get("format") != INDEX_FORMAT:
        raise IndexFormatError(f"{path}: the first line is not an occkit index header ({INDEX_FORMAT})")
    return header


def tables_key(root: str | Path, version: str, max_sweeps: int) -> str:
    """What an index built from ``root/version`` depends on, as one digest: the index format, the occkit version,
    ``max_sweeps``, and the size and SHA-256 of each of the 13 table files (their content: modification times are
    not trusted, a file can change and keep an old one). The dataset's index cache stores it and is rebuilt when it
    differs. Hashing reads every table once: about 0.7 s per GB on one core when the files are in the page cache.
    """
    folder = Path(root) / version
    digest = hashlib.sha256(f"{INDEX_FORMAT}\0{__version__}\0max_sweeps={max_sweeps}\n".encode())
    buffer = bytearray(1 << 20)
    view = memoryview(buffer)
    for name in TABLE_NAMES:
        table = hashlib.sha256()
        size = 0
        try:
            with open(folder / f"{name}.json", "rb", buffering=0) as stream:
                while count := stream.readinto(buffer):
                    table.update(view[:count])
                    size += count
        except FileNotFoundError:
            size = -1  # building fails and names the table
        digest.update(f"{name}\0{size}\0{table.hexdigest()}\n".encode())
    return f"sha256:{digest.hexdigest()}"
