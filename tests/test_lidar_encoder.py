"""LiDAR branch: shapes of the DAOcc config, a masked dense-convolution reference, empty LiDAR, voxel limits."""

from __future__ import annotations

import time

import pytest
import torch
import torch.nn.functional as F
from torch import nn

import occkit.models.lidar_encoder as lidar_encoder
from occkit.config import ConfigError, field_docs, from_dict, to_dict
from occkit.models.lidar_encoder import (
    LidarEncoder,
    LidarEncoderConfig,
    SparseBasicBlock,
    SparseEncoder,
    remove_close_points,
    sparse_encoder_output_shape,
)
from occkit.models.sparse import SparseSequential

#: A small config with the paper's architecture; z is 0.2 m as in DAOcc so the z stack 31 -> 16 -> 8 -> 3 -> 1 works.
TINY = LidarEncoderConfig(
    point_cloud_range=(-20.0, -20.0, -3.0, 20.0, 20.0, 3.0),
    voxel_size=(0.4, 0.4, 0.2),
    base_channels=8,
    encoder_channels=((8, 8, 16), (16, 16, 32), (32, 32, 32), (32, 32)),
    output_channels=32,
)


def random_points(num: int, cfg: LidarEncoderConfig, generator: torch.Generator) -> torch.Tensor:
    """``(num, 5)`` points uniform inside the config's range: ``(x, y, z, intensity, time lag)``."""
    bounds = torch.tensor(cfg.point_cloud_range)
    xyz = bounds[:3] + torch.rand(num, 3, generator=generator) * (bounds[3:] - bounds[:3])
    return torch.cat((xyz, torch.rand(num, 1, generator=generator), torch.rand(num, 1, generator=generator)), dim=1)


