"""Voxel traversal against an exact rational reference: floor semantics, faces, corners, clipping, stopping."""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.geometry.raycast import first_hit, traverse_rays

# A small grid with exactly representable bounds and voxel size, 6 x 5 x 4 voxels.
GRID = VoxelGrid((-1.5, -1.0, -0.5, 1.5, 1.5, 1.5), 0.5)


def _voxel_intervals(origin, end, grid: VoxelGrid, margin: float | None = None):
    """Exact parameter intervals of ``origin + t (end - origin)``, ``t`` in [0, 1], inside each voxel.

    Index-space coordinates are computed in float64 exactly as the grid does, then handled as exact fractions.
    With a ``margin`` (index units) the voxels are closed boxes grown by it, or shrunk where it is negative;
    without, half-open like ``world_to_index``.

    Returns:
        ``{(i, j, k): (lo, lo_closed, hi)}`` for every voxel the segment meets, with the interval's ends.
    """
    lower, size = np.asarray(grid.lower), np.asarray(grid.voxel_size)
    a = [Fraction(float(v)) for v in (np.asarray(origin, np.float64) - lower) / size]
    b = [Fraction(float(v)) for v in (np.asarray(end, np.float64) - lower) / size]
    closed = margin is not None
    grow = Fraction(margin) if closed else Fraction(0)
    result = {}
    for index in np.ndindex(*grid.shape):
        lo, lo_closed, hi, hi_closed = Fraction(0), True, Fraction(1), True
        for ax in range(3):
            d = b[ax] - a[ax]
            cell_lo, cell_hi = index[ax] - grow, index[ax] + 1 + grow
            if d == 0:
                if not (cell_lo <= a[ax] and (a[ax] <= cell_hi if closed else a[ax] < cell_hi)):
                    lo, hi = Fraction(1), Fraction(0)
                continue
            t0, t1 = (cell_lo - a[ax]) / d, (cell_hi - a[ax]) / d
            # At t0 the segment is on the cell's lower face, always in the cell; at t1 on its upper face, which a
            # half-open cell excludes.
            t0_closed, t1_closed = True, closed
            if t0 > t1:
                t0, t1, t0_closed, t1_closed = t1, t0, t1_closed, t0_closed
            if t0 > lo or (t0 == lo and not t0_closed):
                lo, lo_closed = t0, t0_closed
            if t1 < hi or (t1 == hi and not t1_closed):
                hi, hi_closed = t1, t1_closed
        if lo < hi or (lo == hi and lo_closed and hi_closed):
            result[index] = (lo, lo_closed, hi)
    return result


def _reference(origin, end, grid: VoxelGrid, occupied=None) -> set:
    """Voxels holding a point of the segment, up to and including the first occupied one."""
    voxels = _voxel_intervals(origin, end, grid)
    if occupied is None:
        return set(voxels)
    # A voxel entered at t through a closed end holds the point at t, before a voxel entered through an open end.
    order = sorted(voxels, key=lambda v: (voxels[v][0], not voxels[v][1]))
    kept = set()
    for voxel in order:
        kept.add(voxel)
        if occupied[voxel]:
            break
    return kept


def _traverse(origin, end, grid=GRID, occupied=None, stop=False) -> set:
    occupancy = np.zeros(grid.shape, bool) if occupied is None else occupied
    visited = traverse_rays(occupancy, grid, np.asarray([origin], float), np.asarray([end], float), stop)
    return {tuple(int(v) for v in index) for index in np.argwhere(visited)}


def _to_world(index_point, grid=GRID):
    return (np.asarray(index_point, float) * np.asarray(grid.voxel_size) + np.asarray(grid.lower)).tolist()


# ------------------------------------------------------------------------------------------------ exact cases
def test_reference_on_a_hand_example():
    # Index space (0.5, 0.5) -> (5.5, 3.5) crosses x = 3 and y = 2 together: both step at once.
    origin, end = _to_world([0.5, 0.5, 0.5]), _to_world([5.5, 3.5, 0.5])
    expected = {(0, 0, 0), (1, 0, 0), (1, 1, 0), (2, 1, 0), (3, 2, 0), (4, 2, 0), (4, 3, 0), (5, 3, 0)}
    assert _reference(origin, end, GRID) == expected
    assert _traverse(origin, end) == expected


