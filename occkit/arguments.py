"""Checks of command-line arguments, run before any work: ranges, files versus folders, devices, machine sizes.

``occkit`` commands declare their options with the argparse types here (:func:`integer`, :func:`number`), so an
out-of-range value is refused while parsing, and call the other checks first thing in their ``_run_*`` function,
so a run never fails after minutes of work on something it could have seen at the start. Every failure is a
:class:`~occkit.errors.UsageError` naming the option and the value.
"""

from __future__ import annotations

import argparse
import math
import os
import shutil
from collections.abc import Callable
from pathlib import Path

from occkit.errors import UsageError

__all__ = [
    "integer",
    "number",
    "output_file",
    "output_folder",
    "input_file",
    "input_folder",
    "check_device",
    "available_memory",
    "check_memory",
    "check_disk",
    "format_bytes",
]


# ----------------------------------------------------------------------------------------------------- argparse types
def integer(minimum: int | None = None, maximum: int | None = None) -> Callable[[str], int]:
    """An argparse ``type``: an integer in ``[minimum, maximum]`` (None: unbounded on that side)."""

    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected an integer, got {text!r}") from None
        _check_range(value, minimum, maximum, text)
        return value

    parse.__name__ = "integer"
    return parse


def number(minimum: float | None = None, maximum: float | None = None) -> Callable[[str], float]:
    """An argparse ``type``: a finite float in ``[minimum, maximum]`` (None: unbounded on that side)."""

    def parse(text: str) -> float:
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"expected a number, got {text!r}") from None
        if not math.isfinite(value):
            raise argparse.ArgumentTypeError(f"expected a finite number, got {text!r}")
        _check_range(value, minimum, maximum, text)
        return value

    parse.__name__ = "number"
    return parse


def _check_range(value: float, minimum: float | None, maximum: float | None, text: str) -> None:
    low, high = _bound(minimum), _bound(maximum)
    if minimum is not None and maximum is not None and not minimum <= value <= maximum:
        raise argparse.ArgumentTypeError(f"must be between {low} and {high}, got {text}")
    if minimum is not None and value < minimum:
        raise argparse.ArgumentTypeError(f"must be >= {low}, got {text}")
    if maximum is not None and value > maximum:
        raise argparse.ArgumentTypeError(f"must be <= {high}, got {text}")


def _bound(value: float | None) -> str:
    # An integer bound is printed whole: "100000000", not "1e+08".
    return str(value) if isinstance(value, int) else f"{value:g}" if value is not None else ""


# ----------------------------------------------------------------------------------------------------- paths
def _ancestor_file(path: Path) -> Path | None:
    """The first existing ancestor of ``path`` that is not a folder (nothing can be created below it)."""
    for parent in path.absolute().parents:
        if parent.exists():
            return None if parent.is_dir() else parent
    return None


def output_file(path: Path, option: str, suffix: str | None = None, what: str = "the file") -> Path:
    """``path`` can be written as a file: it is not a folder and no ancestor is a file; with ``suffix``, its name
    ends in it (a name promising another format, ``index.json`` for a ``.npz``, is refused)."""
    if path.is_dir():
        raise UsageError(f"{option} {path} is a folder; give a file name")
    blocker = _ancestor_file(path)
    if blocker is not None:
        raise UsageError(f"{option} {path} cannot be created: {blocker} is a file, not a folder")
    if suffix is not None and path.suffix.lower() != suffix:
        raise UsageError(f"{option} {path}: {what} is a {suffix} file, whatever its name says; name it "
                         f"{path.with_suffix(suffix).name}")  # fmt: skip
    return path


def output_folder(path: Path, option: str) -> Path:
    """``path`` can be a folder: it is one already or can be created (no file in the way)."""
    if path.exists() and not path.is_dir():
        raise UsageError(f"{option} {path} is a file; give a folder")
    blocker = _ancestor_file(path)
    if blocker is not None:
        raise UsageError(f"{option} {path} cannot be created: {blocker} is a file, not a folder")
    return path


def input_file(path: Path, option: str) -> Path:
    """``path`` is an existing file."""
    if path.is_dir():
        raise UsageError(f"{option} {path} is a folder; give a file")
    if not path.is_file():
        raise UsageError(f"{option} {path} does not exist")
    return path


def input_folder(path: Path, option: str) -> Path:
    """``path`` is an existing folder."""
    if path.exists() and not path.is_dir():
        raise UsageError(f"{option} {path} is a file; give a folder")
    if not path.is_dir():
        raise UsageError(f"{option} {path} does not exist")
    return path


# ----------------------------------------------------------------------------------------------------- devices
def check_device(text: str | None, option: str = "--device") -> str | None:
    """``cpu``, ``cuda`` or ``cuda:N`` that this machine has (None passes: the command picks one)."""
    if text is None:
        return None
    kind, _, index = text.partition(":")
    if kind not in ("cpu", "cuda") or (index and not index.isdigit()) or (kind == "cpu" and index):
        raise UsageError(f"{option} must be cpu, cuda or cuda:N, got {text!r}")
    if kind == "cuda":
        import torch

        count = torch.cuda.device_count() if torch.cuda.is_available() else 0
        if count == 0:
            raise UsageError(f"{option} {text}: CUDA is not available on this machine (use {option} cpu)")
        if index and int(index) >= count:
            raise UsageError(f"{option} {text}: this machine has {count} CUDA device(s), cuda:0 to cuda:{count - 1}")
    return text


# ----------------------------------------------------------------------------------------------------- sizes
def format_bytes(count: float) -> str:
    for unit in ("B", "KB", "MB", "GB", "TB"):
        if abs(count) < 1024 or unit == "TB":
            return f"{count:.0f} {unit}" if unit == "B" else f"{count:.1f} {unit}"
        count /= 1024
    raise AssertionError("unreachable")


def available_memory() -> int:
    """Bytes of memory a new allocation can have without swapping: ``MemAvailable`` (Linux), else physical memory."""
    try:
        with open("/proc/meminfo") as meminfo:
            for line in meminfo:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except OSError:
        pass
    try:
        return os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    except (ValueError, OSError, AttributeError):
        return 2**62  # unknown: do not refuse


def check_memory(needed: float, what: str, option: str) -> None:
    """Refuse ``option`` when ``what`` needs more than the memory available now (an estimate in bytes)."""
    available = available_memory()
    if needed > available:
        raise UsageError(f"{option}: {what} needs about {format_bytes(needed)} of memory, this machine has "
                         f"{format_bytes(available)} available")  # fmt: skip


def check_disk(folder: Path, needed: float, what: str, option: str) -> None:
    """Refuse ``option`` when ``what`` needs more disk than the file system of ``folder`` has free."""
    existing = next((p for p in [folder.absolute(), *folder.absolute().parents] if p.exists()), Path("/"))
    free = shutil.disk_usage(existing).free
    if needed > free:
        raise UsageError(f"{option} {folder}: {what} needs about {format_bytes(needed)} of disk, "
                         f"{existing} has {format_bytes(free)} free")  # fmt: skip
