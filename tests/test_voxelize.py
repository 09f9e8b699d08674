"""Hard voxelization against a line-by-line port of mmdet3d's ``hard_voxelize`` CPU kernel + ``HardSimpleVFE``."""

from __future__ import annotations

import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from occkit.geometry.grid import VoxelGrid
from occkit.geometry.voxelize import Voxels, hard_voxelize, voxelize_batch

# 4 x 3 x 2 voxels: small enough that random clouds collide a lot.
SMALL_GRID = VoxelGrid((-1.0, -0.5, 0.0, 1.0, 1.0, 1.0), 0.5)


def reference_voxelize(points: torch.Tensor, grid: VoxelGrid, max_points: int, max_voxels: int):
    """mmdet3d ``hard_voxelize`` (CPU kernel) as a python loop, then ``HardSimpleVFE``'s mean."""
    num_channels = points.shape[1]
    index, inside = grid.world_to_index(points[:, :3])
    voxel_of_coord: dict[tuple[int, int, int], int] = {}
    coords, counts, voxels = [], [], []
    for i in range(points.shape[0]):
        if not bool(inside[i]):
            continue
        coord = tuple(int(v) for v in index[i])
        slot = voxel_of_coord.get(coord, -1)
        if slot == -1:
            if len(coords) >= max_voxels:
                continue
            slot = len(coords)
            voxel_of_coord[coord] = slot
            coords.append(coord)
            counts.append(0)
            voxels.append(torch.zeros(max_points, num_channels, dtype=points.dtype))
        if counts[slot] < max_points:
            voxels[slot][counts[slot]] = points[i]
            counts[slot] += 1
    padded = torch.stack(voxels) if voxels else points.new_zeros(0, max_points, num_channels)
    counts_t = torch.tensor(counts, dtype=torch.long)
    features = padded.sum(dim=1) / counts_t.to(points.dtype).view(-1, 1)
    coords_t = torch.tensor(coords, dtype=torch.long).view(-1, 3)
    return Voxels(features, coords_t, counts_t, padded)


def assert_matches_reference(points, grid, max_points, max_voxels):
    got = hard_voxelize(points, grid, max_points, max_voxels, return_points=True)
    want = reference_voxelize(points, grid, max_points, max_voxels)
    assert torch.equal(got.coords, want.coords)
    assert torch.equal(got.counts, want.counts)
    assert torch.equal(got.points, want.points)
    if points.dtype == torch.float64:
        assert torch.equal(got.features, want.features)
    else:
        torch.testing.assert_close(got.features, want.features, rtol=1e-6, atol=1e-6)
    return got


def random_cloud(grid: VoxelGrid, num_points: int, channels: int, seed: int, dtype=torch.float32):
    """Points spread over the grid and a margin outside it, so some are skipped."""
    generator = torch.Generator().manual_seed(seed)
    lower = torch.tensor(grid.lower, dtype=dtype)
    upper = torch.tensor(grid.upper, dtype=dtype)
    margin = 0.2 * (upper - lower)
    xyz = lower - margin + torch.rand(num_points, 3, generator=generator, dtype=dtype) * (upper - lower + 2 * margin)
    extra = torch.randn(num_points, channels - 3, generator=generator, dtype=dtype)
    return torch.cat((xyz, extra), dim=1)


@settings(max_examples=40, deadline=None)
@given(
    num_points=st.integers(0, 120),
    channels=st.integers(3, 6),
    max_points=st.integers(1, 12),
    max_voxels=st.integers(1, 30),
    seed=st.integers(0, 2**31 - 1),
    double=st.booleans(),
)
def test_matches_reference_on_random_clouds(num_points, channels, max_points, max_voxels, seed, double):
    dtype = torch.float64 if double else torch.float32
    points = random_cloud(SMALL_GRID, num_points, channels, seed, dtype)
    assert_matches_reference(points, SMALL_GRID, max_points, max_voxels)


@pytest.mark.parametrize("max_points", [1, 200])
def test_matches_reference_with_extreme_max_points(max_points):
    points = random_cloud(SMALL_GRID, 300, 5, seed=1)
    got = assert_matches_reference(points, SMALL_GRID, max_points, max_voxels=1000)
    if max_points == 1:
        assert torch.all(got.counts == 1)
    else:
        # Nothing is dropped: every in-grid point lands in some voxel.
        assert int(got.counts.sum()) == int(SMALL_GRID.world_to_index(points[:, :3])[1].sum())


def test_max_voxels_keeps_first_appearing_voxels():
    points = random_cloud(SMALL_GRID, 200, 5, seed=2, dtype=torch.float64)
    occupied = hard_voxelize(points, SMALL_GRID, 10, 1000).coords.shape[0]
    assert occupied > 5
    got = assert_matches_reference(points, SMALL_GRID, 10, max_voxels=5)
    assert got.coords.shape[0] == 5
    everything = hard_voxelize(points, SMALL_GRID, 10, 1000)
    assert torch.equal(got.coords, everything.coords[:5])
    assert torch.equal(got.features, everything.features[:5])


