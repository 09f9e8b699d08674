"""The index file: :func:`save_index` writes records, :func:`load_index` reads them back, :func:`read_index_header`
reads the header alone.

An index file (format ``occkit-index/3``; docs/data.md lists every array) is a numpy ``.npz`` holding, per field, one
array over all records: matrices stacked, box fields concatenated with per-record offsets, the sweeps and cameras as
tables of their own with offsets, and every string as an int32 code into one UTF-8 string table; the header is a JSON
string inside. :func:`load_index` checks every column when it reads a file and returns :class:`FrameRecords`, a
sequence that builds each record when it is first used.

An index of an older occkit's format is refused with the command that rebuilds it (:class:`OutdatedIndexError`).
"""

from __future__ import annotations

import io
import json
import operator
import os
import shlex
import zipfile
import zlib
from collections.abc import Iterator, Mapping, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from occkit import __version__
from occkit.data.index.checks import IndexFormatError, _show
from occkit.data.index.columns import _File, _offsets, _Rows, _Writer
from occkit.data.index.kinds import _check, _pack, _reader
from occkit.data.index.records import FrameRecord

#: Value of the ``format`` key of index files.
INDEX_FORMAT = "occkit-index/3"


class OutdatedIndexError(IndexFormatError):
    """An index file of an older occkit's format (the JSON ``occkit-index/1``, the ``.npz`` of ``occkit-index/2``
    without ``box_valid``); the message gives the ``occkit index`` command that rebuilds it."""


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
