"""What every occupancy architecture is: a plan from calibration, a network over inputs and plan, a description.

A model's forward pass has two parts with different lifetimes:

* the **plan**: every tensor that depends only on the rig and the augmentation, not on pixels or points (LSS's
  pooling ranks, the projection's sampling grid, the BVRE grid, camera parameters). It is a dataclass of tensors
  from :meth:`OccupancyModel.plan`;
* the **network**: :meth:`OccupancyModel.network` maps the frame's inputs (images, points) and a plan to the
  outputs.

``forward(batch) = network(inputs(batch), plan(batch))``. Training and evaluation compute the plan on every call;
the inference fast path reuses the first one (:attr:`OccupancyModel.reuse_plan`, set by
:func:`occkit.models.inference.fix_calibration`); the deployed network (:mod:`occkit.models.deployment`) keeps it as
constant buffers. All of them run the same :meth:`~OccupancyModel.network`.

An :class:`Architecture` is what the rest of occkit knows of a model family: its config and model classes and its
benchmark stages, declared at the bottom of the family's model file. Its zoo entries (whole experiments: model,
data, schedule) live in ``occkit/zoo/<family>.py``.
"""

from __future__ import annotations

import abc
import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import torch
from torch import Tensor, nn

from occkit.models.cuda_graph import NetworkGraphs
from occkit.models.heads.flow import FlowHead
from occkit.models.heads.occupancy import occupancy_prediction
from occkit.models.temporal import StreamMemory, TemporalFusion
from occkit.types import Batch, ModelOutput, OccPrediction

__all__ = ["FIXED_CALIBRATION_RETIRED", "OccupancyModel", "Architecture", "Deployment", "CameraInputs", "camera_images"]

#: Why ``fixed_calibration``, a key of older view-transform and DA-Occ configs, is gone.
FIXED_CALIBRATION_RETIRED = ("a fixed rig is an inference optimisation now (occkit bench's fixed_calibration, "
                             "occkit.models.inference.fix_calibration), not a model setting")


