"""Image encoder: a torchvision ResNet and an FPN-style neck, multi-camera images -> one feature map.

Two necks, as the references use them:

* ``lss_fpn`` (DAOcc, BEVFusion's ``GeneralizedLSSFPN``): ResNet-50 C3..C5 (512, 1024, 2048 channels at strides 8,
  16, 32) with frozen BatchNorm statistics; top-down, each level upsampled (bilinear) onto the next finer one,
  concatenated with it and mixed by a 1x1 and a 3x3 conv-BN-ReLU: 256 channels at stride 8 (32 x 88 at 256 x 704).
* ``fpn`` (FlashOcc, BEVDet's ``CustomFPN``): C4 + C5, 1x1 lateral convs, nearest-neighbour top-down addition and
  one 3x3 output conv (biases, no normalisation) on the finest level: 256 channels at stride 16 (16 x 44).

Weights are never downloaded: ``pretrained`` names a local torchvision-format state dict when a user has one.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import torch
import torch.nn.functional as F
import torchvision
from torch import Tensor, nn

__all__ = [
    "ImageEncoderConfig",
    "ResNetBackbone",
    "LSSFPN",
    "FPN",
    "ImageEncoder",
    "load_state_dict_file",
    "conv_bn_relu",
]

_RESNETS = {18: "resnet18", 34: "resnet34", 50: "resnet50", 101: "resnet101"}


@dataclass(frozen=True)
class ImageEncoderConfig:
    """ResNet backbone + LSS-FPN neck."""

    depth: int = 50
    """ResNet depth: 18, 34, 50 or 101 (torchvision's definitions, identical to mmdet's "pytorch" style)."""
    blocks: tuple[int, ...] = ()
    """Blocks per stage overriding the depth's (e.g. (1, 1, 1, 1) for a tiny model); empty keeps the standard ones."""
    out_stages: tuple[int, ...] = (2, 3, 4)
    """ResNet stages fed to the neck (1..4 = C2..C5); DAOcc: C3, C4, C5."""
    frozen_stages: int = -1
    """Stages whose weights are frozen (0 = stem only, -1 = none), as mmdet's ``frozen_stages``."""
    norm_eval: bool = True
    """Keep BatchNorm statistics frozen (eval mode) during training, as the references do for pretrained backbones."""
    pretrained: str | None = None
    """Local torchvision-format ResNet state dict (``.pth`` or ``.safetensors``); None trains from scratch."""
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


def load_state_dict_file(path: str | Path) -> dict[str, Tensor]:
    """Tensors of a local ``.safetensors`` or ``.pth`` file, loaded without unpickling code."""
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"pretrained weights {path} do not exist")
    if path.suffix == ".safetensors":
        from safetensors.torch import load_file

        return load_file(str(path))
    state = torch.load(path, map_location="cpu", weights_only=True)
    if isinstance(state, dict) and "state_dict" in state:
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ValueError(f"{path} holds a {type(state).__name__}, not a state dict")
    return state


def _load_pretrained(net: nn.Module, path: str, name: str) -> None:
    """Copy a local state dict into ``net`` (its classifier ignored); any other difference is an error."""
    state = {k: v for k, v in load_state_dict_file(path).items() if not k.startswith("fc.")}
    expected = {k: v.shape for k, v in net.state_dict().items() if not k.startswith("fc.")}
    missing = sorted(expected.keys() - state.keys())
    unexpected = sorted(state.keys() - expected.keys())
    wrong = sorted(k for k in expected.keys() & state.keys() if state[k].shape != expected[k])
    if missing or unexpected or wrong:
        raise ValueError(
            f"{path} does not match a {name}: missing {missing[:3]}, unexpected {unexpected[:3]}, "
            f"wrong shapes {wrong[:3]}"
        )
    net.load_state_dict(state, strict=False)


class ResNetBackbone(nn.Module):
    """torchvision ResNet without its classifier, returning the requested stages.

    Args:
        cfg: depth, stages, freezing and weights.

    ``forward(images (M, 3, H, W)) -> list of (M, C_s, H / 2^s, W / 2^s)`` for ``s`` in ``cfg.out_stages``.
    """

    def __init__(self, cfg: ImageEncoderConfig) -> None:
        super().__init__()
        if cfg.depth not in _RESNETS:
            raise ValueError(f"image encoder depth must be one of {sorted(_RESNETS)}, got {cfg.depth}")
        if not cfg.out_stages or any(s not in (1, 2, 3, 4) for s in cfg.out_stages):
            raise ValueError(f"out_stages must be a non-empty subset of 1..4, got {cfg.out_stages}")
        net = getattr(torchvision.models, _RESNETS[cfg.depth])(weights=None)
        if cfg.blocks:
            block = type(net.layer1[0])
            net = torchvision.models.ResNet(block, list(cfg.blocks))
        if cfg.pretrained:
            _load_pretrained(net, cfg.pretrained, f"ResNet-{cfg.depth}")
        self.stem = nn.Sequential(net.conv1, net.bn1, net.relu, net.maxpool)
        self.stages = nn.ModuleList([net.layer1, net.layer2, net.layer3, net.layer4][: max(cfg.out_stages)])
        self.out_stages = tuple(cfg.out_stages)
        widths = [stage[-1].conv3.out_channels if hasattr(stage[-1], "conv3") else stage[-1].conv2.out_channels
                  for stage in self.stages]
        self.out_channels = tuple(widths[s - 1] for s in self.out_stages)
        self.strides = tuple(2 ** (s + 1) for s in self.out_stages)
        self.norm_eval = cfg.norm_eval
        self.frozen_stages = cfg.frozen_stages
        self._freeze()

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
