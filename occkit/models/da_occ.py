"""DA-Occ (direction-aware occupancy): LSS with depth scores plus a height-score projection, and DAC decoders.

No public code exists; this follows the paper. Data flow (batch ``B``,
6 cameras at 256 x 704, features 16 x 44)::

    images -> ResNet-50 C4, C5 + FPN -> (B, 6, 256, 16, 44)
      DepthNet (camera-aware, BEVDepth)  -> depth (44 bins) + context (64)      \\
      HeightNet (same, 2 vertical DACs)  -> height scores (16 bins over [-1, 5.4] m)
    depth-score LSS  -> F_bev  (B, 64, 200, 200)  -> BEV encoder -> D_h(F) + D_v(F)          -> (B, 128, 200, 200)
    height-score LSS -> F_3D (B, 64, 16, 32, 32) -> slice along X: F_height (B, 64, 16, 32 * 32) -> D_v (along Z)
        -> heights folded into channels (B, 1024, 32, 32) -> 1x1 conv -> bilinear to 200 x 200 -> (B, 128, 200, 200)
    concat -> 1x1 conv -> channel-to-height head -> (B, 18, 200, 200, 16)

Choices the paper leaves open, made here: the height-score projection weights every frustum point by the height
probability of the voxel it falls in (eq. F_3D(v) = sum over points i in v of softmax_Z(H)_i F_i; no depth
factor); F_HEIGHT is reduced to 128 channels at 32 x 32 *before* being brought to 200 x 200 (bilinear), which costs
0.2% of what reducing at full resolution would; D_h and D_v are single DAC blocks (DAC + BN + ReLU) applied after
FlashOcc's BEV encoder. Loss: 1 x depth BCE + 1 x height BCE + 10 x camera-masked CE + 1 x semantic and 1 x geometric
scene-class affinity (MonoScene), the paper's weights.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.data.dataset import DatasetConfig
from occkit.experiment import CPU_TRAIN, Experiment, TrainConfig, cpu_data
from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.label_space import OCC3D_SPACE
from occkit.losses import (
    depth_bce,
    height_bce,
    scene_class_affinity_geometric,
    scene_class_affinity_semantic,
)
from occkit.models.base import FIXED_CALIBRATION_RETIRED, Architecture, OccupancyModel, camera_images
from occkit.models.bev_encoder import BevEncoder, BevEncoderConfig
from occkit.models.dac import DACBlock
from occkit.models.heads.depth import DepthNet, DepthNetConfig, camera_parameters
from occkit.models.heads.occupancy import OccupancyHead, OccupancyHeadConfig
from occkit.models.image_encoder import ImageEncoder, ImageEncoderConfig
from occkit.models.view_transform.lss import (
    PoolingPlan,
    fold_height,
    frustum,
    gather_point_weights,
    lift_geometry,
    make_pooling_plan,
    voxel_pool,
)
from occkit.nuscenes import CAMERAS
from occkit.types import Batch, ModelOutput

__all__ = ["DAOccLossWeights", "DirectionAwareOccConfig", "DirectionAwarePlan", "DirectionAwareOcc", "ARCHITECTURE",
           "da_occ", "da_occ_tiny"]


@dataclass(frozen=True)
class DAOccLossWeights:
    """Weights of DA-Occ's loss terms (paper: 1, 1, 10, 1, 1)."""

    depth: float = 1.0
    """BCE of the depth bins against LiDAR depth."""
    height: float = 1.0
    """BCE of the height bins against LiDAR height (DHD-style per-patch minimum)."""
    occupancy: float = 10.0
    """Camera-masked cross-entropy."""
    semantic_affinity: float = 1.0
    """MonoScene's semantic scene-class affinity."""
    geometric_affinity: float = 1.0
    """MonoScene's geometric scene-class affinity."""


