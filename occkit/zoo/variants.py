"""Variants of a zoo entry that every family makes the same way: the ``*_flow`` entries."""

from __future__ import annotations

import dataclasses

from occkit.experiment import Experiment
from occkit.models.heads.flow import FlowHeadConfig, MotionConfig

__all__ = ["with_flow_head"]


def with_flow_head(experiment: Experiment, motion: bool = False) -> Experiment:
    """``experiment`` with a flow head on its occupancy head's per-cell features, and data whose labels carry flow
    (``data.flow``): how the zoo's ``*_flow`` entries are made. ``motion`` adds the LiDAR motion input, one channel
    per sweep the data loads, and reads the occupancy head's features detached (the motion input carries the motion)."""
    channels = experiment.model.occupancy.hidden_channels
    motion_cfg = MotionConfig(sweeps=max(experiment.data.sweeps, 0)) if motion else None
    flow = FlowHeadConfig(in_channels=channels, motion=motion_cfg, detach_features=motion)
    model = dataclasses.replace(experiment.model, flow=flow)
    return dataclasses.replace(experiment, model=model, data=dataclasses.replace(experiment.data, flow=True))
