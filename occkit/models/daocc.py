"""DAOcc: detection-assisted camera + LiDAR fusion occupancy (Yang et al., 2024), with BEV range extension.

Data flow (shapes for the paper config, batch ``B``, ``N`` cameras at 256 x 704)::

    images (B, N, 3, 256, 704) -> ResNet-50 C3..C5 -> LSS-FPN -> (B, N, 256, 32, 88)
        -> projection view transform (180 x 180 x 10 voxel centres, +-54 m) -> (B, 1280, 180, 180)
    points (B, P, 5) -> voxelize 0.075 x 0.075 x 0.2 -> sparse SECOND encoder -> (B, 256, 180, 180)
    concat -> ConvFuser -> (B, 512, 180, 180) -> BEV encoder (BasicBlocks + FPN_LSS) -> (B, 512, 180, 180)
        -> BVRE onto the occupancy grid -> (B, 128, 200, 200) -> channel-to-height head -> (B, 18, 200, 200, 16)
        -> CenterHead (training only, detachable) on the 512 x 180 x 180 BEV

Loss: camera-masked cross-entropy (or drop-free CE without the mask) + 0.01 x the detection losses. Without a camera
branch (``image=None``) it is the LiDAR-only variant; without ``lidar`` a camera-only one.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Mapping
from dataclasses import dataclass, field

import torch
from torch import Tensor

from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.geometry.se3 import invert_transform
from occkit.models.base import Architecture, CameraInputs, Deployment, OccupancyModel, camera_images
from occkit.models.bev_encoder import BevEncoder, BevEncoderConfig, ConvFuser
from occkit.models.cuda_graph import side_stream
from occkit.models.heads.center import CenterHead, CenterHeadConfig
from occkit.models.heads.flow import FlowHead, FlowHeadConfig, check_motion_input
from occkit.models.heads.occupancy import OccupancyHead, OccupancyHeadConfig
from occkit.models.heads.panoptic import assign_instances
from occkit.models.image_encoder import ImageEncoder, ImageEncoderConfig
from occkit.models.lidar_encoder import LidarEncoder, LidarEncoderConfig
from occkit.models.range_extension import RangeExtension, RangeExtensionConfig
from occkit.models.sparse_rules import RulebookSparseEncoder
from occkit.models.view_transform.projection import ProjectionConfig, ProjectionViewTransform, SamplingPlan
from occkit.types import Batch, ModelOutput, OccPrediction

__all__ = ["DAOccConfig", "FusionPlan", "DAOcc", "FusionInputs", "ARCHITECTURE", "with_bev_extent"]


@dataclass(frozen=True)
class DAOccConfig:
    """DAOcc, paper configuration on Occ3D-nuScenes by default."""

    occ_range: tuple[float, float, float, float, float, float] = OCC3D_GRID.point_cloud_range
    """Occupancy grid extent (x_min, y_min, z_min, x_max, y_max, z_max), metres, in the label frame (the label
    space's grid; Occ3D's by default)."""
    occ_voxel_size: tuple[float, float, float] = OCC3D_GRID.voxel_size
    """Occupancy voxel size, metres."""
    image: ImageEncoderConfig | None = field(default_factory=ImageEncoderConfig)
    """Camera backbone and neck; None for the LiDAR-only variant."""
    view: ProjectionConfig = field(default_factory=ProjectionConfig)
    """Projection view transform (used with a camera branch)."""
    lidar: LidarEncoderConfig | None = field(default_factory=LidarEncoderConfig)
    """LiDAR voxelization and sparse encoder; None for a camera-only variant."""
    fusion_channels: int = 512
    """Output channels of the ConvFuser."""
    bev: BevEncoderConfig = field(default_factory=BevEncoderConfig)
    """BEV backbone and FPN_LSS neck."""
    range_extension: RangeExtensionConfig = field(default_factory=RangeExtensionConfig)
    """BVRE: the +-54 m BEV resampled onto the occupancy grid."""
    occupancy: OccupancyHeadConfig = field(default_factory=OccupancyHeadConfig)
    """Channel-to-height head and occupancy loss."""
    flow: FlowHeadConfig | None = None
    """Occupancy flow head on the occupancy head's input, the range-extended BEV (the data then loads flow:
    ``data.flow = true``); None: no flow, as the paper."""
    detection: CenterHeadConfig | None = field(default_factory=CenterHeadConfig)
    """Auxiliary CenterPoint head (training only); None removes it."""
    detection_loss_weight: float = 0.01
    """Weight of the detection losses in the total loss."""
    panoptic: bool = False
    """Also predict each voxel's instance (panoptic occupancy): the detection head's object centres (its heatmap's
    peaks with offset and height, read as Panoptic-FlashOcc reads its centre head) moved into the occupancy frame,
    every voxel of a thing class joined to the nearest centre of its class. Needs ``detection``; training is
    unchanged, so a trained DAOcc becomes panoptic at prediction (``--set model.panoptic=true``)."""

    @property
    def sensors(self) -> tuple[str, ...]:
        """The sensors the model reads at inference."""
        return tuple(name for name, branch in (("cameras", self.image), ("LiDAR", self.lidar)) if branch is not None)

    @property
    def training_targets(self) -> tuple[str, ...]:
        """What supervises the model in training beside the occupancy labels (never an input at inference)."""
        return ("3D boxes",) if self.detection is not None else ()

    @property
    def output_grid(self) -> VoxelGrid:
        """The grid the model predicts on (checked against the label space's grid by
        ``experiment.check_label_space``)."""
        return VoxelGrid(self.occ_range, self.occ_voxel_size)

    def __post_init__(self) -> None:
        if self.image is None and self.lidar is None:
            raise ValueError("DAOcc needs a camera branch (image), a LiDAR branch (lidar), or both")
        expected = {
            "bev.in_channels": (self.bev.in_channels, self.fusion_channels, "fusion_channels"),
            "range_extension.in_channels": (self.range_extension.in_channels, self.bev.neck_channels,
                                            "bev.neck_channels"),
            "occupancy.in_channels": (self.occupancy.in_channels, self.range_extension.out_channels,
                                      "range_extension.out_channels"),
        }
        if self.image is not None:
            expected["view.in_channels"] = (self.view.in_channels, self.image.neck_channels, "image.neck_channels")
        check_motion_input(self.flow, lidar=self.lidar is not None)
        if self.flow is not None:
            expected["flow.in_channels"] = (self.flow.in_channels, self.occupancy.hidden_channels,
                                            "occupancy.hidden_channels")
        if self.detection is not None:
            expected["detection.in_channels"] = (self.detection.in_channels, self.bev.neck_channels,
                                                 "bev.neck_channels")
        elif self.panoptic:
            raise ValueError("panoptic = true takes its object centres from the detection head; detection is None")
        for key, (value, wanted, source) in expected.items():
            if value != wanted:
                raise ValueError(f"{key} = {value} must equal {source} = {wanted}")
        grid = VoxelGrid(self.occ_range, self.occ_voxel_size)
        if grid.shape[2] != self.occupancy.height:
            raise ValueError(f"occupancy.height = {self.occupancy.height} but the occupancy grid has {grid.shape[2]}"
                             " voxels along z")


@dataclass
class FusionPlan:
    """DAOcc's calibration-only tensors."""

    sampling: SamplingPlan | None
    """Where each camera samples its features (None without a camera branch)."""
    range_grid: Tensor
    """``(B, X, Y, 2)`` BVRE ``grid_sample`` coordinates of the occupancy columns in the BEV."""
    points_to_grid: Tensor | None = None
    """``(B, 4, 4)`` from the augmented LiDAR frame to the occupancy grid's, for a flow head's motion input (None
    without one)."""


