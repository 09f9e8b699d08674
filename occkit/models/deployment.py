"""Inference networks for one fixed rig: a model with its plan computed once and kept as constants.

A deployed occupancy model sees one vehicle: its cameras, their intrinsics and mounting, the LiDAR mounting, no
augmentation. Everything a model derives from those alone is its plan (:meth:`OccupancyModel.plan
<occkit.models.base.OccupancyModel.plan>`: LSS pooling ranks, projection sampling grids, the BVRE grid, camera
parameters). :class:`DeployedNetwork` computes it once from a reference batch and keeps its tensors as buffers, so
an exported graph holds them as constants; its forward is the model's own :meth:`~occkit.models.base.OccupancyModel.
network` on that plan.

What changes every frame is the input, as the model declares it (:meth:`OccupancyModel.deployment
<occkit.models.base.OccupancyModel.deployment>`): camera images, and for DAOcc the voxelized LiDAR sweep with the
rulebooks of its sparse convolutions (:mod:`occkit.models.sparse_rules`), computed outside the graph by
:meth:`DeployedNetwork.inputs`. The contract: a new calibration (another vehicle, a re-calibrated camera, another
set of working cameras in ``camera_mask``) needs a new network; the batch size is the reference batch's.
``occkit.export`` checks the network's logits against the model's own forward.

A temporal model's network is state in, state out: besides the frame's inputs it takes the history
(:data:`~occkit.models.temporal.HISTORY_INPUTS`: the memory's BEVs, their transforms into the current frame, the
padded flags) and returns this frame's slot of the memory (``history_state``) beside the logits. The caller keeps
the memory between frames (:class:`~occkit.models.temporal.StreamMemory`, :meth:`DeployedNetwork.inputs`), so the
graph itself holds no state and the history never crosses a scene unless the caller lets it.
"""

from __future__ import annotations

import torch
from torch import Tensor, nn

from occkit.models.base import OccupancyModel
from occkit.models.plans import plan_tensors, plan_with_tensors
from occkit.models.temporal import HISTORY_INPUTS, StreamMemory
from occkit.types import Batch

__all__ = ["OUTPUT_NAME", "STATE_NAME", "DeployedNetwork", "deploy"]

#: Name of the first output, occupancy logits ``(B, K, X, Y, Z)`` (the only one of a single-frame model).
OUTPUT_NAME = "occupancy_logits"
#: Name of a temporal model's second output, ``(B, C, X, Y)``, this frame's slot of the stream's memory.
STATE_NAME = "history_state"


