"""BEVDepth-style DepthNet: image features + camera parameters -> per-pixel depth (or height) bins and context.

Camera awareness (BEVDepth): the 27 camera parameters of each image (intrinsics, image and BEV augmentation,
camera -> ego) are batch-normalised, mapped by two MLPs to channel gates (squeeze-and-excitation) for the depth and
the context branch. Depth branch: residual blocks, ASPP and a 1x1 conv to the bins. DA-Occ's HeightNet is the same
network predicting height bins, with its last two residual blocks replaced by two vertical direction-aware
convolutions (DAC down each image column, the direction in which height varies); ``dac_blocks = 0`` puts the residual
blocks back, the paper's ablation without them. DA-Occ's single-frame model lifts with FlashOcc's 1x1 depth net
instead and uses this camera-aware DepthNet only in its depth-supervised variant (``da_occ_depth``).

Deviation: BEVDepth also uses a deformable conv in the depth branch; occkit leaves it out (no custom operators, ONNX
export with standard ops) and says so in its configs.
"""

from __future__ import annotations

from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.models.dac import DACBlock
from occkit.models.image_encoder import conv_bn_relu
from occkit.models.resnet import BasicBlock

__all__ = ["DepthNetConfig", "DepthNet", "camera_parameters", "lidar_target", "NUM_CAMERA_PARAMETERS"]

NUM_CAMERA_PARAMETERS = 27


def lidar_target(maps: Tensor | None, predicted: Tensor, name: str, model: str, stride: int) -> Tensor:
    """The batch's LiDAR ``name`` maps ``(B, N, h, w)`` (depth or height, training only), checked against the
    predicted bins ``(B, N, K, h, w)`` of ``model``, whose image features have ``stride``."""
    if maps is None:
        raise ValueError(f"{model}'s {name} loss needs LiDAR {name} maps: set data.depth_downsample = {stride}")
    if maps.shape[-2:] != predicted.shape[-2:]:
        raise ValueError(f"{name} maps are {tuple(maps.shape[-2:])} but {model}'s features are "
                         f"{tuple(predicted.shape[-2:])}: data.depth_downsample must equal the feature stride {stride}")
    return maps


@dataclass(frozen=True)
class DepthNetConfig:
    """Camera-aware depth/height network."""

    in_channels: int = 256
    """Channels of the image features."""
    mid_channels: int = 256
    """Width of the network."""
    bins: int = 44
    """Output bins (depth or height)."""
    context_channels: int = 64
    """Context channels lifted to 3D; 0 for a bins-only network (HeightNet)."""
    residual_blocks: int = 3
    """BasicBlocks in the bins branch (counting those replaced by DACs)."""
    dac_blocks: int = 0
    """Last residual blocks replaced by vertical DAC blocks (DA-Occ's HeightNet: 2; 0: BasicBlocks throughout)."""
    feature_height: int = 16
    """Rows of the image features (the DAC kernel length), e.g. 256 / 16."""
    aspp: bool = True
    """Atrous spatial pyramid pooling (dilations 1, 6, 12, 18 and image pooling) before the output conv."""

    def __post_init__(self) -> None:
        if not 0 <= self.dac_blocks <= self.residual_blocks:
            raise ValueError(f"dac_blocks = {self.dac_blocks} must be within 0..residual_blocks = "
                             f"{self.residual_blocks}")


def camera_parameters(intrinsics: Tensor, img_aug: Tensor, occ_aug: Tensor, cam2ego: Tensor) -> Tensor:
    """BEVDet's 27 camera parameters per image ``(B, N, 27)``.

    fx, fy, cx, cy; the image augmentation's 2x2 rotation and translation (post_rot, post_tran) in BEVDet's order;
    the BEV augmentation entries (0,0), (0,1), (1,0), (1,1), (2,2); and the top 3 x 4 of camera -> ego.

    Args:
        intrinsics: ``(B, N, 3, 3)``; img_aug: ``(B, N, 3, 3)``; occ_aug: ``(B, 4, 4)``; cam2ego: ``(B, N, 4, 4)``.
    """
    batch, cameras = intrinsics.shape[:2]
    bda = occ_aug[:, None].expand(batch, cameras, 4, 4)
    values = [
        intrinsics[..., 0, 0], intrinsics[..., 1, 1], intrinsics[..., 0, 2], intrinsics[..., 1, 2],
        img_aug[..., 0, 0], img_aug[..., 0, 1], img_aug[..., 0, 2],
        img_aug[..., 1, 0], img_aug[..., 1, 1], img_aug[..., 1, 2],
        bda[..., 0, 0], bda[..., 0, 1], bda[..., 1, 0], bda[..., 1, 1], bda[..., 2, 2],
    ]  # fmt: skip
    return torch.cat([torch.stack(values, dim=-1), cam2ego[..., :3, :].flatten(-2)], dim=-1).float()


