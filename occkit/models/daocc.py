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

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.models.bev_encoder import BevEncoder, BevEncoderConfig, ConvFuser
from occkit.models.heads.center import CenterHead, CenterHeadConfig
from occkit.models.heads.occupancy import OccupancyHead, OccupancyHeadConfig, occupancy_prediction
from occkit.models.image_encoder import ImageEncoder, ImageEncoderConfig
from occkit.models.lidar_encoder import LidarEncoder, LidarEncoderConfig
from occkit.models.range_extension import RangeExtension, RangeExtensionConfig
from occkit.models.view_transform.projection import ProjectionConfig, ProjectionViewTransform
from occkit.types import Batch, ModelOutput, OccPrediction

__all__ = ["DAOccConfig", "DAOcc"]


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
    detection: CenterHeadConfig | None = field(default_factory=CenterHeadConfig)
    """Auxiliary CenterPoint head (training only); None removes it."""
    detection_loss_weight: float = 0.01
    """Weight of the detection losses in the total loss."""

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
        if self.detection is not None:
            expected["detection.in_channels"] = (self.detection.in_channels, self.bev.neck_channels,
                                                 "bev.neck_channels")
        for key, (value, wanted, source) in expected.items():
            if value != wanted:
                raise ValueError(f"{key} = {value} must equal {source} = {wanted}")
        grid = VoxelGrid(self.occ_range, self.occ_voxel_size)
        if grid.shape[2] != self.occupancy.height:
            raise ValueError(f"occupancy.height = {self.occupancy.height} but the occupancy grid has {grid.shape[2]}"
                             " voxels along z")


class DAOcc(nn.Module):
    """``forward(batch) -> ModelOutput``; ``loss(output, batch)``; ``predict(batch) -> OccPrediction``."""

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
        self.detection_head = CenterHead(cfg.detection) if cfg.detection is not None else None

    def remove_detection(self) -> None:
        """Drop the detection branch for deployment: its parameters leave the model and nothing of it runs."""
        self.detection_head = None

    def encode(self, batch: Batch) -> Tensor:
        """The fused and encoded BEV ``(B, bev.neck_channels, X_bev, Y_bev)`` in the augmented LiDAR frame."""
        bevs = []
        if self.image_encoder is not None:
            if batch.images is None:
                raise ValueError("this DAOcc has a camera branch but the batch has no images")
            features = self.image_encoder(batch.images)  # (B, N, C, h, w)
            plan = self.view_transform.plan(
                batch.intrinsics, batch.cam2ego, batch.img_aug, batch.lidar2ego, batch.bev_aug,
                image_size=tuple(batch.images.shape[-2:]), camera_mask=batch.camera_mask,
            )  # fmt: skip
            bevs.append(self.view_transform(features, plan))
        if self.lidar_encoder is not None:
            if batch.points is None:
                raise ValueError("this DAOcc has a LiDAR branch but the batch has no points")
            bevs.append(self.lidar_encoder(batch.points, batch.num_points))
        return self.bev_encoder(self.fuser(bevs))

    def forward(self, batch: Batch, detect: bool | None = None) -> ModelOutput:
        """Run the model; the detection head runs in training, or when ``detect`` is True."""
        bev = self.encode(batch)
        occ_bev = self.range_extension(bev, batch.lidar2ego, batch.bev_aug, batch.occ_aug)
        output = ModelOutput(occupancy=self.occupancy_head(occ_bev))
        run_detection = self.training if detect is None else detect
        if run_detection and self.detection_head is not None:
            output.detection = self.detection_head(bev)
        return output

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
        return losses

    @torch.no_grad()
    def predict(self, batch: Batch, boxes: bool = False) -> OccPrediction:
        """Class ids ``(B, X, Y, Z)`` uint8 and, with ``boxes``, decoded detections in the augmented LiDAR frame."""
        output = self.forward(batch, detect=boxes)
        prediction = occupancy_prediction(output.occupancy)
        if boxes and output.detection is not None:
            prediction.boxes, prediction.box_scores, prediction.box_labels = self.detection_head.decode(
                output.detection
            )
        return prediction
