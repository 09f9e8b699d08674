"""The 13 tables of a nuScenes version folder, read straight from ``<root>/<version>/*.json``.

No nuscenes-devkit: records stay the plain dicts that :mod:`json` returns, each table is kept as its list plus a
token -> record dict. At trainval scale (2.6 M sample_data and ego_pose rows, 1.2 M annotations) memory is the
concern. The JSON parser gives every occurrence of a token its own string object, and a sample_data record names
five other records by token; as each record is parsed, the values of :data:`SHARED_FIELDS` are replaced by one
shared object per distinct value. Done during the parse, the duplicates are freed while the parser still allocates,
so their memory is reused at once: the tables of trainval take about 5 GB instead of 7 (``benchmarks/index_scale.py``).

Every error names the file and, where there is one, the record: ``v1.0-mini/sample_data.json: record 17 has no
'calibrated_sensor_token'``.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

from occkit.nuscenes import TABLE_NAMES

__all__ = ["TABLE_NAMES", "REQUIRED_FIELDS", "SHARED_FIELDS", "TableError", "NuScenesTables", "load_tables"]

#: Fields every record of a table must have: the ones occkit reads (the nuScenes schema has a few more).
REQUIRED_FIELDS: dict[str, tuple[str, ...]] = {
    "category": ("token", "name"),
    "attribute": ("token", "name"),
    "visibility": ("token", "level"),
    "instance": ("token", "category_token"),
    "sensor": ("token", "channel", "modality"),
    "calibrated_sensor": ("token", "sensor_token", "translation", "rotation", "camera_intrinsic"),
    "ego_pose": ("token", "timestamp", "translation", "rotation"),
    "log": ("token",),
    "scene": ("token", "name", "log_token", "first_sample_token"),
    "sample": ("token", "timestamp", "scene_token", "prev", "next"),
    "sample_data": (
        "token",
        "sample_token",
        "ego_pose_token",
        "calibrated_sensor_token",
        "timestamp",
        "is_key_frame",
        "width",
        "height",
        "filename",
        "prev",
        "next",
    ),
    "sample_annotation": (
        "token",
        "sample_token",
        "instance_token",
        "visibility_token",
        "translation",
        "size",
        "rotation",
        "prev",
        "next",
        "num_lidar_pts",
        "num_radar_pts",
    ),
    "map": ("token",),
}


#: Fields whose values repeat across records (tokens that refer to other records, a few small values): the
#: parser hands every occurrence its own object, and loading makes equal values one object (see the module doc).
SHARED_FIELDS: dict[str, tuple[str, ...]] = {
    "instance": ("token", "category_token", "first_annotation_token", "last_annotation_token"),
    "calibrated_sensor": ("token", "sensor_token"),
    "ego_pose": ("token",),
    "scene": ("token", "log_token", "first_sample_token", "last_sample_token"),
    "sample": ("token", "scene_token", "prev", "next"),
    "sample_data": (
        "token",
        "sample_token",
        "ego_pose_token",
        "calibrated_sensor_token",
        "prev",
        "next",
        "fileformat",
        "width",
        "height",
    ),
    "sample_annotation": ("token", "sample_token", "instance_token", "visibility_token", "prev", "next"),
}


#: Fields of :data:`SHARED_FIELDS` that hold values, not tokens of other records.
_SHARED_VALUES = frozenset({"fileformat", "width", "height"})


class TableError(ValueError):
    """A table is missing, unreadable or inconsistent; the message names the file (and record)."""


@dataclass(frozen=True)
class NuScenesTables:
    """The tables of one nuScenes version folder.

    Attributes:
        root: dataset root (the folder that holds ``<version>/``, ``samples/``, ``sweeps/``).
        version: table folder name, e.g. ``v1.0-trainval``.
        tables: table name -> its records in file order.
        tokens: table name -> token -> record (the same dict objects as in ``tables``).
    """

    root: Path
    version: str
    tables: Mapping[str, list[dict]]
    tokens: Mapping[str, dict[str, dict]]

    def __getitem__(self, table: str) -> list[dict]:
        return self.tables[table]

    def file(self, table: str) -> str:
        """The table's file as messages name it, ``<version>/<table>.json``."""
        return f"{self.version}/{table}.json"

    def get(self, table: str, token: str, referrer: str = "") -> dict:
        """The record of ``table`` with ``token``; :class:`TableError` if there is none.

        ``referrer`` (e.g. ``"v1.0-mini/sample_data.json: record <token>"``) says where the token came from.
        """
        try:
            return self.tokens[table][token]
        except (KeyError, TypeError):  # TypeError: an unhashable value (a list) where a token belongs
            where = f"{referrer} refers to" if referrer else "no record with"
            raise TableError(f"{where} {table} token {token!r}, which {self.file(table)} does not have") from None


