"""A plain index of key frames built from the nuScenes tables, saved as typed columns in one ``.npz`` (never pickle).

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
* box yaw is pyquaternion's ``yaw_pitch_roll[0]`` of the box rotation in the frame, as both take it;
* ``box_valid`` is mmdetection3d's ``valid_flag``, ``(num_lidar_pts + num_radar_pts) > 0``, which its
  ``use_valid_flag`` training keeps as targets.

Each field of the records is declared once, with its kind (a safe name, a relative path, an integer, a ``(4, 4)``
matrix, one row per box, a table of sub-records, ...: the ``_Kind`` classes below). Everything else follows from
these declarations: the checks of ``__post_init__``, the JSON form of a record (``to_dict`` / ``from_dict``) and the
columns of the index file.

An index file (format ``occkit-index/3``; docs/data.md lists every array) is a numpy ``.npz`` holding, per field, one
array over all records: matrices stacked, box fields concatenated with per-record offsets, the sweeps and cameras as
tables of their own with offsets, and every string as an int32 code into one UTF-8 string table; the header is a JSON
string inside. :func:`load_index` checks every column when it reads a file and returns :class:`FrameRecords`, a
sequence that builds each record when it is first used.

Names from the tables become file paths (``gts/<scene>/<token>/labels.npz``, ``<out>/<token>.npz``): sample tokens,
scene names and scene tokens must be safe names and every file path a relative path that stays under the root
(:mod:`occkit.data.names`), checked when an index is built, saved and read.
"""

from __future__ import annotations

import abc
import functools
import hashlib
import io
import itertools
import json
import math
import operator
import os
import shlex
import zipfile
import zlib
from collections import defaultdict
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, fields
from dataclasses import field as dataclass_field
from pathlib import Path
from typing import Any, ClassVar, TypeVar

import numpy as np

from occkit import __version__
from occkit.classes import detection_name
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
from occkit.nuscenes import CAMERA_ORDER, LIDAR_CHANNEL, TABLE_NAMES

__all__ = [
    "INDEX_FORMAT",
    "BOX_COLUMNS",
    "IndexFormatError",
    "OutdatedIndexError",
    "SweepRecord",
    "CameraRecord",
    "FrameRecord",
    "FrameRecords",
    "build_index",
    "index_tables",
    "save_index",
    "load_index",
    "read_index_header",
    "tables_key",
    "MIN_QUATERNION_NORM",
]

#: Value of the ``format`` key of index files.
INDEX_FORMAT = "occkit-index/3"

#: nuscenes-devkit's ``box_velocity`` default: neighbours further apart than this (s) give no velocity; twice
#: this for a centred difference.
MAX_VELOCITY_TIME_DIFF = 1.5

#: Columns of a box row: centre (m), size (m, length along the heading), yaw (rad), velocity (m/s).
BOX_COLUMNS = ("x", "y", "z", "l", "w", "h", "yaw", "vx", "vy")


class IndexFormatError(ValueError):
    """An index file or record dict is malformed; the message names the file, record and field."""


class OutdatedIndexError(IndexFormatError):
    """An index file of an older occkit's format (the JSON ``occkit-index/1``, the ``.npz`` of ``occkit-index/2``
    without ``box_valid``); the message gives the ``occkit index`` command that rebuilds it."""


# ----------------------------------------------------------------------------------------------------- field kinds
class _Kind(abc.ABC):
    """What one record field holds. Declared once per field (:func:`_declare`), it gives every use of the field:
    the value a record keeps (``__post_init__``), the JSON form (``to_dict`` / ``from_dict``), and the field's
    columns in an index file (written by :func:`_pack`, checked by :func:`_check`, read by :func:`_reader`)."""

    per_box: bool = False
    """One value per box: the field's length is the record's box count, and its columns share ``boxes.offsets``."""

    def normalise(self, value: Any, where: str) -> Any:
        """The value a record keeps; ValueError naming ``where`` if it cannot be one."""
        return value

    @abc.abstractmethod
    def from_json(self, value: Any, where: str) -> Any:
        """The value of a JSON value; :class:`IndexFormatError` naming ``where`` on bad input."""

    def to_json(self, value: Any) -> Any:
        return value

    @abc.abstractmethod
    def pack(self, values: list, column: str, out: _Writer) -> None:
        """Add the columns named ``column`` (and ``column.*``) of ``values``, one per row, to ``out``."""

    @abc.abstractmethod
    def check(self, file: _File, column: str, name: str, rows: _Rows) -> None:
        """Check the field's columns in ``file``; :class:`IndexFormatError` naming the record and field ``name``."""

    @abc.abstractmethod
    def reader(self, file: _File, column: str) -> Callable[..., Any]:
        """``row -> value`` over checked columns; for box fields ``(start, stop) -> value`` of a record's boxes."""


def _declare(kind: _Kind) -> Any:
    """A dataclass field of ``kind``."""
    return dataclass_field(metadata={"kind": kind})


@functools.cache
def _declared(cls: type) -> tuple[tuple[str, _Kind], ...]:
    """``(name, kind)`` of each field of a record class, in declaration order."""
    return tuple((f.name, f.metadata["kind"]) for f in fields(cls))


@functools.cache
def _normalised(cls: type) -> tuple[tuple[str, Callable[[Any, str], Any], str], ...]:
    """``(name, normalise, where)`` of the fields of a record class whose kind changes values: ``__post_init__`` runs
    for every record built, and most fields are kept as given."""
    return tuple(
        (name, kind.normalise, f"{cls.__name__}.{name}")
        for name, kind in _declared(cls)
        if type(kind).normalise is not _Kind.normalise
    )


@functools.cache
def _box_fields(cls: type) -> tuple[str, ...]:
    return tuple(name for name, kind in _declared(cls) if kind.per_box)