class OccupancyModel(nn.Module, metaclass=abc.ABCMeta):
    """Base of the occupancy architectures: ``forward(batch) = network(inputs(batch), plan(batch))``.

    Subclasses implement :meth:`plan`, :meth:`inputs`, :meth:`network` and :meth:`loss`; they override
    :meth:`deployment` when their graph takes more than camera images, and :meth:`predict` when it returns more than
    the occupancy classes. A temporal model also sets :attr:`temporal`, implements :meth:`frame_bev` and takes the
    history inputs (:data:`~occkit.models.temporal.HISTORY_INPUTS`) in its network.
    """

    reuse_plan: bool = False
    """In eval mode, compute the plan once and reuse it while the batch size and image size stay the same (one rig,
    no test-time augmentation). Set by :func:`occkit.models.inference.fix_calibration`."""

    def __init__(self) -> None:
        super().__init__()
        self._reused: tuple[tuple, Any] | None = None
        self.temporal: TemporalFusion | None = None
        """The history stage of a temporal model (:mod:`occkit.models.temporal`, set by its ``__init__``); None for
        single-frame models."""
        self.flow_head: FlowHead | None = None
        """The occupancy flow head (:mod:`occkit.models.heads.flow`, set by ``__init__`` when the config has
        ``flow``); it reads the occupancy head's per-cell features (:meth:`occupancy_and_flow`)."""
        self.network_graphs: NetworkGraphs | None = None
        """In eval mode on CUDA, :meth:`network` replayed from CUDA graphs (:mod:`occkit.models.cuda_graph`, set by
        :func:`occkit.models.inference.capture_cuda_graphs`); None: run eagerly."""

    @abc.abstractmethod
    def plan(self, batch: Batch) -> Any:
        """The calibration-only tensors of ``batch``'s rig and augmentation (a dataclass of tensors)."""

    @abc.abstractmethod
    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        """The frame's inputs to :meth:`network`, by name."""

    @abc.abstractmethod
    def network(self, inputs: Mapping[str, Tensor], plan: Any) -> ModelOutput:
        """The outputs for ``inputs`` (from :meth:`inputs`) under ``plan`` (from :meth:`plan`)."""

    @abc.abstractmethod
    def loss(self, output: ModelOutput, batch: Batch) -> dict[str, Tensor]:
        """Weighted loss terms; their sum is the training loss."""

    def deployment(self, batch: Batch) -> Deployment:
        """The graph inputs of this model's fixed-rig network for ``batch``'s rig (:mod:`occkit.models.deployment`);
        camera images by default."""
        return CameraInputs(batch)

    def full_precision_plan(self, batch: Batch) -> Any:
        """:meth:`plan` with autocast off: the rig's geometry (lifted frustum points, sampling locations, pooling
        ranks) in float32 whatever precision the network runs at. Under bf16 autocast its matrix products would
        round ego coordinates to 8 significant bits, 0.2 m at 50 m, half an Occ3D voxel."""
        device = next(self.parameters()).device.type
        with torch.autocast(device, enabled=False):
            return self.plan(batch)

    def current_plan(self, batch: Batch) -> Any:
        """:meth:`full_precision_plan`, or the reused one under :attr:`reuse_plan` in eval mode."""
        if not self.reuse_plan or self.training:
            return self.full_precision_plan(batch)
        images = None if batch.images is None else tuple(batch.images.shape)
        key = (len(batch), images)
        if self._reused is None or self._reused[0] != key:
            self._reused = (key, self.full_precision_plan(batch))
        return self._reused[1]

    def forward(self, batch: Batch, *, memory: StreamMemory | None = None) -> ModelOutput:
        """``network(inputs(batch), plan(batch))``; a temporal model's inputs also hold its history
        (:meth:`history_inputs`), and with a ``memory`` the frame is one step of a stream: its history comes from
        the memory and goes back into it."""
        inputs = self.inputs(batch)
        if self.temporal is not None:
            inputs.update(self.history_inputs(batch, memory))
        plan = self.current_plan(batch)
        if self.network_graphs is None or self.training:
            output = self.network(inputs, plan)
        else:
            output = self.network_graphs(self.network, self.graph_inputs(inputs), plan)
        if memory is not None and self.temporal is not None:
            memory.push(output.history_state, batch.ego2global, batch.occ_aug)
        return output

    def eager_stages(self) -> tuple[str, ...]:
        """The child modules that run before a CUDA graph's replay, eagerly, because a graph cannot capture them
        (:meth:`graph_inputs` runs them); none by default."""
        return ()

    def graph_inputs(self, inputs: dict[str, Tensor]) -> dict[str, Tensor]:
        """The inputs of the :meth:`network` that a CUDA graph replays: ``inputs`` with the :meth:`eager_stages` run
        on them and their outputs in their place; ``inputs`` by default."""
        return inputs

    @torch.no_grad()
    def predict(self, batch: Batch, *, memory: StreamMemory | None = None) -> OccPrediction:
        """Class ids ``(B, X, Y, Z)`` uint8, and the flow of a model with a flow head (a stream step with a
        ``memory``)."""
        return self.prediction(self.forward(batch, memory=memory))

    def prediction(self, output: ModelOutput) -> OccPrediction:
        """What :meth:`predict` makes of a forward's output: the class ids, and the flow of a flow head."""
        prediction = occupancy_prediction(output.occupancy)
        prediction.flow = output.flow
        return prediction

    # ----------------------------------------------------------------------------------------------------- flow
    def occupancy_and_flow(
        self, occupancy_head: nn.Module, features: Tensor, motion: tuple[Tensor, Tensor, Tensor] | None = None
    ) -> tuple[Tensor, Tensor | None]:
        """The occupancy head's logits ``(B, K, X, Y, Z)`` of ``features (B, C, X, Y)`` and, with a flow head, the
        velocities ``(B, X, Y, Z, 2)`` from the same per-cell features (and the LiDAR ``motion`` input of a head that
        has one, :class:`~occkit.models.heads.flow.FlowHead`); None without one."""
        if self.flow_head is None:
            return occupancy_head(features), None
        columns = occupancy_head.columns(features)
        return occupancy_head.logits(columns), self.flow_head(columns, motion)

    def flow_losses(self, output: ModelOutput, batch: Batch) -> dict[str, Tensor]:
        """``{"flow": weighted L1}`` of a model with a flow head (:meth:`FlowHead.loss`); empty without one."""
        if self.flow_head is None:
            return {}
        if output.flow is None:
            raise ValueError(f"{type(self).__name__} has a flow head but its output carries no flow")
        return {"flow": self.flow_head.loss(output.flow, batch.voxel_flow, batch.voxel_semantics)}

    # -------------------------------------------------------------------------------------------------- history
    def frame_bev(self, images: Tensor, plan: Any) -> Tensor:
        """A temporal model's BEV of one frame before fusion, ``(B, C, X, Y)``, from its ``images`` under ``plan``."""
        raise NotImplementedError(f"{type(self).__name__} has no BEV history")

    def stream(self) -> StreamMemory:
        """An empty memory for streaming this (temporal) model over scenes in order (:meth:`forward`)."""
        if self.temporal is None:
            raise ValueError(f"{type(self).__name__} is a single-frame model: it has nothing to stream")
        return StreamMemory(self.temporal)

    def history_inputs(self, batch: Batch, memory: StreamMemory | None = None) -> dict[str, Tensor]:
        """The history inputs of :meth:`network` (:data:`~occkit.models.temporal.HISTORY_INPUTS`).

        From ``memory`` when streaming (the recurrent fusion's training, and every model's inference); else from the
        batch's earlier key frames (``DatasetConfig.history``, the concatenation's training), whose BEVs are computed
        here without gradient; else, in evaluation only, none (every slot padded: the model sees the current frame
        alone).
        """
        temporal = self.temporal
        if temporal is None:
            raise ValueError(f"{type(self).__name__} is a single-frame model")
        images = camera_images(batch, type(self).__name__)
        if memory is not None:
            return memory.inputs(batch.scenes, batch.ego2global, batch.occ_aug, images.device, images.dtype)
        if batch.history_images is None:
            if self.training and temporal.cfg.streamed_training:
                raise ValueError(f"{type(self).__name__}'s recurrent history trains on streams: pass a memory "
                                 "(model.stream()) with the frames of each scene in order (occkit train does, with "
                                 "train.sampler: streams)")
            if self.training:
                raise ValueError(f"{type(self).__name__} is temporal: training needs each sample's "
                                 f"{temporal.cfg.history} earlier key frames (set data.history = "
                                 f"{temporal.cfg.history})")
            return temporal.empty_history(len(batch), images.device, images.dtype)
        frames = []
        with torch.no_grad():
            for k in range(batch.history_images.shape[1]):
                frame = dataclasses.replace(batch, images=batch.history_images[:, k],
                                            intrinsics=batch.history_intrinsics[:, k],
                                            cam2ego=batch.history_cam2ego[:, k], img_aug=batch.history_img_aug[:, k])
                frames.append(temporal.pre_process(self.frame_bev(frame.images, self.full_precision_plan(frame))))
        return temporal.history_inputs(torch.stack(frames, dim=1), batch.history_ego2global, batch.ego2global,
                                       batch.occ_aug, batch.history_padded)


