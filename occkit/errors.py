"""The one error path of the command line: which exceptions a user's input causes, and how they are printed.

Library code raises the usual Python types (``ValueError`` for a bad value, ``FileNotFoundError``, ...) or one of
occkit's own, each with a message that names the file, record or option. :func:`is_input_error` says which of them
a user can cause; the ``occkit`` command prints those as one line and exits with code 2 (tracebacks only with
``--debug``). This module imports nothing heavy, so ``occkit --help`` stays instant.
"""

from __future__ import annotations

__all__ = ["InputError", "UsageError", "is_input_error", "one_line"]


class InputError(Exception):
    """Base of occkit's errors caused by input (a broken sample, table or export); the message names the source."""


class UsageError(InputError, ValueError):
    """A command-line option is out of range, of the wrong kind, or asks for more than the machine has."""


def is_input_error(error: BaseException) -> bool:
    """True for errors a user's input or machine causes (bad values, files, sizes), False for occkit's own bugs."""
    return isinstance(error, (InputError, ValueError, OSError, MemoryError))


def one_line(error: BaseException) -> str:
    """The error's message on one line (multi-line messages are joined; an empty one names the type)."""
    text = " ".join(str(error).split()) if str(error).strip() else type(error).__name__
    if isinstance(error, MemoryError):
        return f"out of memory ({text}): choose smaller sizes"
    if isinstance(error, OSError) and error.filename is not None and str(error.filename) not in text:
        return f"{text}: {error.filename}"
    return text