class _Text(_Kind):
    """A string, or ``None`` where ``nullable``. Column: int32 codes into the file's string table, -1 for None."""

    def __init__(self, nullable: bool = False) -> None:
        self.nullable = nullable

    def ok(self, text: Any) -> bool:
        """Whether the field may hold ``text`` (any string here; names and paths are checked further)."""
        return isinstance(text, str)

    def refuse(self, text: Any, where: str) -> None:
        """Raise :class:`IndexFormatError` naming ``where`` for a value that is not :meth:`ok`."""
        _string(text, where)

    def from_json(self, value: Any, where: str) -> Any:
        if not (self.ok(value) or (value is None and self.nullable)):
            self.refuse(value, where)
        return value

    def pack(self, values: list, column: str, out: _Writer) -> None:
        out.add(column, out.codes(values))

    def check(self, file: _File, column: str, name: str, rows: _Rows) -> None:
        codes = file.array(column, np.int32, (), rows.count)
        known = (codes >= (-1 if self.nullable else 0)) & (codes < len(file.strings))
        if not known.all():
            row = _first_false(known)
            got = "null" if codes[row] == -1 else f"string {codes[row]} of a table of {len(file.strings)}"
            raise IndexFormatError(f"{rows.at(row, name)}: expected a string, got {got}")
        # Each distinct string once; a bad one is reported at the first row that uses it.
        unique, first = np.unique(codes, return_index=True)
        for code, row in zip(unique.tolist(), first.tolist(), strict=True):
            if code >= 0 and not self.ok(file.strings[code]):
                self.refuse(file.strings[code], rows.at(row, name))

    def reader(self, file: _File, column: str) -> Callable[[int], Any]:
        texts, codes = file.texts, file.arrays[column].tolist()
        return lambda row: texts[codes[row]]


class _Texts(_Text):
    """A tuple of strings (or of ``None`` too where ``nullable``), one per box. Column as :class:`_Text`, over the
    boxes."""

    per_box = True

    def normalise(self, value: Any, where: str) -> tuple:
        return tuple(value)

    def from_json(self, value: Any, where: str) -> tuple:
        types = (str, type(None)) if self.nullable else (str,)
        return tuple(_typed_list(value, types, "strings or nulls" if self.nullable else "strings", where))

    def to_json(self, value: tuple) -> list:
        return list(value)

    def pack(self, values: list, column: str, out: _Writer) -> None:
        out.add(column, out.codes(list(itertools.chain.from_iterable(values))))

    def reader(self, file: _File, column: str) -> Callable[[int, int], tuple]:
        texts, codes = file.texts, file.arrays[column]
        return lambda start, stop: tuple(map(texts.__getitem__, codes[start:stop].tolist()))


class _Name(_Text):
    """A sample token or scene name / token (:func:`~occkit.data.names.safe_name`); ``""`` too where ``empty``."""

    def __init__(self, empty: bool = False) -> None:
        super().__init__()
        self.empty = empty

    def ok(self, text: Any) -> bool:
        return (self.empty and text == "") or is_safe_name(text)

    def refuse(self, text: Any, where: str) -> None:
        safe_name(_string(text, where), where, IndexFormatError)


class _Path(_Text):
    """A file path relative to the dataset root (:func:`~occkit.data.names.safe_relative_path`); None too where
    ``optional``."""

    def __init__(self, optional: bool = False) -> None:
        super().__init__(nullable=optional)

    def ok(self, text: Any) -> bool:
        return is_safe_relative_path(text)

    def refuse(self, text: Any, where: str) -> None:
        safe_relative_path(_string(text, where), where, IndexFormatError)


class _Integer(_Kind):
    """An integer; column int64."""

    def from_json(self, value: Any, where: str) -> int:
        return _integer(value, where)

    def pack(self, values: list, column: str, out: _Writer) -> None:
        out.add(column, _as_array(values, np.int64))

    def check(self, file: _File, column: str, name: str, rows: _Rows) -> None:
        file.array(column, np.int64, (), rows.count)

    def reader(self, file: _File, column: str) -> Callable[[int], int]:
        return file.arrays[column].tolist().__getitem__


class _Number(_Kind):
    """A finite number; column float64."""

    def from_json(self, value: Any, where: str) -> float:
        return _number(value, where)

    def pack(self, values: list, column: str, out: _Writer) -> None:
        out.add(column, _as_array(values, np.float64), deflate=False)

    def check(self, file: _File, column: str, name: str, rows: _Rows) -> None:
        values = file.array(column, np.float64, (), rows.count)
        finite = np.isfinite(values)
        if not finite.all():
            row = _first_false(finite)
            raise IndexFormatError(f"{rows.at(row, name)}: expected a finite number, got {float(values[row])}")

    def reader(self, file: _File, column: str) -> Callable[[int], float]:
        return file.arrays[column].tolist().__getitem__


class _Array(_Kind):
    """A read-only array of ``dtype`` and ``shape``; a leading -1 in ``shape``: one row per box. Column: the
    records' arrays stacked (box fields concatenated), ``(rows, *shape)`` (``(boxes, *shape[1:])``), deflated in the
    file unless it holds floats that do not ``repeat`` (measurements do not compress; calibrations, the same few
    matrices over and over, do)."""

    def __init__(self, dtype: type, shape: tuple[int, ...], repeats: bool = False) -> None:
        self.dtype, self.shape, self.repeats = np.dtype(dtype), shape, repeats
        self.per_box = shape[0] == -1
        self.tail = shape[1:] if self.per_box else shape

    def normalise(self, value: Any, where: str) -> np.ndarray:
        return _frozen(value, self.shape, self.dtype, where)

    def to_json(self, value: np.ndarray) -> Any:
        return value.tolist()

    def pack(self, values: list, column: str, out: _Writer) -> None:
        if not values:
            array = np.zeros((0, *self.tail), self.dtype)
        else:
            array = np.concatenate(values) if self.per_box else np.stack(values)
        out.add(column, array, deflate=self.repeats or self.dtype.kind != "f")

    def check(self, file: _File, column: str, name: str, rows: _Rows) -> None:
        self.check_values(file.array(column, self.dtype, self.tail, rows.count), name, rows)

    def check_values(self, values: np.ndarray, name: str, rows: _Rows) -> None:
        """Checks of the values beyond dtype and shape."""

    def reader(self, file: _File, column: str) -> Callable[..., np.ndarray]:
        values = file.arrays[column]  # read-only: records share views of it
        return (lambda start, stop: values[start:stop]) if self.per_box else values.__getitem__


