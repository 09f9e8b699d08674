"""Names and relative paths read from data files, checked before any of them becomes a file path.

Sample tokens and scene names become parts of paths (``gts/<scene>/<token>/labels.npz``, ``<out>/<token>.npz``), and
index records hold file paths relative to the dataset root. A crafted table or index could otherwise read or write
outside the folders a command was given (a token ``../../x``, an absolute path). The rules:

* a *name* (sample token, scene name, scene token) is 1 to 128 characters of ``A-Z a-z 0-9 . _ -``, starting with a
  letter or digit: nuScenes tokens (32 hex digits) and scene names (``scene-0061``) pass, a path separator, ``..``
  or a leading dot do not;
* a *relative path* (``samples/CAM_FRONT/x.jpg``) is a non-empty ``/``-separated path with no ``..`` component,
  not absolute (no leading ``/``, no drive), without backslashes or NUL characters.

:func:`path_under` joins a root and a checked relative path: the place to turn a name from data into a path to read
or write. The check is lexical: links inside the root are followed (datasets often link ``samples/`` to another
disk), and nothing is resolved against the file system.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from occkit.errors import InputError

__all__ = [
    "MAX_NAME_LENGTH",
    "UnsafeNameError",
    "is_safe_name",
    "is_safe_relative_path",
    "safe_name",
    "safe_relative_path",
    "path_under",
    "folder_name",
]

#: Longest accepted name (nuScenes tokens have 32 characters).
MAX_NAME_LENGTH = 128

_NAME = re.compile(rf"[A-Za-z0-9][A-Za-z0-9._-]{{0,{MAX_NAME_LENGTH - 1}}}")
_DRIVE = re.compile(r"[A-Za-z]:")
_NOT_IN_FOLDER_NAME = re.compile(r"[^A-Za-z0-9_]")
_NAME_RULE = f"1 to {MAX_NAME_LENGTH} of A-Z a-z 0-9 . _ -, starting with a letter or digit"


class UnsafeNameError(InputError, ValueError):
    """A name or relative path from a data file could leave the folder it is meant for; the message names where."""


def _show(value: object, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 4] + " ..."


def is_safe_name(value: object) -> bool:
    """True if ``value`` is a string that :func:`safe_name` accepts."""
    return isinstance(value, str) and _NAME.fullmatch(value) is not None


def safe_name(value: object, where: str, error: type[Exception] = UnsafeNameError) -> str:
    """``value`` if it is a safe name (see the module doc), else ``error`` naming ``where``.

    Args:
        value: a sample token, scene name or scene token.
        where: what messages call the value's place, e.g. ``"v1.0-mini/sample.json: record 3e8...token"``.
        error: the exception type to raise (the caller's file-format error).
    """
    if not is_safe_name(value):
        raise error(f"{where}: {_show(value)} is not a safe name ({_NAME_RULE})")
    return value  # type: ignore[return-value]


def is_safe_relative_path(value: object) -> bool:
    """True if ``value`` is a string that :func:`safe_relative_path` accepts."""
    return (
        isinstance(value, str)
        and value != ""
        and value[0] != "/"
        and "\\" not in value
        and "\0" not in value
        and _DRIVE.match(value) is None
        and (".." not in value or ".." not in value.split("/"))
    )


def safe_relative_path(value: object, where: str, error: type[Exception] = UnsafeNameError) -> str:
    """``value`` if it is a safe relative path (see the module doc), else ``error`` naming ``where``."""
    if isinstance(value, os.PathLike):
        value = os.fspath(value)
    if is_safe_relative_path(value):
        return value  # type: ignore[return-value]
    if not isinstance(value, str) or not value:
        raise error(f"{where}: expected a relative path, got {_show(value)}")
    if "\\" in value or "\0" in value:
        raise error(f"{where}: {_show(value)} holds a backslash or NUL character, not a relative path of '/' parts")
    if value[0] == "/" or _DRIVE.match(value):
        raise error(f"{where}: {_show(value)} is an absolute path; expected a path relative to the dataset root")
    raise error(f"{where}: {_show(value)} has a '..' component; expected a path that stays under its root")


def path_under(
    root: str | os.PathLike, relative: str | os.PathLike, where: str, error: type[Exception] = UnsafeNameError
) -> Path:
    """``root / relative`` after checking ``relative`` with :func:`safe_relative_path`: the result stays under
    ``root`` (lexically; see the module doc).

    For a file named after a token, check the token first: ``path_under(out, safe_name(token, where) + ".npz",
    where)``.
    """
    return Path(root) / safe_relative_path(relative, where, error)


def folder_name(label: str) -> str:
    """``label``, a name people read (a study arm ``"da_occ_tiny - BEV vertical DAC"``, a labelling variant
    ``"all sweeps + Poisson"``), as the name of the folder its files go to: spaces become ``_``, every other character
    outside ``A-Z a-z 0-9 _`` becomes ``-``, and ``-`` or ``_`` at either end is dropped
    (``"da_occ_tiny_-_BEV_vertical_DAC"``). The result is a safe name (:func:`safe_name`).

    Raises:
        UnsafeNameError: nothing of ``label`` is left, or it is longer than :data:`MAX_NAME_LENGTH`.
    """
    return safe_name(_NOT_IN_FOLDER_NAME.sub("-", label.replace(" ", "_")).strip("-_"), f"folder for {label!r}")
