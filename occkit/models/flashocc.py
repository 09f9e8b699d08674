"""FlashOcc (Yu et al., 2023): camera-only LSS to a flat BEV, then channel-to-height; the baseline of both papers.

Data flow (M0, batch ``B``, 6 cameras at 256 x 704)::

    images (B, 6, 3, 256, 704) -> ResNet-50 C4, C5 -> FPN -> (B, 6, 256, 16, 44)
        -> 1x1 depth net: 44 depth bins (softmax) + 64 context channels -> LSS sum pooling -> (B, 64, 200, 200)
        -> BEV encoder (BasicBlocks [2, 2, 2], strides 2, 2, 2; FPN_LSS back to 200 x 200) -> (B, 128, 200, 200)
        -> channel-to-height head -> (B, 18, 200, 200, 16)

M1 uses 88 depth bins (0.5 m) and 256 BEV channels. Loss: cross-entropy over the camera-visible voxels, no depth
supervision. The BEV is ``(B, C, X, Y)`` in the augmented ego frame (BEVDet's ``(B, C, Y, X)`` is converted in
``occkit.models.view_transform.lss``).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import torch
from torch import Tensor, nn

from occkit.models.bev_encoder import BevEncoder, BevEncoderConfig
from occkit.models.heads.occupancy import OccupancyHead, OccupancyHeadConfig, occupancy_prediction
from occkit.models.image_encoder import ImageEncoder, ImageEncoderConfig
from occkit.models.view_transform.lss import LSSConfig, LSSViewTransform
from occkit.types import Batch, ModelOutput, OccPrediction

__all__ = ["FlashOccConfig", "FlashOcc"]


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

    def __post_init__(self) -> None:
        checks = {
            "lss.in_channels": (self.lss.in_channels, self.image.neck_channels, "image.neck_channels"),
            "bev.in_channels": (self.bev.in_channels, self.lss.context_channels * self.lss.grid_size[2],
                                "lss.context_channels x lss.grid_size[2]"),
            "occupancy.in_channels": (self.occupancy.in_channels, self.bev.neck_channels, "bev.neck_channels"),
        }  # fmt: skip
        for key, (value, wanted, source) in checks.items():
            if value != wanted:
                raise ValueError(f"{key} = {value} must equal {source} = {wanted}")


class FlashOcc(nn.Module):
    """``forward(batch) -> ModelOutput``; ``loss(output, batch)``; ``predict(batch) -> OccPrediction``."""

    def __init__(self, cfg: FlashOccConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.image_encoder = ImageEncoder(cfg.image)
        if self.image_encoder.stride != cfg.lss.feature_stride:
            raise ValueError(f"lss.feature_stride = {cfg.lss.feature_stride} but the image encoder's output stride"
                             f" is {self.image_encoder.stride}")
        self.view_transform = LSSViewTransform(cfg.lss)
        self.bev_encoder = BevEncoder(cfg.bev)
        self.occupancy_head = OccupancyHead(cfg.occupancy)

    def forward(self, batch: Batch) -> ModelOutput:
        if batch.images is None:
            raise ValueError("FlashOcc needs camera images but the batch has none")
        features = self.image_encoder(batch.images)  # (B, N, 256, h, w)
        plan = self.view_transform.plan(batch.intrinsics, batch.cam2ego, batch.img_aug, batch.occ_aug,
                                        image_size=tuple(batch.images.shape[-2:]), camera_mask=batch.camera_mask)
        bev, depth = self.view_transform(features, plan)  # (B, 64, X, Y), (B, N, D, h, w)
        logits = self.occupancy_head(self.bev_encoder(bev))
        return ModelOutput(occupancy=logits, depth=depth)

    def loss(self, output: ModelOutput, batch: Batch) -> dict[str, Tensor]:
        """The occupancy loss (FlashOcc M0/M1 have no depth supervision)."""
        if batch.voxel_semantics is None:
            raise ValueError("the occupancy loss needs batch.voxel_semantics")
        return self.occupancy_head.loss(output.occupancy, batch.voxel_semantics, batch.mask_camera)

    @torch.no_grad()
    def predict(self, batch: Batch) -> OccPrediction:
        return occupancy_prediction(self.forward(batch).occupancy)
