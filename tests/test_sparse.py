"""Sparse convolutions against dense ``conv3d``, forward and backward, and the spconv CPU backward fix."""

from __future__ import annotations

import pytest
import torch
import torch.nn.functional as F
from spconv.pytorch import cppcore as spconv_cppcore
from spconv.pytorch import ops as spconv_ops

from occkit.geometry.grid import VoxelGrid
from occkit.geometry.voxelize import voxelize_batch
from occkit.models.sparse import (
    SPCONV_CPU_BACKWARD_PATCHED,
    SparseConv3d,
    SparseConvTensor,
    SparseSequential,
    SubMConv3d,
    sparse_tensor_from_voxels,
    spconv,
)

SHAPE = (8, 8, 6)
BATCH = 2
C_IN, C_OUT = 4, 6


def random_active_sites(num: int, seed: int) -> torch.Tensor:
    """``(V, 4)`` int64 unique ``(batch, x, y, z)`` over ``BATCH`` samples of a ``SHAPE`` grid."""
    generator = torch.Generator().manual_seed(seed)
    flat = torch.randperm(BATCH * SHAPE[0] * SHAPE[1] * SHAPE[2], generator=generator)[:num]
    batch, rest = flat // (SHAPE[0] * SHAPE[1] * SHAPE[2]), flat % (SHAPE[0] * SHAPE[1] * SHAPE[2])
    x, y, z = rest // (SHAPE[1] * SHAPE[2]), (rest // SHAPE[2]) % SHAPE[1], rest % SHAPE[2]
    return torch.stack((batch, x, y, z), dim=1)


