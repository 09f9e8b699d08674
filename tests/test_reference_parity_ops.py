"""The parity harness's PyTorch stand-ins of the references' compiled ops (``benchmarks/reference_parity/``) against
small cases worked out by hand from the semantics their docstrings state: FlashOcc's BEVPoolv2, and DAOcc's hard
voxelization (BEVFusion's), spconv 1.x's rulebook and sparse convolution. The model goldens are only as good as these
stand-ins. Neither the reference checkouts nor mmcv are needed."""

from __future__ import annotations

import importlib.util
import sys

import pytest
import torch
import torch.nn.functional as F
from conftest import benchmark_module


@pytest.fixture(scope="module")
def ops():
    return benchmark_module("reference_parity/daocc_ops.py")


def voxelize(ops, points, voxel_size=(1.0, 1.0, 1.0), coors_range=(0.0, 0.0, 0.0, 4.0, 3.0, 2.0), max_points=3,
             max_voxels=10):
    """Calls the stand-in the way the reference's ``_Voxelization.forward`` does: zeroed outputs, then the count."""
    points = torch.tensor(points, dtype=torch.float32)
    voxels = points.new_zeros(max_voxels, max_points, points.shape[1])
    coors = torch.zeros(max_voxels, 3, dtype=torch.int32)
    num = torch.zeros(max_voxels, dtype=torch.int32)
    count = ops.hard_voxelize(points, voxels, coors, num, list(voxel_size), list(coors_range), max_points, max_voxels,
                              3, True)
    return count, voxels[:count], coors[:count], num[:count]


def test_voxel_coordinates_are_x_y_z_cells_and_points_outside_the_grid_are_dropped(ops):
    # Grid 4 x 3 x 2 of 1 m cells from the origin; the upper bound of each axis is outside.
    count, voxels, coors, num = voxelize(ops, [[0.5, 2.5, 1.5, 7.0], [-0.1, 1.0, 1.0, 1.0], [4.0, 1.0, 1.0, 1.0],
                                               [1.0, 3.0, 1.0, 1.0], [1.0, 1.0, 2.0, 1.0], [3.99, 0.0, 0.0, 9.0]])
    assert count == 2
    assert coors.tolist() == [[0, 2, 1], [3, 0, 0]]  # (x, y, z), BEVFusion's order
    assert num.tolist() == [1, 1]
    assert torch.equal(voxels[:, 0], torch.tensor([[0.5, 2.5, 1.5, 7.0], [3.99, 0.0, 0.0, 9.0]]))  # every feature
    assert coors.dtype == torch.int32


def test_voxels_are_numbered_by_first_point_and_keep_their_first_points_in_order(ops):
    a1, b1, a2, c1, a3, a4 = ([0.2, 0.2, 0.2], [2.5, 0.5, 0.5], [0.7, 0.1, 0.9], [1.5, 2.5, 1.5], [0.3, 0.3, 0.3],
                              [0.9, 0.9, 0.9])
    count, voxels, coors, num = voxelize(ops, [a1, b1, a2, c1, a3, a4], max_points=3)
    assert count == 3
    assert coors.tolist() == [[0, 0, 0], [2, 0, 0], [1, 2, 1]]
    assert num.tolist() == [3, 1, 1]
    # The cell of a* holds a1, a2, a3 (its first three points, in point order); a4 is dropped.
    assert torch.equal(voxels[0], torch.tensor([a1, a2, a3]))
    assert torch.equal(voxels[1], torch.tensor([b1, [0.0] * 3, [0.0] * 3]))  # unused rows stay as allocated


def test_voxels_beyond_max_voxels_are_dropped_but_earlier_voxels_still_fill(ops):
    a1, b1, c1, a2, d1 = [0.5, 0.5, 0.5], [1.5, 0.5, 0.5], [2.5, 0.5, 0.5], [0.6, 0.6, 0.6], [3.5, 0.5, 0.5]
    count, voxels, coors, num = voxelize(ops, [a1, b1, c1, a2, d1], max_voxels=2)
    assert count == 2
    assert coors.tolist() == [[0, 0, 0], [1, 0, 0]]
    assert num.tolist() == [2, 1]
    assert torch.equal(voxels[0, :2], torch.tensor([a1, a2]))


