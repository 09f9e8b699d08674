"""Occupancy flow head: the occupancy head's per-cell features ``(B, X, Y, C)`` -> per-voxel velocity
``(B, X, Y, Z, 2)`` (m/s, ego frame).

The channel-to-height MLP of the occupancy head (FlashOcc, DAOcc) with two values per voxel instead of the class
logits, on the features the occupancy head's own MLP reads (after its conv3x3), as the CVPR 2024
occupancy-and-flow challenge's baseline predicts flow: an MLP beside the class MLP on the same voxel features, trained
with an L1 loss. A flow branch with its own conv3x3 + ReLU died in training (``daocc_tiny_flow``, 800 and 1000
steps): the L1 pulls toward zero, as most occupied voxels do not move, its ReLUs stopped firing (26 of 32 channels
never did on a training frame) and its flow stayed under 1e-4 m/s everywhere.

The loss is an L1 over the voxels the ground truth marks occupied: free space has no velocity to learn, and the
metric (mAVE) reads flow only where a ray stops on an occupied voxel.

A model with LiDAR adds the motion input (:class:`MotionConfig`): the key frame and each sweep before it counted into
their own channel on the occupancy grid's columns, as MotionNet (Wu et al., CVPR 2020) feeds its BEV network, then a
small dilated 2D CNN whose features join the occupancy head's in the flow MLP. The sweeps show a moving object where
it was (on the synthetic world, a car at 6.6 m/s lay 0.99 m behind its key-frame points in the sweep 0.2 s old), but
DAOcc's voxel encoder averages a voxel's points into ``(x, y, z, intensity, time lag)``, with a time lag (0 to 0.2 s)
hundreds of times smaller than the intensity beside it: neither the flow head nor the detection head's velocity
branch of ``daocc_tiny_flow`` learned any motion from it in 1000 steps (both stayed at the zero-velocity error).
Such a head reads the occupancy head's features detached (``detach_features``): they say what is where, the motion
input how it moves, and the occupancy trains as without the head.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from occkit.classes import OCC3D
from occkit.geometry.grid import VoxelGrid
from occkit.geometry.se3 import transform_points
from occkit.models.heads.occupancy import column_mlp

__all__ = ["MotionConfig", "MotionEncoder", "FlowHeadConfig", "FlowHead", "check_motion_input"]


@dataclass(frozen=True)
class MotionConfig:
    """The LiDAR motion input of a flow head: one BEV channel per sweep on the occupancy grid, and a 2D CNN."""

    sweeps: int = 4
    """Sweeps before the key frame with a channel of their own (``sweeps + 1`` channels): a point's time lag in sweep
    periods picks its channel, and older sweeps than this share the last one."""
    sweep_period: float = 0.05
    """Seconds between two sweeps (LIDAR_TOP spins at 20 Hz)."""
    channels: int = 32
    """Channels of the CNN (each layer's output)."""
    dilations: tuple[int, ...] = (1, 2, 4, 1)
    """One conv3x3 + BatchNorm + ReLU per entry, with this dilation: the default sees 17 columns (6.8 m at 0.4 m), a
    car's length and its motion over the sweeps."""


class MotionEncoder(nn.Module):
    """``forward(points (B, P, 5), num_points (B,), points_to_grid (B, 4, 4)) -> (B, X, Y, channels)``.

    ``points`` are ``(x, y, z, intensity, time lag)`` in the model's LiDAR frame, padded past ``num_points``;
    ``points_to_grid`` maps that frame onto ``grid``'s (the augmented label frame). A channel holds
    ``log(1 + points)`` of its sweep in each column of the grid, between the grid's lowest and highest voxel.
    """

    def __init__(self, cfg: MotionConfig, grid: VoxelGrid) -> None:
        super().__init__()
        layers, channels = [], cfg.sweeps + 1
        for dilation in cfg.dilations:
            layers += [nn.Conv2d(channels, cfg.channels, 3, padding=dilation, dilation=dilation, bias=False),
                       nn.BatchNorm2d(cfg.channels), nn.ReLU(inplace=True)]  # fmt: skip
            channels = cfg.channels
        self.cnn = nn.Sequential(*layers)
        self.grid = grid
        self.cfg = cfg

    def rasterise(self, points: Tensor, num_points: Tensor, points_to_grid: Tensor) -> Tensor:
        """Point counts ``(B, sweeps + 1, X, Y)`` per sweep and column (``log(1 + count)``)."""
        batch, length, _ = points.shape
        nx, ny, _ = self.grid.shape
        xyz = transform_points(points_to_grid.to(points.dtype)[:, None], points[..., :3][:, None])[:, 0]
        index, inside = self.grid.world_to_index(xyz)
        real = torch.arange(length, device=points.device)[None] < num_points.to(points.device)[:, None]
        sweep = torch.round(points[..., 4] / self.cfg.sweep_period).long().clamp(0, self.cfg.sweeps)
        batch_index = torch.arange(batch, device=points.device)[:, None].expand(batch, length)
        cell = ((batch_index * (self.cfg.sweeps + 1) + sweep) * nx + index[..., 0]) * ny + index[..., 1]
        cell = cell[inside & real]
        counts = torch.zeros(batch * (self.cfg.sweeps + 1) * nx * ny, device=points.device, dtype=points.dtype)
        counts.index_add_(0, cell, torch.ones_like(cell, dtype=points.dtype))
        return torch.log1p(counts.view(batch, self.cfg.sweeps + 1, nx, ny))

    def forward(self, points: Tensor, num_points: Tensor, points_to_grid: Tensor) -> Tensor:
        return self.cnn(self.rasterise(points, num_points, points_to_grid)).permute(0, 2, 3, 1)


@dataclass(frozen=True)
class FlowHeadConfig:
    """Channel-to-height flow head and its loss."""

    in_channels: int = 128
    """Channels of the occupancy head's per-cell features (its ``hidden_channels``); the MLP's hidden layer has twice
    as many."""
    height: int = 16
    """Voxels per column (Z)."""
    free_index: int = OCC3D.empty_index
    """Class id of free space: its voxels are left out of the loss."""
    ignore_index: int = OCC3D.ignore_index
    """Label of voxels without ground truth (left out of the loss)."""
    loss_weight: float = 1.0
    """Weight of the L1 loss (means over voxels and both components). The challenge baseline's 0.25 averages over
    every voxel, free ones included (about ten times as many); over the occupied ones alone, 1.0 gives the flow a
    weight the short CPU schedules learn from."""
    motion: MotionConfig | None = None
    """The LiDAR motion input (a model with a LiDAR branch); None: the occupancy head's features alone."""
    detach_features: bool = False
    """Read the occupancy head's features without passing the flow loss back into them, so the occupancy trains as
    without the head; for a head whose motion comes from its own input (``motion``). Shared, the flow loss cost
    ``daocc_tiny_flow`` 10 mIoU at 1000 steps (30.5 against 41.0)."""
    balanced: bool = True
    """Average the L1 over the moving voxels (nonzero ground-truth flow) and over the static occupied ones apart, and
    the two means equally; False: one mean over every occupied voxel. Moving voxels are a few percent of the occupied
    ones (4 % on the synthetic world): under one mean, zero everywhere is already a low loss."""


def check_motion_input(flow: FlowHeadConfig | None, lidar: bool) -> None:
    """Refuse a flow head whose motion input (``flow.motion``) reads LiDAR sweeps the model does not take."""
    if flow is not None and flow.motion is not None and not lidar:
        raise ValueError("flow.motion reads the LiDAR sweeps, which this model does not take at inference (a "
                         "camera-only model's motion comes from its history frames: temporal)")


class FlowHead(nn.Module):
    """``forward(columns (B, X, Y, C), motion) -> flow (B, X, Y, Z, 2)``; ``loss(flow, target, labels)``.

    ``motion``: with ``cfg.motion``, the :class:`MotionEncoder`'s inputs ``(points, num_points, points_to_grid)``;
    ``grid`` is then the occupancy grid the columns stand on.
    """

    def __init__(self, cfg: FlowHeadConfig, grid: VoxelGrid | None = None) -> None:
        super().__init__()
        self.motion = None
        channels = cfg.in_channels
        if cfg.motion is not None:
            if grid is None:
                raise ValueError("a flow head with a motion input needs the occupancy grid")
            self.motion = MotionEncoder(cfg.motion, grid)
            channels += cfg.motion.channels
        self.predictor = column_mlp(channels, cfg.height * 2)
        self.cfg = cfg

    def forward(self, columns: Tensor, motion: tuple[Tensor, Tensor, Tensor] | None = None) -> Tensor:
        if (self.motion is None) != (motion is None):
            raise ValueError("the flow head's motion input is " + ("missing" if motion is None else "unexpected"))
        if self.cfg.detach_features:
            columns = columns.detach()
        if self.motion is not None:
            columns = torch.cat([columns, self.motion(*motion).to(columns.dtype)], dim=-1)
        batch, x, y, _ = columns.shape
        return self.predictor(columns).view(batch, x, y, self.cfg.height, 2)

    def loss(self, flow: Tensor, target: Tensor | None, labels: Tensor) -> Tensor:
        """Weighted L1 of ``flow (B, X, Y, Z, 2)`` against ``target`` over the voxels ``labels (B, X, Y, Z)`` marks
        occupied (neither free nor ignored), balanced between moving and static voxels with ``balanced``; 0 (with a
        gradient path) when there is none."""
        if target is None:
            raise ValueError("the flow loss needs batch.voxel_flow: set data.flow = true (labels with a flow array)")
        occupied = (labels != self.cfg.free_index) & (labels != self.cfg.ignore_index)
        groups = [occupied]
        if self.cfg.balanced:
            moving = occupied & (target != 0).any(dim=-1)
            groups = [moving, occupied & ~moving]
        means = [(flow[group] - target[group]).abs().mean() for group in groups if group.any()]
        if not means:
            return flow.sum() * 0.0
        return self.cfg.loss_weight * torch.stack(means).mean()