class _Matrix(_Array):
    """A float64 ``(rows, columns)`` matrix of finite numbers; ``rows`` None: one row per box."""

    def __init__(self, rows: int | None, columns: int, repeats: bool = False) -> None:
        super().__init__(np.float64, (-1 if rows is None else rows, columns), repeats)
        self.rows, self.columns = rows, columns

    def from_json(self, value: Any, where: str) -> np.ndarray:
        return _matrix(value, self.rows, self.columns, where)

    def check_values(self, values: np.ndarray, name: str, rows: _Rows) -> None:
        lines = values.reshape(-1, self.columns)
        finite = np.isfinite(lines).all(axis=1)
        if not finite.all():
            line = _first_false(finite)
            # A box is one line; otherwise line `line` is row `line % rows` of the matrix of row `line // rows`.
            if self.rows is None:
                where = rows.at(line, name)
            else:
                where = f"{rows.at(line // self.rows, name)}[{line % self.rows}]"
            message = f"expected a list of {self.columns} finite numbers, got {_show(lines[line].tolist())}"
            raise IndexFormatError(f"{where}: {message}")


class _Flags(_Array):
    """One bool per box."""

    def __init__(self) -> None:
        super().__init__(np.bool_, (-1,))

    def from_json(self, value: Any, where: str) -> list:
        return _typed_list(value, (bool,), "booleans", where)


class _Counts(_Array):
    """One count (int64, >= 0) per box."""

    def __init__(self) -> None:
        super().__init__(np.int64, (-1,))

    def from_json(self, value: Any, where: str) -> list:
        return _counts(value, where)

    def check_values(self, values: np.ndarray, name: str, rows: _Rows) -> None:
        counts = values >= 0
        if not counts.all():
            row = _first_false(counts)
            raise IndexFormatError(f"{rows.at(row, name)}: expected a count (0 <= n < 2**63), got {values[row]}")


class _Records(_Kind):
    """A tuple of sub-records of ``cls`` (the sweeps). Columns: ``cls``'s own, ``column.<field>``, over the
    sub-records of all records in order, and ``column.offsets``: record ``i`` has rows ``offsets[i]:offsets[i+1]``."""

    def __init__(self, cls: type[_Record]) -> None:
        self.cls = cls

    def normalise(self, value: Any, where: str) -> tuple:
        return tuple(value)

    def from_json(self, value: Any, where: str) -> tuple:
        return tuple(self.cls.from_dict(item, f"{where}[{i}]") for i, item in enumerate(_list(value, where)))

    def to_json(self, value: tuple) -> list:
        return [record.to_dict() for record in value]

    def pack(self, values: list, column: str, out: _Writer) -> None:
        out.offsets(column, values)
        _pack(self.cls, [record for value in values for record in value], f"{column}.", out)

    def check(self, file: _File, column: str, name: str, rows: _Rows) -> None:
        offsets = file.offsets(column, rows.count)
        _check(self.cls, file, f"{column}.", rows.nested(offsets, lambda i, k, f: f"{rows.at(i, name)}[{k}].{f}"))

    def reader(self, file: _File, column: str) -> Callable[[int], tuple]:
        offsets = file.arrays[f"{column}.offsets"].tolist()
        build = _reader(self.cls, file, f"{column}.")
        return lambda row: tuple(map(build, range(offsets[row], offsets[row + 1])))


class _Channels(_Records):
    """A dict channel -> sub-record of ``cls`` (the cameras), in the record's order. Columns: as :class:`_Records`,
    and ``column.channel``, the channels as string codes."""

    normalise = _Kind.normalise  # the dict is kept as given

    def from_json(self, value: Any, where: str) -> dict:
        if not isinstance(value, dict):
            raise IndexFormatError(f"{where}: expected an object of channel -> {self.cls.NOUN}, got {_show(value)}")
        return {channel: self.cls.from_dict(item, f"{where}.{channel}") for channel, item in value.items()}

    def to_json(self, value: dict) -> dict:
        return {channel: record.to_dict() for channel, record in value.items()}

    def pack(self, values: list, column: str, out: _Writer) -> None:
        out.offsets(column, values)
        out.add(f"{column}.channel", out.codes([channel for value in values for channel in value]))
        _pack(self.cls, [record for value in values for record in value.values()], f"{column}.", out)

    def check(self, file: _File, column: str, name: str, rows: _Rows) -> None:
        offsets = file.offsets(column, rows.count)
        places = rows.nested(offsets, lambda i, k, f: f"{rows.at(i, name)}[{k}].{f}")
        _Text().check(file, f"{column}.channel", "channel", places)
        channels = file.arrays[f"{column}.channel"]
        # A dict holds each channel once: a repeated one in a record would drop a camera.
        owner = np.repeat(np.arange(rows.count), np.diff(offsets))
        order = np.lexsort((channels, owner))
        repeated = (np.diff(owner[order]) == 0) & (np.diff(channels[order]) == 0)
        if repeated.any():
            row = int(order[1:][repeated][0])
            raise IndexFormatError(f"{places.at(row, 'channel')}: {file.strings[channels[row]]!r} is repeated")
        named = rows.nested(offsets, lambda i, k, f: f"{rows.at(i, name)}.{file.strings[channels[offsets[i] + k]]}.{f}")
        _check(self.cls, file, f"{column}.", named)

    def reader(self, file: _File, column: str) -> Callable[[int], dict]:
        offsets = file.arrays[f"{column}.offsets"].tolist()
        channels = [file.strings[code] for code in file.arrays[f"{column}.channel"].tolist()]
        build = _reader(self.cls, file, f"{column}.")
        return lambda row: {channels[j]: build(j) for j in range(offsets[row], offsets[row + 1])}


