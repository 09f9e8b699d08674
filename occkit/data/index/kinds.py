"""What each record field holds, declared once, and what follows from the declarations.

Each field of the records (:mod:`occkit.data.index.records`) is declared once, with its kind (a safe name, a
relative path, an integer, a ``(4, 4)`` matrix, one row per box, a table of sub-records, ...: the ``_Kind``
classes below). Everything else follows from these declarations: the checks of ``__post_init__`` and the JSON form
of a record (``to_dict`` / ``from_dict``), both of :class:`_Record`, and the columns of the index file
(:func:`_pack`, :func:`_check`, :func:`_reader`).
"""

from __future__ import annotations

import abc
import functools
import itertools
from collections.abc import Callable
from dataclasses import field as dataclass_field
from dataclasses import fields
from typing import Any, ClassVar, TypeVar

import numpy as np

from occkit.data.index.checks import (
    IndexFormatError,
    _counts,
    _frozen,
    _integer,
    _list,
    _matrix,
    _number,
    _show,
    _string,
    _typed_list,
)
from occkit.data.index.columns import _as_array, _File, _first_false, _Rows, _Writer
from occkit.data.names import is_safe_name, is_safe_relative_path, safe_name, safe_relative_path


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


# ----------------------------------------------------------------------------------------------------- columns
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