@pytest.mark.parametrize(
    ("a", "b", "expected"),
    [
        # Through a corner upward on both axes: the corner belongs to (1, 1), never (1, 0) or (0, 1).
        ([0.5, 0.5, 0.5], [2.5, 2.5, 0.5], {(0, 0, 0), (1, 1, 0), (2, 2, 0)}),
        # Downward on both: the corner point (1, 1) is still in (1, 1), then (0, 0).
        ([1.5, 1.5, 0.5], [0.5, 0.5, 0.5], {(1, 1, 0), (0, 0, 0)}),
        # Up in x, down in y: the corner (1, 2) belongs to (1, 2), between (0, 2) and (1, 1).
        ([0.5, 2.5, 0.5], [2.5, 0.5, 0.5], {(0, 2, 0), (1, 2, 0), (1, 1, 0), (2, 1, 0), (2, 0, 0)}),
        # Through a 3D corner upward.
        ([0.5, 0.5, 0.5], [2.5, 2.5, 2.5], {(0, 0, 0), (1, 1, 1), (2, 2, 2)}),
    ],
)
def test_edges_and_corners(a, b, expected):
    assert _traverse(_to_world(a), _to_world(b)) == expected == _reference(_to_world(a), _to_world(b), GRID)


def test_axis_parallel_rays_on_faces():
    # Along x on the face y = 2, z = 1 (index space): floor puts the ray in row y = 2, z = 1 only.
    assert _traverse(_to_world([0.2, 2.0, 1.0]), _to_world([4.7, 2.0, 1.0])) == {(i, 2, 1) for i in range(5)}
    # Along y in the interior, and along z down through every layer.
    assert _traverse(_to_world([3.3, 4.9, 0.5]), _to_world([3.3, 0.1, 0.5])) == {(3, j, 0) for j in range(5)}
    assert _traverse(_to_world([5.5, 0.5, 3.99]), _to_world([5.5, 0.5, 0.0])) == {(5, 0, k) for k in range(4)}
    # On the grid's upper faces (x = 6, or y = 5) the ray is outside; on the lower face y = 0 it is inside.
    assert _traverse(_to_world([6.0, 0.5, 0.5]), _to_world([6.0, 4.5, 0.5])) == set()
    assert _traverse(_to_world([0.5, 5.0, 0.5]), _to_world([5.5, 5.0, 0.5])) == set()
    assert _traverse(_to_world([0.5, 0.0, 0.5]), _to_world([2.5, 0.0, 0.5])) == {(0, 0, 0), (1, 0, 0), (2, 0, 0)}


def test_ends_exactly_on_faces():
    # Ending on the face x = 3 going up: the end point belongs to voxel 3, which is visited.
    assert _traverse(_to_world([0.5, 0.5, 0.5]), _to_world([3.0, 0.5, 0.5])) == {(i, 0, 0) for i in range(4)}
    # Ending on the face x = 3 going down: the end point is in voxel 3, the last one.
    assert _traverse(_to_world([5.5, 0.5, 0.5]), _to_world([3.0, 0.5, 0.5])) == {(i, 0, 0) for i in (3, 4, 5)}
    # Starting on a face going down: the start's voxel (floor) and the ones below.
    assert _traverse(_to_world([3.0, 0.5, 0.5]), _to_world([1.5, 0.5, 0.5])) == {(i, 0, 0) for i in (1, 2, 3)}
    # Ending on the grid's upper face: that point is outside, the last voxel is the one below.
    assert _traverse(_to_world([4.5, 0.5, 0.5]), _to_world([6.0, 0.5, 0.5])) == {(4, 0, 0), (5, 0, 0)}
    # Starting on the upper face and leaving: nothing; starting there and entering: everything on the way.
    assert _traverse(_to_world([6.0, 0.5, 0.5]), _to_world([7.0, 0.5, 0.5])) == set()
    assert _traverse(_to_world([6.0, 0.5, 0.5]), _to_world([4.5, 0.5, 0.5])) == {(4, 0, 0), (5, 0, 0)}


