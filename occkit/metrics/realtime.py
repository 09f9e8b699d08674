"""DA-Occ's real-time-aware accuracy: RT-mIoU@K, mIoU discounted by how far a model falls short of K frames/s.

``RT-mIoU@K = mIoU * min(FPS / K, 1)``: a model at or above K fps keeps its mIoU, a slower one loses the fraction of
the frame rate it misses. DA-Occ reports K = 10, 15 and 20 (nuScenes key frames come at 2 Hz, sweeps at 20 Hz).
The result has the unit of the given mIoU (a fraction or percent).

    >>> rt_miou(34.38, fps=7.5, k=15)
    17.19
"""

from __future__ import annotations

from collections.abc import Sequence

__all__ = ["RT_MIOU_RATES", "rt_miou", "rt_miou_table"]

#: The frame rates K of DA-Occ's table.
RT_MIOU_RATES = (10, 15, 20)


def rt_miou(miou: float, fps: float, k: float) -> float:
    """DA-Occ's RT-mIoU@K: mIoU scaled down by how far the frame rate falls short of K fps, ``miou * min(fps/K, 1)``."""
    if k <= 0:
        raise ValueError(f"K must be a positive frame rate, got {k}")
    if fps < 0:
        raise ValueError(f"fps must be non-negative, got {fps}")
    return miou * min(fps / k, 1.0)


def rt_miou_table(miou: float, fps: float, rates: Sequence[float] = RT_MIOU_RATES) -> dict[str, float]:
    """``{"rt_miou@10": ..., "rt_miou@15": ..., "rt_miou@20": ...}`` (keys follow ``rates``)."""
    return {f"rt_miou@{k:g}": rt_miou(miou, fps, k) for k in rates}