# ----------------------------------------------------------------------------------------------------- records
_R = TypeVar("_R", bound="_Record")


class _Record:
    """Behaviour that follows from the field declarations; equality through :meth:`to_dict` (the
    dataclass-generated one cannot compare numpy arrays)."""

    NOUN: ClassVar[str]
    """What a record is called in messages without a place (``from_dict``'s default ``where``)."""

    def __post_init__(self) -> None:
        for name, normalise, where in _normalised(type(self)):
            value = getattr(self, name)
            kept = normalise(value, where)
            if kept is not value:
                object.__setattr__(self, name, kept)
        counts = {name: len(getattr(self, name)) for name in _box_fields(type(self))}
        if len(set(counts.values())) > 1:
            raise ValueError(f"{type(self).__name__} box fields must have one length each, got {counts}")

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready dict: matrices and boxes as nested lists of floats, sub-records as dicts."""
        return {name: kind.to_json(getattr(self, name)) for name, kind in _declared(type(self))}

    @classmethod
    def from_dict(cls: type[_R], data: Any, where: str | None = None) -> _R:
        """Inverse of :meth:`to_dict`.

        Raises:
            IndexFormatError: ``data`` is not such a dict; the message names ``where`` (default: :attr:`NOUN`) and
                the field, e.g. ``index.json: record 12.boxes_ego[3]: expected a list of 9 finite numbers, got
                [1.0, 'a', ...]``.
        """
        where = cls.NOUN if where is None else where
        data = _fields(cls, data, where)
        values = {name: kind.from_json(data[name], f"{where}.{name}") for name, kind in _declared(cls)}
        try:
            return cls(**values)
        except ValueError as error:  # box fields of different lengths
            raise IndexFormatError(f"{where}: {error}") from None

    def __eq__(self, other: object) -> bool:
        if type(other) is not type(self):
            return NotImplemented
        return self.to_dict() == other.to_dict()  # type: ignore[attr-defined]

    __hash__ = None  # type: ignore[assignment]


def _frozen(value: Any, shape: tuple[int, ...], dtype: np.dtype, where: str) -> np.ndarray:
    """``value`` as a read-only array of ``dtype`` of ``shape`` (-1: any length). An array that is read-only and of
    ``dtype`` already (a column of a loaded index, another record's field) is kept, not copied."""
    if isinstance(value, np.ndarray) and value.dtype == dtype and not value.flags.writeable:
        array = value
    else:
        array = np.array(value, dtype=dtype)
        array.setflags(write=False)
    if array.ndim != len(shape) or any(n not in (-1, m) for n, m in zip(shape, array.shape, strict=True)):
        wanted = "(" + ", ".join("N" if n == -1 else str(n) for n in shape) + ")"
        raise ValueError(f"{where} must have shape {wanted}, got {array.shape}")
    return array


@dataclass(frozen=True, eq=False)
class SweepRecord(_Record):
    """One LiDAR sweep before a key frame."""

    NOUN: ClassVar[str] = "sweep"

    path: str = _declare(_Path())
    """Point file, relative to the dataset root."""
    timestamp: int = _declare(_Integer())
    """Microseconds."""
    sweep2lidar: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64: points of this sweep's LiDAR frame -> the key frame's LiDAR frame (through both ego
    poses and the global frame)."""
    time_lag: float = _declare(_Number())
    """Seconds from this sweep to the key frame, ``(key timestamp - timestamp) / 1e6``; >= 0."""


@dataclass(frozen=True, eq=False)
class CameraRecord(_Record):
    """The key-frame image of one camera."""

    NOUN: ClassVar[str] = "camera"

    path: str = _declare(_Path())
    """Image file, relative to the dataset root."""
    timestamp: int = _declare(_Integer())
    """Microseconds; the camera fires a little after the LiDAR key-frame timestamp."""
    width: int = _declare(_Integer())
    """Image width (pixels)."""
    height: int = _declare(_Integer())
    """Image height (pixels)."""
    intrinsics: np.ndarray = _declare(_Matrix(3, 3, repeats=True))
    """``(3, 3)`` float64 pinhole matrix."""
    cam2ego: np.ndarray = _declare(_Matrix(4, 4, repeats=True))
    """``(4, 4)`` float64 calibration: camera -> ego."""
    ego2global: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64 ego pose at the camera's own timestamp."""
    cam2keyego: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64 camera -> ego at the key frame: ``inv(key ego2global) @ ego2global @ cam2ego``."""


@dataclass(frozen=True, eq=False)
class FrameRecord(_Record):
    """One key frame (nuScenes sample): paths, poses, sensor geometry and boxes.

    Box fields are parallel: row / item ``i`` of each describes the sample's ``i``-th annotation.
    Box rows are ``(x, y, z, l, w, h, yaw, vx, vy)`` (:data:`BOX_COLUMNS`): the box centre (m), its length along
    the heading, width and height (m; nuScenes stores ``size`` as w, l, h), the heading angle about +z (rad, 0 along
    +x), and the velocity (m/s) in the same frame.
    """

    NOUN: ClassVar[str] = "record"

    token: str = _declare(_Name())
    """Sample token (a safe name: :mod:`occkit.data.names`)."""
    scene: str = _declare(_Name(empty=True))
    """Scene name, e.g. ``scene-0061`` (a safe name; ``""`` for frames of info files without one)."""
    scene_token: str = _declare(_Name(empty=True))
    """Scene token (a safe name or ``""``)."""
    timestamp: int = _declare(_Integer())
    """Sample timestamp, microseconds (the LIDAR_TOP key-frame timestamp)."""
    prev: str = _declare(_Name(empty=True))
    """Previous sample token, ``""`` at the start of the scene."""
    next: str = _declare(_Name(empty=True))
    """Next sample token, ``""`` at the end of the scene."""
    index_in_scene: int = _declare(_Integer())
    """Position of the sample in its scene, from 0."""
    ego2global: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64 ego pose at the LiDAR key-frame timestamp."""
    lidar_path: str = _declare(_Path())
    """Key-frame LiDAR point file, relative to the dataset root."""
    lidar2ego: np.ndarray = _declare(_Matrix(4, 4, repeats=True))
    """``(4, 4)`` float64 LIDAR_TOP calibration."""
    sweeps: tuple[SweepRecord, ...] = _declare(_Records(SweepRecord))
    """Earlier sweeps, newest first, within the scene; at most the ``max_sweeps`` the index was built with."""
    cameras: dict[str, CameraRecord] = _declare(_Channels(CameraRecord))
    """Channel -> key-frame image, in :data:`CAMERA_ORDER`. Treat as read-only."""
    boxes_ego: np.ndarray = _declare(_Matrix(None, 9))
    """``(N, 9)`` float64 boxes in the key frame's ego frame."""
    boxes_lidar: np.ndarray = _declare(_Matrix(None, 9))
    """``(N, 9)`` float64 boxes in the key frame's LiDAR frame."""
    velocity_valid: np.ndarray = _declare(_Flags())
    """``(N,)`` bool: False where nuscenes-devkit's velocity is NaN (no neighbour annotation within reach); the
    velocity columns hold 0 there."""
    box_categories: tuple[str, ...] = _declare(_Texts())
    """nuScenes category names, e.g. ``vehicle.car``."""
    box_detection_names: tuple[str | None, ...] = _declare(_Texts(nullable=True))
    """Detection class (:data:`occkit.classes.DETECTION_CLASSES`) or None for categories that are not targets."""
    box_instances: tuple[str, ...] = _declare(_Texts())
    """Instance tokens (the same object across samples)."""
    box_num_lidar_pts: np.ndarray = _declare(_Counts())
    """``(N,)`` int64 LiDAR points inside each box."""
    box_valid: np.ndarray = _declare(_Flags())
    """``(N,)`` bool: mmdetection3d's ``valid_flag``, ``num_lidar_pts + num_radar_pts > 0``: the box holds at least
    one LiDAR or radar point. Training with ``use_valid_flag`` (DAOcc, FlashOcc) keeps only these boxes as targets
    (:attr:`occkit.data.dataset.DatasetConfig.valid_boxes_only`)."""
    box_visibility: tuple[str, ...] = _declare(_Texts())
    """nuScenes visibility tokens, ``"1"`` (0-40% visible) to ``"4"`` (80-100%)."""
    occ_path: str | None = _declare(_Path(optional=True))
    """``gts/<scene>/<token>/labels.npz`` (Occ3D labels) if that file exists under the root, else None."""

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


# ----------------------------------------------------------------------------------------------------- JSON checks
def _show(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 4] + " ..."


def _fields(cls: type, data: Any, where: str) -> dict[str, Any]:
    """``data`` as a dict with exactly the dataclass's fields."""
    if not isinstance(data, dict):
        raise IndexFormatError(f"{where}: expected an object of {cls.__name__} fields, got {_show(data)}")
    names = [name for name, _ in _declared(cls)]
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
        # Dicts from to_dict hold floats only: the first test is the fast path.
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


# ----------------------------------------------------------------------------------------------------- columns
@dataclass(frozen=True)
class _Rows:
    """The rows of one table of an index file (frames, sweeps, cameras, boxes) and where each is, for messages."""

    count: int
    at: Callable[[int, str], str]
    """``(row, field) -> place``, e.g. ``index.npz: record 3.sweeps[2].path``."""

    def nested(self, offsets: np.ndarray, place: Callable[[int, int, str], str]) -> _Rows:
        """The rows of a child table, of which ``offsets[i]:offsets[i + 1]`` belong to row ``i``; ``place(i, k,
        field)`` names the field of the ``k``-th of them."""

        def at(row: int, field: str) -> str:
            parent = int(np.searchsorted(offsets, row, side="right")) - 1
            return place(parent, row - int(offsets[parent]), field)

        return _Rows(int(offsets[-1]), at)


class _Writer:
    """The columns of records being saved, and the strings they refer to (each distinct one once)."""

    def __init__(self) -> None:
        self.arrays: dict[str, np.ndarray] = {}
        self.deflated: set[str] = set()
        self.strings: dict[Any, int] = {}

    def add(self, name: str, array: np.ndarray, deflate: bool = True) -> None:
        """Array ``name`` of the file, stored deflated or as it is."""
        self.arrays[name] = array
        if deflate:
            self.deflated.add(name)

    def codes(self, values: list) -> np.ndarray:
        """int32 codes of ``values`` in the string table, -1 for None. Values that are no strings are kept too: the
        check of the columns names them."""
        table = self.strings
        for value in dict.fromkeys(values):  # each distinct value once, in order: a million box strings are few
            if value is not None and value not in table:
                table[value] = len(table)
        return np.fromiter(map(table.get, values, itertools.repeat(-1)), dtype=np.int32, count=len(values))

    def offsets(self, name: str, values: list) -> None:
        """``name.offsets``, int64 ``(len(values) + 1,)``: where the items of each value start, and the end."""
        self.add(f"{name}.offsets", _offsets([len(v) for v in values]))


def _offsets(lengths: list[int]) -> np.ndarray:
    """int64 ``(len(lengths) + 1,)``: where each of consecutive runs of ``lengths`` items starts, and the end."""
    return np.concatenate(([0], np.cumsum(lengths, dtype=np.int64)))


def _as_array(values: list, dtype: type) -> np.ndarray:
    """``values`` as an array of their own type, integers as floats where ``dtype`` is float64: a value of another
    type is refused by the check of the columns, never cast to ``dtype`` (1.5 as an integer would become 1)."""
    array = np.asarray(values)
    exact = array.dtype.kind in "iu" and np.dtype(dtype).kind == "f"
    return array.astype(dtype) if len(values) == 0 or exact else array


class _File:
    """The arrays and decoded strings of an index file, or of records being saved, as the checks and readers use
    them; ``path`` names it in messages."""

    def __init__(self, path: str, arrays: dict[str, np.ndarray], strings: list) -> None:
        self.path, self.arrays, self.strings = path, arrays, strings
        self.texts = [*strings, None]  # code -1 (None) reads the last item
        self.checked: set[str] = set()

    def array(self, name: str, dtype: type, tail: tuple[int, ...], rows: int) -> np.ndarray:
        """Array ``name``, which must be of ``dtype`` and shape ``(rows, *tail)``."""
        if name not in self.arrays:
            raise IndexFormatError(f"{self.path}: no array {name!r}")
        self.checked.add(name)
        array, shape = self.arrays[name], (rows, *tail)
        if array.dtype != dtype or array.shape != shape:
            raise IndexFormatError(
                f"{self.path}: array {name!r} is {array.dtype} {array.shape}, expected {np.dtype(dtype)} {shape}"
            )
        return array

    def offsets(self, name: str, parents: int) -> np.ndarray:
        """``name.offsets`` of a child table of ``parents`` rows."""
        offsets = self.array(f"{name}.offsets", np.int64, (), parents + 1)
        if offsets[0] != 0 or (np.diff(offsets) < 0).any():
            raise IndexFormatError(f"{self.path}: array '{name}.offsets' must start at 0 and never fall")
        return offsets


def _pack(cls: type, records: list, prefix: str, out: _Writer) -> None:
    """The columns of ``records`` of ``cls``, named ``prefix<field>``."""
    boxes = _box_fields(cls)
    if boxes:
        out.offsets(f"{prefix}boxes", [getattr(record, boxes[0]) for record in records])
    for name, kind in _declared(cls):
        kind.pack([getattr(record, name) for record in records], prefix + name, out)


def _check(cls: type, file: _File, prefix: str, rows: _Rows) -> None:
    """Check the columns of ``cls`` named ``prefix<field>``, of ``rows``."""
    boxes = rows
    if _box_fields(cls):
        offsets = file.offsets(f"{prefix}boxes", rows.count)
        boxes = rows.nested(offsets, lambda i, k, f: f"{rows.at(i, f)}[{k}]")
    for name, kind in _declared(cls):
        kind.check(file, prefix + name, name, boxes if kind.per_box else rows)


def _reader(cls: type, file: _File, prefix: str) -> Callable[[int], Any]:
    """``row -> record`` of ``cls`` over the checked columns named ``prefix<field>``."""
    getters = [(name, kind.reader(file, prefix + name), kind.per_box) for name, kind in _declared(cls)]
    boxes = file.arrays[f"{prefix}boxes.offsets"].tolist() if _box_fields(cls) else []

    def build(row: int) -> Any:
        # The values are what __post_init__ would keep (read-only views, tuples), checked column by column already:
        # running it again per record would take most of the time of reading a large index.
        record = object.__new__(cls)
        record.__dict__.update(
            {name: get(boxes[row], boxes[row + 1]) if per_box else get(row) for name, get, per_box in getters}
        )
        return record

    return build


def _first_false(flags: np.ndarray) -> int:
    return int(np.argmin(flags))


class FrameRecords(Sequence[FrameRecord]):
    """The frames of an index file, as :func:`load_index` returns them: a read-only sequence over the file's
    columns, all checked when the file was read. A record is built when it is first used and then kept (the same
    object each time). Equal to any sequence of equal records, a list among them."""

    def __init__(self, file: _File, count: int) -> None:
        self._file = file
        self._records: list[FrameRecord | None] = [None] * count
        self._build = _reader(FrameRecord, file, "")

    def __len__(self) -> int:
        return len(self._records)

    def __getitem__(self, index: Any) -> Any:
        if isinstance(index, slice):
            return [self[i] for i in range(*index.indices(len(self)))]
        record = self._records[index]  # IndexError and TypeError as a list's
        if record is None:
            index = operator.index(index) % len(self)
            record = self._records[index] = self._build(index)
        return record

    def __iter__(self) -> Iterator[FrameRecord]:
        return (self[i] for i in range(len(self)))

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Sequence) or isinstance(other, (str, bytes)):
            return NotImplemented
        return len(self) == len(other) and all(a == b for a, b in zip(self, other, strict=True))

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        return f"FrameRecords({len(self)} frames of {self._file.path})"

    def __getstate__(self) -> dict[str, Any]:
        # The reader is made of closures, which do not pickle (DataLoader workers that spawn get the columns).
        return {key: value for key, value in self.__dict__.items() if key != "_build"}

    def __setstate__(self, state: dict[str, Any]) -> None:
        self.__dict__.update(state)
        self._build = _reader(FrameRecord, self._file, "")


