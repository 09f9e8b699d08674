"""Image encoder: a ResNet (torchvision's, :mod:`occkit.models.resnet`) and an FPN-style neck, multi-camera images
-> one feature map.

Two necks, as the references use them:

* ``lss_fpn`` (DAOcc, BEVFusion's ``GeneralizedLSSFPN``): ResNet-50 C3..C5 (512, 1024, 2048 channels at strides 8,
  16, 32) with frozen BatchNorm statistics; top-down, each level upsampled (bilinear) onto the next finer one,
  concatenated with it and mixed by a 1x1 and a 3x3 conv-BN-ReLU: 256 channels at stride 8 (32 x 88 at 256 x 704).
* ``fpn`` (FlashOcc, BEVDet's ``CustomFPN``): C4 + C5, 1x1 lateral convs, nearest-neighbour top-down addition and
  one 3x3 output conv (biases, no normalisation) on the finest level: 256 channels at stride 16 (16 x 44).

``pretrained`` names the backbone's initial weights (a torchvision or timm source, or a local file; see
:mod:`occkit.models.pretrained`); building never reads them, ``occkit.models.pretrained.initialise`` does.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.models.resnet import DEPTHS, BasicBlock, Bottleneck, ResNet, resnet

__all__ = [
    "ImageEncoderConfig",
    "ResNetBackbone",
    "LSSFPN",
    "FPN",
    "ImageEncoder",
    "conv_bn_relu",
]

@dataclass(frozen=True)
class ImageEncoderConfig:
    """ResNet backbone + LSS-FPN neck."""

    depth: int = 50
    """ResNet depth: 18, 34, 50 or 101 (torchvision's definitions, identical to mmdet's "pytorch" style)."""
    blocks: tuple[int, ...] = ()
    """Blocks per stage overriding the depth's (e.g. (1, 1, 1, 1) for a tiny model); empty keeps the standard ones."""
    base_channels: int = 64
    """Width of the stem and of the first stage's blocks, doubling per stage (mmdet's ``base_channels``); 64 is
    torchvision's and every published model's, narrower ones serve reduced-width tests."""
    out_stages: tuple[int, ...] = (2, 3, 4)
    """ResNet stages fed to the neck (1..4 = C2..C5); DAOcc: C3, C4, C5."""
    frozen_stages: int = -1
    """Stages whose weights are frozen (0 = stem only, -1 = none), as mmdet's ``frozen_stages``."""
    norm_eval: bool = True
    """Keep BatchNorm statistics frozen (eval mode) during training, as the references do for pretrained backbones."""
    pretrained: str | None = None
    """Initial weights: ``torchvision:IMAGENET1K_V1`` (torchvision's weights of this depth, downloaded into torch's
    cache), ``timm:NAME``, or a local file (torchvision / timm state dict, ``.safetensors``, or an mmdet / mmdet3d
    checkpoint whose backbone is picked out); None: random (then norm_eval and frozen_stages must be off)."""
    neck: Literal["lss_fpn", "fpn"] = "lss_fpn"
    """``lss_fpn``: concat + 1x1 + 3x3 with BatchNorm (DAOcc); ``fpn``: add + 3x3 without (FlashOcc, DA-Occ)."""
    neck_channels: int = 256
    """Channels of the neck's output."""