def load_tables(root: str | Path, version: str) -> NuScenesTables:
    """Read the 13 tables of ``root/version``.

    Raises:
        FileNotFoundError: the root or the version folder does not exist.
        TableError: a table is missing or is not valid JSON, is not a list of objects, has a record without a
            required field (:data:`REQUIRED_FIELDS`) or repeats a token.
    """
    root = Path(root)
    folder = root / version
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} does not exist")
    if not folder.is_dir():
        found = sorted(p.name for p in root.iterdir() if p.is_dir() and (p / "sample.json").is_file())
        hint = f"; version folders found: {', '.join(found)}" if found else ""
        raise FileNotFoundError(f"{folder} does not exist{hint}")
    shared: dict = {}
    tables = {name: _read_table(folder, f"{version}/{name}.json", name, shared) for name in TABLE_NAMES}
    tokens = {name: _by_token(records, f"{version}/{name}.json") for name, records in tables.items()}
    return NuScenesTables(root=root, version=version, tables=tables, tokens=tokens)


def _read_table(folder: Path, file: str, name: str, shared: dict) -> list[dict]:
    path = folder / f"{name}.json"
    try:
        # Text, not bytes: json.load(binary file) holds the bytes and their decoded copy through the parse.
        text = path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise TableError(f"{file}: table is missing (a nuScenes version folder has {len(TABLE_NAMES)})") from None
    except UnicodeDecodeError as error:
        raise TableError(f"{file}: not valid JSON ({error})") from None
    fields = SHARED_FIELDS.get(name)
    try:
        records = json.loads(text, object_hook=_sharer(fields, shared, file) if fields else None)
    except json.JSONDecodeError as error:
        raise TableError(f"{file}: not valid JSON ({error})") from None
    if not isinstance(records, list):
        raise TableError(f"{file}: expected a JSON list of records, got {type(records).__name__}")
    _check_fields(records, REQUIRED_FIELDS[name], file)
    return records


def _sharer(fields: tuple[str, ...], shared: dict, file: str) -> Callable[[dict], dict]:
    """A json ``object_hook`` that replaces the values of ``fields`` by the equal object in ``shared``, and refuses
    a token field (a reference to another record) that holds no string or integer."""
    share = shared.setdefault
    tokens = frozenset(field for field in fields if field not in _SHARED_VALUES)

    def hook(record: dict) -> dict:
        for field in fields:
            value = record.get(field)
            # Exact types: lists are unhashable, and True == 1 must not turn a bool into an int.
            if value.__class__ is str or value.__class__ is int:
                record[field] = share(value, value)
            elif value is not None and field in tokens:
                shown = repr(value) if len(repr(value)) <= 60 else repr(value)[:56] + " ..."
                raise TableError(f"{file}: record {record.get('token')!r}.{field}: expected a token, got {shown}")
        return record

    return hook


def _check_fields(records: list, required: tuple[str, ...], file: str) -> None:
    needed = frozenset(required)
    for i, record in enumerate(records):
        # dict_keys compare as sets: one C-level subset test per record keeps this linear and cheap.
        if isinstance(record, dict) and record.keys() >= needed:
            continue
        if not isinstance(record, dict):
            raise TableError(f"{file}: record {i} is a {type(record).__name__}, not an object")
        missing = [field for field in required if field not in record]
        raise TableError(f"{file}: record {i} has no {missing[0]!r}")


def _by_token(records: list[dict], file: str) -> dict[str, dict]:
    try:
        tokens = {record["token"]: record for record in records}
    except TypeError:  # an unhashable token
        i = next(i for i, record in enumerate(records) if not _hashable(record["token"]))
        raise TableError(f"{file}: record {i}: token must be a string, got {records[i]['token']!r:.60}") from None
    if len(tokens) != len(records):
        seen: set[str] = set()
        for i, record in enumerate(records):
            if record["token"] in seen:
                raise TableError(f"{file}: record {i} repeats token {record['token']!r}")
            seen.add(record["token"])
    return tokens


def _hashable(value: object) -> bool:
    try:
        hash(value)
    except TypeError:
        return False
    return True