class DeployedNetwork(nn.Module):
    """``forward(*inputs) -> (B, K, X, Y, Z)`` occupancy logits, inputs in the order of :attr:`input_names`; for a
    temporal model ``(logits, history_state)`` (:attr:`output_names`).

    Args:
        model: the model, in eval mode.
        batch: a batch of the rig; its plan becomes the network's constants.
    """

    def __init__(self, model: OccupancyModel, batch: Batch) -> None:
        super().__init__()
        self.model = model
        self.deployment = model.deployment(batch)
        self.temporal = model.temporal
        plan = model.full_precision_plan(batch)
        # Buffers, not persistent: they follow .to(device) but stay out of state dicts (derived, not learned). The
        # template keeps the plan's structure and sizes without its tensors, which live in the buffers only.
        self._plan_buffers = {}
        for path, tensor in plan_tensors(plan).items():
            name = "plan_" + path.replace(".", "_")
            self.register_buffer(name, tensor.detach(), persistent=False)
            self._plan_buffers[path] = name
        self._template = plan_with_tensors(plan, dict.fromkeys(self._plan_buffers))

    @property
    def input_names(self) -> list[str]:
        """Names of the forward arguments, in order: the frame's, then a temporal model's history."""
        return self.deployment.input_names + (list(HISTORY_INPUTS) if self.temporal is not None else [])

    @property
    def input_docs(self) -> dict[str, str]:
        """Input name -> what it holds, with its shape."""
        docs = dict(self.deployment.input_docs)
        if self.temporal is not None:
            slots, channels, (x, y) = self.temporal.memory_frames, self.temporal.channels, self.temporal.bev_size
            docs.update(history=f"(B, {slots}, {channels}, {x}, {y}) float32 the stream's memory, newest first "
                                f"(zeros where padded)",
                        current_to_history=f"(B, {slots}, 4, 4) float32 current ego frame -> each slot's frame",
                        history_padded=f"(B, {slots}) bool slots without an earlier frame of the scene")  # fmt: skip
        return docs

    @property
    def output_names(self) -> list[str]:
        """Names of the outputs, in order."""
        return [OUTPUT_NAME] + ([STATE_NAME] if self.temporal is not None else [])

    @property
    def output_docs(self) -> dict[str, str]:
        """Output name -> what it holds, with its shape."""
        docs = {OUTPUT_NAME: "occupancy logits (B, K, X, Y, Z)"}
        if self.temporal is not None:
            docs[STATE_NAME] = (f"(B, {self.temporal.channels}, X, Y) this frame's slot of the memory, the next "
                                f"frame's newest history")
        return docs

    @property
    def dynamic_axes(self) -> dict[str, dict[int, str]]:
        """Input name -> {axis: name} of the axes whose size changes from frame to frame."""
        return self.deployment.dynamic_axes

    def inputs(self, batch: Batch, memory: StreamMemory | None = None) -> dict[str, Tensor]:
        """The network's inputs for a batch of the same rig, by name, in :attr:`input_names` order; a temporal
        model's history from ``memory`` (None: no history, every slot padded). The caller pushes the network's
        ``history_state`` into the memory after the frame."""
        inputs = self.deployment.inputs(batch)
        if self.temporal is not None:
            images = batch.images
            device, dtype = (images.device, images.dtype) if images is not None else (batch.ego2global.device,
                                                                                      torch.float32)
            inputs.update(memory.inputs(batch.scenes, batch.ego2global, batch.occ_aug, device, dtype)
                          if memory is not None else self.temporal.empty_history(len(batch), device, dtype))
        return inputs

    def stream(self, batch: Batch, memory: StreamMemory) -> Tensor:
        """One frame of a stream through this network (a temporal model's): its logits; the memory moves on."""
        occupancy, state = self(*self.inputs(batch, memory).values())
        memory.push(state, batch.ego2global, batch.occ_aug)
        return occupancy

    def plan(self) -> object:
        """The fixed plan, its tensors those of the buffers (on the network's device)."""
        tensors = {path: getattr(self, name) for path, name in self._plan_buffers.items()}
        return plan_with_tensors(self._template, tensors)

    def forward(self, *inputs: Tensor) -> Tensor | tuple[Tensor, Tensor]:
        if len(inputs) != len(self.input_names):
            raise ValueError(f"expected {len(self.input_names)} inputs ({', '.join(self.input_names)}), "
                             f"got {len(inputs)}")
        named = dict(zip(self.input_names, inputs, strict=True))
        frame = dict(self.deployment({name: named[name] for name in self.deployment.input_names}))
        if self.temporal is None:
            return self.model.network(frame, self.plan()).occupancy
        output = self.model.network({**frame, **{name: named[name] for name in HISTORY_INPUTS}}, self.plan())
        return output.occupancy, output.history_state


def deploy(model: nn.Module, batch: Batch) -> DeployedNetwork:
    """The fixed-rig inference network of ``model`` (put in eval mode) for the rig of ``batch``.

    Raises:
        ValueError: for a model that is not an :class:`~occkit.models.base.OccupancyModel`, a flow head with the LiDAR
            motion input, or a batch without the inputs it needs.
    """
    if not isinstance(model, OccupancyModel):
        raise ValueError(f"no fixed-rig network for {type(model).__name__}: it is not an occkit OccupancyModel")
    if model.flow_head is not None and model.flow_head.motion is not None:
        raise ValueError("the fixed-rig network outputs occupancy only, and this model's flow head reads LiDAR points "
                         "it does not take: set model.flow_head = None first (occkit export does)")
    model.eval()
    return DeployedNetwork(model, batch).eval()
