"""FlashOcc (Yu et al., 2023): camera-only LSS to a flat BEV, then channel-to-height; the baseline of both papers.

Data flow (M0, batch ``B``, 6 cameras at 256 x 704)::

    images (B, 6, 3, 256, 704) -> ResNet-50 C4, C5 -> FPN -> (B, 6, 256, 16, 44)
        -> 1x1 depth net: 44 depth bins (softmax) + 64 context channels -> LSS sum pooling -> (B, 64, 200, 200)
        -> BEV encoder (BasicBlocks [2, 2, 2], strides 2, 2, 2; FPN_LSS back to 200 x 200) -> (B, 128, 200, 200)
        -> channel-to-height head -> (B, 18, 200, 200, 16)

Panoptic-FlashOcc (``instances``) adds an instance-centre head on the same 128-channel BEV: a CenterPoint heatmap of
the 10 detection classes with the centre's sub-cell offset and height (trained on the ego-frame boxes, the other
regression branches at zero weight), whose peaks become instance centres; each voxel of a thing class joins the
nearest centre of its class (:mod:`occkit.models.heads.panoptic`).

M1 uses 88 depth bins (0.5 m) and 256 BEV channels. Loss: cross-entropy over the camera-visible voxels, no depth
supervision. The BEV is ``(B, C, X, Y)`` in the augmented ego frame (BEVDet's ``(B, C, Y, X)`` is converted in
``occkit.models.view_transform.lss``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

from torch import Tensor

from occkit.geometry.grid import VoxelGrid
from occkit.losses import depth_bce
from occkit.models.base import Architecture, OccupancyModel, camera_images
from occkit.models.bev_encoder import BevEncoder, BevEncoderConfig
from occkit.models.heads.center import CenterHead, CenterHeadConfig
from occkit.models.heads.depth import lidar_target
from occkit.models.heads.flow import FlowHead, FlowHeadConfig, check_motion_input
from occkit.models.heads.occupancy import OccupancyHead, OccupancyHeadConfig
from occkit.models.heads.panoptic import assign_instances
from occkit.models.image_encoder import ImageEncoder, ImageEncoderConfig
from occkit.models.temporal import HISTORY_INPUTS, TemporalConfig, TemporalFusion
from occkit.models.view_transform.lss import LSSConfig, LSSViewTransform, PoolingPlan
from occkit.types import Batch, ModelOutput, OccPrediction

__all__ = ["FlashOccConfig", "FlashOcc", "ARCHITECTURE"]


@dataclass(frozen=True)
class FlashOccConfig:
    """FlashOcc, M0 on Occ3D-nuScenes by default."""

    image: ImageEncoderConfig = field(
        default_factory=lambda: ImageEncoderConfig(out_stages=(3, 4), norm_eval=False, neck="fpn")
    )
    """ResNet-50 C4 + C5 with BEVDet's FPN (BatchNorm statistics train, as the reference)."""
    lss: LSSConfig = field(default_factory=LSSConfig)
    """Depth net, frustum and pooling onto the 200 x 200 x 1 Occ3D columns."""
    bev: BevEncoderConfig = field(
        default_factory=lambda: BevEncoderConfig(
            in_channels=64, strides=(2, 2, 2), channels=(128, 256, 512), neck_channels=128, neck_extra_upsample=2
        )
    )
    """BEV backbone and FPN_LSS neck (M0: 128 output channels; M1: 256)."""
    occupancy: OccupancyHeadConfig = field(default_factory=OccupancyHeadConfig)
    """Channel-to-height head and camera-masked CE."""
    flow: FlowHeadConfig | None = None
    """Occupancy flow head on the occupancy head's input (the data then loads flow: ``data.flow = true``); None:
    no flow, as the paper."""
    depth_weight: float = 0.0
    """Weight of BEVDepth's depth BCE of the LSS depth bins against LiDAR depth, training only (the data then loads
    depth maps: ``data.depth_downsample = lss.feature_stride``). 0 in M0 and M1, which train without depth
    supervision, as the paper does, and so does the CPU-sized entry (docs/training.md: even exact depth does not
    get a camera-only model past the ground in a short schedule)."""
    temporal: TemporalConfig | None = None
    """BEV history (BEVDet4D's, FlashOcc's 4D models): the LSS BEV fused with earlier frames' before the BEV
    encoder, whose ``in_channels`` is then ``temporal.out_channels(context)``; None: a single frame."""
    instances: CenterHeadConfig | None = None
    """Panoptic-FlashOcc's instance-centre head on the BEV encoder's output (its ``in_channels`` = the neck's, its
    cells the occupancy grid's columns), trained on 3D boxes in the ego frame (``data.boxes``, ``data.box_frame =
    ego``); ``predict`` then gives each voxel of a thing class an instance. None: semantic occupancy, as FlashOcc."""

    @property
    def sensors(self) -> tuple[str, ...]:
        """The sensors the model reads at inference (LiDAR, where the data loads it, only supervises)."""
        return ("cameras",)

    @property
    def training_targets(self) -> tuple[str, ...]:
        """What supervises the model in training beside the occupancy labels (never an input at inference)."""
        return (("LiDAR depth",) if self.depth_weight else ()) + (("3D boxes",) if self.instances else ())

    @property
    def output_grid(self) -> VoxelGrid:
        """The grid the model predicts on: the LSS BEV's extent and cells, its height range cut into the occupancy
        head's ``height`` layers (checked against the label space's grid by ``experiment.check_label_space``)."""
        x_min, y_min, z_min, x_max, y_max, z_max = self.lss.point_cloud_range
        return VoxelGrid.from_shape((x_min, y_min, z_min, x_max, y_max, z_max),
                                    (*self.lss.grid_size[:2], self.occupancy.height))  # fmt: skip

    @property
    def fused_channels(self) -> int:
        """Channels of the BEV entering the encoder: the LSS BEV's, or its fusion with the history's."""
        channels = self.lss.context_channels * self.lss.grid_size[2]
        return channels if self.temporal is None else self.temporal.out_channels(channels)

    def __post_init__(self) -> None:
        checks = {
            "lss.in_channels": (self.lss.in_channels, self.image.neck_channels, "image.neck_channels"),
            "bev.in_channels": (self.bev.in_channels, self.fused_channels,
                                "lss.context_channels x lss.grid_size[2]" + (" fused with the history by "
                                                                             "temporal" if self.temporal else "")),
            "occupancy.in_channels": (self.occupancy.in_channels, self.bev.neck_channels, "bev.neck_channels"),
        }  # fmt: skip
        if self.instances is not None:
            checks["instances.in_channels"] = (self.instances.in_channels, self.bev.neck_channels, "bev.neck_channels")
            checks["instances.bev_shape"] = (self.instances.bev_shape, tuple(self.lss.grid_size[:2]),
                                             "lss.grid_size[:2], the occupancy columns")  # fmt: skip
        check_motion_input(self.flow, lidar=False)
        if self.flow is not None:
            checks["flow.in_channels"] = (self.flow.in_channels, self.occupancy.hidden_channels,
                                          "occupancy.hidden_channels")  # fmt: skip
        for key, (value, wanted, source) in checks.items():
            if value != wanted:
                raise ValueError(f"{key} = {value} must equal {source} = {wanted}")


