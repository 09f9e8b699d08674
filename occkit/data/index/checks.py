"""Checks of the JSON values a record is read from (``from_dict``), and :class:`IndexFormatError`, which every
malformed record dict or index file raises, naming the file, record and field.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np


class IndexFormatError(ValueError):
    """An index file or record dict is malformed; the message names the file, record and field."""


def _show(value: Any, limit: int = 60) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 4] + " ..."


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