def camera_images(batch: Batch, model: str) -> Tensor:
    """``batch.images``, or a ValueError saying that ``model`` needs them."""
    if batch.images is None:
        raise ValueError(f"{model} needs camera images but the batch has none")
    return batch.images


class Deployment(nn.Module, metaclass=abc.ABCMeta):
    """The graph inputs of a model's fixed-rig network (:mod:`occkit.models.deployment`), as the model declares them.

    :meth:`inputs` makes them from a batch of the rig, outside the graph; :meth:`forward` runs inside the graph and
    turns them into the inputs of :meth:`OccupancyModel.network` (the identity unless a subclass says otherwise).
    """

    def __init__(self) -> None:
        super().__init__()
        self.input_names: list[str] = []
        """Names of the graph inputs, in order."""
        self.input_docs: dict[str, str] = {}
        """Input name -> what it holds, with its shape."""
        self.dynamic_axes: dict[str, dict[int, str]] = {}
        """Input name -> {axis: name} of the axes whose size changes from frame to frame."""

    def declare(self, name: str, doc: str, dynamic_axes: dict[int, str] | None = None) -> None:
        """Add a graph input."""
        self.input_names.append(name)
        self.input_docs[name] = doc
        if dynamic_axes:
            self.dynamic_axes[name] = dynamic_axes

    @abc.abstractmethod
    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        """The graph inputs for a batch of the same rig, by name, in :attr:`input_names` order."""

    def forward(self, inputs: Mapping[str, Tensor]) -> Mapping[str, Tensor]:
        return inputs


class CameraInputs(Deployment):
    """One graph input, ``images (B, N, 3, H, W)``, of the reference batch's shape."""

    def __init__(self, batch: Batch) -> None:
        super().__init__()
        self.image_shape = tuple(camera_images(batch, "the model").shape)
        self.declare("images", f"{self.image_shape} float32 normalised camera images (test transform)")

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        images = batch.images
        if images is None or tuple(images.shape) != self.image_shape:
            got = None if images is None else tuple(images.shape)
            raise ValueError(f"the network was made for images of shape {self.image_shape}, got {got}")
        return {"images": images}


@dataclass(frozen=True)
class Architecture:
    """A model family as the zoo, the engine, the benchmark and the exporter see it."""

    name: str
    """The ``architecture`` key of experiments and checkpoints."""
    config: type
    """The model's config dataclass."""
    model: Callable[[Any], OccupancyModel]
    """The model class: ``model(config)``."""
    stages: Mapping[str, tuple[str, ...]]
    """Benchmark stage -> the model's child modules that make it up; work outside them is reported as ``other``."""

    def build(self, config: Any) -> OccupancyModel:
        """A freshly initialised model of ``config``."""
        if not isinstance(config, self.config):
            raise TypeError(f"{self.name} needs a {self.config.__name__}, got {type(config).__name__}")
        return self.model(config)
