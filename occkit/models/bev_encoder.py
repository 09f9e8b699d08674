"""BEV encoder of BEVDet/FlashOcc/DAOcc: a residual 2D backbone and the FPN_LSS neck, ``(B, C, X, Y)`` throughout.

Backbone (BEVDet's ``CustomResNet``): per stage one BasicBlock with stride ``s`` (shortcut = a 3x3 strided conv with
bias and no BatchNorm, as the reference) and ``n - 1`` plain BasicBlocks. Neck (``FPN_LSS``): the coarser level is
upsampled (bilinear, align_corners=True) onto the finer one, concatenated, mixed by two conv3x3-BN-ReLU, optionally
upsampled again and projected.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor, nn

from occkit.models.image_encoder import conv_bn_relu
from occkit.models.resnet import BasicBlock

__all__ = ["BevEncoderConfig", "BevBackbone", "FPNLSS", "BevEncoder", "ConvFuser"]


@dataclass(frozen=True)
class BevEncoderConfig:
    """BEV backbone (BasicBlock stages) + FPN_LSS neck."""

    in_channels: int = 512
    """Channels of the input BEV."""
    blocks: tuple[int, ...] = (2, 2, 2)
    """BasicBlocks per stage."""
    strides: tuple[int, ...] = (1, 1, 2)
    """Stride of each stage's first block (DAOcc: 1, 1, 2; FlashOcc: 2, 2, 2)."""
    channels: tuple[int, ...] = (128, 256, 512)
    """Output channels of each stage."""
    neck_levels: tuple[int, int] = (0, 2)
    """Stages fused by the neck: (finer, coarser)."""
    neck_channels: int = 512
    """Output channels of the neck."""
    neck_extra_upsample: int = 1
    """Further upsampling after the fusion (FlashOcc: 2, back to the input resolution); 1 for none."""

    def __post_init__(self) -> None:
        if not len(self.blocks) == len(self.strides) == len(self.channels):
            raise ValueError(f"blocks, strides and channels need one entry per stage: {self}")
        if not all(0 <= level < len(self.blocks) for level in self.neck_levels):
            raise ValueError(f"neck_levels {self.neck_levels} must index the {len(self.blocks)} stages")


class BevBackbone(nn.Module):
    """``(B, C_in, X, Y)`` -> one feature map per stage."""

    def __init__(self, cfg: BevEncoderConfig) -> None:
        super().__init__()
        stages = []
        channels = cfg.in_channels
        for count, stride, width in zip(cfg.blocks, cfg.strides, cfg.channels, strict=True):
            shortcut = nn.Conv2d(channels, width, 3, stride, 1)
            layers = [BasicBlock(channels, width, stride=stride, downsample=shortcut)]
            layers += [BasicBlock(width, width) for _ in range(count - 1)]
            stages.append(nn.Sequential(*layers))
            channels = width
        self.stages = nn.ModuleList(stages)

    def forward(self, bev: Tensor) -> list[Tensor]:
        features = []
        for stage in self.stages:
            bev = stage(bev)
            features.append(bev)
        return features


class FPNLSS(nn.Module):
    """BEVDet's ``FPN_LSS``: fuse a fine and a coarse BEV level at the fine resolution."""

    def __init__(self, fine_channels: int, coarse_channels: int, scale: int, out_channels: int, extra_upsample: int):
        super().__init__()
        mid = out_channels * (2 if extra_upsample > 1 else 1)
        self.scale = scale
        self.fuse = nn.Sequential(
            conv_bn_relu(fine_channels + coarse_channels, mid, 3), conv_bn_relu(mid, mid, 3)
        )
        self.extra_upsample = extra_upsample
        self.project = (
            nn.Sequential(conv_bn_relu(mid, out_channels, 3), nn.Conv2d(out_channels, out_channels, 1))
            if extra_upsample > 1
            else None
        )

    def forward(self, fine: Tensor, coarse: Tensor) -> Tensor:
        coarse = nn.functional.interpolate(coarse, scale_factor=self.scale, mode="bilinear", align_corners=True)
        fused = self.fuse(torch.cat([fine, coarse], dim=1))
        if self.project is None:
            return fused
        fused = nn.functional.interpolate(fused, scale_factor=self.extra_upsample, mode="bilinear", align_corners=True)
        return self.project(fused)


class BevEncoder(nn.Module):
    """``(B, C_in, X, Y)`` -> ``(B, neck_channels, X', Y')``."""

    def __init__(self, cfg: BevEncoderConfig) -> None:
        super().__init__()
        self.backbone = BevBackbone(cfg)
        fine, coarse = cfg.neck_levels
        scale = 1
        for stride in cfg.strides[fine + 1 : coarse + 1]:
            scale *= stride
        self.neck = FPNLSS(cfg.channels[fine], cfg.channels[coarse], scale, cfg.neck_channels, cfg.neck_extra_upsample)
        self.levels = cfg.neck_levels
        self.out_channels = cfg.neck_channels

    def forward(self, bev: Tensor) -> Tensor:
        features = self.backbone(bev)
        return self.neck(features[self.levels[0]], features[self.levels[1]])


class ConvFuser(nn.Module):
    """BEVFusion's fuser: concatenate BEV maps and mix them with conv3x3-BN-ReLU."""

    def __init__(self, in_channels: tuple[int, ...], out_channels: int) -> None:
        super().__init__()
        self.mix = conv_bn_relu(sum(in_channels), out_channels, 3)
        self.in_channels = tuple(in_channels)
        self.out_channels = out_channels

    def forward(self, bevs: list[Tensor]) -> Tensor:
        """``bevs``: maps ``(B, C_i, X, Y)`` in ``in_channels`` order -> ``(B, out_channels, X, Y)``."""
        return self.mix(torch.cat(bevs, dim=1))