class _Mlp(nn.Sequential):
    def __init__(self, in_features: int, hidden: int) -> None:
        super().__init__(nn.Linear(in_features, hidden), nn.ReLU(inplace=True), nn.Linear(hidden, hidden))


class _SqueezeExcite(nn.Module):
    """Gate features by a vector computed elsewhere (the camera MLP): ``x * sigmoid(expand(relu(reduce(g))))``."""

    def __init__(self, channels: int) -> None:
        super().__init__()
        self.reduce = nn.Conv2d(channels, channels, 1)
        self.expand = nn.Conv2d(channels, channels, 1)

    def forward(self, x: Tensor, gate: Tensor) -> Tensor:
        return x * torch.sigmoid(self.expand(F.relu(self.reduce(gate))))


class _ASPP(nn.Module):
    """DeepLab's ASPP as BEVDepth uses it: 1x1, three dilated 3x3 and image pooling, concatenated, 1x1 back."""

    def __init__(self, channels: int, dilations: tuple[int, ...] = (6, 12, 18)) -> None:
        super().__init__()
        self.branches = nn.ModuleList([conv_bn_relu(channels, channels, 1)])
        for rate in dilations:
            self.branches.append(nn.Sequential(
                nn.Conv2d(channels, channels, 3, padding=rate, dilation=rate, bias=False),
                nn.BatchNorm2d(channels), nn.ReLU(inplace=True),
            ))  # fmt: skip
        self.pool = nn.Sequential(nn.Conv2d(channels, channels, 1, bias=False), nn.BatchNorm2d(channels), nn.ReLU())
        self.project = nn.Sequential(conv_bn_relu(channels * (len(dilations) + 2), channels, 1), nn.Dropout(0.5))

    def forward(self, x: Tensor) -> Tensor:
        pooled = self.pool(x.mean(dim=(2, 3), keepdim=True)).expand(-1, -1, *x.shape[2:])
        return self.project(torch.cat([branch(x) for branch in self.branches] + [pooled], dim=1))


class DepthNet(nn.Module):
    """``forward(features (M, C_in, h, w), cameras (M, 27)) -> (bins (M, D, h, w), context (M, C_ctx, h, w) | None)``.

    ``bins`` are logits (softmax over dim 1 gives the distribution).
    """

    def __init__(self, cfg: DepthNetConfig) -> None:
        super().__init__()
        mid = cfg.mid_channels
        self.reduce = conv_bn_relu(cfg.in_channels, mid, 3)
        self.camera_norm = nn.BatchNorm1d(NUM_CAMERA_PARAMETERS)
        self.bins_mlp = _Mlp(NUM_CAMERA_PARAMETERS, mid)
        self.bins_gate = _SqueezeExcite(mid)
        layers: list[nn.Module] = [BasicBlock(mid, mid) for _ in range(cfg.residual_blocks - cfg.dac_blocks)]
        layers += [DACBlock(mid, cfg.feature_height, "v") for _ in range(cfg.dac_blocks)]
        if cfg.aspp:
            layers.append(_ASPP(mid))
        layers.append(nn.Conv2d(mid, cfg.bins, 1))
        self.bins_branch = nn.Sequential(*layers)
        if cfg.context_channels:
            self.context_mlp = _Mlp(NUM_CAMERA_PARAMETERS, mid)
            self.context_gate = _SqueezeExcite(mid)
            self.context_out = nn.Conv2d(mid, cfg.context_channels, 1)
        self.cfg = cfg

    def forward(self, features: Tensor, cameras: Tensor) -> tuple[Tensor, Tensor | None]:
        cameras = self.camera_norm(cameras.reshape(-1, NUM_CAMERA_PARAMETERS))  # (M, 27)
        x = self.reduce(features)
        bins = self.bins_branch(self.bins_gate(x, self.bins_mlp(cameras)[..., None, None]))
        if not self.cfg.context_channels:
            return bins, None
        context = self.context_out(self.context_gate(x, self.context_mlp(cameras)[..., None, None]))
        return bins, context
