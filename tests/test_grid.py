"""VoxelGrid: shapes, centres and world <-> index for the benchmark grids and arbitrary ones."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid


def test_benchmark_grids():
    assert OCC3D_GRID.shape == (200, 200, 16)
    assert SURROUNDOCC_GRID.shape == (200, 200, 16)
    assert OCC3D_GRID.voxel_size == (0.4, 0.4, 0.4)
    assert OCC3D_GRID.num_voxels == 640_000
    # Occ3D voxel centre = (i + 0.5) * 0.4 + min: first and last centres along x and z.
    xs = OCC3D_GRID.axis_centers(0, dtype=torch.float64)
    zs = OCC3D_GRID.axis_centers(2, dtype=torch.float64)
    assert xs[0].item() == pytest.approx(-39.8) and xs[-1].item() == pytest.approx(39.8)
    assert zs[0].item() == pytest.approx(-0.8) and zs[-1].item() == pytest.approx(5.2)
    assert SURROUNDOCC_GRID.axis_centers(2)[0].item() == pytest.approx(-4.75)


def test_anisotropic_grid_of_daocc_lidar_encoder():
    grid = VoxelGrid([-54, -54, -5, 54, 54, 3], [0.075, 0.075, 0.2])
    assert grid.shape == (1440, 1440, 40)


def test_centers_layout():
    grid = VoxelGrid((0, 0, 0, 4, 2, 1), (1.0, 1.0, 0.5))
    centres = grid.centers()
    assert centres.shape == (4, 2, 2, 3)
    assert torch.equal(centres[3, 1, 0], torch.tensor([3.5, 1.5, 0.25]))
    assert torch.equal(grid.index_to_world(torch.tensor([[3, 1, 0]])), centres[3, 1, 0][None])


def test_world_to_index_floor_and_bounds():
    grid = OCC3D_GRID
    points = torch.tensor(
        [
            [-40.0, -40.0, -1.0],  # lower corner: inside, voxel 0
            [39.99, 39.99, 5.39],  # just below the upper corner: last voxel
            [40.0, 0.0, 0.0],  # upper bound on x: outside
            [0.0, 0.0, -1.01],  # below z range: outside
            [-0.01, 0.01, 0.0],  # negative coordinates floor, not truncate
        ]
    )
    index, inside = grid.world_to_index(points)
    assert inside.tolist() == [True, True, False, False, True]
    assert index[0].tolist() == [0, 0, 0]
    assert index[1].tolist() == [199, 199, 15]
    assert index[4].tolist() == [99, 100, 2]
    assert index.dtype == torch.int64


@settings(max_examples=50, deadline=None)
@given(
    st.tuples(st.integers(0, 199), st.integers(0, 199), st.integers(0, 15)),
    st.tuples(*[st.floats(0.01, 0.99)] * 3),
)
def test_index_world_round_trip(index, fraction):
    index = torch.tensor(index)
    size = torch.tensor(OCC3D_GRID.voxel_size, dtype=torch.float64)
    inside_point = (
        OCC3D_GRID.index_to_world(index, torch.float64) + (torch.tensor(fraction, dtype=torch.float64) - 0.5) * size
    )
    back, inside = OCC3D_GRID.world_to_index(inside_point)
    assert inside.item()
    assert torch.equal(back, index)
    flat = OCC3D_GRID.ravel_index(index)
    assert torch.equal(OCC3D_GRID.unravel_index(flat), index)


def test_ravel_matches_torch_flatten():
    grid = VoxelGrid((0, 0, 0, 3, 4, 5), 1.0)
    volume = torch.arange(grid.num_voxels).reshape(grid.shape)
    index = torch.tensor([[2, 3, 4], [1, 0, 3]])
    assert torch.equal(grid.ravel_index(index), volume[index[:, 0], index[:, 1], index[:, 2]])


def test_batched_points_and_dtype():
    points = torch.zeros(2, 7, 3, dtype=torch.float64)
    index, inside = OCC3D_GRID.world_to_index(points)
    assert index.shape == (2, 7, 3) and inside.shape == (2, 7)
    assert OCC3D_GRID.centers(dtype=torch.float64).dtype == torch.float64


@pytest.mark.parametrize(
    ("bounds", "size", "message"),
    [
        ((0, 0, 0, 1, 1), 0.5, "6 numbers"),
        ((0, 0, 0, 1, 1, 1), (0.5, 0.5), "one number or three"),
        ((0, 0, 0, 1, 1, 1), 0.0, "must be positive"),
        ((1, 0, 0, 0, 1, 1), 0.5, "x_max <= x_min"),
        ((0, 0, 0, 1, 1, 1), 0.3, "x extent 1 m is not a whole number of 0.3 m voxels"),
    ],
)
def test_invalid_grids(bounds, size, message):
    with pytest.raises(ValueError, match=message):
        VoxelGrid(bounds, size)


def test_grid_is_hashable_value():
    assert VoxelGrid([-40, -40, -1, 40, 40, 5.4], 0.4) == OCC3D_GRID
    assert len({OCC3D_GRID, VoxelGrid((-40, -40, -1, 40, 40, 5.4), (0.4, 0.4, 0.4))}) == 1
    assert "shape=(200, 200, 16)" in repr(OCC3D_GRID)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    points = torch.rand(1000, 3) * 100 - 50
    index_cpu, inside_cpu = OCC3D_GRID.world_to_index(points)
    index_gpu, inside_gpu = OCC3D_GRID.world_to_index(points.cuda())
    assert torch.equal(index_gpu.cpu(), index_cpu) and torch.equal(inside_gpu.cpu(), inside_cpu)


def test_from_shape_cuts_a_range_into_voxel_counts():
    grid = VoxelGrid.from_shape((-54.0, -54.0, -5.0, 54.0, 54.0, 3.0), (180, 180, 10))
    assert grid.shape == (180, 180, 10)
    assert grid.voxel_size == pytest.approx((0.6, 0.6, 0.8))
    with pytest.raises(ValueError, match="positive voxel counts"):
        VoxelGrid.from_shape((-1.0, -1.0, -1.0, 1.0, 1.0, 1.0), (2, 0, 2))