def pad_batch(clouds: list[torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Zero-padded ``(B, P_max, C)`` batch and ``(B,)`` counts, as the data loader gives them."""
    num_points = torch.tensor([c.shape[0] for c in clouds], dtype=torch.int64)
    points = torch.zeros(len(clouds), max(int(num_points.max()), 1), clouds[0].shape[1])
    for b, cloud in enumerate(clouds):
        points[b, : cloud.shape[0]] = cloud
    return points, num_points


# ------------------------------------------------------------------------------------------------ paper config
def expected_parameter_count(cfg: LidarEncoderConfig) -> int:
    """Conv weights (no bias) plus BN affine parameters, counted from the block structure."""
    total = 27 * cfg.in_channels * cfg.base_channels + 2 * cfg.base_channels
    channels = cfg.base_channels
    for i, stage in enumerate(cfg.encoder_channels):
        for j, out in enumerate(stage):
            if j == len(stage) - 1 and i != len(cfg.encoder_channels) - 1:
                total += 27 * channels * out + 2 * out
            else:
                total += 2 * (27 * out * out + 2 * out)
            channels = out
    return total + 3 * channels * cfg.output_channels + 2 * cfg.output_channels


def test_paper_config_shapes_and_parameter_count():
    cfg = LidarEncoderConfig()
    assert cfg.grid.shape == (1440, 1440, 40)
    assert cfg.sparse_shape == (1440, 1440, 41)
    assert sparse_encoder_output_shape(cfg.sparse_shape, cfg.downsample_paddings) == (180, 180, 2)
    model = LidarEncoder(cfg)
    assert (model.out_channels, model.bev_shape) == (256, (180, 180)) == (cfg.out_channels, cfg.bev_shape)
    num_params = sum(p.numel() for p in model.encoder.parameters())
    print(f"paper-config sparse encoder parameters: {num_params}")
    assert num_params == expected_parameter_count(cfg) == 2_694_352

    # BEVFusion's parameter names, so that a reference state dict maps key for key.
    names = dict(model.encoder.named_parameters())
    for name in (
        "conv_input.0.weight",
        "encoder_layers.encoder_layer1.0.conv1.weight",
        "encoder_layers.encoder_layer1.1.bn2.weight",
        "encoder_layers.encoder_layer1.2.0.weight",
        "encoder_layers.encoder_layer4.1.conv2.weight",
        "conv_out.0.weight",
        "conv_out.1.bias",
    ):
        assert name in names
    assert tuple(names["conv_out.0.weight"].shape) == (128, 1, 1, 3, 128)
    assert isinstance(model.encoder.encoder_layers.encoder_layer3[2][0], lidar_encoder.SparseConv3d)
    assert list(model.encoder.encoder_layers.encoder_layer3[2][0].padding) == [1, 1, 0]

    generator = torch.Generator().manual_seed(0)
    points, num_points = pad_batch([random_points(3000, cfg, generator), random_points(2000, cfg, generator)])
    with torch.no_grad():
        bev = model(points, num_points)
    assert bev.shape == (2, 256, 180, 180) and bev.dtype == torch.float32
    assert bool(torch.isfinite(bev).all()) and all(bool(bev[b].abs().sum() > 0) for b in range(2))


@pytest.mark.parametrize(
    ("point_cloud_range", "voxel_size", "paddings", "expected"),
    [
        ((-20, -20, -3, 20, 20, 3), (0.4, 0.4, 0.2), ((1, 1, 1), (1, 1, 1), (1, 1, 0)), (13, 13, 1)),
        ((-10, -12, -2, 10, 12, 3), (0.5, 0.4, 0.2), ((1, 1, 1), (1, 1, 1), (1, 1, 0)), (5, 8, 1)),
        ((-10, -10, -2, 10, 10, 1.8), (0.5, 0.5, 0.2), ((1, 1, 0), (1, 1, 1)), (10, 10, 2)),
    ],
)
def test_output_size_follows_the_conv_arithmetic(point_cloud_range, voxel_size, paddings, expected):
    channels = ((4, 4, 8), (8, 8, 8), (8, 8, 8), (8, 8))[: len(paddings) + 1]
    cfg = LidarEncoderConfig(
        point_cloud_range=point_cloud_range, voxel_size=voxel_size, base_channels=4,
        encoder_channels=channels, downsample_paddings=paddings, output_channels=6,
    )  # fmt: skip
    model = LidarEncoder(cfg).eval()
    assert model.bev_shape == expected[:2] and model.out_channels == 6 * expected[2]
    points, num_points = pad_batch([random_points(500, cfg, torch.Generator().manual_seed(1))])
    with torch.no_grad():
        bev = model(points, num_points)
    assert bev.shape == (1, 6 * expected[2], *expected[:2])


def test_grid_too_low_for_the_z_stack_is_a_config_error():
    # 6 m of 0.4 m voxels: z 15 + 1 -> 8 -> 4 -> 1, and conv_out's kernel 3 no longer fits.
    data = to_dict(TINY) | {"voxel_size": [0.4, 0.4, 0.4]}
    with pytest.raises(ConfigError, match="conv_out"):
        from_dict(LidarEncoderConfig, data)


@pytest.mark.parametrize(
    ("changes", "message"),
    [
        ({"encoder_channels": ((8, 16, 16), (16, 16, 32), (32, 32, 32), (32, 32))}, "residual basic block"),
        ({"downsample_paddings": ((1, 1, 1), (1, 1, 1))}, "downsample_paddings"),
        ({"voxel_size": (0.3, 0.4, 0.2)}, "whole number"),
        ({"max_voxels_train": 0}, "max_voxels_train"),
    ],
)
def test_bad_configs_are_rejected(changes, message):
    with pytest.raises(ValueError, match=message):
        LidarEncoderConfig(**(to_dict(TINY) | changes))


def test_config_round_trips_and_documents_every_field():
    for cfg in (LidarEncoderConfig(), TINY):
        assert from_dict(LidarEncoderConfig, to_dict(cfg)) == cfg
    docs = field_docs(LidarEncoderConfig)
    assert all(docs.get(name) for name in to_dict(TINY))


# ------------------------------------------------------------------------------------------ dense reference
def dense_leaf(conv: nn.Module) -> torch.Tensor:
    """spconv weight ``(out, kx, ky, kz, in)`` as a ``conv3d`` weight ``(out, in, kx, ky, kz)`` leaf."""
    return conv.weight.detach().permute(0, 4, 1, 2, 3).contiguous().requires_grad_(True)


class MaskedDenseReference:
    """The sparse encoder on dense tensors: values stay exactly zero outside the active sites of each layer."""

    def __init__(self, encoder: SparseEncoder) -> None:
        self.encoder = encoder
        self.weights: dict[nn.Module, torch.Tensor] = {}

    def conv(self, conv: nn.Module, x: torch.Tensor, mask: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        weight = self.weights.setdefault(conv, dense_leaf(conv))
        stride, padding = tuple(conv.stride), tuple(conv.padding)
        out = F.conv3d(x, weight, stride=stride, padding=padding)
        if not conv.subm:
            # A strided sparse conv is active wherever its receptive field holds an active input site.
            kernel = torch.ones(1, 1, *conv.kernel_size)
            mask = (F.conv3d(mask, kernel, stride=stride, padding=padding) > 0).to(x.dtype)
        # A submanifold conv outputs only at its input sites.
        return out * mask, mask

    @staticmethod
    def bn(bn: nn.BatchNorm1d, x: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
        normed = F.batch_norm(x, bn.running_mean, bn.running_var, bn.weight, bn.bias, training=False, eps=bn.eps)
        return normed * mask

    def conv_bn_relu(self, module: SparseSequential, x, mask):
        x, mask = self.conv(module[0], x, mask)
        return F.relu(self.bn(module[1], x, mask)), mask

    def block(self, block: SparseBasicBlock, x, mask):
        out, _ = self.conv(block.conv1, x, mask)
        out = F.relu(self.bn(block.bn1, out, mask))
        out, _ = self.conv(block.conv2, out, mask)
        return F.relu(self.bn(block.bn2, out, mask) + x), mask

    def __call__(self, features: torch.Tensor, coords: torch.Tensor, batch_size: int) -> torch.Tensor:
        shape = self.encoder.sparse_shape
        index = tuple(coords.T)
        x = features.new_zeros(batch_size, *shape, features.shape[1]).index_put(index, features)
        x = x.permute(0, 4, 1, 2, 3)
        mask = torch.zeros(batch_size, *shape).index_put(index, torch.ones(coords.shape[0])).unsqueeze(1)
        x, mask = self.conv_bn_relu(self.encoder.conv_input, x, mask)
        for stage in self.encoder.encoder_layers:
            for module in stage:
                step = self.block if isinstance(module, SparseBasicBlock) else self.conv_bn_relu
                x, mask = step(module, x, mask)
        x, mask = self.conv_bn_relu(self.encoder.conv_out, x, mask)
        b, c, nx, ny, nz = x.shape
        return x.permute(0, 1, 4, 2, 3).reshape(b, c * nz, nx, ny)


def randomize_batch_norms(module: nn.Module, generator: torch.Generator) -> None:
    for bn in module.modules():
        if isinstance(bn, nn.BatchNorm1d):
            channels = bn.num_features
            bn.running_mean.copy_(0.2 * torch.randn(channels, generator=generator))
            bn.running_var.copy_(0.5 + torch.rand(channels, generator=generator))
            with torch.no_grad():
                bn.weight.copy_(0.5 + torch.rand(channels, generator=generator))
                bn.bias.copy_(0.2 * torch.randn(channels, generator=generator))


@pytest.mark.parametrize(
    ("sparse_shape", "encoder_channels", "paddings", "num_active"),
    [
        # The paper's four stages and paddings: x 24 -> 12 -> 6 -> 3, z 25 -> 13 -> 7 -> 3 -> 1.
        ((24, 24, 25), ((4, 4, 6), (6, 6, 8), (8, 8, 8), (8, 8)), ((1, 1, 1), (1, 1, 1), (1, 1, 0)), 400),
        # One downsampling without z padding: x 16 -> 8, z 11 -> 5 -> 2; a finer map with two heights per column
        # checks the masks closely and the BEV channel order c * Z' + z.
        ((16, 16, 11), ((4, 4, 6), (6, 6)), ((1, 1, 0),), 300),
    ],
)
def test_sparse_encoder_matches_masked_dense_convolutions(sparse_shape, encoder_channels, paddings, num_active):
    generator = torch.Generator().manual_seed(0)
    batch_size, in_channels = 2, 3
    encoder = SparseEncoder(in_channels, sparse_shape, 4, encoder_channels, paddings, output_channels=5)
    randomize_batch_norms(encoder, generator)
    encoder.eval()

    cells = torch.randperm(batch_size * sparse_shape[0] * sparse_shape[1] * sparse_shape[2], generator=generator)
    coords = torch.stack(torch.unravel_index(cells[:num_active], (batch_size, *sparse_shape)), dim=1)
    features = torch.randn(num_active, in_channels, generator=generator)

    sparse_in = features.clone().requires_grad_(True)
    bev = encoder(sparse_in, coords, batch_size)
    reference = MaskedDenseReference(encoder)
    dense_in = features.clone().requires_grad_(True)
    expected = reference(dense_in, coords, batch_size)
    assert bev.shape == expected.shape == (batch_size, encoder.out_channels, *encoder.bev_shape)
    assert bool(expected.abs().sum() > 0)
    torch.testing.assert_close(bev, expected, rtol=1e-4, atol=1e-4)

    upstream = torch.randn(bev.shape, generator=generator)
    (bev * upstream).sum().backward()
    (expected * upstream).sum().backward()
    torch.testing.assert_close(sparse_in.grad, dense_in.grad, rtol=1e-4, atol=1e-4)
    assert len(reference.weights) == sum(1 for m in encoder.modules() if hasattr(m, "subm"))
    for conv, weight in reference.weights.items():
        torch.testing.assert_close(conv.weight.grad.permute(0, 4, 1, 2, 3), weight.grad, rtol=1e-4, atol=1e-4)


# ----------------------------------------------------------------------------------------------- empty LiDAR
def test_empty_lidar_gives_zeros_without_calling_spconv(monkeypatch):
    def fail(*args, **kwargs):
        raise AssertionError("spconv must not run on an empty batch")

    monkeypatch.setattr(lidar_encoder, "sparse_tensor_from_voxels", fail)
    model = LidarEncoder(TINY)
    generator = torch.Generator().manual_seed(2)
    near_ego = torch.rand(50, 5, generator=generator) - 0.5
    out_of_range = random_points(50, TINY, generator) + torch.tensor([100.0, 0, 0, 0, 0])
    cases = [
        (torch.zeros(3, 7, 5), torch.zeros(3, dtype=torch.int64)),
        pad_batch([near_ego, out_of_range]),
        (torch.zeros(2, 0, 5, dtype=torch.float64), torch.zeros(2, dtype=torch.int64)),
    ]
    for points, num_points in cases:
        bev = model(points, num_points)
        assert bev.shape == (points.shape[0], 32, 13, 13) and bev.dtype == points.dtype
        assert bev.device == points.device and not bool(bev.any())
        # Every parameter still gets a gradient (zero), as on a step with LiDAR.
        model.zero_grad(set_to_none=True)
        bev.float().sum().backward()
        assert all(p.grad is not None and not bool(p.grad.any()) for p in model.parameters())
    with torch.no_grad():
        assert not model(*cases[0]).requires_grad


def test_partially_empty_batch_matches_samples_run_alone():
    model = LidarEncoder(TINY).eval()
    generator = torch.Generator().manual_seed(3)
    cloud = random_points(2000, TINY, generator)
    points, num_points = pad_batch([torch.zeros(0, 5), cloud, torch.zeros(0, 5)])
    with torch.no_grad():
        bev = model(points, num_points)
        alone = model(*pad_batch([cloud]))
    assert bev.shape == (3, 32, 13, 13)
    assert not bool(bev[0].any()) and not bool(bev[2].any())
    torch.testing.assert_close(bev[1], alone[0], rtol=1e-5, atol=1e-5)
    # Rows beyond num_points are never read, whatever they hold.
    points[0, :5] = cloud[:5]
    with torch.no_grad():
        assert not bool(model(points, num_points)[0].any())


def test_remove_close_points_drops_the_square_around_the_sensor():
    points = torch.tensor(
        [
            [0.0, 0.0, 10.0, 1.0],  # above the sensor: removed at any height
            [0.99, -0.99, -2.0, 2.0],
            [-0.5, 1.0, 0.0, 3.0],  # |y| = 1 is not below the radius
            [1.5, 0.2, 0.0, 4.0],
            [-3.0, -3.0, 0.0, 5.0],
        ]
    )
    kept = remove_close_points(points, 1.0)
    assert torch.equal(kept, points[2:])
    assert torch.equal(remove_close_points(points, 0.0), points)
    assert torch.equal(remove_close_points(points, 2.0), points[4:])


def test_encoder_removes_near_ego_points_and_keeps_z_inside_the_voxel_grid():
    generator = torch.Generator().manual_seed(4)
    far = random_points(300, TINY, generator)
    far = far[(far[:, 0].abs() >= 1.0) | (far[:, 1].abs() >= 1.0)]
    near = torch.rand(40, 5, generator=generator) * torch.tensor([1.8, 1.8, 5.0, 1.0, 1.0]) - torch.tensor(
        [0.9, 0.9, 2.5, 0.0, 0.0]
    )
    model = LidarEncoder(TINY)
    features, coords, counts = model.voxelize(*pad_batch([torch.cat((near, far))]))
    reference_features, reference_coords, _ = LidarEncoder(TINY).voxelize(*pad_batch([far]))
    assert torch.equal(coords, reference_coords) and torch.equal(features, reference_features)
    assert int(counts.sum()) == far.shape[0]
    # Voxels fill the 30 z cells of the grid; the encoder's 31st z cell is always empty (SECOND convention).
    assert TINY.grid.shape[2] == 30 and TINY.sparse_shape[2] == 31
    assert int(coords[:, 3].max()) <= 29
    keep_all = LidarEncoder(LidarEncoderConfig(**(to_dict(TINY) | {"remove_close": 0.0})))
    assert int(keep_all.voxelize(*pad_batch([torch.cat((near, far))]))[2].sum()) == far.shape[0] + near.shape[0]


def test_max_voxels_depends_on_training_mode():
    cfg = LidarEncoderConfig(**(to_dict(TINY) | {"max_voxels_train": 5, "max_voxels_test": 7}))
    model = LidarEncoder(cfg)
    generator = torch.Generator().manual_seed(5)
    batch = pad_batch([random_points(400, cfg, generator), random_points(300, cfg, generator)])
    for train, limit in ((True, 5), (False, 7)):
        model.train(train)
        assert model.max_voxels == limit
        _, coords, _ = model.voxelize(*batch)
        assert torch.bincount(coords[:, 0], minlength=2).tolist() == [limit, limit]
        with torch.no_grad():
            assert model(*batch).shape == (2, 32, 13, 13)


def test_voxelization_is_not_differentiable_and_rejects_bad_counts():
    model = LidarEncoder(TINY)
    points, num_points = pad_batch([random_points(100, TINY, torch.Generator().manual_seed(6))])
    features, _, _ = model.voxelize(points.requires_grad_(True), num_points)
    assert not features.requires_grad
    with pytest.raises(ValueError, match="num_points"):
        model.voxelize(points, torch.tensor([101]))
    with pytest.raises(ValueError, match="points must have shape"):
        model.voxelize(points[..., :4], num_points)


# ----------------------------------------------------------------------------------------------- training
def test_tiny_config_trains_every_parameter_quickly():
    torch.manual_seed(0)
    model = LidarEncoder(TINY).train()
    generator = torch.Generator().manual_seed(7)
    batch = pad_batch([random_points(20_000, TINY, generator)])
    model(*batch).square().mean().backward()  # warm-up: first calls build spconv's kernels
    model.zero_grad(set_to_none=True)
    start = time.perf_counter()
    bev = model(*batch)
    bev.square().mean().backward()
    elapsed = time.perf_counter() - start
    print(f"tiny config forward + backward on 20k points: {elapsed:.3f} s")
    assert bev.shape == (1, 32, 13, 13)
    for name, param in model.named_parameters():
        assert param.grad is not None, name
        assert bool(torch.isfinite(param.grad).all()), name
    assert sum(bool(p.grad.any()) for p in model.parameters()) == len(list(model.parameters()))
    # Generous bound: about 0.2 s on two idle cores; this only guards against a slow path sneaking in.
    assert elapsed < 3.0


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    torch.manual_seed(0)
    model = LidarEncoder(TINY).eval()
    points, num_points = pad_batch([random_points(3000, TINY, torch.Generator().manual_seed(8)), torch.zeros(0, 5)])
    with torch.no_grad():
        cpu = model(points, num_points)
        cuda = model.cuda()(points.cuda(), num_points.cuda())
        empty = model(torch.zeros(2, 4, 5, device="cuda"), torch.zeros(2, dtype=torch.int64, device="cuda"))
    assert cuda.device.type == "cuda" and empty.device.type == "cuda" and not bool(empty.any())
    torch.testing.assert_close(cuda.cpu(), cpu, rtol=1e-3, atol=1e-3)