def test_voxel_cells_are_floored_in_float32_from_the_range_minimum(ops):
    # Negative ranges and non-unit voxels: cell = floor((p - min) / size).
    count, _, coors, _ = voxelize(ops, [[-0.01, -0.8, -5.0], [0.0, 0.79, 2.99]], voxel_size=(0.075, 0.4, 0.2),
                                  coors_range=(-4.8, -4.0, -5.0, 4.8, 4.0, 3.0))
    assert count == 2
    assert coors.tolist() == [[63, 8, 0], [64, 11, 39]]


def rulebook(ops, indices, out_shape, kernel, stride, padding, subm):
    indices = torch.tensor(indices, dtype=torch.int32)
    ones = [1] * len(kernel)
    return ops.get_indice_pairs(indices, int(indices[:, 0].max()) + 1, out_shape, out_shape, kernel, stride, padding,
                                ones, [0] * len(kernel), int(subm), 0)


def pairs_of(pairs, counts):
    return [list(zip(pairs[k, 0, :n].tolist(), pairs[k, 1, :n].tolist(), strict=True)) for k, n in enumerate(counts)]


def test_submanifold_rulebook_pairs_active_sites_only_and_keeps_input_order(ops):
    # Sites at x = 1, 2, 4 of a 5 x 1 x 1 grid; kernel 3 along x, padding 1: output o takes input o - 1 + k.
    indices = [[0, 2, 0, 0], [0, 1, 0, 0], [0, 4, 0, 0]]
    out, pairs, counts = rulebook(ops, indices, [5, 1, 1], [3, 1, 1], [1, 1, 1], [1, 0, 0], subm=True)
    assert out.tolist() == indices  # outputs at the input sites, in their order
    assert counts.tolist() == [1, 3, 1]
    # Offset 0: input x = 1 (row 1) feeds output x = 2 (row 0); offset 2: input x = 2 feeds output x = 1.
    assert pairs_of(pairs, counts.tolist()) == [[(1, 0)], [(0, 0), (1, 1), (2, 2)], [(0, 1)]]
    assert pairs.shape == (3, 2, 3) and pairs[0, :, 1:].eq(-1).all()  # padded with -1


def test_submanifold_convolution_sums_the_kernel_over_active_neighbours(ops):
    indices = [[0, 1, 0, 0], [0, 2, 0, 0], [0, 4, 0, 0]]
    out, pairs, counts = rulebook(ops, indices, [5, 1, 1], [3, 1, 1], [1, 1, 1], [1, 0, 0], subm=True)
    weights = torch.tensor([2.0, 3.0, 5.0]).view(3, 1, 1, 1, 1)  # (kx, ky, kz, in, out)
    features = torch.tensor([[1.0], [10.0], [100.0]])
    result = ops.indice_conv(features, weights, pairs, counts, len(out), 0, 1)
    # x=1: 3*1 + 5*10 (its right neighbour, offset 2); x=2: 2*1 (left, offset 0) + 3*10; x=4: 3*100.
    assert result.flatten().tolist() == [53.0, 32.0, 300.0]


def test_strided_convolution_outputs_every_reached_site_sorted_by_position(ops):
    # A 6 x 1 x 1 grid, kernel 3, stride 2, padding 1: 3 outputs; output o takes input 2o - 1 + k.
    indices = [[0, 3, 0, 0], [0, 0, 0, 0]]
    out, pairs, counts = rulebook(ops, indices, [3, 1, 1], [3, 1, 1], [2, 1, 1], [1, 0, 0], subm=False)
    assert out.tolist() == [[0, 0, 0, 0], [0, 1, 0, 0], [0, 2, 0, 0]]
    # x=3 reaches o=2 (k=0) and o=1 (k=2); x=0 reaches o=0 (k=1).
    assert pairs_of(pairs, counts.tolist()) == [[(0, 2)], [(1, 0)], [(0, 1)]]
    weights = torch.tensor([2.0, 3.0, 5.0]).view(3, 1, 1, 1, 1)
    result = ops.indice_conv(torch.tensor([[10.0], [1.0]]), weights, pairs, counts, len(out), 0, 0)
    assert result.flatten().tolist() == [3.0, 50.0, 20.0]