# ----------------------------------------------------------------------------------------------------- files
_REQUIRED_META = ("version", "root", "max_sweeps")

#: What reading a damaged ``.npz`` can raise (zipfile and numpy's format reader).
_READ_ERRORS = (OSError, ValueError, EOFError, KeyError, NotImplementedError, zipfile.BadZipFile, zlib.error)

#: The first bytes of a zip file, and of the JSON index files of format 1 (header first); format 2 was a ``.npz``
#: as now, without ``box_valid`` (its header says so).
_ZIP_MAGIC = b"PK\x03\x04"
_JSON_INDEX_START = b'{"format": "occkit-index/1"'


def save_index(records: Sequence[FrameRecord], path: str | Path, meta: Mapping[str, Any]) -> Path:
    """Write ``records`` as an index file (``.npz``, see the module doc), atomically.

    Every column is checked as :func:`load_index` checks it before anything is written, so no file holds a value
    its reader refuses.

    Args:
        records: the frames, e.g. from :func:`build_index`.
        path: the file to write (its name is kept as given); parent folders are created.
        meta: at least ``version``, ``root`` and ``max_sweeps`` of the build; other JSON values (``split``, ...)
            are kept too. ``format``, ``created_by`` and ``frames`` are set here.

    Raises:
        ValueError: ``meta`` lacks a key.
        IndexFormatError: a record holds a value the format refuses (NaN, an unsafe name or path, ...); the message
            names the file, the record, its sample and the field.
    """
    path = Path(path)
    missing = [key for key in _REQUIRED_META if key not in meta]
    if missing:
        raise ValueError(f"index meta needs {', '.join(missing)}; got keys {', '.join(meta) or 'none'}")
    header = {
        "format": INDEX_FORMAT,
        "created_by": f"occkit {__version__}",
        **{key: value for key, value in meta.items() if key not in ("format", "created_by", "frames")},
        "frames": len(records),
    }
    out = _Writer()
    out.add("header", np.array(json.dumps(header)), deflate=False)
    _pack(FrameRecord, list(records), "", out)
    strings = list(out.strings)  # in code order
    place = _Rows(len(records), lambda i, f: f"{path}: record {i} (sample {records[i].token}).{f}")
    _check(FrameRecord, _File(str(path), out.arrays, strings), "", place)
    encoded = [text.encode("utf-8", "surrogatepass") for text in strings]  # checked: all are strings
    out.add("strings", np.frombuffer(b"".join(encoded), dtype=np.uint8))
    out.add("strings.offsets", _offsets([len(text) for text in encoded]))
    path.parent.mkdir(parents=True, exist_ok=True)
    # A per-process name: ranks of one torchrun job may build the same cache at the same moment.
    partial = path.with_name(f".{path.name}.{os.getpid()}.partial")
    try:
        with zipfile.ZipFile(partial, "w", allowZip64=True) as archive:
            # One .npy per array, as np.savez writes; the header first, so that reading it alone stays cheap.
            for name, array in out.arrays.items():
                _write_array(archive, name, array, name in out.deflated)
        os.replace(partial, path)
    finally:
        partial.unlink(missing_ok=True)
    return path


