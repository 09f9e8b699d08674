"""ResNet as torchvision defines it (v1.5: the stride on the bottleneck's 3x3), with its module names and its
initialisation, so that torchvision's and mmdet's ResNet weights load as they are and a seed draws the same weights.

occkit defines it rather than importing ``torchvision.models``: importing torchvision imports ``torch._dynamo``
(through ``torchvision.ops``), about 1.7 s added to every ``occkit`` command that builds a model. torchvision is
imported only where its weights are fetched (:mod:`occkit.models.pretrained`).

What differs from torchvision is only what occkit never uses: no grouped or dilated convolutions, no other
normalisation than ``BatchNorm2d``, no zero-initialised residual branches. ``tests/test_resnet.py`` checks that a seed
gives torchvision's parameters and outputs, for every depth.
"""

from __future__ import annotations

from collections.abc import Sequence

from torch import Tensor, nn

__all__ = ["BasicBlock", "Bottleneck", "ResNet", "resnet", "DEPTHS"]


def _conv3x3(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 3, stride, padding=1, bias=False)


def _conv1x1(in_channels: int, out_channels: int, stride: int = 1) -> nn.Conv2d:
    return nn.Conv2d(in_channels, out_channels, 1, stride, bias=False)


class BasicBlock(nn.Module):
    """Two 3x3 conv-BN (ReLU between them and after the sum) and a shortcut: ``downsample(x)``, or ``x``.

    ``(B, in_channels, H, W) -> (B, channels, H / stride, W / stride)``; ``downsample`` must map between the two.
    """

    expansion = 1

    def __init__(self, in_channels: int, channels: int, stride: int = 1, downsample: nn.Module | None = None) -> None:
        super().__init__()
        # Registration order is torchvision's: it fixes the order of the initial draws and of the state dict.
        self.conv1 = _conv3x3(in_channels, channels, stride)
        self.bn1 = nn.BatchNorm2d(channels)
        self.relu = nn.ReLU(inplace=True)
        self.conv2 = _conv3x3(channels, channels)
        self.bn2 = nn.BatchNorm2d(channels)
        self.downsample = downsample
        self.stride = stride

    def forward(self, x: Tensor) -> Tensor:
        # torchvision's order, the shortcut last: the order of the backward pass, and so its sums, follow it.
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.bn2(self.conv2(out))
        out += x if self.downsample is None else self.downsample(x)  # in place, as torchvision
        return self.relu(out)


class Bottleneck(nn.Module):
    """1x1 conv-BN-ReLU (to ``channels``), 3x3 conv-BN-ReLU with the stride, 1x1 conv-BN (to ``4 x channels``), plus
    the shortcut, then ReLU.

    ``(B, in_channels, H, W) -> (B, 4 channels, H / stride, W / stride)``.
    """

    expansion = 4

    def __init__(self, in_channels: int, channels: int, stride: int = 1, downsample: nn.Module | None = None) -> None:
        super().__init__()
        self.conv1 = _conv1x1(in_channels, channels)
        self.bn1 = nn.BatchNorm2d(channels)
        self.conv2 = _conv3x3(channels, channels, stride)
        self.bn2 = nn.BatchNorm2d(channels)
        self.conv3 = _conv1x1(channels, channels * self.expansion)
        self.bn3 = nn.BatchNorm2d(channels * self.expansion)
        self.relu = nn.ReLU(inplace=True)
        self.downsample = downsample
        self.stride = stride

    def forward(self, x: Tensor) -> Tensor:
        out = self.relu(self.bn1(self.conv1(x)))
        out = self.relu(self.bn2(self.conv2(out)))
        out = self.bn3(self.conv3(out))
        out += x if self.downsample is None else self.downsample(x)
        return self.relu(out)


class ResNet(nn.Module):
    """Stem (7x7 stride-2 conv-BN-ReLU, 3x3 stride-2 max pool), four stages of ``blocks[s]`` blocks at widths 64,
    128, 256, 512 (strides 4, 8, 16, 32), global average pool and a 1000-class linear classifier.

    Convolutions are drawn from He's normal (fan out), BatchNorm starts at weight 1, bias 0; the classifier keeps
    ``nn.Linear``'s draw. ``forward(images (B, 3, H, W)) -> logits (B, 1000)``.
    """

    def __init__(self, block: type[BasicBlock | Bottleneck], blocks: Sequence[int], num_classes: int = 1000) -> None:
        super().__init__()
        self.inplanes = 64  # input channels of the next stage _make_layer builds
        self.conv1 = nn.Conv2d(3, self.inplanes, kernel_size=7, stride=2, padding=3, bias=False)
        self.bn1 = nn.BatchNorm2d(self.inplanes)
        self.relu = nn.ReLU(inplace=True)
        self.maxpool = nn.MaxPool2d(kernel_size=3, stride=2, padding=1)
        self.layer1 = self._make_layer(block, 64, blocks[0])
        self.layer2 = self._make_layer(block, 128, blocks[1], stride=2)
        self.layer3 = self._make_layer(block, 256, blocks[2], stride=2)
        self.layer4 = self._make_layer(block, 512, blocks[3], stride=2)
        self.avgpool = nn.AdaptiveAvgPool2d((1, 1))
        self.fc = nn.Linear(512 * block.expansion, num_classes)
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.constant_(module.weight, 1)
                nn.init.constant_(module.bias, 0)

    def _make_layer(self, block: type[BasicBlock | Bottleneck], channels: int, count: int,
                    stride: int = 1) -> nn.Sequential:  # fmt: skip
        """A stage of ``count`` blocks from ``self.inplanes`` channels, the first with ``stride`` and a 1x1 conv-BN
        shortcut where the shape changes (built before the block, as torchvision does)."""
        downsample = None
        if stride != 1 or self.inplanes != channels * block.expansion:
            downsample = nn.Sequential(_conv1x1(self.inplanes, channels * block.expansion, stride),
                                       nn.BatchNorm2d(channels * block.expansion))  # fmt: skip
        layers = [block(self.inplanes, channels, stride, downsample)]
        self.inplanes = channels * block.expansion
        layers += [block(self.inplanes, channels) for _ in range(1, count)]
        return nn.Sequential(*layers)

    def forward(self, x: Tensor) -> Tensor:
        x = self.maxpool(self.relu(self.bn1(self.conv1(x))))
        x = self.layer4(self.layer3(self.layer2(self.layer1(x))))
        return self.fc(self.avgpool(x).flatten(1))


#: Depth -> block and blocks per stage: torchvision's ``resnet18`` ... ``resnet101``.
DEPTHS: dict[int, tuple[type[BasicBlock | Bottleneck], tuple[int, int, int, int]]] = {
    18: (BasicBlock, (2, 2, 2, 2)),
    34: (BasicBlock, (3, 4, 6, 3)),
    50: (Bottleneck, (3, 4, 6, 3)),
    101: (Bottleneck, (3, 4, 23, 3)),
}


def resnet(depth: int) -> ResNet:
    """The ResNet of ``depth`` (a key of :data:`DEPTHS`), random weights: ``torchvision.models.resnet{depth}()``."""
    if depth not in DEPTHS:
        raise ValueError(f"ResNet depth must be one of {sorted(DEPTHS)}, got {depth}")
    block, blocks = DEPTHS[depth]
    return ResNet(block, blocks)