def test_kernel_offsets_are_row_major_and_weights_map_in_to_out_channels(ops):
    # A 2 x 2 x 1 kernel over a 2 x 2 x 1 grid with no padding: one output at the origin; offset k = 2 * kx + ky.
    indices = [[0, 0, 1, 0], [0, 1, 0, 0]]
    out, pairs, counts = rulebook(ops, indices, [1, 1, 1], [2, 2, 1], [1, 1, 1], [0, 0, 0], subm=False)
    assert out.tolist() == [[0, 0, 0, 0]]
    assert counts.tolist() == [0, 1, 1, 0]  # (0, 1) is offset 1, (1, 0) offset 2
    weights = torch.zeros(2, 2, 1, 2, 3)
    weights[0, 1, 0] = torch.tensor([[1.0, 2.0, 3.0], [4.0, 5.0, 6.0]])
    weights[1, 0, 0] = torch.tensor([[0.0, 0.0, 1.0], [0.0, 1.0, 0.0]])
    features = torch.tensor([[1.0, 10.0], [7.0, 100.0]])
    result = ops.indice_conv(features, weights, pairs, counts, 1, 0, 0)
    # [1, 10] @ W[0,1] + [7, 100] @ W[1,0] = [41, 52, 63] + [0, 100, 7]
    assert result.tolist() == [[41.0, 152.0, 70.0]]


def dense_reference(indices, features, shape, weights, stride, padding, subm):
    """The same convolution on dense volumes: F.conv3d with the weights reordered to (out, in, k...); a submanifold
    one keeps the input sites, a regular one every site whose receptive field holds an active input."""
    batch = int(indices[:, 0].max()) + 1
    volume = torch.zeros(batch, features.shape[1], *shape)
    active = torch.zeros(batch, 1, *shape)
    where = (indices[:, 0], indices[:, 1], indices[:, 2], indices[:, 3])
    volume[where[0], :, where[1], where[2], where[3]] = features
    active[where[0], 0, where[1], where[2], where[3]] = 1.0
    kernel = weights.permute(4, 3, 0, 1, 2)
    output = F.conv3d(volume, kernel, stride=stride, padding=padding)
    if subm:
        return output, active
    reached = F.conv3d(active, torch.ones(1, 1, *weights.shape[:3]), stride=stride, padding=padding) > 0
    return output, reached.float()


