"""Voxel traversal of line segments (Amanatides & Woo), the ray caster behind visibility masks and RayIoU.

Segments are walked in index space ``u = (p - lower) / voxel_size``, the arithmetic of
:meth:`VoxelGrid.world_to_index`, so a point belongs to voxel ``floor(u)`` exactly as there: a point on a face shared
by two voxels belongs to the upper one, and a point on the grid's upper faces is outside. The voxels a segment
visits are exactly those holding at least one of its points. Where a segment crosses an edge or a corner, the axes
crossing upward are stepped first and those crossing downward second, since the crossing point itself already
belongs to the upper voxel on the first kind of axis and still to the current one on the second.

Numpy arrays in and out; numba kernels walk the rays.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from occkit.geometry.grid import VoxelGrid

__all__ = ["traverse_rays", "first_hit"]


@njit(cache=True)
def _coordinate(a, b, ax, clip_axis, entering, shape):
    """Coordinate along ``ax`` of the clipped segment's first (``entering``) or last point.

    The point is ``a`` or ``b`` when ``clip_axis`` is -1, else where the segment meets the grid face across
    ``clip_axis``. It is evaluated as ``a + d (face - a_c) / d_c`` rather than ``a + t d``: one rounding fewer, so a
    point that lies exactly on a voxel face is found on it, and on the clipping face itself it is set exactly.
    """
    if clip_axis == -1:
        return a[ax] if entering else b[ax]
    d_clip = b[clip_axis] - a[clip_axis]
    face = 0.0 if (d_clip > 0.0) == entering else float(shape[clip_axis])
    if ax == clip_axis:
        return face
    return a[ax] + (b[ax] - a[ax]) * (face - a[clip_axis]) / d_clip


@njit(cache=True)
def _end_voxel(a, b, clip_axis, entering, shape, out):
    """Voxel of the first (``entering``) or last point of the segment clipped to the grid.

    Args:
        a, b: ``(3,)`` segment end points in index space.
        clip_axis: axis whose grid face the point lies on, or -1 when the point is ``a`` (entering) or ``b``.
        entering: whether the point starts the clipped segment.
        shape: grid shape ``(X, Y, Z)``.
        out: ``(3,)`` int64, receives the voxel.

    Returns:
        Whether the point itself lies in the grid. When it lies on an upper face (outside), ``out`` is the voxel of
        the segment's points right beside it, inside the grid.
    """
    inside = True
    for ax in range(3):
        if _coordinate(a, b, ax, clip_axis, entering, shape) >= shape[ax]:
            inside = False
    for ax in range(3):
        u = _coordinate(a, b, ax, clip_axis, entering, shape)
        out[ax] = math.floor(u)
        d = b[ax] - a[ax]
        # Beside a point outside on an upper face, the segment's points lie below an integer coordinate they reach
        # on axes it leaves upward (exit) or arrives at downward (entry): those belong to the voxel below.
        below = d < 0.0 if entering else d > 0.0
        if not inside and below and out[ax] == u:
            out[ax] -= 1
        out[ax] = min(max(out[ax], 0), shape[ax] - 1)
    return inside


@njit(cache=True)
def _clip(a, b, shape):
    """Parameter interval ``[t_lo, t_hi]`` of ``a + t (b - a)``, ``t`` in ``[0, 1]``, inside the box ``[0, shape]``.

    Returns:
        ``(t_lo, t_hi, lo_axis, hi_axis)``: the axes whose faces bound the interval (-1 where ``t = 0`` or ``t = 1``
        bounds it); ``t_lo > t_hi`` when the segment misses the grid.
    """
    t_lo, t_hi, lo_axis, hi_axis = 0.0, 1.0, -1, -1
    for ax in range(3):
        d = b[ax] - a[ax]
        if d == 0.0:
            # Parallel to the axis: inside along it only within [0, n), upper face excluded.
            if a[ax] < 0.0 or a[ax] >= shape[ax]:
                return 1.0, 0.0, -1, -1
            continue
        t0 = -a[ax] / d
        t1 = (shape[ax] - a[ax]) / d
        if t0 > t1:
            t0, t1 = t1, t0
        if t0 > t_lo:
            t_lo, lo_axis = t0, ax
        if t1 < t_hi:
            t_hi, hi_axis = t1, ax
    return t_lo, t_hi, lo_axis, hi_axis


@njit(cache=True)
def _visit(occupied, visited, cur, mark, stop_at_occupied):
    """Mark voxel ``cur`` when ``mark``; true when the walk must stop there."""
    if mark:
        visited[cur[0], cur[1], cur[2]] = True
    return stop_at_occupied and occupied[cur[0], cur[1], cur[2]]


@njit(cache=True)
def _walk(occupied, visited, a, b, stop_at_occupied, mark, cur, last, step, left, t_next):
    """Visit the voxels of one segment ``a -> b`` (index space) in order.

    Args:
        occupied: ``(X, Y, Z)`` bool.
        visited: ``(X, Y, Z)`` bool, voxels visited are set when ``mark``.
        a, b: ``(3,)`` float64 segment ends in index space.
        stop_at_occupied: end the walk at the first occupied voxel, included.
        mark: whether to write ``visited``.
        cur, last, step, left: ``(3,)`` int64 scratch, t_next: ``(3,)`` float64 scratch (no allocation per ray).

    Returns:
        ``(i, j, k, t)``: the occupied voxel the walk stopped at and the parameter where the segment enters it, or
        ``(-1, -1, -1, inf)`` when it did not stop.
    """
    shape = occupied.shape
    t_lo, t_hi, lo_axis, hi_axis = _clip(a, b, shape)
    if t_lo > t_hi:
        return -1, -1, -1, np.inf
    inside = _end_voxel(a, b, lo_axis, True, shape, cur)
    if t_lo == t_hi:
        # A single point of the segment touches the grid: a zero-length segment or a grazing contact.
        if inside and _visit(occupied, visited, cur, mark, stop_at_occupied):
            return cur[0], cur[1], cur[2], t_lo
        return -1, -1, -1, np.inf
    _end_voxel(a, b, hi_axis, False, shape, last)
    remaining = 0
    for ax in range(3):
        step[ax] = 1 if last[ax] > cur[ax] else -1
        left[ax] = abs(last[ax] - cur[ax])
        remaining += left[ax]
        if left[ax] > 0:
            t_next[ax] = (cur[ax] + (step[ax] > 0) - a[ax]) / (b[ax] - a[ax])
    if _visit(occupied, visited, cur, mark, stop_at_occupied):
        return cur[0], cur[1], cur[2], t_lo
    # Exactly sum(|last - cur|) unit steps reach the last voxel: rounding can reorder near-ties, never overshoot.
    while remaining > 0:
        t_min = np.inf
        for ax in range(3):
            if left[ax] > 0 and t_next[ax] < t_min:
                t_min = t_next[ax]
        for direction in (1, -1):
            moved = False
            for ax in range(3):
                if left[ax] > 0 and step[ax] == direction and t_next[ax] == t_min:
                    cur[ax] += direction
                    left[ax] -= 1
                    remaining -= 1
                    moved = True
                    t_next[ax] = (cur[ax] + (direction > 0) - a[ax]) / (b[ax] - a[ax])
            if moved and _visit(occupied, visited, cur, mark, stop_at_occupied):
                return cur[0], cur[1], cur[2], max(t_min, t_lo)
    return -1, -1, -1, np.inf


@njit(cache=True)
def _traverse_kernel(occupied, starts, ends, stop_at_occupied, visited):
    work = np.empty((4, 3), np.int64)
    t_next = np.empty(3)
    for r in range(starts.shape[0]):
        _walk(occupied, visited, starts[r], ends[r], stop_at_occupied, True, work[0], work[1], work[2], work[3], t_next)


@njit(cache=True)
def _first_hit_kernel(occupied, starts, ends, index, t_hit):
    work = np.empty((4, 3), np.int64)
    t_next = np.empty(3)
    for r in range(starts.shape[0]):
        # Nothing is marked (mark=False), so occupied stands in for the visited grid.
        i, j, k, t = _walk(
            occupied, occupied, starts[r], ends[r], True, False, work[0], work[1], work[2], work[3], t_next
        )
        index[r, 0], index[r, 1], index[r, 2] = i, j, k
        t_hit[r] = t


def _check_occupied(occupied: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    occupied = np.ascontiguousarray(occupied, dtype=bool)
    if occupied.shape != grid.shape:
        raise ValueError(f"occupied has shape {occupied.shape}, the grid {grid.shape}")
    return occupied


def _points(points: np.ndarray, name: str) -> np.ndarray:
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise ValueError(f"{name} must have shape (R, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise ValueError(f"{name} must be finite")
    return points


def _index_space(points: np.ndarray, grid: VoxelGrid) -> np.ndarray:
    """``(R, 3)`` metric points as continuous voxel coordinates, with world_to_index's arithmetic."""
    return np.ascontiguousarray((points - np.asarray(grid.lower)) / np.asarray(grid.voxel_size))


