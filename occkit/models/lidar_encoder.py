"""The LiDAR branch of DAOcc: multi-sweep points -> hard voxelization -> SECOND-style sparse 3D encoder -> dense BEV.

The design is BEVFusion's ``SparseEncoder`` with ``block_type="basicblock"`` as configured by DAOcc:

* points ``(x, y, z, intensity, time lag)`` in the key LiDAR frame; points with ``|x| < 1 and |y| < 1`` are removed;
* hard voxelization on a 0.075 x 0.075 x 0.2 m grid over ``[-54, 54] x [-54, 54] x [-5, 3]`` (1440 x 1440 x 40),
  at most 10 points per voxel, voxel feature = mean of its points;
* the sparse encoder sees a spatial shape of 1440 x 1440 x 41: SECOND's extra z cell, see
  :attr:`LidarEncoderConfig.sparse_shape_z_extra`;
* ``conv_input`` (SubM 5 -> 16), four stages of submanifold basic blocks, each stage but the last ending in a
  stride-2 sparse convolution, then ``conv_out`` (kernel (1, 1, 3), stride (1, 1, 2)) that squeezes z to 2;
* the dense ``(B, 128, 180, 180, 2)`` volume is flattened to a ``(B, 256, 180, 180)`` BEV map, channel ``c * Z + z``.

The layers are spconv modules (they hold the weights, and spconv runs them on CUDA); on the CPU the encoder runs the
same layers through :mod:`occkit.models.sparse_gemm` (:attr:`SparseEncoder.backend`).

Every tensor keeps occkit's ``(x, y, z)`` axis order (see :mod:`occkit.models.sparse`); BEV maps are ``(B, C, X, Y)``
with dim 2 along x (forward) and dim 3 along y. Parameter names follow BEVFusion's (``conv_input.0``,
``encoder_layers.encoder_layer1.0.conv1``, ``bn1``, ..., ``conv_out.0``); the weights are spconv 2.x's
``(out, kx, ky, kz, in)``, while DAOcc's checkpoints hold its bundled spconv 1.x's ``(kx, ky, kz, in, out)``, which
``occkit convert`` permutes (:mod:`occkit.convert`).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from occkit.geometry.grid import VoxelGrid
from occkit.geometry.voxelize import voxelize_batch
from occkit.models.sparse import (
    SparseConv3d,
    SparseConvTensor,
    SparseSequential,
    SubMConv3d,
    sparse_tensor_from_voxels,
    spconv,
)
from occkit.models.sparse_gemm import build_neighbour_tables, gather_gemm_conv
from occkit.models.sparse_rules import ConvSpec, coordinate_keys, encoder_conv_specs

__all__ = [
    "SPARSE_BACKENDS",
    "LidarEncoderConfig",
    "LidarEncoder",
    "SparseEncoder",
    "SparseBasicBlock",
    "remove_close_points",
    "sparse_encoder_output_shape",
]

#: How the sparse encoder's convolutions run: ``spconv`` (the reference, and the CUDA path), ``gather_gemm``
#: (:mod:`occkit.models.sparse_gemm`, the CPU path) or ``auto`` (spconv on CUDA tensors, gather_gemm otherwise).
SPARSE_BACKENDS = ("auto", "spconv", "gather_gemm")

#: BatchNorm settings of SECOND / BEVFusion sparse encoders (mmcv ``BN1d`` with eps 1e-3, momentum 0.01).
BN_EPS = 1e-3
BN_MOMENTUM = 0.01

#: ``conv_out`` of the reference: kernel, stride and padding per axis ``(x, y, z)``; it only downsamples z.
CONV_OUT_KERNEL = (1, 1, 3)
CONV_OUT_STRIDE = (1, 1, 2)
CONV_OUT_PADDING = (0, 0, 0)


@dataclass(frozen=True)
class LidarEncoderConfig:
    """Voxelization and sparse encoder of the LiDAR branch; the defaults are DAOcc's nuScenes config."""

    point_cloud_range: tuple[float, float, float, float, float, float] = (-54.0, -54.0, -5.0, 54.0, 54.0, 3.0)
    """Voxelized region ``(x_min, y_min, z_min, x_max, y_max, z_max)`` in metres, key LiDAR frame."""
    voxel_size: tuple[float, float, float] = (0.075, 0.075, 0.2)
    """Voxel edge lengths ``(x, y, z)`` in metres."""
    max_points_per_voxel: int = 10
    """Points kept per voxel (the first ones in input order); the voxel feature is their mean."""
    max_voxels_train: int = 120000
    """Voxels kept per sample in training mode (the first to appear)."""
    max_voxels_test: int = 160000
    """Voxels kept per sample in eval mode."""
    in_channels: int = 5
    """Point channels fed to the encoder, the first ones of each point: (x, y, z, intensity, time lag)."""
    remove_close: float = 1.0
    """Drop points with both |x| and |y| below this many metres (returns from the ego car); 0 keeps all."""
    base_channels: int = 16
    """Output channels of conv_input, the submanifold convolution on the raw voxel features."""
    encoder_channels: tuple[tuple[int, ...], ...] = ((16, 16, 32), (32, 32, 64), (64, 64, 128), (128, 128))
    """Per stage, output channels of each block; the last entry of every stage but the last is a stride-2 conv."""
    downsample_paddings: tuple[tuple[int, int, int], ...] = ((1, 1, 1), (1, 1, 1), (1, 1, 0))
    """Padding (x, y, z) of the stride-2 convolution closing each stage but the last."""
    output_channels: int = 128
    """Channels of conv_out, the (1, 1, 3) stride (1, 1, 2) convolution that squeezes z before the BEV flattening."""
    sparse_shape_z_extra: int = 1
    """Extra z cells on top of the grid in the encoder's spatial shape (SECOND/mmdet3d: 40 + 1 = 41 -> 21, 11, 5, 2)."""

    def __post_init__(self) -> None:
        for name in ("max_points_per_voxel", "max_voxels_train", "max_voxels_test", "in_channels", "base_channels"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be >= 1, got {getattr(self, name)}")
        if self.in_channels < 3:
            raise ValueError(f"in_channels must include x, y, z (>= 3), got {self.in_channels}")
        if self.output_channels < 1:
            raise ValueError(f"output_channels must be >= 1, got {self.output_channels}")
        if self.remove_close < 0:
            raise ValueError(f"remove_close must be >= 0 metres, got {self.remove_close}")
        if self.sparse_shape_z_extra < 0:
            raise ValueError(f"sparse_shape_z_extra must be >= 0, got {self.sparse_shape_z_extra}")
        # Building the grid checks the range and voxel size; the shape check catches a grid the convolutions
        # would shrink to nothing, here rather than deep inside spconv.
        _check_architecture(self.base_channels, self.encoder_channels, self.downsample_paddings)
        sparse_encoder_output_shape(self.sparse_shape, self.downsample_paddings)

    @property
    def grid(self) -> VoxelGrid:
        """The voxelization grid, shape ``(X, Y, Z)`` (1440 x 1440 x 40 by default)."""
        return VoxelGrid(self.point_cloud_range, self.voxel_size)

    @property
    def sparse_shape(self) -> tuple[int, int, int]:
        """Spatial shape given to spconv, ``(X, Y, Z + sparse_shape_z_extra)`` (1440 x 1440 x 41 by default)."""
        x, y, z = self.grid.shape
        return (x, y, z + self.sparse_shape_z_extra)

    @property
    def bev_shape(self) -> tuple[int, int]:
        """``(X', Y')`` of the output BEV map (180 x 180 by default)."""
        return sparse_encoder_output_shape(self.sparse_shape, self.downsample_paddings)[:2]

    @property
    def out_channels(self) -> int:
        """Channels of the output BEV map, ``output_channels * Z'`` (128 * 2 = 256 by default)."""
        return self.output_channels * sparse_encoder_output_shape(self.sparse_shape, self.downsample_paddings)[2]


def _conv_size(size: int, kernel: int, stride: int, padding: int) -> int:
    """Output length of a convolution along one axis (no dilation): spconv's own arithmetic."""
    return (size + 2 * padding - kernel) // stride + 1


def sparse_encoder_output_shape(
    sparse_shape: Sequence[int], downsample_paddings: Sequence[Sequence[int]]
) -> tuple[int, int, int]:
    """Spatial shape ``(X', Y', Z')`` of the sparse encoder's last volume, before the BEV flattening.

    Submanifold convolutions keep the shape; each stride-2 kernel-3 convolution maps ``n -> (n + 2p - 3) // 2 + 1``
    and ``conv_out`` (kernel ``(1, 1, 3)``, stride ``(1, 1, 2)``, no padding) maps ``z -> (z - 3) // 2 + 1``.

    Args:
        sparse_shape: ``(X, Y, Z)`` spatial shape given to spconv.
        downsample_paddings: ``(x, y, z)`` padding of each stride-2 convolution, in order.

    Returns:
        ``(X', Y', Z')``; ``(180, 180, 2)`` for DAOcc's ``(1440, 1440, 41)``.

    Raises:
        ValueError: if some layer would produce an empty axis.
    """
    if len(sparse_shape) != 3:
        raise ValueError(f"sparse_shape must be (X, Y, Z), got {tuple(sparse_shape)}")
    shape = [int(s) for s in sparse_shape]
    layers = [(f"stride-2 conv {i + 1}", (3, 3, 3), (2, 2, 2), tuple(p)) for i, p in enumerate(downsample_paddings)]
    layers.append(("conv_out", CONV_OUT_KERNEL, CONV_OUT_STRIDE, CONV_OUT_PADDING))
    for name, kernel, stride, padding in layers:
        if len(padding) != 3:
            raise ValueError(f"{name}: padding must be (x, y, z), got {padding}")
        new_shape = [_conv_size(shape[a], kernel[a], stride[a], padding[a]) for a in range(3)]
        if min(new_shape) < 1:
            raise ValueError(
                f"sparse shape {tuple(int(s) for s in sparse_shape)} is too small: {name} maps {tuple(shape)} to "
                f"{tuple(new_shape)}; enlarge the grid (z needs at least 3 cells before conv_out)"
            )
        shape = new_shape
    return tuple(shape)  # type: ignore[return-value]


def _check_architecture(
    base_channels: int,
    encoder_channels: Sequence[Sequence[int]],
    downsample_paddings: Sequence[Sequence[int]],
) -> None:
    """Reject encoder layouts the reference block structure cannot build, naming the offending entry."""
    if len(encoder_channels) == 0 or any(len(stage) == 0 for stage in encoder_channels):
        raise ValueError(f"encoder_channels needs at least one stage and one block per stage, got {encoder_channels}")
    if len(downsample_paddings) != len(encoder_channels) - 1:
        raise ValueError(
            f"downsample_paddings needs one (x, y, z) padding per stage but the last: {len(encoder_channels) - 1}, "
            f"got {len(downsample_paddings)}"
        )
    channels = base_channels
    for i, stage in enumerate(encoder_channels):
        for j, out in enumerate(stage):
            if out < 1:
                raise ValueError(f"encoder_channels[{i}][{j}] must be >= 1, got {out}")
            downsample = j == len(stage) - 1 and i != len(encoder_channels) - 1
            # A basic block adds its input to its output, so it cannot change the channel count.
            if not downsample and out != channels:
                raise ValueError(
                    f"encoder_channels[{i}][{j}] = {out} is a residual basic block and must keep its input's "
                    f"{channels} channels"
                )
            channels = out


def _batch_norm(channels: int) -> nn.BatchNorm1d:
    """BatchNorm over voxel features ``(V, C)`` with the reference's eps and momentum."""
    return nn.BatchNorm1d(channels, eps=BN_EPS, momentum=BN_MOMENTUM)


def _conv_bn_relu(conv: spconv.SparseModule, channels: int) -> SparseSequential:
    """``conv -> BN -> ReLU`` as a ``SparseSequential`` named ``0, 1, 2``, like mmdet3d's sparse conv module."""
    return SparseSequential(conv, _batch_norm(channels), nn.ReLU())


class SparseBasicBlock(spconv.SparseModule):
    """Residual block of two submanifold 3x3x3 convolutions: ``relu(bn2(conv2(relu(bn1(conv1(x))))) + x)``.

    Submanifold convolutions output exactly at their input sites, in the same order, so the identity is the input
    feature matrix itself.
    """

    def __init__(self, channels: int, indice_key: str | None = None) -> None:
        """Args: channels: ``C`` in and out; indice_key: spconv rulebook cache key shared with same-site convs."""
        super().__init__()
        self.conv1 = SubMConv3d(channels, channels, 3, padding=1, bias=False, indice_key=indice_key)
        self.bn1 = _batch_norm(channels)
        self.conv2 = SubMConv3d(channels, channels, 3, padding=1, bias=False, indice_key=indice_key)
        self.bn2 = _batch_norm(channels)
        self.relu = nn.ReLU()

    def forward(self, x: SparseConvTensor) -> SparseConvTensor:
        """``(V, C)`` features at ``V`` sites -> ``(V, C)`` features at the same sites."""
        identity = x.features
        out = self.conv1(x)
        out = out.replace_feature(self.relu(self.bn1(out.features)))
        out = self.conv2(out)
        return out.replace_feature(self.relu(self.bn2(out.features) + identity))


class SparseEncoder(nn.Module):
    """SECOND-style sparse 3D encoder producing a dense BEV map (BEVFusion's ``SparseEncoder``, basic blocks).

    Args:
        in_channels: ``C`` of the voxel features.
        sparse_shape: ``(X, Y, Z)`` spatial shape of the voxel coordinates (with any extra z cells).
        base_channels: output channels of ``conv_input``.
        encoder_channels: per stage, the output channels of each block (see :class:`LidarEncoderConfig`).
        downsample_paddings: ``(x, y, z)`` padding of the stride-2 convolution closing each stage but the last.
        output_channels: channels of ``conv_out``.
    """

    def __init__(
        self,
        in_channels: int,
        sparse_shape: Sequence[int],
        base_channels: int = 16,
        encoder_channels: Sequence[Sequence[int]] = ((16, 16, 32), (32, 32, 64), (64, 64, 128), (128, 128)),
        downsample_paddings: Sequence[Sequence[int]] = ((1, 1, 1), (1, 1, 1), (1, 1, 0)),
        output_channels: int = 128,
    ) -> None:
        super().__init__()
        _check_architecture(base_channels, encoder_channels, downsample_paddings)
        self.sparse_shape = tuple(int(s) for s in sparse_shape)
        self.output_shape = sparse_encoder_output_shape(self.sparse_shape, downsample_paddings)
        self.output_channels = output_channels

        self.conv_input = _conv_bn_relu(
            SubMConv3d(in_channels, base_channels, 3, padding=1, bias=False, indice_key="subm1"), base_channels
        )
        self.encoder_layers = SparseSequential()
        channels = base_channels
        last_stage = len(encoder_channels) - 1
        for i, stage in enumerate(encoder_channels):
            blocks: list[nn.Module] = []
            for j, out in enumerate(stage):
                if j == len(stage) - 1 and i != last_stage:
                    conv = SparseConv3d(
                        channels,
                        out,
                        3,
                        stride=2,
                        padding=tuple(downsample_paddings[i]),
                        bias=False,
                        indice_key=f"spconv{i + 1}",
                    )
                    blocks.append(_conv_bn_relu(conv, out))
                else:
                    # All blocks of a stage before its downsampling share one site set, hence one rulebook key.
                    blocks.append(SparseBasicBlock(out, indice_key=f"subm{i + 1}"))
                channels = out
            self.encoder_layers.add_module(f"encoder_layer{i + 1}", SparseSequential(*blocks))
        conv_out = SparseConv3d(
            channels,
            output_channels,
            CONV_OUT_KERNEL,
            stride=CONV_OUT_STRIDE,
            padding=CONV_OUT_PADDING,
            bias=False,
            indice_key="spconv_down2",
        )
        self.conv_out = _conv_bn_relu(conv_out, output_channels)
        self.backend = "auto"
        """How sparse convolutions run (:data:`SPARSE_BACKENDS`); ``auto``: spconv on CUDA, ``gather_gemm`` else."""
        self._conv_specs: list[ConvSpec] | None = None

    @property
    def out_channels(self) -> int:
        """Channels of the BEV map, ``output_channels * Z'``."""
        return self.output_channels * self.output_shape[2]

    @property
    def bev_shape(self) -> tuple[int, int]:
        """``(X', Y')`` of the BEV map."""
        return self.output_shape[:2]

    def empty_bev(self, batch_size: int, dtype: torch.dtype, device: torch.device) -> Tensor:
        """The ``(B, out_channels, X', Y')`` zero map of a batch without voxels, built without spconv.

        spconv cannot run on zero sites. While gradients are recorded, the zeros are tied to every parameter with
        weight 0, so each parameter still gets a (zero) gradient: distributed data parallel and gradient clipping
        then see the same parameter set on every step, whether or not the batch had LiDAR points.
        """
        bev = torch.zeros(batch_size, self.out_channels, *self.bev_shape, dtype=dtype, device=device)
        params = [p for p in self.parameters() if p.requires_grad]
        if torch.is_grad_enabled() and params:
            tie = torch.stack([p.sum() for p in params]).sum() * 0
            bev = bev + tie.to(device=device, dtype=dtype)
        return bev

    def forward(self, features: Tensor, coords: Tensor, batch_size: int) -> Tensor:
        """Encode voxels into a dense BEV map.

        Args:
            features: ``(V, in_channels)`` voxel features.
            coords: ``(V, 4)`` integer ``(batch, x, y, z)``, unique, inside ``sparse_shape``.
            batch_size: ``B``; samples without voxels get an all-zero map.

        Returns:
            ``(B, out_channels, X', Y')``, channel ``c * Z' + z`` holding channel ``c`` of the volume at height
            ``z`` (BEVFusion's order); ``(B, 256, 180, 180)`` for DAOcc.
        """
        if features.shape[0] == 0:
            return self.empty_bev(batch_size, features.dtype, features.device)
        backend = self.backend
        if backend == "auto":
            backend = "spconv" if features.is_cuda else "gather_gemm"
        if backend == "gather_gemm":
            tables = build_neighbour_tables(self.conv_specs, coords, batch_size)
            x = self.run_rows(features, lambda conv, rows: gather_gemm_conv(rows, conv.weight,
                                                                            tables[conv.indice_key]))
            return self.bev_from_rows(x, tables[self.conv_specs[-1].key].out_coords, batch_size)
        if backend != "spconv":
            raise ValueError(f"sparse backend must be one of {', '.join(SPARSE_BACKENDS)}, got {backend!r}")
        x = sparse_tensor_from_voxels(features, coords, self.sparse_shape, batch_size)
        x = self.conv_input(x)
        x = self.encoder_layers(x)
        x = self.conv_out(x)
        volume = x.dense()  # (B, C, X', Y', Z')
        b, c, nx, ny, nz = volume.shape
        return volume.permute(0, 1, 4, 2, 3).reshape(b, c * nz, nx, ny)

    @property
    def conv_specs(self) -> list[ConvSpec]:
        """Geometry of each rulebook key, in forward order (:func:`~occkit.models.sparse_rules.encoder_conv_specs`)."""
        if self._conv_specs is None:
            self._conv_specs = encoder_conv_specs(self)
        return self._conv_specs

    def run_rows(self, features: Tensor, conv: Callable[[nn.Module, Tensor], Tensor]) -> Tensor:
        """The encoder's layers on ``(N, C)`` feature rows, in the order spconv runs them, each sparse convolution
        executed by ``conv(module, rows)``; BatchNorm, ReLU and the residual additions as the modules define them.

        Submanifold convolutions keep their rows, so a basic block's identity is its input rows. Returns the rows of
        ``conv_out``'s output sites.
        """

        def run(module: nn.Module, x: Tensor) -> Tensor:
            if isinstance(module, (SubMConv3d, SparseConv3d)):
                return conv(module, x)
            if isinstance(module, SparseBasicBlock):
                out = module.relu(module.bn1(conv(module.conv1, x)))
                return module.relu(module.bn2(conv(module.conv2, out)) + x)
            if isinstance(module, SparseSequential):
                for child in module.children():
                    x = run(child, x)
                return x
            if isinstance(module, (nn.BatchNorm1d, nn.ReLU)):
                return module(x)
            raise TypeError(f"no row-wise execution for {type(module).__name__} in the sparse encoder")

        for stage in (self.conv_input, self.encoder_layers, self.conv_out):
            features = run(stage, features)
        return features

    def bev_from_rows(self, features: Tensor, coords: Tensor, batch_size: int) -> Tensor:
        """``(N, C)`` features at the ``(N, 4)`` output sites -> the ``(B, C * Z', X', Y')`` BEV, channel
        ``c * Z' + z``; as ``forward`` returns it."""
        size_x, size_y, size_z = self.output_shape
        channels = features.shape[1]
        rows = coordinate_keys(coords, self.output_shape)
        volume = features.new_zeros(batch_size * size_x * size_y * size_z, channels)
        volume = volume.scatter(0, rows[:, None].expand(-1, channels), features)
        volume = volume.view(batch_size, size_x, size_y, size_z, channels)
        # (B, X, Y, Z, C) -> (B, C, Z, X, Y) -> (B, C * Z, X, Y), the encoder's channel order.
        return volume.permute(0, 4, 3, 1, 2).reshape(batch_size, channels * size_z, size_x, size_y)


def remove_close_points(points: Tensor, radius: float) -> Tensor:
    """Drop points inside the square ``|x| < radius and |y| < radius`` around the sensor, at any height.

    Args:
        points: ``(N, C)`` with metric ``x, y`` in the first two channels.
        radius: half side in metres; ``0`` keeps every point.

    Returns:
        ``(N', C)`` the remaining points, in order.
    """
    if radius <= 0:
        return points
    close = (points[:, 0].abs() < radius) & (points[:, 1].abs() < radius)
    return points[~close]


class LidarEncoder(nn.Module):
    """Padded point batch -> voxels -> :class:`SparseEncoder` -> dense BEV map.

    Args:
        cfg: :class:`LidarEncoderConfig`.

    Near-ego removal here runs on all points, merged in the key LiDAR frame. The reference (BEVFusion's
    ``LoadPointsFromMultiSweeps`` with ``remove_close``) filters only the earlier sweeps, each in its own sensor frame
    before moving it to the key frame, and leaves the key frame's points unfiltered; the model sees only the merged
    cloud, so this is the closest it can do.
    """

    def __init__(self, cfg: LidarEncoderConfig | None = None) -> None:
        super().__init__()
        self.cfg = cfg if cfg is not None else LidarEncoderConfig()
        self.grid = self.cfg.grid
        self.encoder = SparseEncoder(
            self.cfg.in_channels,
            self.cfg.sparse_shape,
            self.cfg.base_channels,
            self.cfg.encoder_channels,
            self.cfg.downsample_paddings,
            self.cfg.output_channels,
        )

    @property
    def out_channels(self) -> int:
        """Channels of the BEV map (256 for DAOcc)."""
        return self.encoder.out_channels

    @property
    def bev_shape(self) -> tuple[int, int]:
        """``(X', Y')`` of the BEV map (180 x 180 for DAOcc)."""
        return self.encoder.bev_shape

    @property
    def max_voxels(self) -> int:
        """Voxels kept per sample: ``max_voxels_train`` in training mode, ``max_voxels_test`` in eval mode."""
        return self.cfg.max_voxels_train if self.training else self.cfg.max_voxels_test

    def voxelize(self, points: Tensor, num_points: Tensor) -> tuple[Tensor, Tensor, Tensor]:
        """Remove near-ego points and hard-voxelize each sample of a padded batch, without gradient.

        Args:
            points: ``(B, P_max, C)`` zero-padded points, ``C >= in_channels``; the first ``in_channels`` are used.
            num_points: ``(B,)`` integer count of valid rows of each sample.

        Returns:
            features: ``(V, in_channels)`` mean point of each voxel.
            coords: ``(V, 4)`` int64 ``(batch, x, y, z)`` on the voxel grid (``z < Z``).
            counts: ``(V,)`` int64 points per voxel.
        """
        if points.dim() != 3 or points.shape[2] < self.cfg.in_channels:
            raise ValueError(
                f"points must have shape (B, P_max, C >= {self.cfg.in_channels}), got {tuple(points.shape)}"
            )
        if num_points.shape != (points.shape[0],):
            raise ValueError(f"num_points must have shape ({points.shape[0]},), got {tuple(num_points.shape)}")
        counts = [int(n) for n in num_points.tolist()]
        if any(n < 0 or n > points.shape[1] for n in counts):
            raise ValueError(f"num_points must lie in [0, {points.shape[1]}], got {counts}")
        # The voxel features are plain means of sensor points: nothing upstream of them is learned.
        with torch.no_grad():
            clouds = [
                remove_close_points(points[b, :n, : self.cfg.in_channels], self.cfg.remove_close)
                for b, n in enumerate(counts)
            ]
            return voxelize_batch(clouds, self.grid, self.cfg.max_points_per_voxel, self.max_voxels)

    def forward(self, points: Tensor, num_points: Tensor) -> Tensor:
        """Encode a batch of LiDAR point clouds into a BEV map.

        Args:
            points: ``(B, P_max, C)`` zero-padded ``(x, y, z, intensity, time lag)`` in the key LiDAR frame.
            num_points: ``(B,)`` integer count of valid rows of each sample.

        Returns:
            ``(B, out_channels, X', Y')`` in the points' dtype and device, ``(B, 256, 180, 180)`` for DAOcc; all
            zeros for a sample without points in range.
        """
        features, coords, _ = self.voxelize(points, num_points)
        return self.encoder(features, coords, points.shape[0])
