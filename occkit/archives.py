"""Files occkit did not write, read only after what they declare fits the file, the caller and the machine.

A zip archive (torch's checkpoint format, numpy's ``.npz``) declares each member's uncompressed size in its central
directory, and a ``.npy`` header declares its array's shape and dtype. Readers that trust the declarations allocate
what a file of a few MB claims (gigabytes of deflated zeros) before any check of theirs can run. The functions here
read only the declarations (``zipfile`` reads the central directory, numpy's header readers the first bytes of a
member), compare them with what the caller expects, with the file's size and with the memory available, and refuse
with one message naming the file, the member and the sizes; only then is any data read.

* :func:`check_torch_file`: before ``torch.load`` (checkpoints, converted weights, pretrained backbones).
* :class:`NpzArchive` and :func:`read_npy`: ``.npz`` predictions and labels, SurroundOcc's ``.npy`` labels.
"""

from __future__ import annotations

import threading
import zipfile
import zlib
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import numpy as np

from occkit.arguments import available_memory, format_bytes

__all__ = ["TORCH_SIZE_SLACK", "check_torch_file", "NpyHeader", "NpzArchive", "read_npy"]

#: How much more than its size on disk a torch file may declare uncompressed. torch stores every record uncompressed,
#: so its files declare no more than they hold; the slack admits a file another tool re-zipped with small
#: compressed records (the pickle), never one that inflates to much more than it weighs.
TORCH_SIZE_SLACK = 4 << 20

_ZIP_MAGIC = (b"PK\x03\x04", b"PK\x05\x06")  # a member's local header; an empty archive's end record
_NPY_MAGIC = b"\x93NUMPY"
_PICKLE_PROTOCOL = b"\x80"  # torch's legacy format begins with a pickled magic number
#: What reading a broken zip member raises (besides OSError and ValueError): a bad archive, a corrupt deflate
#: stream, a compression method or encryption zipfile does not support.
_ZIP_ERRORS = (OSError, ValueError, EOFError, zipfile.BadZipFile, zlib.error, NotImplementedError, RuntimeError)


def _first_bytes(path: Path, count: int = 8) -> bytes:
    with open(path, "rb") as handle:
        return handle.read(count)


# ----------------------------------------------------------------------------------------------------- torch files
def check_torch_file(path: str | Path) -> None:
    """Refuse a file that is no torch checkpoint, or whose zip declares more than it holds or the machine has.

    torch's zip format (every ``torch.save`` since 1.6) is checked from its central directory: no record may declare
    much more than it takes on disk (a deflated bomb), their sum not more than the file's size (overlapping records)
    nor than the memory available. The older format (a pickle stream) is left to ``torch.load``: its storages are
    allocated from declared sizes but only filled from the file, so they cost no more memory than the file has.

    Raises:
        ValueError: neither format, a broken zip, or declared sizes out of bounds (the message names file, record
            and sizes).
    """
    path = Path(path)
    head = _first_bytes(path, 4)
    if head in _ZIP_MAGIC:
        _check_torch_zip(path, path.stat().st_size)
    elif not head.startswith(_PICKLE_PROTOCOL):
        shown = "it is empty" if not head else f"it starts with {head!r}"
        raise ValueError(f"{path} is not a readable checkpoint: neither torch's zip format nor its older pickle "
                         f"format ({shown})")  # fmt: skip


def _check_torch_zip(path: Path, size: int) -> None:
    try:
        with zipfile.ZipFile(path) as archive:
            members = archive.infolist()
    except _ZIP_ERRORS as error:
        raise ValueError(f"{path} is not a readable checkpoint: a broken zip archive ({error})") from error
    for member in members:
        if member.file_size - member.compress_size > TORCH_SIZE_SLACK:
            raise ValueError(
                f"{path} is not a checkpoint torch wrote: its record {member.filename} declares "
                f"{format_bytes(member.file_size)} uncompressed from {format_bytes(member.compress_size)} on disk "
                "(torch stores records uncompressed); refused before reading it"
            )
    declared = sum(member.file_size for member in members)
    if declared > size + TORCH_SIZE_SLACK:
        raise ValueError(f"{path} is not a checkpoint torch wrote: its {len(members)} records declare "
                         f"{format_bytes(declared)} in a file of {format_bytes(size)}; refused before reading them")
    available = available_memory()
    if declared > available:
        raise ValueError(f"{path} needs about {format_bytes(declared)} of memory to load, this machine has "
                         f"{format_bytes(available)} available")  # fmt: skip


# ----------------------------------------------------------------------------------------------------- numpy files
class NpyHeader(NamedTuple):
    """What a ``.npy`` header declares, and where its data begins."""

    shape: tuple[int, ...]
    dtype: np.dtype
    fortran_order: bool
    offset: int

    @property
    def nbytes(self) -> int:
        return int(np.prod(self.shape, dtype=object)) * self.dtype.itemsize


#: numpy parses a header with ``ast.literal_eval``, and CPython 3.11 keeps the AST constructor's recursion depth in
#: state its threads share: two threads parsing at once can fail with "SystemError: AST constructor recursion depth
#: mismatch" (seen here in ``eval-preds``, which scores frames in a thread pool). So one parse at a time; a header is
#: a few hundred bytes.
_HEADER_LOCK = threading.Lock()


def _read_header(stream) -> NpyHeader:
    """The header of the ``.npy`` stream, read without its data; ValueError for anything else."""
    version = np.lib.format.read_magic(stream)
    with _HEADER_LOCK:
        if version == (1, 0):
            shape, fortran_order, dtype = np.lib.format.read_array_header_1_0(stream)
        elif version in ((2, 0), (3, 0)):
            shape, fortran_order, dtype = np.lib.format.read_array_header_2_0(stream)
        else:
            raise ValueError(f"unknown .npy format version {version[0]}.{version[1]}")
    return NpyHeader(tuple(shape), np.dtype(dtype), bool(fortran_order), stream.tell())