class FlashOcc(OccupancyModel):
    """``forward(batch) -> ModelOutput``; ``loss(output, batch)``; ``predict(batch) -> OccPrediction``.

    Plan: the LSS :class:`~occkit.models.view_transform.lss.PoolingPlan`. Inputs: ``images``.
    """

    def __init__(self, cfg: FlashOccConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.image_encoder = ImageEncoder(cfg.image)
        if self.image_encoder.stride != cfg.lss.feature_stride:
            raise ValueError(f"lss.feature_stride = {cfg.lss.feature_stride} but the image encoder's output stride"
                             f" is {self.image_encoder.stride}")
        self.view_transform = LSSViewTransform(cfg.lss)
        if cfg.temporal is not None:
            x_min, y_min, _, x_max, y_max, _ = cfg.lss.point_cloud_range
            self.temporal = TemporalFusion(cfg.temporal, cfg.lss.context_channels * cfg.lss.grid_size[2],
                                           (x_min, y_min, x_max, y_max), cfg.lss.grid_size[:2])
        self.bev_encoder = BevEncoder(cfg.bev)
        self.occupancy_head = OccupancyHead(cfg.occupancy)
        if cfg.flow is not None:
            self.flow_head = FlowHead(cfg.flow)
        self.instance_head = CenterHead(cfg.instances) if cfg.instances is not None else None

    def plan(self, batch: Batch) -> PoolingPlan:
        images = camera_images(batch, "FlashOcc")
        return self.view_transform.plan(batch.intrinsics, batch.cam2ego, batch.img_aug, batch.occ_aug,
                                        image_size=tuple(images.shape[-2:]), camera_mask=batch.camera_mask)

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        return {"images": camera_images(batch, "FlashOcc")}

    def frame_bev(self, images: Tensor, plan: PoolingPlan) -> Tensor:
        return self.view_transform(self.image_encoder(images), plan)[0]

    def network(self, inputs: Mapping[str, Tensor], plan: PoolingPlan) -> ModelOutput:
        features = self.image_encoder(inputs["images"])  # (B, N, 256, h, w)
        bev, depth = self.view_transform(features, plan)  # (B, 64, X, Y), (B, N, D, h, w)
        state = None
        if self.temporal is not None:  # (B, (K + 1) 64, X, Y) for BEVDet4D's concatenation
            bev, state = self.temporal(bev, *(inputs[name] for name in HISTORY_INPUTS))
        features = self.bev_encoder(bev)  # (B, 128, X, Y)
        logits, flow = self.occupancy_and_flow(self.occupancy_head, features)
        centres = self.instance_head(features) if self.instance_head is not None else None
        return ModelOutput(occupancy=logits, depth=depth, history_state=state, flow=flow, detection=centres)

    def loss(self, output: ModelOutput, batch: Batch) -> dict[str, Tensor]:
        """The occupancy loss, with ``depth_weight`` the depth BCE (FlashOcc M0/M1 have no depth supervision), and with
        an instance head its centre heatmap and offset / height losses (``det_heatmap``, ``det_bbox``)."""
        if batch.voxel_semantics is None:
            raise ValueError("the occupancy loss needs batch.voxel_semantics")
        losses = self.occupancy_head.loss(output.occupancy, batch.voxel_semantics, batch.mask_camera)
        if self.cfg.depth_weight:
            maps = lidar_target(batch.depth_maps, output.depth, "depth", "FlashOcc", self.cfg.lss.feature_stride)
            losses["depth"] = self.cfg.depth_weight * depth_bce(output.depth, maps, self.cfg.lss.depth_range)
        losses.update(self.flow_losses(output, batch))
        if self.instance_head is not None:
            if batch.boxes is None:
                raise ValueError("the instance-centre loss needs batch.boxes (data.boxes = true, data.box_frame = ego)")
            centres = self.instance_head.loss(output.detection, batch.boxes, batch.box_labels)
            losses.update({name: centres[name] for name in ("det_heatmap", "det_bbox")})
        return losses

    def prediction(self, output: ModelOutput) -> OccPrediction:
        """Class ids (and flow); with an instance head, also each voxel's instance id (0 for stuff)."""
        prediction = super().prediction(output)
        if self.instance_head is not None:
            centres, _, labels = self.instance_head.centres(output.detection)
            prediction.instances = assign_instances(prediction.semantics, centres, labels, self.cfg.output_grid)
        return prediction


ARCHITECTURE = Architecture(
    name="flashocc",
    config=FlashOccConfig,
    model=FlashOcc,
    stages={
        "image_encoder": ("image_encoder",),
        "view_transform": ("view_transform",),
        "fusion_bev_encoder": ("temporal", "bev_encoder"),
        "heads": ("occupancy_head", "flow_head", "instance_head"),
    },
)