def densify(features: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """``(B, C, X, Y, Z)`` with ``features`` at ``coords`` and zeros elsewhere, differentiable in ``features``."""
    dense = features.new_zeros(BATCH, *SHAPE, features.shape[1])
    dense = dense.index_put(tuple(coords.long().T), features)
    return dense.permute(0, 4, 1, 2, 3)


def at_sites(dense: torch.Tensor, coords: torch.Tensor) -> torch.Tensor:
    """``(V, C)`` rows of a ``(B, C, X, Y, Z)`` tensor at ``(V, 4)`` sites."""
    b, x, y, z = coords.long().T
    return dense.permute(0, 2, 3, 4, 1)[b, x, y, z]


def dense_weight(conv) -> torch.Tensor:
    """spconv 2.x weight ``(out, k0, k1, k2, in)`` as a leaf in ``conv3d`` layout ``(out, in, k0, k1, k2)``."""
    return conv.weight.detach().permute(0, 4, 1, 2, 3).contiguous().requires_grad_(True)


def make_inputs(seed: int = 0, num: int = 30):
    coords = random_active_sites(num, seed)
    generator = torch.Generator().manual_seed(seed + 1)
    features = torch.randn(num, C_IN, generator=generator)
    return coords, features


def test_spconv_weight_layout_is_out_k_k_k_in():
    conv = SubMConv3d(C_IN, C_OUT, 3, padding=1)
    assert tuple(conv.weight.shape) == (C_OUT, 3, 3, 3, C_IN)


def test_submanifold_conv_matches_dense_conv_forward_and_backward():
    torch.manual_seed(0)
    coords, features = make_inputs(seed=0)
    conv = SubMConv3d(C_IN, C_OUT, 3, padding=1, bias=True)
    torch.nn.init.normal_(conv.bias)

    sparse_features = features.clone().requires_grad_(True)
    out = conv(sparse_tensor_from_voxels(sparse_features, coords, SHAPE, BATCH))
    # Submanifold: outputs exactly at the input sites.
    assert torch.equal(out.indices.long(), coords)

    dense_features = features.clone().requires_grad_(True)
    weight = dense_weight(conv)
    bias = conv.bias.detach().clone().requires_grad_(True)
    dense_out = F.conv3d(densify(dense_features, coords), weight, bias, padding=1)
    expected = at_sites(dense_out, out.indices)
    torch.testing.assert_close(out.features, expected, rtol=1e-4, atol=1e-4)

    loss_weights = torch.randn(out.features.shape)
    (out.features * loss_weights).sum().backward()
    (expected * loss_weights).sum().backward()
    torch.testing.assert_close(sparse_features.grad, dense_features.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(conv.weight.grad.permute(0, 4, 1, 2, 3), weight.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(conv.bias.grad, bias.grad, rtol=1e-4, atol=1e-4)


def test_strided_sparse_conv_matches_dense_conv_forward_and_backward():
    torch.manual_seed(1)
    coords, features = make_inputs(seed=2)
    conv = SparseConv3d(C_IN, C_OUT, 3, stride=2, padding=1, bias=True)
    torch.nn.init.normal_(conv.bias)

    sparse_features = features.clone().requires_grad_(True)
    out = conv(sparse_tensor_from_voxels(sparse_features, coords, SHAPE, BATCH))
    out_shape = tuple((s + 2 - 3) // 2 + 1 for s in SHAPE)
    assert list(out.spatial_shape) == list(out_shape)

    dense_features = features.clone().requires_grad_(True)
    weight = dense_weight(conv)
    bias = conv.bias.detach().clone().requires_grad_(True)
    dense_in = densify(dense_features, coords)
    # An output site is active iff its receptive field holds an active input; only there does the bias apply.
    occupancy = densify(torch.ones(coords.shape[0], 1), coords)
    active = F.conv3d(occupancy, torch.ones(1, 1, 3, 3, 3), stride=2, padding=1) > 0
    assert int(active.sum()) == out.indices.shape[0]
    assert bool(active[:, 0][tuple(out.indices.long().T)].all())

    dense_out = F.conv3d(dense_in, weight, None, stride=2, padding=1) + bias.view(1, -1, 1, 1, 1) * active
    torch.testing.assert_close(out.dense(), dense_out, rtol=1e-4, atol=1e-4)

    expected = at_sites(dense_out, out.indices)
    loss_weights = torch.randn(out.features.shape)
    (out.features * loss_weights).sum().backward()
    (expected * loss_weights).sum().backward()
    torch.testing.assert_close(sparse_features.grad, dense_features.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(conv.weight.grad.permute(0, 4, 1, 2, 3), weight.grad, rtol=1e-4, atol=1e-4)
    torch.testing.assert_close(conv.bias.grad, bias.grad, rtol=1e-4, atol=1e-4)


def test_sparse_sequential_backward_matches_masked_dense_network():
    torch.manual_seed(2)
    coords, features = make_inputs(seed=4)
    net = SparseSequential(
        SubMConv3d(C_IN, C_OUT, 3, padding=1, bias=False, indice_key="subm1"),
        torch.nn.ReLU(),
        SparseConv3d(C_OUT, 5, 3, stride=2, padding=1, bias=False),
    )
    sparse_features = features.clone().requires_grad_(True)
    out = net(sparse_tensor_from_voxels(sparse_features, coords, SHAPE, BATCH))

    dense_features = features.clone().requires_grad_(True)
    occupancy = densify(torch.ones(coords.shape[0], 1), coords)
    hidden = F.conv3d(densify(dense_features, coords), dense_weight(net[0]), padding=1) * occupancy
    dense_out = F.conv3d(F.relu(hidden), dense_weight(net[2]), stride=2, padding=1)
    torch.testing.assert_close(out.dense(), dense_out, rtol=1e-4, atol=1e-4)

    out.features.square().sum().backward()
    at_sites(dense_out, out.indices).square().sum().backward()
    torch.testing.assert_close(sparse_features.grad, dense_features.grad, rtol=1e-4, atol=1e-4)


def test_sparse_tensor_from_voxels_keeps_occkit_axis_order():
    coords, features = make_inputs(seed=6)
    tensor = sparse_tensor_from_voxels(features, coords, SHAPE, BATCH)
    assert isinstance(tensor, SparseConvTensor)
    assert tensor.indices.dtype == torch.int32
    assert list(tensor.spatial_shape) == list(SHAPE)
    dense = tensor.dense()
    assert tuple(dense.shape) == (BATCH, C_IN, *SHAPE)
    torch.testing.assert_close(dense, densify(features, coords))


def test_voxelized_points_train_through_a_sparse_encoder():
    grid = VoxelGrid((0.0, 0.0, 0.0, 4.0, 4.0, 3.0), 0.5)
    assert grid.shape == SHAPE
    generator = torch.Generator().manual_seed(8)
    clouds = [
        (torch.rand(60, 4, generator=generator) * torch.tensor([4.0, 4.0, 3.0, 1.0])).requires_grad_(True)
        for _ in range(BATCH)
    ]
    features, coords, _ = voxelize_batch(clouds, grid, 5, 100)
    net = SparseSequential(SubMConv3d(4, 8, 3, padding=1), torch.nn.ReLU(), SparseConv3d(8, 8, 3, 2, 1))
    out = net(sparse_tensor_from_voxels(features, coords, grid.shape, BATCH))
    out.features.sum().backward()
    for cloud in clouds:
        assert cloud.grad is not None and bool(cloud.grad.abs().sum() > 0)
    assert all(p.grad is not None and bool(p.grad.abs().sum() > 0) for p in net.parameters())


@pytest.mark.parametrize(
    ("features", "coords", "spatial_shape", "batch_size", "error", "message"),
    [
        (torch.zeros(3), torch.zeros(3, 4, dtype=torch.long), SHAPE, 1, ValueError, r"features must have shape"),
        (torch.zeros(3, 2), torch.zeros(3, 3, dtype=torch.long), SHAPE, 1, ValueError, r"coords must have shape"),
        (torch.zeros(3, 2), torch.zeros(2, 4, dtype=torch.long), SHAPE, 1, ValueError, r"coords must have shape"),
        (torch.zeros(3, 2), torch.zeros(3, 4), SHAPE, 1, TypeError, "coords must be an integer tensor"),
        (torch.zeros(3, 2), torch.zeros(3, 4, dtype=torch.long), (8, 8), 1, ValueError, "spatial_shape"),
        (torch.zeros(3, 2), torch.zeros(3, 4, dtype=torch.long), SHAPE, 0, ValueError, "batch_size must be >= 1"),
    ],
)
def test_sparse_tensor_from_voxels_rejects_bad_input(features, coords, spatial_shape, batch_size, error, message):
    with pytest.raises(error, match=message):
        sparse_tensor_from_voxels(features, coords, spatial_shape, batch_size)


def test_module_exports_spconv_pytorch():
    assert spconv.SubMConv3d is SubMConv3d
    assert spconv.SparseConvTensor is SparseConvTensor


@pytest.mark.skipif(torch.cuda.is_available(), reason="the patch is only installed without CUDA")
def test_cpu_backward_patch_is_active_and_needed(monkeypatch):
    assert SPCONV_CPU_BACKWARD_PATCHED
    assert spconv_ops.get_current_stream() == 0
    coords, features = make_inputs(seed=9)
    conv = SubMConv3d(C_IN, C_OUT, 3, padding=1)

    def backward():
        leaf = features.clone().requires_grad_(True)
        conv(sparse_tensor_from_voxels(leaf, coords, SHAPE, BATCH)).features.sum().backward()
        return leaf.grad

    assert backward().abs().sum() > 0
    # Without the patch, spconv 2.3.8's backward asks CUDA for its current stream and fails.
    monkeypatch.setattr(spconv_ops, "get_current_stream", spconv_cppcore.get_current_stream)
    with pytest.raises(RuntimeError):
        backward()


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_is_left_unpatched_and_matches_cpu():
    assert not SPCONV_CPU_BACKWARD_PATCHED
    assert spconv_ops.get_current_stream is spconv_cppcore.get_current_stream
    torch.manual_seed(3)
    coords, features = make_inputs(seed=10)
    results = []
    for device in ("cpu", "cuda"):
        torch.manual_seed(4)
        net = SparseSequential(SubMConv3d(C_IN, C_OUT, 3, padding=1), SparseConv3d(C_OUT, C_OUT, 3, 2, 1)).to(device)
        leaf = features.to(device).requires_grad_(True)
        out = net(sparse_tensor_from_voxels(leaf, coords.to(device), SHAPE, BATCH))
        dense = out.dense()
        dense.square().sum().backward()
        results.append((dense.cpu(), leaf.grad.cpu(), net[0].weight.grad.cpu()))
    for cpu_value, cuda_value in zip(*results, strict=True):
        torch.testing.assert_close(cuda_value, cpu_value, rtol=1e-3, atol=1e-3)


def test_cpu_scatter_add_is_race_free_on_large_layers():
    # spconv's own CPU scatter_add shares row pointers between threads; with 200k rows it adds rows to wrong
    # outputs on every run with two threads. occkit's replacement must match index_add_ exactly.
    from spconv.pytorch import ops as spconv_ops
    from spconv.pytorch.cppcore import torch_tensor_to_tv

    generator = torch.Generator().manual_seed(0)
    rows, channels = 200_000, 16
    inputs = torch.randn(rows, channels, generator=generator)
    indices = torch.randperm(rows, generator=generator).int()
    out = torch.ones(rows, channels)
    spconv_ops.SpconvOps.scatter_add_cpu(
        torch_tensor_to_tv(out), torch_tensor_to_tv(inputs), torch_tensor_to_tv(indices[: rows // 2])
    )
    expected = torch.ones(rows, channels).index_add_(0, indices[: rows // 2].long(), inputs[: rows // 2])
    assert torch.equal(out, expected)


def test_large_submanifold_conv_matches_dense_conv():
    # Big enough that the parallel CPU kernels split the work between threads.
    generator = torch.Generator().manual_seed(1)
    shape = (48, 48, 24)
    flat = torch.randperm(48 * 48 * 24, generator=generator)[:20_000]
    coords = torch.stack((flat // (48 * 24), (flat // 24) % 48, flat % 24), dim=1)
    features = torch.randn(coords.shape[0], 8, generator=generator)
    conv = SubMConv3d(8, 8, 3, padding=1, bias=False)
    torch.nn.init.normal_(conv.weight, generator=generator)
    indices = torch.cat((torch.zeros(coords.shape[0], 1, dtype=torch.long), coords), dim=1)
    out = conv(sparse_tensor_from_voxels(features, indices, shape, 1))
    dense_in = torch.zeros(1, 8, *shape)
    dense_in[0, :, coords[:, 0], coords[:, 1], coords[:, 2]] = features.T
    dense_weight = conv.weight.permute(0, 4, 1, 2, 3)  # (out, k0, k1, k2, in) -> (out, in, k0, k1, k2)
    dense_out = torch.nn.functional.conv3d(dense_in, dense_weight, padding=1)
    out_coords = out.indices[:, 1:].long()
    expected = dense_out[0, :, out_coords[:, 0], out_coords[:, 1], out_coords[:, 2]].T
    torch.testing.assert_close(out.features, expected, rtol=1e-4, atol=1e-4)