@dataclass(frozen=True)
class DirectionAwareOccConfig:
    """DA-Occ, single frame, the paper's 16 x 32 x 32 height grid."""

    #: Keys of older versions, skipped on load (see :func:`occkit.config.from_dict`).
    RETIRED_KEYS: ClassVar[dict[str, str]] = {"fixed_calibration": FIXED_CALIBRATION_RETIRED}

    image: ImageEncoderConfig = field(
        default_factory=lambda: ImageEncoderConfig(out_stages=(3, 4), norm_eval=False, neck="fpn")
    )
    """ResNet-50 C4 + C5 with BEVDet's FPN, 256 channels at stride 16."""
    feature_stride: int = 16
    """Stride of the image features."""
    depth_range: tuple[float, float, float] = (1.0, 45.0, 1.0)
    """Depth bins (min, max, step), metres."""
    height_range: tuple[float, float, float] = (-1.0, 5.4, 0.4)
    """Height bins (min, max, step), metres in the ego frame: one per voxel layer of the height grid."""
    occ_range: tuple[float, float, float, float, float, float] = OCC3D_GRID.point_cloud_range
    """Occupancy grid extent, ego frame (Occ3D's grid)."""
    bev_size: tuple[int, int] = (200, 200)
    """BEV cells (X, Y) of the depth-score projection and the output."""
    height_grid_size: tuple[int, int, int] = (32, 32, 16)
    """Voxels (X, Y, Z) of the height-score projection."""
    depth_net: DepthNetConfig = field(default_factory=lambda: DepthNetConfig(bins=44, context_channels=64))
    """Camera-aware DepthNet (depth bins and the lifted context)."""
    height_net: DepthNetConfig = field(
        default_factory=lambda: DepthNetConfig(bins=16, context_channels=0, dac_blocks=2)
    )
    """HeightNet: DepthNet's structure for height bins, its last two blocks vertical DACs."""
    bev: BevEncoderConfig = field(
        default_factory=lambda: BevEncoderConfig(
            in_channels=64, strides=(2, 2, 2), channels=(128, 256, 512), neck_channels=128, neck_extra_upsample=2
        )
    )
    """FlashOcc's BEV encoder on F_bev."""
    fusion_channels: int = 128
    """Channels of the fused BEV (and of F_HEIGHT after its 1x1 reduction)."""
    occupancy: OccupancyHeadConfig = field(default_factory=OccupancyHeadConfig)
    """Channel-to-height head."""
    loss_weights: DAOccLossWeights = field(default_factory=DAOccLossWeights)
    """Weights of the loss terms."""

    @property
    def sensors(self) -> tuple[str, ...]:
        """The sensors the model reads at inference (LiDAR, where the data loads it, only supervises)."""
        return ("cameras",)

    def __post_init__(self) -> None:
        height_bins = round((self.height_range[1] - self.height_range[0]) / self.height_range[2])
        checks = {
            "depth_net.in_channels": (self.depth_net.in_channels, self.image.neck_channels, "image.neck_channels"),
            "height_net.in_channels": (self.height_net.in_channels, self.image.neck_channels, "image.neck_channels"),
            "depth_net.bins": (self.depth_net.bins, round((self.depth_range[1] - self.depth_range[0])
                                                          / self.depth_range[2]), "the depth_range bins"),
            "height_net.bins": (self.height_net.bins, height_bins, "the height_range bins"),
            "height_grid_size[2]": (self.height_grid_size[2], height_bins, "the height_range bins"),
            "bev.in_channels": (self.bev.in_channels, self.depth_net.context_channels, "depth_net.context_channels"),
            "fusion_channels": (self.fusion_channels, self.bev.neck_channels, "bev.neck_channels"),
            "occupancy.in_channels": (self.occupancy.in_channels, self.fusion_channels, "fusion_channels"),
        }  # fmt: skip
        for key, (value, wanted, source) in checks.items():
            if value != wanted:
                raise ValueError(f"{key} = {value} must equal {source} = {wanted}")


@dataclass
class DirectionAwarePlan:
    """DA-Occ's calibration-only tensors."""

    camera_params: Tensor
    """``(B, N, 27)`` camera parameters of the camera-aware depth and height nets."""
    z_bins: Tensor
    """``(B, N, D, h, w)`` int64 height bin of every frustum point."""
    bev: PoolingPlan
    """Depth-score pooling onto the ``X x Y x 1`` BEV."""
    height: PoolingPlan
    """Height-score pooling onto the ``X' x Y' x Z`` height volume."""