def conv_bn_relu(in_channels: int, out_channels: int, kernel_size: int, stride: int = 1) -> nn.Sequential:
    """``Conv2d`` (no bias) + ``BatchNorm2d`` + ``ReLU`` with "same" padding: mmcv's default ``ConvModule``."""
    return nn.Sequential(
        nn.Conv2d(in_channels, out_channels, kernel_size, stride, padding=kernel_size // 2, bias=False),
        nn.BatchNorm2d(out_channels),
        nn.ReLU(inplace=True),
    )


def _layers(net: ResNet) -> list[nn.Sequential]:
    return [net.layer1, net.layer2, net.layer3, net.layer4]


def _resnet(block: type[BasicBlock | Bottleneck], blocks: Sequence[int], base_channels: int) -> ResNet:
    """torchvision's ResNet with ``blocks`` per stage and stage widths ``base_channels * 2^s`` (torchvision fixes 64;
    its ``_make_layer`` builds the stages from ``inplanes`` as mmdet's ResNet does from ``base_channels``)."""
    if base_channels < 1:
        raise ValueError(f"base_channels must be positive, got {base_channels}")
    net = ResNet(block, list(blocks))
    if base_channels != 64:
        net.inplanes = base_channels
        net.conv1 = nn.Conv2d(3, base_channels, kernel_size=7, stride=2, padding=3, bias=False)
        net.bn1 = nn.BatchNorm2d(base_channels)
        for stage, count in enumerate(blocks):
            layer = net._make_layer(block, base_channels * 2**stage, count, stride=1 if stage == 0 else 2)
            setattr(net, f"layer{stage + 1}", layer)
    return net


class ResNetBackbone(nn.Module):
    """ResNet without its classifier, returning the requested stages.

    Args:
        cfg: depth, stages, freezing and weights.

    ``forward(images (M, 3, H, W)) -> list of (M, C_s, H / 2^s, W / 2^s)`` for ``s`` in ``cfg.out_stages``.
    """

    def __init__(self, cfg: ImageEncoderConfig) -> None:
        super().__init__()
        if cfg.depth not in DEPTHS:
            raise ValueError(f"image encoder depth must be one of {sorted(DEPTHS)}, got {cfg.depth}")
        if not cfg.out_stages or any(s not in (1, 2, 3, 4) for s in cfg.out_stages):
            raise ValueError(f"out_stages must be a non-empty subset of 1..4, got {cfg.out_stages}")
        net = resnet(cfg.depth)
        if cfg.blocks or cfg.base_channels != 64:
            net = _resnet(type(net.layer1[0]), cfg.blocks or [len(layer) for layer in _layers(net)], cfg.base_channels)
        self.stem = nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool)
        self.stages = nn.ModuleList([net.layer1, net.layer2, net.layer3, net.layer4][: max(cfg.out_stages)])
        self.out_stages = tuple(cfg.out_stages)
        widths = [stage[-1].conv3.out_channels if hasattr(stage[-1], "conv3") else stage[-1].conv2.out_channels
                  for stage in self.stages]
        self.out_channels = tuple(widths[s - 1] for s in self.out_stages)
        self.strides = tuple(2 ** (s + 1) for s in self.out_stages)
        self.norm_eval = cfg.norm_eval
        self.frozen_stages = cfg.frozen_stages
        self.pretrained, self.depth = cfg.pretrained, cfg.depth
        self._freeze()

    def load_torchvision_state(self, state: dict[str, Tensor], source: str) -> None:
        """Copy torchvision-named ResNet weights (``conv1``, ``bn1``, ``layerK...``; no classifier) into the stages
        this backbone keeps; deeper stages in ``state`` are ignored, any other difference is an error naming
        ``source``."""
        renamed = {}
        for key, value in state.items():
            head, _, rest = key.partition(".")
            if head in ("conv1", "bn1"):
                renamed[f"stem.{0 if head == 'conv1' else 1}.{rest}"] = value
            elif head.startswith("layer") and head[5:].isdigit():
                if int(head[5:]) <= len(self.stages):
                    renamed[f"stages.{int(head[5:]) - 1}.{rest}"] = value
            else:
                renamed[key] = value
        expected = {k: v.shape for k, v in self.state_dict().items()}
        # torchvision's original files predate BatchNorm's num_batches_tracked counter: keep ours (0) then.
        missing = sorted(k for k in expected.keys() - renamed.keys() if not k.endswith("num_batches_tracked"))
        unexpected = sorted(renamed.keys() - expected.keys())
        wrong = sorted(k for k in expected.keys() & renamed.keys() if renamed[k].shape != expected[k])
        if missing or unexpected or wrong:
            raise ValueError(f"{source} does not fit a ResNet-{self.depth} with blocks "
                             f"{[len(stage) for stage in self.stages]}: missing {missing[:3]}, unexpected "
                             f"{unexpected[:3]}, wrong shapes {wrong[:3]}")  # fmt: skip
        self.load_state_dict(renamed, strict=False)

    def _freeze(self) -> None:
        frozen = [self.stem] * (self.frozen_stages >= 0) + list(self.stages[: max(self.frozen_stages, 0)])
        for module in frozen:
            module.eval()
            for p in module.parameters():
                p.requires_grad_(False)

    def train(self, mode: bool = True) -> ResNetBackbone:
        super().train(mode)
        self._freeze()
        if mode and self.norm_eval:
            for m in self.modules():
                if isinstance(m, nn.BatchNorm2d):
                    m.eval()
        return self

    def forward(self, images: Tensor) -> list[Tensor]:
        x = self.stem(images)
        features = []
        for index, stage in enumerate(self.stages, start=1):
            x = stage(x)
            if index in self.out_stages:
                features.append(x)
        return features