def test_matches_world_to_index_at_the_ends():
    rng = np.random.default_rng(3)
    origins = rng.uniform(GRID.lower, GRID.upper, (200, 3))
    ends = rng.uniform(GRID.lower, GRID.upper, (200, 3))
    for points in (origins, ends):
        index, inside = GRID.world_to_index(torch.as_tensor(points, dtype=torch.float64))
        assert inside.all()
        for r in range(len(points)):
            visited = _traverse(origins[r], ends[r])
            assert tuple(index[r].tolist()) in visited


def test_segments_from_outside_the_grid():
    # Entering through x = 0 at a slant, leaving through y = 5: clipped at both ends.
    origin, end = _to_world([-2.3, 1.2, 0.7]), _to_world([3.1, 7.4, 3.2])
    assert _traverse(origin, end) == _reference(origin, end, GRID)
    # Passing beside the grid entirely, and lying in its plane beyond it.
    assert _traverse(_to_world([-1.0, -1.0, 0.5]), _to_world([7.0, -0.5, 0.5])) == set()
    assert _traverse(_to_world([-3.0, 2.0, 2.0]), _to_world([-0.5, 4.0, 2.0])) == set()
    # Entering exactly at the grid's corner (0, 0, 0).
    assert _traverse(_to_world([-1.0, -1.0, -1.0]), _to_world([1.5, 1.5, 1.5])) == {(0, 0, 0), (1, 1, 1)}


def test_zero_length_segments():
    point = _to_world([2.5, 3.5, 1.0])
    assert _traverse(point, point) == {(2, 3, 1)}
    assert _traverse(_to_world([6.0, 1.0, 1.0]), _to_world([6.0, 1.0, 1.0])) == set()
    assert _traverse(_to_world([-0.5, 1.0, 1.0]), _to_world([-0.5, 1.0, 1.0])) == set()


def test_random_segments_match_the_reference():
    rng = np.random.default_rng(0)
    lower, upper = np.asarray(GRID.lower), np.asarray(GRID.upper)
    for _ in range(150):
        origin = rng.uniform(lower - 1.0, upper + 1.0)
        end = rng.uniform(lower - 1.0, upper + 1.0)
        assert _traverse(origin, end) == _reference(origin, end, GRID)


# ------------------------------------------------------------------------------------------------ stopping
def test_stop_at_occupied_includes_the_blocker_only():
    occupied = np.zeros(GRID.shape, bool)
    occupied[3, :, :] = True  # a wall at x index 3
    origin, end = _to_world([0.5, 1.5, 1.5]), _to_world([5.5, 3.5, 2.5])
    stopped = _traverse(origin, end, occupied=occupied, stop=True)
    assert stopped == _reference(origin, end, GRID, occupied)
    assert max(v[0] for v in stopped) == 3 and sum(v[0] == 3 for v in stopped) == 1
    full = _traverse(origin, end, occupied=occupied)
    assert any(v[0] == 5 for v in full)
    # Starting inside an occupied voxel marks it alone.
    assert _traverse(_to_world([3.5, 1.5, 1.5]), end, occupied=occupied, stop=True) == {(3, 1, 1)}


def test_stop_at_occupied_random():
    rng = np.random.default_rng(1)
    lower, upper = np.asarray(GRID.lower), np.asarray(GRID.upper)
    occupied = rng.random(GRID.shape) < 0.15
    for _ in range(100):
        origin = rng.uniform(lower - 1.0, upper + 1.0)
        end = rng.uniform(lower - 1.0, upper + 1.0)
        assert _traverse(origin, end, occupied=occupied, stop=True) == _reference(origin, end, GRID, occupied)