class DAOcc(OccupancyModel):
    """``forward(batch) -> ModelOutput``; ``loss(output, batch)``; ``predict(batch) -> OccPrediction``.

    Plan: :class:`FusionPlan`. Inputs: ``images (B, N, 3, H, W)`` with a camera branch; with a LiDAR branch either
    ``points (B, P, C)`` and ``num_points (B,)`` (the sparse encoder runs on them) or a ready ``lidar_bev`` (the
    deployed network runs it from rulebooks, :class:`LidarRulebookInputs`).
    """

    def __init__(self, cfg: DAOccConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.grid = VoxelGrid(cfg.occ_range, cfg.occ_voxel_size)
        branch_channels, bev_shapes = [], []
        self.image_encoder = ImageEncoder(cfg.image) if cfg.image is not None else None
        self.view_transform = ProjectionViewTransform(cfg.view) if cfg.image is not None else None
        if self.view_transform is not None:
            branch_channels.append(self.view_transform.out_channels)
            bev_shapes.append(tuple(cfg.view.grid_size[:2]))
        self.lidar_encoder = LidarEncoder(cfg.lidar) if cfg.lidar is not None else None
        if self.lidar_encoder is not None:
            branch_channels.append(self.lidar_encoder.out_channels)
            bev_shapes.append(tuple(self.lidar_encoder.bev_shape))
        if len(set(bev_shapes)) != 1:
            raise ValueError(f"camera BEV {bev_shapes[0]} and LiDAR BEV {bev_shapes[1]} must have the same size")
        self.bev_shape = bev_shapes[0]
        self.fuser = ConvFuser(tuple(branch_channels), cfg.fusion_channels)
        self.bev_encoder = BevEncoder(cfg.bev)
        self.range_extension = RangeExtension(cfg.range_extension, self.grid)
        self.occupancy_head = OccupancyHead(cfg.occupancy)
        if cfg.flow is not None:
            self.flow_head = FlowHead(cfg.flow, self.grid)
        self.detection_head = CenterHead(cfg.detection) if cfg.detection is not None else None

    def remove_detection(self) -> None:
        """Drop the detection branch for deployment: its parameters leave the model and nothing of it runs."""
        self.detection_head = None

    def plan(self, batch: Batch) -> FusionPlan:
        sampling = None
        if self.view_transform is not None:
            images = camera_images(batch, "this DAOcc (it has a camera branch)")
            sampling = self.view_transform.plan(
                batch.intrinsics, batch.cam2ego, batch.img_aug, batch.lidar2ego, batch.bev_aug,
                image_size=tuple(images.shape[-2:]), camera_mask=batch.camera_mask,
            )  # fmt: skip
        to_bev = self.range_extension.to_bev_frame(batch.lidar2ego, batch.bev_aug, batch.occ_aug)
        grid = self.range_extension.sampling_grid(to_bev)
        points_to_grid = None
        if self.flow_head is not None and self.flow_head.motion is not None:
            points_to_grid = invert_transform(to_bev)
        return FusionPlan(sampling=sampling, range_grid=grid, points_to_grid=points_to_grid)

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        inputs = {}
        if self.image_encoder is not None:
            inputs["images"] = camera_images(batch, "this DAOcc (it has a camera branch)")
        if self.lidar_encoder is not None:
            if batch.points is None:
                raise ValueError("this DAOcc has a LiDAR branch but the batch has no points")
            inputs.update(points=batch.points, num_points=batch.num_points)
        return inputs

    def camera_bev(self, inputs: Mapping[str, Tensor], plan: FusionPlan) -> dict[str, Tensor]:
        """The camera branch: ``camera_bev (B, view.out_channels, X_bev, Y_bev)`` from ``images``."""
        return {"camera_bev": self.view_transform(self.image_encoder(inputs["images"]), plan.sampling)}

    def encode(self, inputs: Mapping[str, Tensor], plan: FusionPlan) -> Tensor:
        """The fused and encoded BEV ``(B, bev.neck_channels, X_bev, Y_bev)`` in the augmented LiDAR frame; a ready
        ``camera_bev`` or ``lidar_bev`` in ``inputs`` stands for its branch."""
        bevs = []
        if self.image_encoder is not None:
            camera_bev = inputs.get("camera_bev")
            bevs.append(self.camera_bev(inputs, plan)["camera_bev"] if camera_bev is None else camera_bev)
        if self.lidar_encoder is not None:
            lidar_bev = inputs.get("lidar_bev")
            bevs.append(self.lidar_encoder(inputs["points"], inputs["num_points"]) if lidar_bev is None else lidar_bev)
        return self.bev_encoder(self.fuser(bevs))

    def network(self, inputs: Mapping[str, Tensor], plan: FusionPlan, detect: bool | None = None) -> ModelOutput:
        """The occupancy logits, and the detection head's outputs in training or when ``detect`` is True."""
        bev = self.encode(inputs, plan)
        motion = None
        if self.flow_head is not None and self.flow_head.motion is not None:
            if "points" not in inputs:
                raise ValueError("the flow head's motion input needs the LiDAR points (points, num_points)")
            motion = (inputs["points"], inputs["num_points"], plan.points_to_grid)
        logits, flow = self.occupancy_and_flow(self.occupancy_head, self.range_extension(bev, plan.range_grid), motion)
        output = ModelOutput(occupancy=logits, flow=flow)
        run_detection = self.training if detect is None else detect
        if run_detection and self.detection_head is not None:
            output.detection = self.detection_head(bev)
        return output

    def forward(self, batch: Batch, detect: bool | None = None) -> ModelOutput:
        """Run the model; the detection head runs in training, or when ``detect`` is True."""
        inputs, plan = self.inputs(batch), self.current_plan(batch)
        if detect or self.training or self.network_graphs is None:
            return self.network(inputs, plan, detect)
        images = inputs.get("images")
        if images is None or not images.is_cuda or "lidar_encoder" not in self.eager_stages():
            return self.network_graphs(self.network, self.graph_inputs(inputs), plan)
        return self._overlapped_replay(inputs, plan)

    def _overlapped_replay(self, inputs: dict[str, Tensor], plan: FusionPlan) -> ModelOutput:
        """The network from two CUDA graphs with the sparse LiDAR encoder between them, eager: the camera branch's
        graph replays on a side stream while the encoder runs on the current one, whose host work (voxelization,
        spconv's rulebooks, the sizes they wait for) then overlaps the camera branch on the device; the fusion, BEV
        encoder and heads replay from the second graph once both BEVs exist."""
        images = inputs["images"]
        current, side = torch.cuda.current_stream(images.device), side_stream(images.device)
        side.wait_stream(current)
        with torch.cuda.stream(side):
            camera_bev = self.network_graphs(self.camera_bev, {"images": images}, plan)["camera_bev"]
        images.record_stream(side)  # read on the side stream: not to be reused before it has been
        lidar_bev = self.lidar_encoder(inputs["points"], inputs["num_points"])
        current.wait_stream(side)
        camera_bev.record_stream(current)  # made on the side stream, read on this one
        return self.network_graphs(self.network, {"camera_bev": camera_bev, "lidar_bev": lidar_bev}, plan)

    def eager_stages(self) -> tuple[str, ...]:
        """The LiDAR encoder (spconv builds its rulebooks on the host, which a CUDA graph cannot capture), unless a
        flow head's motion input needs the points inside the network too."""
        if self.lidar_encoder is None or (self.flow_head is not None and self.flow_head.motion is not None):
            return ()
        return ("lidar_encoder",)

    def graph_inputs(self, inputs: dict[str, Tensor]) -> dict[str, Tensor]:
        if "lidar_encoder" not in self.eager_stages() or "lidar_bev" in inputs:
            return inputs
        graphed = {name: value for name, value in inputs.items() if name not in ("points", "num_points")}
        graphed["lidar_bev"] = self.lidar_encoder(inputs["points"], inputs["num_points"])
        return graphed

    def deployment(self, batch: Batch) -> Deployment:
        return FusionInputs(self, batch)

    def loss(self, output: ModelOutput, batch: Batch) -> dict[str, Tensor]:
        """Weighted loss terms; their sum is the training loss."""
        if batch.voxel_semantics is None:
            raise ValueError("the occupancy loss needs batch.voxel_semantics")
        losses = self.occupancy_head.loss(output.occupancy, batch.voxel_semantics, batch.mask_camera)
        if output.detection is not None:
            if batch.boxes is None:
                raise ValueError("the detection loss needs batch.boxes (DatasetConfig.boxes = True)")
            detection = self.detection_head.loss(output.detection, batch.boxes, batch.box_labels)
            for name in ("det_heatmap", "det_bbox"):
                losses[name] = self.cfg.detection_loss_weight * detection[name]
        losses.update(self.flow_losses(output, batch))
        return losses

    @torch.no_grad()
    def predict(self, batch: Batch, boxes: bool = False) -> OccPrediction:
        """Class ids ``(B, X, Y, Z)`` uint8, with ``panoptic`` each voxel's instance, and with ``boxes`` decoded
        detections in the augmented LiDAR frame."""
        panoptic = self.cfg.panoptic and self.detection_head is not None
        output = self.forward(batch, detect=boxes or panoptic)
        prediction = self.prediction(output)
        if boxes and output.detection is not None:
            prediction.boxes, prediction.box_scores, prediction.box_labels = self.detection_head.decode(
                output.detection
            )
        if panoptic:
            centres, _, labels = self.detection_head.centres(output.detection)  # augmented LiDAR frame
            to_occupancy = invert_transform(self.range_extension.to_bev_frame(batch.lidar2ego, batch.bev_aug,
                                                                              batch.occ_aug).double())  # fmt: skip
            centres = [(c.double() @ m[:3, :3].T + m[:3, 3]).float()
                       for c, m in zip(centres, to_occupancy, strict=True)]  # fmt: skip
            prediction.instances = assign_instances(prediction.semantics, centres, labels, self.cfg.output_grid)
        return prediction


class FusionInputs(Deployment):
    """Graph inputs of DAOcc's fixed-rig network (those of the branches the model has).

    * ``images (B, N, 3, H, W)``;
    * ``voxel_features (V, C)``: the mean point of every voxel (``LidarEncoder.voxelize``);
    * ``rules_<key> (2, K', L_key)`` int64, one per sparse convolution key of the encoder (``subm1``, ``spconv1``,
      ..., ``spconv_down2``): input rows and output rows of each kernel offset's pairs, see
      :mod:`occkit.models.sparse_rules`;
    * ``coords_<key> (N_key, 4)`` int64 ``(batch, x, y, z)``, the active sites after each strided convolution; the
      network reads their count, and places the last ones in the dense LiDAR BEV.

    Voxelization and rulebook building run outside the graph (:meth:`inputs`); inside it the sparse encoder runs
    from the rulebooks (:class:`~occkit.models.sparse_rules.RulebookSparseEncoder`, the same weights as spconv's
    layers) and hands :meth:`DAOcc.network` a ready ``lidar_bev``.
    """

    def __init__(self, model: DAOcc, batch: Batch) -> None:
        super().__init__()
        self.cameras = CameraInputs(batch) if model.image_encoder is not None else None
        if self.cameras is not None:
            self.declare("images", self.cameras.input_docs["images"])
        self.batch_size = len(batch)
        self.voxelize = None if model.lidar_encoder is None else model.lidar_encoder.voxelize
        self.sparse_encoder = None
        if model.lidar_encoder is not None:
            self.sparse_encoder = RulebookSparseEncoder(model.lidar_encoder.encoder, self.batch_size)
            channels = model.lidar_encoder.cfg.in_channels
            self.declare("voxel_features", f"(V, {channels}) float32 mean point of each voxel", {0: "voxels"})
            for spec in self.sparse_encoder.specs:
                kind = "submanifold, centre offset left out" if spec.subm else f"stride {spec.stride}"
                self.declare(f"rules_{spec.key}", f"(2, {len(spec.offsets)}, L) int64 rulebook of the {spec.key} "
                             f"convolutions ({kind}): input rows [0] and output rows [1] per kernel offset",
                             {2: f"pairs_{spec.key}"})  # fmt: skip
            for spec in self.sparse_encoder.strided_specs:
                self.declare(f"coords_{spec.key}", f"(N, 4) int64 (batch, x, y, z) active sites after {spec.key}, "
                             f"{spec.out_shape}", {0: f"sites_{spec.key}"})  # fmt: skip

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        tensors = {} if self.cameras is None else self.cameras.inputs(batch)
        if self.sparse_encoder is not None:
            if batch.points is None or len(batch) != self.batch_size:
                raise ValueError(f"the network was made for LiDAR batches of {self.batch_size} sample(s)")
            features, coords, _ = self.voxelize(batch.points, batch.num_points)
            # spconv's extra z cell is never occupied, so the voxel coordinates are valid encoder sites as they are.
            pairs, out_coords = self.sparse_encoder.rulebook_tensors(coords)
            tensors["voxel_features"] = features
            tensors.update({f"rules_{s.key}": p for s, p in zip(self.sparse_encoder.specs, pairs, strict=True)})
            tensors.update({f"coords_{s.key}": c for s, c in zip(self.sparse_encoder.strided_specs, out_coords,
                                                                  strict=True)})  # fmt: skip
        return tensors

    def forward(self, inputs: Mapping[str, Tensor]) -> dict[str, Tensor]:
        named = {} if self.cameras is None else {"images": inputs["images"]}
        if self.sparse_encoder is not None:
            pairs = [inputs[f"rules_{s.key}"] for s in self.sparse_encoder.specs]
            coords = [inputs[f"coords_{s.key}"] for s in self.sparse_encoder.strided_specs]
            named["lidar_bev"] = self.sparse_encoder(inputs["voxel_features"], pairs, coords)  # (B, C', X, Y)
        return named


def with_bev_extent(model: DAOccConfig, extent: float) -> DAOccConfig:
    """``model`` whose LiDAR, projection, BEV and detection range is +-``extent`` m in x and y: the BEV cell size
    and the height range and cells are kept (the BEV range extension's ablation shrinks ``extent`` to the grid's)."""
    view = model.view
    cell = (view.point_cloud_range[3] - view.point_cloud_range[0]) / view.grid_size[0]
    cells = round(2 * extent / cell)
    low, high = view.point_cloud_range[2], view.point_cloud_range[5]
    lidar_range = (-extent, -extent, low, extent, extent, high)
    return dataclasses.replace(
        model,
        view=dataclasses.replace(view, point_cloud_range=lidar_range, grid_size=(cells, cells, view.grid_size[2])),
        lidar=None if model.lidar is None else dataclasses.replace(model.lidar, point_cloud_range=lidar_range),
        range_extension=dataclasses.replace(model.range_extension, bev_range=(-extent, -extent, extent, extent)),
        detection=None if model.detection is None
        else dataclasses.replace(model.detection, point_cloud_range=lidar_range),
    )  # fmt: skip


ARCHITECTURE = Architecture(
    name="daocc",
    config=DAOccConfig,
    model=DAOcc,
    stages={
        "image_encoder": ("image_encoder",),
        "view_transform": ("view_transform",),
        "lidar_encoder": ("lidar_encoder",),
        "fusion_bev_encoder": ("fuser", "bev_encoder"),
        "heads": ("range_extension", "occupancy_head", "flow_head"),
    },
)
