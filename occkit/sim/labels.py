"""Ground-truth occupancy of one key frame of the synthetic world: Occ3D labels, SurroundOcc voxels.

The visibility masks are computed from these labels by :mod:`occkit.geometry.visibility`.

A voxel is occupied by a solid when the solid meets the voxel's cube, tested exactly for every kind (the world's
solids and the label frames only turn about the vertical, so each test splits into a z part and an xy part):

* box: z-interval overlap, and a separating-axis test of the yawed rectangle against the voxel's square;
* cylinder: z-interval overlap, and distance from the axis to the square at most the radius;
* ellipsoid: the smallest ellipsoid-normalised squared distance over the cube is at most 1. It separates into
  ``dz^2 / c^2`` (the centre height clamped to the voxel's z range) plus the minimum of the yawed ellipse's quadratic
  form over the square, which lies at the centre (inside) or on one of the four edges (a clamped 1D minimum each).

Along the grid's axes the voxel is half-open like :meth:`VoxelGrid.world_to_index`, so every point of a solid, its
surface included, falls in an occupied voxel, and no voxel is marked that the solid does not reach (but for a
nanometre of slack against rounding). Voxels inside solids are occupied (solid ground truth, as SurroundOcc's).
Where solids of different classes share a voxel, the class earlier in :data:`CLASS_PRIORITY` wins.

The ground plane ``z = 0`` (global) lies in one voxel layer, painted with the :class:`GroundMap` class in the
majority of ``supersample x supersample`` sub-cells of each voxel (ties to the lower class id), unless a solid
occupies the voxel.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from occkit.classes import OCC3D, THING_CLASSES
from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid
from occkit.sim.primitives import BOX, CYLINDER, GroundMap, Primitives

__all__ = [
    "FREE",
    "CLASS_PRIORITY",
    "occupancy_labels",
    "occupancy_flow_labels",
    "surroundocc_labels",
]

#: Occ3D label of free space.
FREE = OCC3D.empty_index
#: Class ids whose voxels carry their object's instance id.
_THING_IDS = np.array([OCC3D.index(name) for name in THING_CLASSES], dtype=np.uint8)

#: Occ3D class ids from the one that wins a shared voxel to the one that loses it: small dynamic objects, vehicles,
#: manmade, vegetation, then the flat classes.
CLASS_PRIORITY: tuple[int, ...] = tuple(
    OCC3D.index(name)
    for name in (
        "pedestrian",
        "bicycle",
        "motorcycle",
        "traffic_cone",
        "barrier",
        "others",
        "car",
        "construction_vehicle",
        "truck",
        "trailer",
        "bus",
        "manmade",
        "vegetation",
        "sidewalk",
        "other_flat",
        "driveable_surface",
        "terrain",
    )
)

# Rank per label value (higher wins); free space ranks below every class.
_RANK = np.full(256, -1, dtype=np.int16)
_RANK[list(CLASS_PRIORITY)] = np.arange(len(CLASS_PRIORITY), 0, -1)

# Slack on the curved and yawed tests: points sampled on a surface carry ~1e-15 m of rounding, and must still land
# in marked voxels; a nanometre of fattening is invisible at voxel scale.
_SLACK = 1e-9


# ---------------------------------------------------------------------------------------------------- solids
@njit(cache=True)
def _index_range(lo, hi, lower, size, n):
    """Inclusive range of voxel indices along one axis whose half-open cells meet ``[lo, hi]``, clipped to the grid."""
    first = max(math.floor((lo - lower) / size), 0)
    last = min(math.floor((hi - lower) / size), n - 1)
    return first, last


@njit(cache=True)
def _box_meets_square(dx, dy, half_x, half_y, cos_yaw, sin_yaw, hx, hy):
    """Whether a yawed rectangle meets an axis-aligned square, on the rectangle's own axes.

    The square's axes are settled by the index ranges of the caller; these are the two remaining separating axes.

    Args:
        dx, dy: square centre minus rectangle centre (m).
        half_x, half_y: square half sizes (m).
        cos_yaw, sin_yaw: rectangle heading.
        hx, hy: rectangle half length and half width (m).
    """
    along = dx * cos_yaw + dy * sin_yaw
    across = -dx * sin_yaw + dy * cos_yaw
    reach_along = abs(cos_yaw) * half_x + abs(sin_yaw) * half_y
    reach_across = abs(sin_yaw) * half_x + abs(cos_yaw) * half_y
    return abs(along) <= hx + reach_along + _SLACK and abs(across) <= hy + reach_across + _SLACK


@njit(cache=True)
def _ellipse_square_min(x0, x1, y0, y1, qa, qb, qc):
    """Minimum of ``qa x^2 + 2 qb x y + qc y^2`` (positive definite) over the square ``[x0, x1] x [y0, y1]``.

    Coordinates are relative to the ellipse centre. A convex quadratic with its minimum (the origin) outside the
    square reaches its minimum over the square on the boundary: the best of the four edges, each a clamped 1D minimum.
    """
    if x0 <= 0.0 <= x1 and y0 <= 0.0 <= y1:
        return 0.0
    best = np.inf
    for x in (x0, x1):
        y = min(max(-qb * x / qc, y0), y1)
        best = min(best, qa * x * x + 2.0 * qb * x * y + qc * y * y)
    for y in (y0, y1):
        x = min(max(-qb * y / qa, x0), x1)
        best = min(best, qa * x * x + 2.0 * qb * x * y + qc * y * y)
    return best


@njit(cache=True)
def _claim(labels, owner, rank, i, j, k, cls, p):
    if rank[cls] > rank[labels[i, j, k]]:
        labels[i, j, k] = cls
        owner[i, j, k] = p


@njit(cache=True)
def _paint_solids(labels, owner, rank, kind, center, half_size, yaw, semantic, lower, size):
    """Write every solid's class into the voxels it meets, where it outranks the current label.

    Args:
        labels: ``(X, Y, Z)`` uint8, updated in place.
        owner: ``(X, Y, Z)`` int32, updated in place: the index of the solid whose class a voxel took.
        rank: ``(256,)`` int16 priority of each label value.
        kind, center, half_size, yaw, semantic: the :class:`Primitives` fields in the grid's frame.
        lower, size: ``(3,)`` grid lower corner and voxel size (m).
    """
    nx, ny, nz = labels.shape
    half_x, half_y = 0.5 * size[0], 0.5 * size[1]
    for p in range(kind.shape[0]):
        cx, cy, cz = center[p, 0], center[p, 1], center[p, 2]
        hx, hy, hz = half_size[p, 0], half_size[p, 1], half_size[p, 2]
        cos_yaw, sin_yaw = math.cos(yaw[p]), math.sin(yaw[p])
        if kind[p] == BOX:
            ex = abs(cos_yaw) * hx + abs(sin_yaw) * hy
            ey = abs(sin_yaw) * hx + abs(cos_yaw) * hy
        elif kind[p] == CYLINDER:
            ex = ey = hx
        else:
            ex = math.sqrt((hx * cos_yaw) ** 2 + (hy * sin_yaw) ** 2)
            ey = math.sqrt((hx * sin_yaw) ** 2 + (hy * cos_yaw) ** 2)
        i0, i1 = _index_range(cx - ex, cx + ex, lower[0], size[0], nx)
        j0, j1 = _index_range(cy - ey, cy + ey, lower[1], size[1], ny)
        k0, k1 = _index_range(cz - hz, cz + hz, lower[2], size[2], nz)
        if i0 > i1 or j0 > j1 or k0 > k1:
            continue
        # The ellipse's quadratic form (x, y) -> (along / hx)^2 + (across / hy)^2.
        qa = (cos_yaw / hx) ** 2 + (sin_yaw / hy) ** 2
        qb = cos_yaw * sin_yaw * (1.0 / hx**2 - 1.0 / hy**2)
        qc = (sin_yaw / hx) ** 2 + (cos_yaw / hy) ** 2
        cls = semantic[p]
        for i in range(i0, i1 + 1):
            x0 = lower[0] + i * size[0]
            for j in range(j0, j1 + 1):
                y0 = lower[1] + j * size[1]
                if kind[p] == BOX:
                    dx, dy = x0 + half_x - cx, y0 + half_y - cy
                    if _box_meets_square(dx, dy, half_x, half_y, cos_yaw, sin_yaw, hx, hy):
                        for k in range(k0, k1 + 1):
                            _claim(labels, owner, rank, i, j, k, cls, p)
                elif kind[p] == CYLINDER:
                    dx = min(max(cx, x0), x0 + size[0]) - cx
                    dy = min(max(cy, y0), y0 + size[1]) - cy
                    if dx * dx + dy * dy <= (hx + _SLACK) ** 2:
                        for k in range(k0, k1 + 1):
                            _claim(labels, owner, rank, i, j, k, cls, p)
                else:
                    flat = _ellipse_square_min(x0 - cx, x0 + size[0] - cx, y0 - cy, y0 + size[1] - cy, qa, qb, qc)
                    if flat > 1.0 + _SLACK:
                        continue
                    for k in range(k0, k1 + 1):
                        z0 = lower[2] + k * size[2]
                        dz = (min(max(cz, z0), z0 + size[2]) - cz) / hz
                        if flat + dz * dz <= 1.0 + _SLACK:
                            _claim(labels, owner, rank, i, j, k, cls, p)


# ---------------------------------------------------------------------------------------------------- frames
def _level_pose(frame2global: np.ndarray, name: str) -> tuple[float, np.ndarray]:
    """Yaw (rad) and ``(3,)`` translation of a pose that only turns about the vertical; ValueError otherwise."""
    pose = np.asarray(frame2global, dtype=np.float64)
    if pose.shape != (4, 4):
        raise ValueError(f"{name} must be a (4, 4) matrix, got {pose.shape}")
    rotation = pose[:3, :3]
    yaw = math.atan2(rotation[1, 0], rotation[0, 0])
    c, s = math.cos(yaw), math.sin(yaw)
    level = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if not np.allclose(rotation, level, atol=1e-6):
        tilt = math.degrees(math.acos(min(1.0, abs(rotation[2, 2]))))
        raise ValueError(
            f"{name} must be a rotation about z (a level frame on flat ground); it tilts by {tilt:.4g} deg"
        )
    return yaw, pose[:3, 3].copy()


def _check_primitives(primitives: Primitives) -> None:
    if len(primitives) and (primitives.half_size <= 0).any():
        raise ValueError("primitives must have positive half sizes")
    if len(primitives) and (primitives.semantic >= FREE).any():
        raise ValueError(f"primitive classes must be Occ3D ids 0..{FREE - 1}")


def _paint_ground(
    labels: np.ndarray, ground: GroundMap, yaw: float, translation: np.ndarray, grid: VoxelGrid, supersample: int
) -> None:
    """Write the GroundMap's majority class into the voxel layer holding the plane ``z_global = 0``."""
    nx, ny, nz = grid.shape
    # The frame is level, so the ground stays horizontal in it, at the height of the global origin.
    layer = math.floor((-translation[2] - grid.lower[2]) / grid.voxel_size[2])
    if not 0 <= layer < nz:
        return
    offsets = (np.arange(supersample) + 0.5) / supersample
    xs = grid.lower[0] + (np.arange(nx)[:, None] + offsets).ravel() * grid.voxel_size[0]
    ys = grid.lower[1] + (np.arange(ny)[:, None] + offsets).ravel() * grid.voxel_size[1]
    x, y = np.meshgrid(xs, ys, indexing="ij")
    c, s = math.cos(yaw), math.sin(yaw)
    xy_global = np.stack((c * x - s * y + translation[0], s * x + c * y + translation[1]), axis=-1)
    cells = ground.lookup(xy_global.reshape(-1, 2)).reshape(nx, supersample, ny, supersample)
    cells = cells.transpose(0, 2, 1, 3).reshape(nx, ny, -1)
    classes = np.unique(cells)
    votes = np.stack([(cells == cls).sum(axis=-1) for cls in classes], axis=-1)
    labels[:, :, layer] = classes[votes.argmax(axis=-1)]


