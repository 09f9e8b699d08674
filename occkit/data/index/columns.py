"""The columns of an index file in memory, as the field kinds (:mod:`occkit.data.index.kinds`) write, check and read
them: :class:`_Writer` collects them while records are saved, :class:`_File` holds them and the decoded string
table while they are checked and read, :class:`_Rows` names each row of a table in messages.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from occkit.data.index.checks import IndexFormatError


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


def _first_false(flags: np.ndarray) -> int:
    return int(np.argmin(flags))
