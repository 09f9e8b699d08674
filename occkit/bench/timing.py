"""Wall times on a device: one call with the device's queue drained, two timings in interleaved pairs, percentiles."""

from __future__ import annotations

import time
from collections.abc import Callable

import numpy as np
import torch

__all__ = ["synchronizer", "timed", "paired_times", "percentile"]


def synchronizer(device: torch.device) -> Callable[[], None]:
    """A call that waits for ``device``'s queued work (CUDA); nothing to wait for on a CPU."""
    if device.type == "cuda":
        return lambda: torch.cuda.synchronize(device)
    return lambda: None


def timed(run: Callable[[], object], synchronize: Callable[[], None]) -> float:
    """Seconds of one ``run()``, with the device's queue drained before and after."""
    synchronize()
    start = time.perf_counter()
    run()
    synchronize()
    return time.perf_counter() - start


def paired_times(first: Callable[[], float], second: Callable[[], float], pairs: int) -> tuple[list, list]:
    """Two timings (callables returning seconds) run in ``pairs`` interleaved pairs, the order alternating from pair
    to pair, so that a change of machine load hits both alike; the two lists of seconds."""
    times: tuple[list, list] = ([], [])
    for index in range(pairs):
        for side in (0, 1) if index % 2 == 0 else (1, 0):
            times[side].append((first, second)[side]())
    return times


def percentile(values: list[float], q: float) -> float:
    """The ``q``-th percentile (0 to 100) of ``values``, linearly interpolated."""
    return float(np.percentile(np.asarray(values), q))