def _write_array(archive: zipfile.ZipFile, name: str, array: np.ndarray, deflate: bool) -> None:
    """``array`` as member ``name.npy`` of ``archive``, deflated (fast level 1) or stored."""
    buffer = io.BytesIO()
    np.lib.format.write_array(buffer, array, allow_pickle=False)
    # A fixed time stamp: the same records give the same bytes.
    member = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    member.external_attr = 0o600 << 16
    method = zipfile.ZIP_DEFLATED if deflate else zipfile.ZIP_STORED
    archive.writestr(member, buffer.getbuffer(), compress_type=method, compresslevel=1)


def load_index(path: str | Path) -> tuple[FrameRecords, dict[str, Any]]:
    """Read an index file written by :func:`save_index`, checking every column.

    Returns:
        The records (a sequence that builds each record when it is first used) and the header (``format``,
        ``version``, ``root``, ``max_sweeps``, ``created_by``, ``frames`` and any other meta saved).

    Raises:
        FileNotFoundError: no such file.
        OutdatedIndexError: an index of an older occkit's format (JSON ``occkit-index/1``, ``occkit-index/2``);
            the message gives the ``occkit index`` command that rebuilds it.
        IndexFormatError: not an occkit index of this format, a damaged file, or a malformed column (an unsafe
            name or path among them, see :mod:`occkit.data.names`); the message names the file and, for a value,
            the record and field.
    """
    path = Path(path)
    with _open_index(path) as npz:
        header = _header(path, npz)
        try:
            arrays = {name: npz[name] for name in npz.files if name != "header"}
        except _READ_ERRORS as error:
            raise IndexFormatError(f"{path}: damaged index file ({type(error).__name__}: {error})") from None
    frames = header.get("frames")
    if type(frames) is not int or frames < 0:
        raise IndexFormatError(f"{path}: header 'frames' must be a count, got {_show(frames)}")
    for array in arrays.values():
        array.setflags(write=False)  # records share views of the columns
    file = _File(str(path), arrays, _string_table(path, arrays))
    _check(FrameRecord, file, "", _Rows(frames, lambda i, f: f"{path}: record {i}.{f}"))
    unknown = sorted(set(arrays) - file.checked)
    if unknown:
        raise IndexFormatError(f"{path}: unknown array(s) {', '.join(unknown)}")
    return FrameRecords(file, frames), header