def traverse_rays(
    occupied: np.ndarray, grid: VoxelGrid, origins: np.ndarray, ends: np.ndarray, stop_at_occupied: bool = False
) -> np.ndarray:
    """Voxels crossed by line segments.

    Args:
        occupied: ``(X, Y, Z)`` bool, the grid's occupancy (read only with ``stop_at_occupied``).
        grid: the voxel grid, frame of ``origins`` and ``ends``.
        origins: ``(R, 3)`` float64 segment starts in metres; may lie outside the grid.
        ends: ``(R, 3)`` float64 segment ends in metres.
        stop_at_occupied: stop each segment at the first occupied voxel it reaches, that voxel included.

    Returns:
        ``(X, Y, Z)`` bool, true for every voxel holding a point of some segment (the voxels of ``origins`` and
        ``ends`` included when inside the grid), up to the first occupied voxel with ``stop_at_occupied``.
    """
    occupied = _check_occupied(occupied, grid)
    origins, ends = _points(origins, "origins"), _points(ends, "ends")
    if origins.shape != ends.shape:
        raise ValueError(f"origins {origins.shape} and ends {ends.shape} must have the same shape")
    visited = np.zeros(grid.shape, dtype=bool)
    _traverse_kernel(occupied, _index_space(origins, grid), _index_space(ends, grid), bool(stop_at_occupied), visited)
    return visited