def _frame_labels(
    primitives: Primitives,
    ground: GroundMap,
    frame2global: np.ndarray,
    grid: VoxelGrid,
    supersample: int,
    name: str,
) -> tuple[np.ndarray, np.ndarray, float]:
    """Dense labels over ``grid`` in the frame of the level pose ``frame2global``.

    Returns:
        ``(labels, owner, yaw)``: ``(X, Y, Z)`` uint8 Occ3D labels, ``(X, Y, Z)`` int32 index into ``primitives`` of
        the solid each voxel's class came from (-1: free or ground), and the frame's yaw in the global frame (rad).
    """
    if supersample < 1:
        raise ValueError(f"supersample must be >= 1, got {supersample}")
    _check_primitives(primitives)
    yaw, translation = _level_pose(frame2global, name)
    labels = np.full(grid.shape, FREE, dtype=np.uint8)
    owner = np.full(grid.shape, -1, dtype=np.int32)
    _paint_ground(labels, ground, yaw, translation, grid, supersample)
    c, s = math.cos(yaw), math.sin(yaw)
    offset = primitives.center - translation
    center = np.stack(
        (c * offset[:, 0] + s * offset[:, 1], -s * offset[:, 0] + c * offset[:, 1], offset[:, 2]), axis=-1
    )
    _paint_solids(
        labels,
        owner,
        _RANK,
        np.ascontiguousarray(primitives.kind, dtype=np.int8),
        np.ascontiguousarray(center),
        np.ascontiguousarray(primitives.half_size, dtype=np.float64),
        np.ascontiguousarray(primitives.yaw - yaw, dtype=np.float64),
        np.ascontiguousarray(primitives.semantic, dtype=np.uint8),
        np.asarray(grid.lower),
        np.asarray(grid.voxel_size),
    )
    return labels, owner, yaw