def test_first_appearance_order_and_point_cap_on_a_hand_made_cloud():
    points = torch.tensor(
        [
            [0.75, 0.25, 0.25, 1.0],  # voxel (3, 1, 0), slot 0
            [-0.75, -0.25, 0.75, 2.0],  # voxel (0, 0, 1), slot 1
            [0.70, 0.30, 0.20, 3.0],  # slot 0, second point
            [5.00, 0.00, 0.00, 9.0],  # outside, skipped
            [0.60, 0.40, 0.10, 4.0],  # slot 0, third point: over the cap of 2, dropped
            [-0.25, 0.75, 0.25, 5.0],  # voxel (1, 2, 0): a third voxel, over max_voxels, dropped
            [-0.70, -0.20, 0.70, 6.0],  # slot 1, second point
        ]
    )
    got = assert_matches_reference(points, SMALL_GRID, max_points=2, max_voxels=2)
    assert got.coords.tolist() == [[3, 1, 0], [0, 0, 1]]
    assert got.counts.tolist() == [2, 2]
    torch.testing.assert_close(got.features[:, 3], torch.tensor([2.0, 4.0]))


def test_lower_boundary_is_inside_and_upper_boundary_is_outside():
    lower, upper = SMALL_GRID.lower, SMALL_GRID.upper
    points = torch.tensor(
        [
            [lower[0], lower[1], lower[2], 1.0],  # exactly on the lower corner: voxel (0, 0, 0)
            [upper[0], 0.0, 0.5, 2.0],  # x exactly on the upper face: outside
            [0.0, upper[1], 0.5, 3.0],  # y exactly on the upper face: outside
            [0.0, 0.0, upper[2], 4.0],  # z exactly on the upper face: outside
            [upper[0] - 1e-3, upper[1] - 1e-3, upper[2] - 1e-3, 5.0],  # just inside: last voxel
        ],
        dtype=torch.float64,
    )
    got = assert_matches_reference(points, SMALL_GRID, 4, 10)
    last = [s - 1 for s in SMALL_GRID.shape]
    assert got.coords.tolist() == [[0, 0, 0], last]
    assert got.features[:, 3].tolist() == [1.0, 5.0]


def test_points_all_outside_give_no_voxels():
    points = torch.tensor([[10.0, 0.0, 0.5, 1.0], [0.0, -3.0, 0.5, 1.0], [0.0, 0.0, -0.1, 1.0]])
    got = hard_voxelize(points, SMALL_GRID, 4, 10, return_points=True)
    assert got.features.shape == (0, 4)
    assert got.coords.shape == (0, 3)
    assert got.counts.shape == (0,)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
def test_empty_input_gives_empty_output_with_right_shapes_and_types(dtype):
    got = hard_voxelize(torch.zeros(0, 5, dtype=dtype), SMALL_GRID, 3, 10, return_points=True)
    assert got.features.shape == (0, 5) and got.features.dtype == dtype
    assert got.coords.shape == (0, 3) and got.coords.dtype == torch.long
    assert got.counts.shape == (0,) and got.counts.dtype == torch.long
    assert got.points.shape == (0, 3, 5)
    assert_matches_reference(torch.zeros(0, 5, dtype=dtype), SMALL_GRID, 3, 10)


def test_points_are_only_returned_on_request():
    points = random_cloud(SMALL_GRID, 20, 4, seed=3)
    assert hard_voxelize(points, SMALL_GRID, 3, 10).points is None
    got = hard_voxelize(points, SMALL_GRID, 3, 10, return_points=True)
    assert got.points.shape == (got.coords.shape[0], 3, 4)


def test_lidar_scale_config_matches_reference():
    """The BEVFusion/DAOcc LiDAR setting, on a cloud dense enough to hit the 10-point cap."""
    grid = VoxelGrid((-54.0, -54.0, -5.0, 54.0, 54.0, 3.0), (0.075, 0.075, 0.2))
    generator = torch.Generator().manual_seed(4)
    centres = torch.rand(40, 3, generator=generator) * torch.tensor([100.0, 100.0, 7.0]) - torch.tensor([50, 50, 4])
    xyz = centres.repeat_interleave(15, dim=0) + 0.02 * torch.randn(600, 3, generator=generator)
    points = torch.cat((xyz, torch.rand(600, 2, generator=generator)), dim=1)
    got = assert_matches_reference(points, grid, 10, 120000)
    assert int(got.counts.max()) == 10


def test_coords_index_the_voxels_that_contain_the_mean_point_cloud():
    points = random_cloud(SMALL_GRID, 100, 3, seed=5, dtype=torch.float64)
    got = hard_voxelize(points, SMALL_GRID, 100, 100)
    # A mean of points in one box lies in that box.
    index, inside = SMALL_GRID.world_to_index(got.features)
    assert bool(inside.all())
    assert torch.equal(index, got.coords)


