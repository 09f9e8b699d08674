"""The parity harness's PyTorch definitions of the references' CUDA ops, against the ops' documented semantics.

The model goldens are only as good as these stand-ins, which replace compiled ops while the reference code runs
(``benchmarks/reference_parity/``); each is checked here on cases small enough to work out by hand.
"""

from __future__ import annotations

import pytest
import torch
from conftest import benchmark_module


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


def test_mmcv_ops_placeholders_fail_loudly_when_used():
    openmmlab = benchmark_module("reference_parity/openmmlab.py")
    nms = openmmlab.placeholder("mmcv.ops.nms")
    with pytest.raises(RuntimeError, match="stand-in of the parity harness"):
        nms()
