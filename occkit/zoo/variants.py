"""Variants of a zoo entry that every family makes the same way: the ``*_flow`` entries, and an entry moved to the
OpenOcc v2 label space (``*_openocc``)."""

from __future__ import annotations

import dataclasses

from occkit.experiment import Experiment
from occkit.label_space import OCC3D_SPACE, OPENOCC_SPACE
from occkit.models.heads.flow import FlowHeadConfig, MotionConfig

__all__ = ["with_flow_head", "in_openocc"]


def with_flow_head(experiment: Experiment, motion: bool = False) -> Experiment:
    """``experiment`` with a flow head on its occupancy head's per-cell features, and data whose labels carry flow
    (``data.flow``): how the zoo's ``*_flow`` entries are made. ``motion`` adds the LiDAR motion input, one channel
    per sweep the data loads, and reads the occupancy head's features detached (the motion input carries the motion)."""
    channels = experiment.model.occupancy.hidden_channels
    motion_cfg = MotionConfig(sweeps=max(experiment.data.sweeps, 0)) if motion else None
    flow = FlowHeadConfig(in_channels=channels, motion=motion_cfg, detach_features=motion)
    model = dataclasses.replace(experiment.model, flow=flow)
    return dataclasses.replace(experiment, model=model, data=dataclasses.replace(experiment.data, flow=True))


def in_openocc(experiment: Experiment) -> Experiment:
    """An Occ3D entry on OpenOcc v2's labels (the CVPR 2024 challenge's): the same grid and frame, OpenOcc's 17
    classes (free = 16) in the occupancy and flow heads, and a loss over every voxel, as the labels carry no
    visibility mask (drop-free cross-entropy; the Lovasz term, where the entry has one, counts every voxel too)."""
    space = OPENOCC_SPACE
    if experiment.data.label_space != OCC3D_SPACE.name:
        raise ValueError(f"in_openocc moves an occ3d entry, not one of {experiment.data.label_space}")
    model = experiment.model
    changes = {"occupancy": dataclasses.replace(model.occupancy, num_classes=space.num_classes,
                                                free_index=space.free_index, use_mask=False)}  # fmt: skip
    if model.flow is not None:
        changes["flow"] = dataclasses.replace(model.flow, free_index=space.free_index)
    data = dataclasses.replace(experiment.data, label_space=space.name)
    return dataclasses.replace(experiment, model=dataclasses.replace(model, **changes), data=data)
