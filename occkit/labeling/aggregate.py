"""Aggregating a scene's LiDAR sweeps: static points in the world, each object's points in its own box.

The steps follow the published pipelines (Occ3D, Sec. 3.2; SurroundOcc's ``generate_occupancy_nuscenes``):

1. Every sweep's points go to the global frame; points on the ego vehicle's body are dropped.
2. Points inside an annotated box (enlarged by ``box_scale`` as SurroundOcc does) belong to that object, stored in
   the box's frame so they can be placed back wherever the object is at a key frame. In a key frame, a point
   belongs to the object when its lidarseg class is the box's class; in a sweep without labels, when it lies above
   the box's lowest ``ground_clearance`` metres (below is the ground the object stands on). A point inside several
   boxes goes to the smallest.
3. The other points are the static scene. Key-frame points keep their lidarseg class; a key-frame point of a class
   that moves (vehicles, pedestrians, cycles) outside every box is an object that was not annotated (beyond the
   annotation range) and is dropped, since it cannot be placed at other times.
4. Static points of non-key sweeps take the class of the nearest key-frame point (Occ3D's KNN step) within
   ``knn_radius``; they are dropped when none is that near or when the nearest is a dropped moving-class point.
"""

from __future__ import annotations

from collections import defaultdict
from dataclasses import dataclass

import numpy as np

from occkit.classes import OCC3D
from occkit.labeling.sources import Boxes, ScenePlan, read_sweep

__all__ = ["MOVING_CLASSES", "FLAT_CLASSES", "EGO_BODY", "AggregateConfig", "SceneCloud", "aggregate_scene",
           "points_in_boxes", "object_membership"]  # fmt: skip

#: Occ3D classes of things that move: their points outside every box cannot be placed at other instants.
MOVING_CLASSES = frozenset(OCC3D.index(n) for n in ("bicycle", "bus", "car", "construction_vehicle", "motorcycle",
                                                    "pedestrian", "trailer", "truck"))  # fmt: skip
#: Occ3D classes of the ground.
FLAT_CLASSES = frozenset(OCC3D.index(n) for n in ("driveable_surface", "other_flat", "sidewalk", "terrain"))
#: The ego vehicle's body in the ego frame (x forward from the rear axle, z up from the ground), lower and upper
#: corners (m): a nuScenes Renault Zoe with a margin; returns inside it are the car itself.
EGO_BODY = ((-1.0, -1.0, 0.1), (3.3, 1.0, 2.2))


@dataclass(frozen=True)
class AggregateConfig:
    """How sweeps are split and labelled (the defaults follow SurroundOcc and Occ3D)."""

    box_scale: float = 1.1
    """Boxes are enlarged by this factor in every dimension to take in all of an object's points (SurroundOcc)."""
    ground_clearance: float = 0.15
    """Metres above a box's bottom (the annotated box's, not the enlarged one's) below which an unlabelled sweep
    point is ground, not the object."""
    knn_radius: float = 0.5
    """A non-key sweep point takes the class of the nearest key-frame point within this distance (m)."""

    def __post_init__(self) -> None:
        if not self.box_scale >= 1.0:
            raise ValueError(f"box_scale must be >= 1, got {self.box_scale}")
        if self.ground_clearance < 0 or not self.knn_radius > 0:
            raise ValueError("ground_clearance must be >= 0 and knn_radius > 0")


@dataclass
class SceneCloud:
    """A scene's aggregated, labelled points.

    Attributes:
        origin: ``(3,)`` float64 global position the static points are stored relative to (keeps float32 exact).
        static_xyz: ``(S, 3)`` float32 static points, global frame minus ``origin``.
        static_label: ``(S,)`` uint8 their Occ3D classes.
        objects: instance id -> (``(P, 3)`` float32 points in the box frame, ``(P,)`` uint8 classes).
        rays: per sweep, ``(sensor origin (3,), returns (N, 3))`` float32, global minus ``origin``: every return,
            for casting the LiDAR visibility mask.
        counts: points kept and dropped by each rule.
    """

    origin: np.ndarray
    static_xyz: np.ndarray
    static_label: np.ndarray
    objects: dict[int, tuple[np.ndarray, np.ndarray]]
    rays: list[tuple[np.ndarray, np.ndarray]]
    counts: dict[str, int]


