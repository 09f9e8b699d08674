"""LiDAR sweeps of the synthetic world: one exact ray per beam firing, with dropout, range noise and intensity.

Every firing of :meth:`LidarSpec.ray_directions` is cast from the sensor's origin (``ego2global @ lidar2ego``) as it
stands at the sweep's instant (no motion during the sweep). A return is kept when it lies beyond
:data:`MIN_RANGE` and within the sensor's range and survives a seeded random dropout; its range gets a little
seeded Gaussian noise. Intensity is the surface's reflectivity times the cosine of the incidence angle with a mild
falloff with distance, on nuScenes' 0..255 scale. The ego vehicle has no solid, so no beam hits it.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from occkit.classes import lidarseg_index
from occkit.sim.primitives import GroundMap, Primitives
from occkit.sim.raytrace import GROUND, cast_rays, hit_labels
from occkit.sim.rig import LidarSpec

__all__ = [
    "MIN_RANGE",
    "RANGE_NOISE",
    "GROUND_REFLECTIVITY",
    "MARKING_REFLECTIVITY",
    "FLAT_CATEGORIES",
    "LidarScan",
    "scan_lidar",
    "lidarseg_labels",
]

#: Returns closer than this (m) are discarded, as the sensor's own housing would hide them.
MIN_RANGE = 1.0
#: Standard deviation (m) of the range noise, clipped at 2.5 standard deviations.
RANGE_NOISE = 0.01
#: Reflectivity of the flat classes (Occ3D id -> reflectivity); road paint is much brighter than asphalt.
GROUND_REFLECTIVITY = {11: 0.12, 12: 0.2, 13: 0.25, 14: 0.1}
MARKING_REFLECTIVITY = 0.7
#: nuScenes category of each flat Occ3D class of the painted ground.
FLAT_CATEGORIES = {11: "flat.driveable_surface", 12: "flat.other", 13: "flat.sidewalk", 14: "flat.terrain"}
# Range (m) at which intensity has fallen to half.
_FALLOFF_RANGE = 120.0


@dataclass
class LidarScan:
    """One sweep, ``N`` returns in firing order (azimuth, then ring).

    Attributes:
        points: ``(N, 5)`` float32 ``x, y, z`` (m, LiDAR frame), intensity (0..255), ring index (0..31, lowest beam 0).
        semantic: ``(N,)`` uint8 Occ3D class of the surface hit.
        instance: ``(N,)`` int32 instance id of the solid hit, -1 for the ground.
        distance: ``(N,)`` float32 measured range (m), noise included.
    """

    points: np.ndarray
    semantic: np.ndarray
    instance: np.ndarray
    distance: np.ndarray

    def __len__(self) -> int:
        return int(self.points.shape[0])


def scan_lidar(
    lidar: LidarSpec,
    ego2global: np.ndarray,
    primitives: Primitives,
    ground: GroundMap | None,
    seed: int,
    dropout: float = 0.05,
) -> LidarScan:
    """One sweep of ``lidar`` mounted on the ego vehicle at ``ego2global`` (``(4, 4)``, ego to global).

    Args:
        lidar: the sensor's pose in ego, beams and range.
        ego2global: ``(4, 4)`` pose of the ego vehicle.
        primitives, ground: the world at the sweep's timestamp; ``ground=None`` leaves out the ground plane.
        seed: seed of the dropout and range noise (``np.random.default_rng``), drawn for every firing.
        dropout: fraction of returns lost, in ``[0, 1]``.
    """
    if not 0.0 <= dropout <= 1.0:
        raise ValueError(f"dropout must be in [0, 1], got {dropout}")
    lidar2global = np.asarray(ego2global, np.float64) @ lidar.lidar2ego
    directions, rings = lidar.ray_directions()
    world_directions = directions @ lidar2global[:3, :3].T
    hits = cast_rays(lidar2global[:3, 3], world_directions, lidar.max_range, primitives, ground)
    rng = np.random.default_rng(seed)
    survives = rng.random(len(directions)) >= dropout
    noise = np.clip(rng.normal(0.0, RANGE_NOISE, len(directions)), -2.5 * RANGE_NOISE, 2.5 * RANGE_NOISE)
    keep = survives & (hits.distance > MIN_RANGE) & (hits.distance <= lidar.max_range)

    semantic, instance, marking = hit_labels(hits, primitives, ground)
    reflectivity = np.zeros(len(directions))
    solid = keep & (hits.primitive >= 0)
    reflectivity[solid] = primitives.reflectivity[hits.primitive[solid]]
    on_ground = keep & (hits.primitive == GROUND)
    for flat_class, value in GROUND_REFLECTIVITY.items():
        reflectivity[on_ground & (semantic == flat_class)] = value
    reflectivity[on_ground & marking] = MARKING_REFLECTIVITY

    cos_incidence = np.abs(np.einsum("ij,ij->i", hits.normal[keep], world_directions[keep]))
    distance = hits.distance[keep] + noise[keep]
    falloff = 1.0 / (1.0 + (hits.distance[keep] / _FALLOFF_RANGE) ** 2)
    intensity = np.clip(np.round(255.0 * reflectivity[keep] * cos_incidence * falloff), 0.0, 255.0)
    points = np.concatenate(
        (directions[keep] * distance[:, None], intensity[:, None], rings[keep, None].astype(np.float64)), axis=1
    )
    return LidarScan(points.astype(np.float32), semantic[keep], instance[keep], distance.astype(np.float32))


def lidarseg_labels(scan: LidarScan, categories: tuple[str, ...]) -> np.ndarray:
    """nuScenes-lidarseg labels of a sweep: ``(N,)`` uint8 category index per point (:data:`LIDARSEG_CATEGORIES`).

    A point on a solid takes its object's category (``categories[instance]``, every object's, annotated or not);
    a point on the ground takes the flat category of the ground class under it.
    """
    labels = np.zeros(len(scan), np.uint8)  # 0 = noise, which no kept return is
    solid = scan.instance >= 0
    per_object = np.array([lidarseg_index(c) for c in categories], np.uint8)
    labels[solid] = per_object[scan.instance[solid]]
    for flat_class, category in FLAT_CATEGORIES.items():
        labels[~solid & (scan.semantic == flat_class)] = lidarseg_index(category)
    return labels