class _Reader:
    """Messages and checks the two readers share: ``where`` names the file (and sample), ``what`` its content."""

    def __init__(self, path: Path, where: str | None, what: str, error: type[ValueError]):
        self.path, self.where, self.what, self.error = path, where or str(path), what, error

    def fail(self, why: str) -> ValueError:
        return self.error(f"{self.where}: cannot read {self.what}: {why}")

    def check(self, key: str, header: NpyHeader, holds: int, check: Callable[[NpyHeader], None] | None) -> None:
        """The caller's ``check`` (shape, dtype) first, then that the data is there and fits in memory."""
        if header.dtype.hasobject:
            raise self.fail(f"{key} holds Python objects (pickled data), which occkit does not unpickle")
        if check is not None:
            check(header)
        if header.nbytes > holds:
            raise self.fail(f"{key} declares {header.dtype} {header.shape} ({format_bytes(header.nbytes)}) but holds "
                            f"{format_bytes(max(holds, 0))}: the file is truncated or forged")  # fmt: skip
        available = available_memory()
        if header.nbytes > available:
            raise self.fail(f"{key} declares {header.dtype} {header.shape}, {format_bytes(header.nbytes)}: more than "
                            f"the {format_bytes(available)} of memory available")  # fmt: skip


class NpzArchive(_Reader):
    """A ``.npz`` file whose arrays are read one by one, each only after its header passed the caller's check.

    Usage::

        with NpzArchive(path, "labels", where=f"sample {token}: {path}", error=LabelError) as archive:
            semantics = archive.read("semantics", check)   # check(header) raises when shape or dtype is wrong

    Raises (from the constructor and :meth:`read`): ``error`` (a ValueError) naming ``where``: not a zip of
    ``.npy`` arrays (e.g. text, a pickle, a bare ``.npy``), a broken archive, a member that is not an array or holds
    objects, a header the check refuses, data shorter than declared or larger than the memory available.
    ``FileNotFoundError`` passes through for the caller to word.
    """

    def __init__(self, path: str | Path, what: str, where: str | None = None, error: type[ValueError] = ValueError):
        super().__init__(Path(path), where, what, error)
        head = _first_bytes(self.path)
        if head.startswith(_NPY_MAGIC):
            raise self.fail("a single .npy array, not a .npz archive of named arrays")
        if head[:4] not in _ZIP_MAGIC:
            shown = "it is empty" if not head else f"it starts with {head!r}"
            raise self.fail(f"not a .npz archive (a zip of .npy arrays, as numpy.savez writes; {shown})")
        try:
            self._zip = zipfile.ZipFile(self.path)
        except _ZIP_ERRORS as error:
            raise self.fail(f"a broken .npz archive ({error})") from error
        members = self._zip.infolist()
        self._members = {m.filename.removesuffix(".npy"): m for m in members if m.filename.endswith(".npy")}

    @property
    def keys(self) -> list[str]:
        """The names of the archive's arrays (its ``NAME.npy`` members)."""
        return list(self._members)

    def __contains__(self, key: str) -> bool:
        return key in self._members

    def header(self, key: str) -> NpyHeader:
        """The header of array ``key`` (KeyError when absent)."""
        member = self._members[key]
        try:
            with self._zip.open(member) as stream:
                return _read_header(stream)
        except _ZIP_ERRORS as error:
            raise self.fail(f"{key} is not a readable .npy array ({error})") from error

    def read(self, key: str, check: Callable[[NpyHeader], None] | None = None) -> np.ndarray:
        """Array ``key`` (KeyError when absent), read after ``check(header)`` and the size checks passed."""
        header = self.header(key)
        self.check(key, header, self._members[key].file_size - header.offset, check)
        try:
            with self._zip.open(self._members[key]) as stream:
                return np.lib.format.read_array(stream, allow_pickle=False)
        except _ZIP_ERRORS as error:
            raise self.fail(f"{key} is not a readable .npy array ({error})") from error

    def close(self) -> None:
        self._zip.close()

    def __enter__(self) -> NpzArchive:
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def read_npy(path: str | Path, what: str, check: Callable[[NpyHeader], None] | None = None, where: str | None = None,
             error: type[ValueError] = ValueError) -> np.ndarray:  # fmt: skip
    """The array of a ``.npy`` file, read after ``check(header)`` passed and its data was found to be there.

    Raises:
        FileNotFoundError: no such file.
        error: (a ValueError) naming ``where``: not a ``.npy`` file (an ``.npz``, text, a pickle), an array of
            objects, a header the check refuses, data shorter than declared or larger than the memory available.
    """
    reader = _Reader(Path(path), where, what, error)
    head = _first_bytes(reader.path)
    if head[:4] in _ZIP_MAGIC:
        raise reader.fail("a .npz archive, not a single .npy array")
    if not head.startswith(_NPY_MAGIC):
        shown = "it is empty" if not head else f"it starts with {head!r}"
        raise reader.fail(f"not a .npy file (as numpy.save writes; {shown})")
    try:
        with open(reader.path, "rb") as stream:
            header = _read_header(stream)
    except ValueError as error:  # numpy's refusal of the header
        raise reader.fail(f"not a readable .npy array ({error})") from error
    reader.check("the array", header, reader.path.stat().st_size - header.offset, check)
    try:
        with open(reader.path, "rb") as stream:
            return np.lib.format.read_array(stream, allow_pickle=False)
    except (ValueError, EOFError) as error:
        raise reader.fail(f"not a readable .npy array ({error})") from error