@pytest.mark.parametrize("subm", [True, False])
def test_sparse_convolution_equals_dense_convolution_on_its_output_sites(ops, subm):
    generator = torch.Generator().manual_seed(0)
    shape = [7, 6, 5]
    sites = torch.randperm(2 * 7 * 6 * 5, generator=generator)[:60]
    indices = torch.stack([sites // 210, sites // 30 % 7, sites // 5 % 6, sites % 5], dim=1).int()
    features = torch.randn(60, 3, generator=generator)
    weights = torch.randn(3, 3, 3, 3, 4, generator=generator)
    stride, padding = ([1, 1, 1], [1, 1, 1]) if subm else ([2, 2, 2], [1, 0, 1])
    out_shape = shape if subm else [(n + 2 * p - 3) // s + 1 for n, p, s in zip(shape, padding, stride, strict=True)]
    out, pairs, counts = ops.get_indice_pairs(indices, 2, out_shape, shape, [3, 3, 3], stride, padding, [1, 1, 1],
                                              [0, 0, 0], int(subm), 0)
    result = ops.indice_conv(features, weights, pairs, counts, len(out), 0, int(subm))
    dense, sites_out = dense_reference(indices.long(), features, shape, weights, stride, padding, subm)
    expected_sites = torch.nonzero(sites_out[:, 0])
    if subm:
        assert torch.equal(out, indices)
    else:
        assert out.long().tolist() == expected_sites.tolist()  # every reached site, in (batch, x, y, z) order
    gathered = dense[out[:, 0].long(), :, out[:, 1].long(), out[:, 2].long(), out[:, 3].long()]
    assert torch.allclose(result, gathered, atol=1e-5)
    assert len(out) == len(expected_sites)


def test_unneeded_variants_refuse(ops):
    indices = torch.tensor([[0, 0, 0, 0]], dtype=torch.int32)
    with pytest.raises(NotImplementedError):
        ops.get_indice_pairs(indices, 1, [2, 2, 2], [1, 1, 1], [3, 3, 3], [1, 1, 1], [0, 0, 0], [1, 1, 1], [0, 0, 0],
                             0, 1)
    with pytest.raises(NotImplementedError):
        ops.indice_conv(torch.ones(1, 1), torch.ones(1, 1, 1, 1, 1), torch.zeros(1, 2, 1, dtype=torch.int32),
                        torch.ones(1, dtype=torch.int32), 1, 1, 0)


def test_stand_in_modules_define_the_run_ops_and_refuse_the_rest(ops):
    finder = ops.openmmlab.StandInFinder(ops.COMPILED, ("mmcv.ops",))
    assert finder.find_spec("json") is None
    voxel_layer = importlib.util.module_from_spec(finder.find_spec("mmdet3d.ops.voxel.voxel_layer"))
    assert voxel_layer.hard_voxelize is ops.hard_voxelize
    with pytest.raises(RuntimeError, match="dynamic_voxelize"):
        voxel_layer.dynamic_voxelize(torch.zeros(1, 3))
    bev_pool = importlib.util.module_from_spec(finder.find_spec("mmdet3d.ops.bev_pool.bev_pool_ext"))
    with pytest.raises(RuntimeError, match="bev_pool_forward"):
        bev_pool.bev_pool_forward()
    nms = importlib.util.module_from_spec(finder.find_spec("mmcv.ops.nms"))
    subclass = type("Derived", (nms.NMSop,), {})  # mmdet subclasses mmcv.ops classes at import time
    with pytest.raises(RuntimeError):
        subclass()
    with pytest.raises(RuntimeError, match="NMSop"):
        nms.NMSop.apply(torch.zeros(1, 4))  # an autograd Function's entry point


def test_installed_answers_imports_only_while_it_lasts(ops):
    with ops.installed():
        assert isinstance(sys.meta_path[0], ops.openmmlab.StandInFinder)
    assert not any(isinstance(finder, ops.openmmlab.StandInFinder) for finder in sys.meta_path)


# ----------------------------------------------------------------------------------------------- FlashOcc
@pytest.fixture(scope="module")
def flashocc_ops():
    return benchmark_module("reference_parity/flashocc_ops.py")


def test_bev_pool_v2_sums_depth_times_feature_of_each_pillar_into_its_cell(flashocc_ops):
    # One camera, 2 depth bins, a 1 x 2 feature map of 2 channels: 4 frustum points.
    depth = torch.tensor([[[[[0.5, 0.25]], [[0.125, 2.0]]]]])  # (B=1, N=1, D=2, fH=1, fW=2); flat: .5 .25 .125 2
    feat = torch.tensor([[[[[1.0, 10.0], [3.0, 30.0]]]]])  # (B, N, fH, fW, C=2); flat pixels: (1, 10), (3, 30)
    # Points sorted by BEV cell: cell 1 gets depth[0] * pixel 0 and depth[3] * pixel 1; cell 4 gets depth[2] * pixel 0;
    # depth[1] falls outside the grid (no entry).
    ranks_depth = torch.tensor([0, 3, 2], dtype=torch.int32)
    ranks_feat = torch.tensor([0, 1, 0], dtype=torch.int32)
    ranks_bev = torch.tensor([1, 1, 4], dtype=torch.int32)
    starts, lengths = torch.tensor([0, 2], dtype=torch.int32), torch.tensor([2, 1], dtype=torch.int32)
    out = flashocc_ops.bev_pool_v2(depth, feat, ranks_depth, ranks_feat, ranks_bev, (1, 1, 2, 3, 2), starts, lengths)

    assert out.shape == (1, 2, 1, 2, 3)  # (B, C, Dz, Dy, Dx)
    expected = torch.zeros(1, 1, 2, 3, 2)  # (B, Dz, Dy, Dx, C), flat cell index = (z * Dy + y) * Dx + x
    expected.view(-1, 2)[1] = torch.tensor([0.5 * 1 + 2.0 * 3, 0.5 * 10 + 2.0 * 30])
    expected.view(-1, 2)[4] = torch.tensor([0.125 * 1, 0.125 * 10])
    assert torch.equal(out, expected.permute(0, 4, 1, 2, 3))


def test_bev_pool_v2_refuses_intervals_that_do_not_cover_the_points(flashocc_ops):
    depth, feat = torch.ones(1, 1, 1, 1, 2), torch.ones(1, 1, 1, 2, 1)
    ranks, one_interval = torch.tensor([0, 1], dtype=torch.int32), (torch.tensor([0]), torch.tensor([1]))
    with pytest.raises(ValueError, match="cover"):
        flashocc_ops.bev_pool_v2(depth, feat, ranks, ranks, ranks, (1, 1, 1, 2, 1), *one_interval)