class LSSFPN(nn.Module):
    """BEVFusion's ``GeneralizedLSSFPN``: fuse coarse-to-fine by upsample + concat + 1x1 + 3x3, keep the finest level.

    Args:
        in_channels: channels of the input levels, finest first (e.g. 512, 1024, 2048).
        out_channels: output channels (256).

    ``forward(levels) -> (M, out_channels, H_0, W_0)`` at the finest level's resolution.
    """

    def __init__(self, in_channels: tuple[int, ...], out_channels: int) -> None:
        super().__init__()
        if len(in_channels) < 2:
            raise ValueError(f"LSSFPN needs at least two levels, got {in_channels}")
        self.lateral = nn.ModuleList()
        self.output = nn.ModuleList()
        for level in range(len(in_channels) - 1):
            # The coarsest pair concatenates two backbone levels; the finer ones a level and the fused output.
            coarser = in_channels[level + 1] if level == len(in_channels) - 2 else out_channels
            self.lateral.append(conv_bn_relu(in_channels[level] + coarser, out_channels, 1))
            self.output.append(conv_bn_relu(out_channels, out_channels, 3))
        self.out_channels = out_channels

    def forward(self, levels: list[Tensor]) -> Tensor:
        fused = levels[-1]
        for level in range(len(levels) - 2, -1, -1):
            upsampled = F.interpolate(fused, size=levels[level].shape[-2:], mode="bilinear", align_corners=False)
            fused = self.output[level](self.lateral[level](torch.cat([levels[level], upsampled], dim=1)))
        return fused


class FPN(nn.Module):
    """BEVDet's ``CustomFPN`` with one output: 1x1 laterals, top-down nearest upsampling + add, 3x3 on the finest.

    ``forward(levels) -> (M, out_channels, H_0, W_0)`` at the finest level's resolution.
    """

    def __init__(self, in_channels: tuple[int, ...], out_channels: int) -> None:
        super().__init__()
        self.lateral = nn.ModuleList(nn.Conv2d(c, out_channels, 1) for c in in_channels)
        self.output = nn.Conv2d(out_channels, out_channels, 3, padding=1)
        self.out_channels = out_channels

    def forward(self, levels: list[Tensor]) -> Tensor:
        fused = self.lateral[-1](levels[-1])
        for level in range(len(levels) - 2, -1, -1):
            lateral = self.lateral[level](levels[level])
            fused = lateral + F.interpolate(fused, size=lateral.shape[-2:], mode="nearest")
        return self.output(fused)


class ImageEncoder(nn.Module):
    """Multi-camera images ``(B, N, 3, H, W)`` -> features ``(B, N, C, H / s, W / s)``, ``s`` the finest stride."""

    def __init__(self, cfg: ImageEncoderConfig) -> None:
        super().__init__()
        self.backbone = ResNetBackbone(cfg)
        neck = {"lss_fpn": LSSFPN, "fpn": FPN}[cfg.neck]
        self.neck = neck(self.backbone.out_channels, cfg.neck_channels)
        self.out_channels = cfg.neck_channels
        self.stride = self.backbone.strides[0]

    def forward(self, images: Tensor) -> Tensor:
        batch, cameras = images.shape[:2]
        features = self.neck(self.backbone(images.flatten(0, 1)))  # (B*N, C, h, w)
        return features.unflatten(0, (batch, cameras))