def points_in_boxes(points: np.ndarray, boxes: Boxes, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Which box each point lies in, and where in it.

    Args:
        points: ``(N, 3)`` float64, global frame.
        boxes: the boxes; each is enlarged by ``scale`` about its centre.
        scale: enlargement factor.

    Returns:
        ``(N,)`` int64 index of the box holding each point, -1 for none (a point in several boxes goes to the
        smallest), and ``(N, 3)`` float64 the point in that box's frame (meaningless where the index is -1).
    """
    owner = np.full(len(points), -1, np.int64)
    local = np.zeros_like(points)
    if len(boxes) == 0 or len(points) == 0:
        return owner, local
    half = boxes.size[:, [1, 0, 2]] * (scale / 2)  # (length, width, height) along the box's x, y, z
    buckets = _Buckets(points[:, :2])
    for b in np.argsort(-np.prod(boxes.size, axis=1), kind="stable"):  # largest first: smaller boxes overwrite
        near = buckets.near(boxes.center[b, :2], float(np.linalg.norm(half[b])))
        if near.size == 0:
            continue
        inside = (points[near] - boxes.center[b]) @ boxes.rotation[b]
        hit = (np.abs(inside) <= half[b]).all(axis=1)
        owner[near[hit]] = b
        local[near[hit]] = inside[hit]
    return owner, local


class _Buckets:
    """Points sorted into square cells of the ground plane, to find those near a place without a full scan."""

    def __init__(self, xy: np.ndarray, cell: float = 4.0) -> None:
        self.cell = cell
        index = np.floor(xy / cell).astype(np.int64)
        self.low = index.min(axis=0)
        self.rows = int(index[:, 1].max() - self.low[1]) + 1
        key = (index[:, 0] - self.low[0]) * self.rows + (index[:, 1] - self.low[1])
        self.order = np.argsort(key, kind="stable")
        self.keys = key[self.order]
        self.columns = int(index[:, 0].max() - self.low[0]) + 1

    def near(self, centre: np.ndarray, radius: float) -> np.ndarray:
        """Indices of the points in the cells the square ``centre +- radius`` touches (a superset of those in it),
        in increasing order."""
        lo = np.floor((centre - radius) / self.cell).astype(np.int64) - self.low
        hi = np.floor((centre + radius) / self.cell).astype(np.int64) - self.low
        lo_y, hi_y = max(int(lo[1]), 0), min(int(hi[1]), self.rows - 1)
        if lo_y > hi_y:
            return np.zeros(0, np.int64)
        parts = []
        for column in range(max(int(lo[0]), 0), min(int(hi[0]), self.columns - 1) + 1):
            start, stop = np.searchsorted(self.keys, [column * self.rows + lo_y, column * self.rows + hi_y + 1])
            parts.append(self.order[start:stop])
        return np.sort(np.concatenate(parts)) if parts else np.zeros(0, np.int64)


def object_membership(
    owner: np.ndarray, local: np.ndarray, boxes: Boxes, labels: np.ndarray | None, config: AggregateConfig
) -> np.ndarray:
    """``(N,)`` bool: the points that belong to the object whose box holds them (module doc, step 2).

    Args:
        owner, local: :func:`points_in_boxes`'s output for the sweep's points and ``boxes``.
        boxes: the boxes at the sweep's instant.
        labels: ``(N,)`` Occ3D classes of a key frame's points, or None for a sweep without labels.
        config: the box enlargement and the ground clearance.
    """
    inside = owner >= 0
    mine = np.zeros(len(owner), bool)
    if labels is not None:
        mine[inside] = labels[inside] == boxes.label[owner[inside]]
    else:
        bottom = -boxes.size[owner[inside], 2] / 2  # the annotated box's bottom, not the enlarged one's
        mine[inside] = local[inside, 2] > bottom + config.ground_clearance
    return mine


def _transform(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def aggregate_scene(plan: ScenePlan, lookup: np.ndarray, config: AggregateConfig = AggregateConfig()) -> SceneCloud:  # noqa: B008
    """Read every sweep of ``plan`` and aggregate it (module doc). ``lookup`` maps lidarseg indices to Occ3D ids."""
    origin = plan.sweeps[0].ego2global[:3, 3].copy()
    counts: dict[str, int] = defaultdict(int)
    key_xyz, key_label, sweep_xyz = [], [], []
    object_parts: dict[int, list[tuple[np.ndarray, np.ndarray]]] = defaultdict(list)
    rays = []
    low, high = np.asarray(EGO_BODY[0]), np.asarray(EGO_BODY[1])
    for sweep in plan.sweeps:
        points, labels = read_sweep(plan, sweep, lookup)
        in_ego = _transform(sweep.lidar2ego, points)
        body = ((in_ego >= low) & (in_ego <= high)).all(axis=1)
        counts["ego_body"] += int(body.sum())
        in_ego = in_ego[~body]
        labels = labels[~body] if labels is not None else None
        world = _transform(sweep.ego2global, in_ego)
        sensor = _transform(sweep.ego2global @ sweep.lidar2ego, np.zeros((1, 3)))[0]
        rays.append(((sensor - origin).astype(np.float32), (world - origin).astype(np.float32)))
        counts["returns"] += len(points)

        owner, local = points_in_boxes(world, sweep.boxes, config.box_scale)
        mine = object_membership(owner, local, sweep.boxes, labels, config)
        for b in np.unique(owner[mine]):
            sel = mine & (owner == b)
            part_labels = labels[sel] if labels is not None else np.full(int(sel.sum()), sweep.boxes.label[b], np.uint8)
            object_parts[int(sweep.boxes.instance[b])].append((local[sel].astype(np.float32), part_labels))
        counts["object"] += int(mine.sum())

        rest = world[~mine] - origin
        if labels is not None:
            key_xyz.append(rest)
            key_label.append(labels[~mine])
        else:
            sweep_xyz.append(rest)

    key_xyz_all = np.concatenate(key_xyz) if key_xyz else np.zeros((0, 3))
    key_label_all = np.concatenate(key_label) if key_label else np.zeros(0, np.uint8)
    moving = np.isin(key_label_all, list(MOVING_CLASSES))
    ignored = key_label_all == OCC3D.ignore_index
    counts["moving_outside_boxes"] = int(moving.sum())
    counts["ignored_class"] = int(ignored.sum())
    static_xyz, static_label = [key_xyz_all[~moving & ~ignored]], [key_label_all[~moving & ~ignored]]
    counts["static_key"] = len(static_label[0])

    swept = np.concatenate(sweep_xyz) if sweep_xyz else np.zeros((0, 3))
    if len(swept) and len(key_xyz_all):
        from scipy.spatial import cKDTree

        reference = ~ignored
        distance, nearest = cKDTree(key_xyz_all[reference]).query(swept, k=1, distance_upper_bound=config.knn_radius)
        found = np.isfinite(distance)
        label = np.full(len(swept), OCC3D.ignore_index, np.uint8)
        label[found] = key_label_all[reference][nearest[found]]
        keep = found & ~np.isin(label, list(MOVING_CLASSES))
        counts["sweep_unlabelled"] = int((~found).sum())
        counts["sweep_moving_neighbour"] = int((found & ~keep).sum())
        counts["static_sweep"] = int(keep.sum())
        static_xyz.append(swept[keep])
        static_label.append(label[keep])
    objects = {
        instance: (np.concatenate([p for p, _ in parts]), np.concatenate([lab for _, lab in parts]))
        for instance, parts in sorted(object_parts.items())
    }
    return SceneCloud(
        origin=origin,
        static_xyz=np.concatenate(static_xyz).astype(np.float32),
        static_label=np.concatenate(static_label).astype(np.uint8),
        objects=objects,
        rays=rays,
        counts=dict(counts),
    )