def test_first_hit_distance_is_analytic():
    occupied = np.zeros(GRID.shape, bool)
    occupied[4, :, :] = True  # wall from x = 0.5 m
    origins = np.array([[-1.2, 0.1, 0.3], [-3.0, 0.2, 0.6], [0.7, 0.2, 0.3], [-1.2, 0.1, 0.3], [-1.2, 0.1, 0.3]])
    directions = np.array([[1.0, 0.2, 0.1], [1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [-1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    index, distance = first_hit(occupied, GRID, origins, directions, 10.0)
    assert index.dtype == np.int64 and distance.dtype == np.float64
    assert distance[0] == pytest.approx((0.5 + 1.2) / directions[0, 0], abs=1e-12)
    assert index[0].tolist() == list(GRID.world_to_index(torch.tensor(origins[0] + distance[0] * directions[0]))[0])
    assert distance[1] == pytest.approx(3.5) and index[1].tolist() == [4, 2, 2]
    assert distance[2] == 0.0 and index[2].tolist() == [4, 2, 1]  # starts in the wall
    assert index[3].tolist() == [-1, -1, -1] and distance[3] == math.inf  # away from the wall
    assert index[4].tolist() == [-1, -1, -1] and distance[4] == math.inf  # along it
    # Too short to reach the wall.
    index, distance = first_hit(occupied, GRID, origins[:2], directions[:2], np.array([1.0, 3.4]))
    assert (index == -1).all() and np.isinf(distance).all()


def test_first_hit_agrees_with_the_reference():
    rng = np.random.default_rng(2)
    occupied = rng.random(GRID.shape) < 0.1
    lower, upper = np.asarray(GRID.lower), np.asarray(GRID.upper)
    origins = rng.uniform(lower - 1.0, upper + 1.0, (100, 3))
    directions = rng.normal(size=(100, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    index, distance = first_hit(occupied, GRID, origins, directions, 6.0)
    for r in range(100):
        voxels = _voxel_intervals(origins[r], origins[r] + 6.0 * directions[r], GRID)
        hits = sorted((lo, v) for v, (lo, _, _) in voxels.items() if occupied[v])
        if not hits:
            assert index[r].tolist() == [-1, -1, -1] and distance[r] == math.inf
        else:
            assert tuple(index[r]) == hits[0][1]
            assert distance[r] == pytest.approx(float(hits[0][0]) * 6.0, abs=1e-9)


# ------------------------------------------------------------------------------------------------ properties
_lattice = st.integers(-8, 32).map(lambda n: n / 4)  # index-space coordinates on a quarter-voxel lattice


@settings(max_examples=200, deadline=None)
@given(st.lists(_lattice, min_size=6, max_size=6))
def test_lattice_segments_are_exact(coords):
    # Faces, edges and corners are hit all the time here; every value and every tie is exactly representable.
    origin, end = _to_world(coords[:3]), _to_world(coords[3:])
    assert _traverse(origin, end) == _reference(origin, end, GRID)


@settings(max_examples=150, deadline=None)
@given(st.lists(st.floats(-3.0, 3.0, allow_nan=False), min_size=6, max_size=6))
def test_any_segment_matches_up_to_rounding(coords):
    # For arbitrary floats a crossing, or a coordinate, within rounding of a face can be decided either way: the walk
    # visits every voxel the segment enters by more than 1e-9 voxel, and none it does not come within 1e-9 of.
    origin, end = coords[:3], coords[3:]
    visited = _traverse(origin, end)
    assert set(_voxel_intervals(origin, end, GRID, margin=-1e-9)) <= visited
    assert visited <= set(_voxel_intervals(origin, end, GRID, margin=1e-9))


def test_large_grid_runs():
    rng = np.random.default_rng(4)
    origins = rng.uniform(OCC3D_GRID.lower, OCC3D_GRID.upper, (1000, 3))
    ends = rng.uniform(OCC3D_GRID.lower, OCC3D_GRID.upper, (1000, 3))
    visited = traverse_rays(np.zeros(OCC3D_GRID.shape, bool), OCC3D_GRID, origins, ends)
    index, _ = OCC3D_GRID.world_to_index(torch.as_tensor(np.concatenate([origins, ends])))
    assert visited[tuple(index.T)].all()


def test_input_checks():
    occupied = np.zeros(GRID.shape, bool)
    with pytest.raises(ValueError, match="shape"):
        traverse_rays(np.zeros((2, 2, 2), bool), GRID, np.zeros((1, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="finite"):
        traverse_rays(occupied, GRID, np.full((1, 3), np.nan), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="same shape"):
        traverse_rays(occupied, GRID, np.zeros((2, 3)), np.zeros((1, 3)))
    with pytest.raises(ValueError, match="max_distance"):
        first_hit(occupied, GRID, np.zeros((1, 3)), np.ones((1, 3)), -1.0)