class DirectionAwareOcc(OccupancyModel):
    """``forward(batch) -> ModelOutput`` (occupancy, depth, height); ``loss(output, batch)``; ``predict(batch)``.

    Plan: :class:`DirectionAwarePlan`. Inputs: ``images``.
    """

    def __init__(self, cfg: DirectionAwareOccConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.bev_grid = VoxelGrid.from_shape(cfg.occ_range, (*cfg.bev_size, 1))
        self.height_grid = VoxelGrid.from_shape(cfg.occ_range, cfg.height_grid_size)
        self.image_encoder = ImageEncoder(cfg.image)
        self.depth_net = DepthNet(cfg.depth_net)
        self.height_net = DepthNet(cfg.height_net)
        self.bev_encoder = BevEncoder(cfg.bev)
        channels, (x, y) = cfg.fusion_channels, cfg.bev_size
        self.bev_horizontal = DACBlock(channels, y, "h")  # D_h: along y (BEV dim 3)
        self.bev_vertical = DACBlock(channels, x, "v")  # D_v: along x (BEV dim 2)
        context = cfg.depth_net.context_channels
        self.height_vertical = DACBlock(context, cfg.height_grid_size[2], "v")  # D_v on F_height: along Z
        self.height_reduce = nn.Conv2d(context * cfg.height_grid_size[2], channels, 1)
        self.fuse = nn.Conv2d(2 * channels, channels, 1)
        self.occupancy_head = OccupancyHead(cfg.occupancy)

    def plan(self, batch: Batch) -> DirectionAwarePlan:
        images = camera_images(batch, "DA-Occ")
        points_uvd = frustum(tuple(images.shape[-2:]), self.cfg.feature_stride, self.cfg.depth_range,
                             device=images.device)
        points = lift_geometry(points_uvd, batch.intrinsics.float(), batch.cam2ego.float(), batch.img_aug.float(),
                               batch.occ_aug.float())  # (B, N, D, h, w, 3)
        z_bins = self.height_grid.world_to_index(points)[0][..., 2].clamp(0, self.cfg.height_grid_size[2] - 1)
        return DirectionAwarePlan(
            camera_params=camera_parameters(batch.intrinsics, batch.img_aug, batch.occ_aug, batch.cam2ego),
            z_bins=z_bins,
            bev=make_pooling_plan(points, self.bev_grid, batch.camera_mask),
            height=make_pooling_plan(points, self.height_grid, batch.camera_mask),
        )

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        return {"images": camera_images(batch, "DA-Occ")}

    def network(self, inputs: Mapping[str, Tensor], plan: DirectionAwarePlan) -> ModelOutput:
        features = self.image_encoder(inputs["images"])  # (B, N, C, h, w)
        batch_size, cameras = features.shape[:2]
        flat = features.flatten(0, 1)
        depth_logits, context = self.depth_net(flat, plan.camera_params)
        height_logits, _ = self.height_net(flat, plan.camera_params)
        depth = depth_logits.softmax(dim=1).unflatten(0, (batch_size, cameras))  # (B, N, D, h, w)
        height = height_logits.softmax(dim=1).unflatten(0, (batch_size, cameras))  # (B, N, Z, h, w)
        context = context.unflatten(0, (batch_size, cameras))  # (B, N, C, h, w)

        bev = fold_height(voxel_pool(depth, context, plan.bev))  # F_bev (B, C, X, Y)
        bev = self.bev_encoder(bev)
        bev = self.bev_horizontal(bev) + self.bev_vertical(bev)  # F_BEV'

        volume = voxel_pool(gather_point_weights(height, plan.z_bins), context, plan.height)  # F_3D (B, C, Z, X, Y)
        c, z, x, y = volume.shape[1:]
        sliced = self.height_vertical(volume.reshape(batch_size, c, z, x * y))  # F_height (B, C, Z, X*Y), DAC on Z
        folded = sliced.reshape(batch_size, c, z, x, y).transpose(1, 2).reshape(batch_size, z * c, x, y)
        heights = F.interpolate(self.height_reduce(folded), size=bev.shape[-2:], mode="bilinear", align_corners=False)

        logits = self.occupancy_head(self.fuse(torch.cat([heights, bev], dim=1)))
        return ModelOutput(occupancy=logits, depth=depth, height=height)

    def loss(self, output: ModelOutput, batch: Batch) -> dict[str, Tensor]:
        """The five weighted terms of DA-Occ's loss."""
        if batch.voxel_semantics is None:
            raise ValueError("the occupancy loss needs batch.voxel_semantics")
        if batch.depth_maps is None or batch.height_maps is None:
            raise ValueError("DA-Occ's loss needs LiDAR depth and height maps: set DatasetConfig.depth_downsample "
                             f"= {self.cfg.feature_stride}")
        if batch.depth_maps.shape[-2:] != output.depth.shape[-2:]:
            raise ValueError(f"depth maps are {tuple(batch.depth_maps.shape[-2:])} but the features are "
                             f"{tuple(output.depth.shape[-2:])}: depth_downsample must equal the feature stride")
        w = self.cfg.loss_weights
        labels, mask = batch.voxel_semantics, batch.mask_camera
        return {
            "depth": w.depth * depth_bce(output.depth, batch.depth_maps, self.cfg.depth_range),
            "height": w.height * height_bce(output.height, batch.height_maps, self.cfg.height_range),
            # The head's own loss: its class balance and optional Lovasz term apply as in the other models.
            **{name: (w.occupancy if name == "occupancy" else 1.0) * term
               for name, term in self.occupancy_head.loss(output.occupancy, labels, mask).items()},
            "semantic_affinity": w.semantic_affinity * scene_class_affinity_semantic(output.occupancy, labels, mask),
            "geometric_affinity": w.geometric_affinity * scene_class_affinity_geometric(
                output.occupancy, labels, self.cfg.occupancy.free_index, mask
            ),
        }



# ------------------------------------------------------------------------------------------------- zoo presets
#: DA-Occ's schedule: AdamW 1e-4, weight decay 0.05, gradient clip 5.
TRAIN = TrainConfig(epochs=24, batch_size=4, lr=1e-4, weight_decay=0.05, grad_clip=5.0)

#: The paper's inputs: six cameras, and the key-frame LiDAR sweep for the depth and height targets (training only).
DATA = DatasetConfig(cameras=CAMERAS, sweeps=0, boxes=False, augment=True, depth_downsample=16,
                     label_space=OCC3D_SPACE.name)  # fmt: skip


def da_occ() -> Experiment:
    """DA-Occ, single frame: ResNet-50 at 256 x 704, camera-aware DepthNet and HeightNet (two vertical DACs),
    depth-score BEV plus a 16 x 32 x 32 height-score volume, DAC decoders; 34.38 mIoU in the paper."""
    return Experiment("da_occ", DirectionAwareOccConfig(), DATA, TRAIN)


def da_occ_tiny() -> Experiment:
    """DA-Occ's architecture scaled down for CPUs: ResNet-18 (one block per stage) C4/C5 at 128 x 352, 22 depth
    bins, 32-channel depth and height nets without ASPP, narrow BEV encoder; Occ3D output grid unchanged."""
    net = {"in_channels": 64, "mid_channels": 32, "residual_blocks": 2, "feature_height": 8, "aspp": False}
    model = DirectionAwareOccConfig(
        image=ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), out_stages=(3, 4), norm_eval=False, neck="fpn",
                                 neck_channels=64),
        depth_range=(1.0, 45.0, 2.0),
        depth_net=DepthNetConfig(bins=22, context_channels=16, **net),
        height_net=DepthNetConfig(bins=16, context_channels=0, dac_blocks=2, **net),
        bev=BevEncoderConfig(in_channels=16, strides=(2, 2, 2), channels=(32, 64, 128), blocks=(1, 1, 1),
                             neck_channels=32, neck_extra_upsample=2),
        fusion_channels=32,
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, class_balance=True),
    )  # fmt: skip
    return Experiment("da_occ", model, cpu_data(DATA), CPU_TRAIN)


ARCHITECTURE = Architecture(
    name="da_occ",
    config=DirectionAwareOccConfig,
    model=DirectionAwareOcc,
    presets={f.__name__: f for f in (da_occ, da_occ_tiny)},
    stages={
        "image_encoder": ("image_encoder",),
        "view_transform": ("depth_net", "height_net"),
        # DA-Occ's decoders: the DACs on F_bev and on the height volume, its reduction and the fusing 1x1 conv.
        "fusion_bev_encoder": ("bev_encoder", "bev_horizontal", "bev_vertical", "height_vertical", "height_reduce",
                               "fuse"),
        "heads": ("occupancy_head",),
    },
)  # fmt: skip