def first_hit(
    occupied: np.ndarray,
    grid: VoxelGrid,
    origins: np.ndarray,
    directions: np.ndarray,
    max_distance: float | np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """First occupied voxel along rays.

    Args:
        occupied: ``(X, Y, Z)`` bool.
        grid: the voxel grid, frame of the rays.
        origins: ``(R, 3)`` float64 ray origins in metres; may lie outside the grid.
        directions: ``(R, 3)`` float64 unit directions.
        max_distance: metres, one number or ``(R,)``: rays are cast over ``[0, max_distance]``.

    Returns:
        voxel_index: ``(R, 3)`` int64 ``(x, y, z)`` index of the first occupied voxel, ``-1`` rows where none.
        distance: ``(R,)`` float64 metres from the origin to where the ray enters that voxel (0 when the origin lies
        in it), ``inf`` where none.
    """
    occupied = _check_occupied(occupied, grid)
    origins, directions = _points(origins, "origins"), _points(directions, "directions")
    if origins.shape != directions.shape:
        raise ValueError(f"origins {origins.shape} and directions {directions.shape} must have the same shape")
    reach = np.broadcast_to(np.asarray(max_distance, dtype=np.float64), origins.shape[:1])
    if not (np.isfinite(reach).all() and (reach >= 0).all()):
        raise ValueError("max_distance must be finite and >= 0")
    ends = origins + directions * reach[:, None]
    index = np.empty(origins.shape, dtype=np.int64)
    t_hit = np.empty(origins.shape[0])
    _first_hit_kernel(occupied, _index_space(origins, grid), _index_space(ends, grid), index, t_hit)
    hit = index[:, 0] >= 0
    distance = np.where(hit, t_hit * reach, np.inf)
    return index, distance