def test_is_deterministic():
    points = random_cloud(SMALL_GRID, 500, 5, seed=6)
    first = hard_voxelize(points, SMALL_GRID, 7, 15, return_points=True)
    second = hard_voxelize(points, SMALL_GRID, 7, 15, return_points=True)
    for name in ("features", "coords", "counts", "points"):
        assert torch.equal(getattr(first, name), getattr(second, name)), name


def test_features_are_differentiable_in_the_feature_channels():
    # Points sit well inside their voxels, so xyz does not move when the feature channels are perturbed.
    xyz = torch.tensor(
        [[0.1, 0.1, 0.1], [0.2, 0.2, 0.3], [0.3, 0.1, 0.2], [-0.8, 0.6, 0.6], [0.4, 0.4, 0.4]], dtype=torch.float64
    )
    extra = torch.randn(5, 2, dtype=torch.float64, generator=torch.Generator().manual_seed(7), requires_grad=True)

    def mean_features(channels):
        return hard_voxelize(torch.cat((xyz, channels), dim=1), SMALL_GRID, 3, 10).features

    assert torch.autograd.gradcheck(mean_features, (extra,))
    # The point over the 3-point cap of voxel (2, 1, 0) gets no gradient.
    mean_features(extra).sum().backward()
    assert torch.equal(extra.grad[4], torch.zeros(2, dtype=torch.float64))
    assert bool((extra.grad[:4] != 0).all())


def test_voxelize_batch_concatenates_with_a_batch_column():
    clouds = [random_cloud(SMALL_GRID, n, 5, seed=10 + n) for n in (50, 0, 80)]
    features, coords, counts = voxelize_batch(clouds, SMALL_GRID, 4, 12)
    singles = [hard_voxelize(c, SMALL_GRID, 4, 12) for c in clouds]
    sizes = [s.coords.shape[0] for s in singles]
    assert sizes[1] == 0 and sizes[0] > 0 and sizes[2] > 0
    assert coords.shape == (sum(sizes), 4) and coords.dtype == torch.long
    assert torch.equal(coords[:, 0], torch.repeat_interleave(torch.arange(3), torch.tensor(sizes)))
    assert torch.equal(coords[:, 1:], torch.cat([s.coords for s in singles]))
    assert torch.equal(features, torch.cat([s.features for s in singles]))
    assert torch.equal(counts, torch.cat([s.counts for s in singles]))


def test_voxelize_batch_rejects_empty_and_mixed_channel_inputs():
    with pytest.raises(ValueError, match="at least one"):
        voxelize_batch([], SMALL_GRID, 4, 12)
    with pytest.raises(ValueError, match="one channel count"):
        voxelize_batch([torch.zeros(2, 4), torch.zeros(2, 5)], SMALL_GRID, 4, 12)


@pytest.mark.parametrize(
    ("points", "max_points", "max_voxels", "error", "message"),
    [
        (torch.zeros(5), 3, 10, ValueError, r"points must have shape \(N, >=3\), got \(5,\)"),
        (torch.zeros(2, 3, 4), 3, 10, ValueError, r"points must have shape \(N, >=3\), got \(2, 3, 4\)"),
        (torch.zeros(5, 2), 3, 10, ValueError, r"points must have shape \(N, >=3\), got \(5, 2\)"),
        (torch.zeros(5, 4, dtype=torch.long), 3, 10, TypeError, "floating point"),
        (torch.zeros(5, 4), 0, 10, ValueError, "max_points_per_voxel must be >= 1, got 0"),
        (torch.zeros(5, 4), 3, 0, ValueError, "max_voxels must be >= 1, got 0"),
    ],
)
def test_bad_input_is_rejected_with_a_named_error(points, max_points, max_voxels, error, message):
    with pytest.raises(error, match=message):
        hard_voxelize(points, SMALL_GRID, max_points, max_voxels)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    grid = VoxelGrid((-54.0, -54.0, -5.0, 54.0, 54.0, 3.0), (0.075, 0.075, 0.2))
    generator = torch.Generator().manual_seed(11)
    centres = torch.rand(2000, 3, generator=generator) * torch.tensor([110.0, 110.0, 9.0]) - torch.tensor([55, 55, 6])
    xyz = centres.repeat_interleave(20, dim=0) + 0.03 * torch.randn(40000, 3, generator=generator)
    points = torch.cat((xyz, torch.rand(40000, 2, generator=generator)), dim=1)
    cpu = hard_voxelize(points, grid, 10, 3000, return_points=True)
    cuda = hard_voxelize(points.cuda(), grid, 10, 3000, return_points=True)
    assert cuda.features.is_cuda and cuda.coords.is_cuda
    assert torch.equal(cuda.coords.cpu(), cpu.coords)
    assert torch.equal(cuda.counts.cpu(), cpu.counts)
    assert torch.equal(cuda.points.cpu(), cpu.points)
    torch.testing.assert_close(cuda.features.cpu(), cpu.features, rtol=1e-6, atol=1e-6)
    again = hard_voxelize(points.cuda(), grid, 10, 3000)
    assert torch.equal(again.features, cuda.features)