def read_index_header(path: str | Path) -> dict[str, Any]:
    """The header of an index file written by :func:`save_index` (what :func:`load_index` returns second), read
    alone: cheap for any size of index.

    Raises:
        FileNotFoundError: no such file.
        IndexFormatError: no occkit index of this format; :class:`OutdatedIndexError` for an older occkit's (see
            :func:`load_index`).
    """
    path = Path(path)
    with _open_index(path) as npz:
        return _header(path, npz)


def _open_index(path: Path) -> np.lib.npyio.NpzFile:
    """The open ``.npz`` of an index file (reading its directory only)."""
    try:
        with open(path, "rb") as stream:
            start = stream.read(len(_JSON_INDEX_START))
            if start == _JSON_INDEX_START:
                header = _json_header(start + stream.readline(1 << 20))
                raise OutdatedIndexError(f"{path}: {_rebuild_hint(path, header, 1)}")
    except FileNotFoundError:
        raise FileNotFoundError(f"index file {path} does not exist") from None
    if not start.startswith(_ZIP_MAGIC):
        raise IndexFormatError(f"{path}: not an occkit index (an {INDEX_FORMAT} .npz file)")
    try:
        return np.load(path)  # allow_pickle=False: object arrays are refused, nothing is unpickled
    except _READ_ERRORS as error:
        raise IndexFormatError(f"{path}: damaged index file ({type(error).__name__}: {error})") from None


