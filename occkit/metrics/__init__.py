"""Occupancy metrics of the field's benchmarks, reproducing the official implementations' numbers."""

from occkit.metrics.confusion import (
    OccupancyMetric,
    confusion_matrix,
    distance_bins,
    geometry_iou,
    iou_from_confusion,
    miou,
    surroundocc_metrics,
)
from occkit.metrics.rayiou import RAYIOU_THRESHOLDS, cast_rays_exact, ray_directions, rayiou
from occkit.metrics.realtime import RT_MIOU_RATES, rt_miou, rt_miou_table

__all__ = [
    "OccupancyMetric",
    "confusion_matrix",
    "distance_bins",
    "geometry_iou",
    "iou_from_confusion",
    "miou",
    "rt_miou",
    "rt_miou_table",
    "RT_MIOU_RATES",
    "surroundocc_metrics",
    "RAYIOU_THRESHOLDS",
    "cast_rays_exact",
    "ray_directions",
    "rayiou",
]
