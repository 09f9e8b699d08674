"""The one error path of the command line: which exceptions a user's input causes, and how they are printed.

Library code raises the usual Python types (``ValueError`` for a bad value, ``FileNotFoundError``, ...) or one of
occkit's own, each with a message that names the file, record or option. :func:`is_input_error` says which of them
a user can cause; the ``occkit`` command prints those as one line and exits with code 2 (tracebacks only with
``--debug``). This module imports nothing heavy, so ``occkit --help`` stays instant.
"""

from __future__ import annotations

import re

__all__ = ["InputError", "UsageError", "MissingDependencyError", "require_module", "is_input_error", "one_line"]


class InputError(Exception):
    """Base of occkit's errors caused by input (a broken sample, table or export); the message names the source."""


class UsageError(InputError, ValueError):
    """A command-line option is out of range, of the wrong kind, or asks for more than the machine has."""


class MissingDependencyError(InputError, ImportError):
    """An optional extra that a command needs (open3d, albumentations, rerun, onnxruntime) is not installed, or does
    not import; the message says what to install. An ``ImportError``, so ``except ImportError`` still catches it."""


def require_module(module: str, needed_for: str, install: str):
    """Import the optional ``module`` that ``needed_for`` needs, or raise :class:`MissingDependencyError` naming it,
    why it failed (a missing package or a system library it loads) and the ``install`` command."""
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError as error:
        raise MissingDependencyError(f"{needed_for} needs {module} ({error}): {install}") from error


def is_input_error(error: BaseException) -> bool:
    """True for errors a user's input or machine causes (bad values, files, sizes), False for occkit's own bugs."""
    return isinstance(error, (InputError, ValueError, OSError, MemoryError))


def one_line(error: BaseException) -> str:
    """The error's message on one line (multi-line messages are joined; an empty one names the type)."""
    message = _worker_message(str(error))
    text = " ".join(message.split()) if message.strip() else type(error).__name__
    if isinstance(error, MemoryError):
        return f"out of memory ({text}): choose smaller sizes"
    if isinstance(error, OSError) and error.filename is not None and str(error.filename) not in text:
        return f"{text}: {error.filename}"
    return text


#: How PyTorch raises a loader worker's error in the main process: the worker's type and whole traceback as message.
_WORKER_ERROR = re.compile(r"Caught (\w+) in DataLoader worker process \d+\.\nOriginal Traceback")


def _worker_message(message: str) -> str:
    """The original message of a loader worker's error that PyTorch rebuilt (the traceback's last exception line);
    other messages unchanged. occkit's loaders (``occkit.data.loader``) raise the worker's own error; this keeps
    any other loader's error to one line too."""
    caught = _WORKER_ERROR.match(message)
    if caught is None:
        return message
    # The last exception of the traceback follows its last "Traceback" header and the indented frame lines.
    last = message.rsplit("Traceback (most recent call last):\n", 1)[-1].splitlines()
    while last and last[0].startswith(" "):
        last.pop(0)
    text = "\n".join(last)
    # The exception line starts with the type's qualified name ("pkg.module.SampleError: message").
    name, sep, rest = text.partition(": ")
    if name.split(".")[-1] == caught.group(1):
        return rest if sep else ""
    return text