# ---------------------------------------------------------------------------------------------------- labels
def occupancy_labels(
    primitives: Primitives,
    ground: GroundMap,
    ego2global: np.ndarray,
    grid: VoxelGrid = OCC3D_GRID,
    supersample: int = 2,
) -> np.ndarray:
    """Occ3D-style semantic occupancy of the world in the ego frame.

    Args:
        primitives: the world's solids at the key frame's instant (global frame).
        ground: the painted ground plane.
        ego2global: ``(4, 4)`` float64 ego pose; must only turn about z (the ego stays level on flat ground).
        grid: the label grid, in the ego frame.
        supersample: sub-cells per voxel edge voting for the ground class.

    Returns:
        ``(X, Y, Z)`` uint8, ``labels[i, j, k]`` the class of voxel ``(x_i, y_j, z_k)``: Occ3D ids 0..16, 17 free.
    """
    return _frame_labels(primitives, ground, ego2global, grid, supersample, "ego2global")[0]


def occupancy_flow_labels(
    primitives: Primitives,
    velocity: np.ndarray,
    ground: GroundMap,
    ego2global: np.ndarray,
    grid: VoxelGrid = OCC3D_GRID,
    supersample: int = 2,
    instances: bool = False,
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Occ3D-style semantic occupancy and its flow in the ego frame (the challenge's ``flow`` of OpenOcc v2).

    A voxel's flow is the velocity of the solid that gave it its class: its object's box velocity, the same for
    every voxel of the object (the benchmark's flow comes from box velocities, so a turning object's rotation is not
    in it), turned into the ego frame. It is the object's own velocity, not relative to the moving ego: zero on
    ground and free voxels and on static solids.

    Args:
        primitives: the world's solids at the key frame's instant (global frame).
        velocity: ``(P, 2)`` float64 global ``vx, vy`` (m/s) of each solid (:meth:`World.primitive_velocities`).
        ground, ego2global, grid, supersample: as :func:`occupancy_labels`.
        instances: also return each voxel's object: the world's object id + 1 (``primitives.instance``, the same
            for an object in every frame) where the voxel's class is a thing class (:data:`THING_CLASSES`), 0 for
            stuff, ground and free space.

    Returns:
        ``(labels, flow)``: the labels of :func:`occupancy_labels` and ``(X, Y, Z, 2)`` float32 ego-frame
        ``vx, vy`` (m/s); with ``instances``, also the ``(X, Y, Z)`` int32 instance ids.
    """
    velocity = np.asarray(velocity, dtype=np.float64)
    if velocity.shape != (len(primitives), 2):
        raise ValueError(f"velocity must have shape ({len(primitives)}, 2), one row per solid; got {velocity.shape}")
    labels, owner, yaw = _frame_labels(primitives, ground, ego2global, grid, supersample, "ego2global")
    c, s = math.cos(yaw), math.sin(yaw)
    # Global to ego is the transpose of the ego's rotation about z.
    ego_velocity = np.stack((c * velocity[:, 0] + s * velocity[:, 1], -s * velocity[:, 0] + c * velocity[:, 1]), -1)
    flow = np.zeros((*grid.shape, 2), dtype=np.float32)
    solid = owner >= 0
    flow[solid] = ego_velocity[owner[solid]]
    if not instances:
        return labels, flow
    ids = np.zeros(grid.shape, dtype=np.int32)
    thing = solid & np.isin(labels, _THING_IDS)
    ids[thing] = primitives.instance[owner[thing]].astype(np.int32) + 1
    return labels, flow, ids


def surroundocc_labels(
    primitives: Primitives,
    ground: GroundMap,
    lidar2global: np.ndarray,
    grid: VoxelGrid = SURROUNDOCC_GRID,
    supersample: int = 2,
) -> np.ndarray:
    """SurroundOcc-style sparse occupancy of the world in the LiDAR frame.

    The same voxel test as :func:`occupancy_labels`, over SurroundOcc's grid in the LiDAR frame (x right, y forward,
    z up, 1.84 m above the ground for LIDAR_TOP, where the ground plane is at ``z = -1.84``).

    Args:
        primitives: the world's solids (global frame).
        ground: the painted ground plane.
        lidar2global: ``(4, 4)`` float64 LiDAR pose; must only turn about z.
        grid: the label grid, in the LiDAR frame.
        supersample: sub-cells per voxel edge voting for the ground class.

    Returns:
        ``(N, 4)`` int64 rows ``(x_idx, y_idx, z_idx, label)`` of the occupied voxels in C order of the index, free
        voxels omitted. Labels 1..16 are the Occ3D classes of the same ids; Occ3D "others" (0) is written as 0, the
        value SurroundOcc's files give to noise.
    """
    labels = _frame_labels(primitives, ground, lidar2global, grid, supersample, "lidar2global")[0]
    index = np.argwhere(labels != FREE)
    return np.concatenate((index, labels[tuple(index.T)][:, None]), axis=1).astype(np.int64)
