"""The zoo's table of entries: each family's presets (``occkit/zoo/<family>.py``) register themselves with
:func:`preset`, and :mod:`occkit.zoo` reads the table."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from occkit.experiment import Experiment

__all__ = ["Entry", "ENTRIES", "preset"]


@dataclass(frozen=True)
class Entry:
    """One zoo entry: its architecture and the function that returns its whole experiment (named after the entry;
    its docstring describes it, and ``occkit.experiment.reproduces`` marks its paper row)."""

    architecture: str
    make: Callable[[], Experiment]


#: Entry name -> entry, in registration order.
ENTRIES: dict[str, Entry] = {}


def preset(architecture: str) -> Callable[[Callable[[], Experiment]], Callable[[], Experiment]]:
    """Register the decorated function as the zoo entry of its name, an experiment of ``architecture``.

    Raises:
        ValueError: an entry of that name is already registered.
    """

    def register(make: Callable[[], Experiment]) -> Callable[[], Experiment]:
        if make.__name__ in ENTRIES:
            raise ValueError(f"zoo entry {make.__name__!r} is registered twice")
        ENTRIES[make.__name__] = Entry(architecture, make)
        return make

    return register
