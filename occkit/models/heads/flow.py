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
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from occkit.classes import OCC3D
from occkit.experiment import Experiment
from occkit.models.heads.occupancy import column_mlp

__all__ = ["FlowHeadConfig", "FlowHead", "with_flow_head"]


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
    balanced: bool = True
    """Average the L1 over the moving voxels (nonzero ground-truth flow) and over the static occupied ones apart, and
    the two means equally; False: one mean over every occupied voxel. Moving voxels are a few percent of the occupied
    ones (4 % on the synthetic world): under one mean, zero everywhere is already a low loss."""


class FlowHead(nn.Module):
    """``forward(columns (B, X, Y, C)) -> flow (B, X, Y, Z, 2)``; ``loss(flow, target, labels)``."""

    def __init__(self, cfg: FlowHeadConfig) -> None:
        super().__init__()
        self.predictor = column_mlp(cfg.in_channels, cfg.height * 2)
        self.cfg = cfg

    def forward(self, columns: Tensor) -> Tensor:
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


def with_flow_head(experiment: Experiment) -> Experiment:
    """``experiment`` with a flow head on its occupancy head's per-cell features, and data whose labels carry flow
    (``data.flow``): how the zoo's ``*_flow`` entries are made."""
    channels = experiment.model.occupancy.hidden_channels
    model = dataclasses.replace(experiment.model, flow=FlowHeadConfig(in_channels=channels))
    return dataclasses.replace(experiment, model=model, data=dataclasses.replace(experiment.data, flow=True))
