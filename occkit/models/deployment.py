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
"""

from __future__ import annotations

from torch import Tensor, nn

from occkit.models.base import OccupancyModel, plan_tensors, plan_with_tensors
from occkit.types import Batch

__all__ = ["OUTPUT_NAME", "DeployedNetwork", "deploy"]

#: Name of the single output, occupancy logits ``(B, K, X, Y, Z)``.
OUTPUT_NAME = "occupancy_logits"


class DeployedNetwork(nn.Module):
    """``forward(*inputs) -> (B, K, X, Y, Z)`` occupancy logits, inputs in the order of :attr:`input_names`.

    Args:
        model: the model, in eval mode.
        batch: a batch of the rig; its plan becomes the network's constants.
    """

    def __init__(self, model: OccupancyModel, batch: Batch) -> None:
        super().__init__()
        self.model = model
        self.deployment = model.deployment(batch)
        plan = model.plan(batch)
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
        """Names of the forward arguments, in order."""
        return self.deployment.input_names

    @property
    def input_docs(self) -> dict[str, str]:
        """Input name -> what it holds, with its shape."""
        return self.deployment.input_docs

    @property
    def dynamic_axes(self) -> dict[str, dict[int, str]]:
        """Input name -> {axis: name} of the axes whose size changes from frame to frame."""
        return self.deployment.dynamic_axes

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        """The network's inputs for a batch of the same rig, by name, in :attr:`input_names` order."""
        return self.deployment.inputs(batch)

    def plan(self) -> object:
        """The fixed plan, its tensors those of the buffers (on the network's device)."""
        tensors = {path: getattr(self, name) for path, name in self._plan_buffers.items()}
        return plan_with_tensors(self._template, tensors)

    def forward(self, *inputs: Tensor) -> Tensor:
        if len(inputs) != len(self.input_names):
            raise ValueError(f"expected {len(self.input_names)} inputs ({', '.join(self.input_names)}), "
                             f"got {len(inputs)}")
        named = dict(zip(self.input_names, inputs, strict=True))
        return self.model.network(self.deployment(named), self.plan()).occupancy


def deploy(model: nn.Module, batch: Batch) -> DeployedNetwork:
    """The fixed-rig inference network of ``model`` (put in eval mode) for the rig of ``batch``.

    Raises:
        ValueError: for a model that is not an :class:`~occkit.models.base.OccupancyModel`, or a batch without the
            inputs it needs.
    """
    if not isinstance(model, OccupancyModel):
        raise ValueError(f"no fixed-rig network for {type(model).__name__}: it is not an occkit OccupancyModel")
    model.eval()
    return DeployedNetwork(model, batch).eval()
