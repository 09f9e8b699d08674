"""The benchmark's input: one key frame at a model's own input setting, from a dataset or the benchmark's world."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from occkit import zoo
from occkit.engine.reference_frame import SyntheticWorld, load_reference_frame
from occkit.types import Batch

__all__ = ["DEFAULT_DATA", "WORLD", "load_sample"]

#: Where the benchmark world is simulated when no dataset is given.
DEFAULT_DATA = Path("data/bench-1600x900")

#: The benchmark world: the papers' 1600x900 images and three key frames at 2 Hz, so that the last one has 20 LiDAR
#: sweeps behind it, more than any model asks for; simulated once into :data:`DEFAULT_DATA`, kept for later runs.
WORLD = SyntheticWorld(image_size=(1600, 900), frames=3, folder=DEFAULT_DATA)


def load_sample(model: str, data: str | Path | None = None, batch_size: int = 1,
                log: Callable[[str], None] = print) -> Batch:  # fmt: skip
    """The last key frame of ``data`` at ``model``'s input setting (test transform), repeated ``batch_size`` times.

    ``data`` None uses :data:`DEFAULT_DATA`, simulating :data:`WORLD` first if absent; any other missing folder is
    an error.
    """
    return load_reference_frame(zoo.experiment(model).data, data, WORLD, batch_size=batch_size, log=log).batch