def _json_header(first_line: bytes) -> dict[str, Any]:
    """The header of a JSON index (``occkit-index/1``), which its first line holds before the records; ``{}`` if
    it does not read."""
    try:
        header = json.loads(first_line.decode("utf-8").rstrip()[: -len(', "records": [')] + "}")
    except (UnicodeDecodeError, json.JSONDecodeError):
        return {}
    return header if isinstance(header, dict) else {}


def _older_format(found: Any) -> int | None:
    """The number of an older occkit's index format ``found`` (``occkit-index/<n>``), else None."""
    prefix, _, current = INDEX_FORMAT.rpartition("/")
    if isinstance(found, str) and found.startswith(prefix + "/") and found[len(prefix) + 1 :].isdigit():
        number = int(found[len(prefix) + 1 :])
        return number if number < int(current) else None
    return None


def _rebuild_hint(path: Path, header: Mapping[str, Any], number: int) -> str:
    """What to say of an index of the older format ``occkit-index/<number>``: the command that rebuilds it from
    what its header recorded (root, version, max_sweeps, split, info file)."""
    command = ["occkit", "index", "--root", str(header.get("root", "ROOT")), "--version",
               str(header.get("version", "VERSION")), "--max-sweeps", str(header.get("max_sweeps", 10))]  # fmt: skip
    if header.get("split", "all") != "all":
        command += ["--split", str(header["split"])]
    if "from_info" in header:
        command += ["--from-info", str(header["from_info"]), "--trust-pickle"]
    what = "a JSON index" if number == 1 else "an index"
    rebuilt = path.with_suffix(".npz")  # occkit index writes .npz files only
    where = "" if rebuilt == path else f" and point data.index at {rebuilt}"
    return (
        f"{what} of an older occkit (occkit-index/{number}); this occkit reads {INDEX_FORMAT} (.npz): rebuild it "
        f"with `{shlex.join([*command, '--out', str(rebuilt)])}`{where}"
    )


def _header(path: Path, npz: np.lib.npyio.NpzFile) -> dict[str, Any]:
    try:
        header = json.loads(str(npz["header"][()]))
    except (*_READ_ERRORS, json.JSONDecodeError):
        header = None
    found = header.get("format") if isinstance(header, dict) else None
    if found != INDEX_FORMAT:
        number = _older_format(found)
        if number is not None:
            raise OutdatedIndexError(f"{path}: {_rebuild_hint(path, header, number)}")
        raise IndexFormatError(f"{path}: not an occkit index (format {found!r}, expected {INDEX_FORMAT!r})")
    return header


def _string_table(path: Path, arrays: dict[str, np.ndarray]) -> list[str]:
    """The strings of arrays ``strings`` (UTF-8, concatenated) and ``strings.offsets`` (taken out of ``arrays``)."""
    blob, offsets = arrays.pop("strings", None), arrays.pop("strings.offsets", None)
    if not (
        isinstance(blob, np.ndarray)
        and isinstance(offsets, np.ndarray)
        and blob.dtype == np.uint8
        and blob.ndim == 1
        and offsets.dtype == np.int64
        and offsets.ndim == 1
        and len(offsets) > 0
        and offsets[0] == 0
        and offsets[-1] == len(blob)
        and (np.diff(offsets) >= 0).all()
    ):
        raise IndexFormatError(
            f"{path}: no string table: expected arrays 'strings' (uint8) and 'strings.offsets' (int64, rising from 0 "
            "to the length of 'strings')"
        )
    raw, bounds = blob.tobytes(), offsets.tolist()
    try:
        return [raw[a:b].decode("utf-8", "surrogatepass") for a, b in zip(bounds[:-1], bounds[1:], strict=True)]
    except UnicodeDecodeError as error:
        raise IndexFormatError(f"{path}: the string table is not UTF-8 ({error})") from None


def _labelled_tokens(folder: Path) -> set[str]:
    """Names of the sample folders in an Occ3D scene folder (``gts/<scene>``) that hold a ``labels.npz``: what a
    record's ``occ_path`` says. One directory listing, one stat per sample folder; none for a missing folder."""
    try:
        entries = list(os.scandir(folder))
    except (FileNotFoundError, NotADirectoryError):
        return set()
    return {entry.name for entry in entries if os.path.isfile(os.path.join(entry.path, "labels.npz"))}


def _label_listing(root: Path) -> Iterator[str]:
    """``scene/token`` of every Occ3D ``labels.npz`` under ``root/gts``, in sorted order (an index's ``occ_path``
    values come from this listing, so its cache key covers it: labels added or removed after the cache was built)."""
    try:
        scenes = sorted(entry.name for entry in os.scandir(root / "gts") if entry.is_dir())
    except (FileNotFoundError, NotADirectoryError):
        return
    for scene in scenes:
        for token in sorted(_labelled_tokens(root / "gts" / scene)):
            yield f"{scene}/{token}"


def tables_key(root: str | Path, version: str, max_sweeps: int) -> str:
    """What an index built from ``root/version`` depends on, as one digest: the index format, the occkit version,
    ``max_sweeps``, the size and SHA-256 of each of the 13 table files (their content: modification times are not
    trusted, a file can change and keep an old one), and which key frames have an Occ3D ``labels.npz`` under
    ``root/gts`` (each record's ``occ_path``). The dataset's index cache stores it and is rebuilt when it differs.
    Hashing reads every table once: about 0.7 s per GB on one core when the files are in the page cache; the label
    listing is one directory listing per scene and one stat per frame.
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
    labels = hashlib.sha256()
    for entry in _label_listing(Path(root)):
        labels.update(f"{entry}\n".encode())
    digest.update(f"labels\0{labels.hexdigest()}\n".encode())
    return f"sha256:{digest.hexdigest()}"
