"""Image encoder: ResNet stages, LSS-FPN shapes, frozen statistics and stages (weights: test_pretrained.py)."""

from __future__ import annotations

import pytest
import torch

from occkit.models.complexity import count_parameters
from occkit.models.image_encoder import ImageEncoder, ImageEncoderConfig, ResNetBackbone

TINY = ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), neck_channels=32)


def test_resnet50_lss_fpn_shapes_and_parameters_at_the_paper_resolution():
    encoder = ImageEncoder(ImageEncoderConfig()).eval()
    assert encoder.backbone.out_channels == (512, 1024, 2048)
    assert encoder.stride == 8
    # torchvision's ResNet-50 without its classifier: 23.51 M parameters.
    assert count_parameters(encoder.backbone) == 23_508_032
    with torch.no_grad():
        levels = encoder.backbone(torch.zeros(1, 3, 256, 704))
        assert [tuple(f.shape[1:]) for f in levels] == [(512, 32, 88), (1024, 16, 44), (2048, 8, 22)]
        assert tuple(encoder.neck(levels).shape) == (1, 256, 32, 88)


def test_base_channels_narrow_every_stage_as_mmdets_resnet_does():
    backbone = ResNetBackbone(ImageEncoderConfig(base_channels=4, out_stages=(1, 2, 3, 4)))
    # Bottleneck stages: 4 * base * 2^s output channels; the stem keeps base channels.
    assert backbone.out_channels == (16, 32, 64, 128)
    assert backbone.stem[0].out_channels == 4
    assert [len(stage) for stage in backbone.stages] == [3, 4, 6, 3]  # ResNet-50's blocks are kept
    # Every weight is 1/16 of ResNet-50's width squared, give or take the stem and BatchNorm.
    assert count_parameters(backbone) == pytest.approx(23_508_032 / 256, rel=0.05)
    with pytest.raises(ValueError, match="base_channels"):
        ResNetBackbone(ImageEncoderConfig(base_channels=0))


def test_multi_camera_layout_and_gradients():
    encoder = ImageEncoder(TINY)
    out = encoder(torch.randn(2, 3, 3, 64, 176))
    assert tuple(out.shape) == (2, 3, 32, 8, 22)
    out.square().mean().backward()
    assert all(p.grad is not None for p in encoder.parameters() if p.requires_grad)


def test_norm_eval_keeps_batchnorm_statistics_frozen_in_training():
    encoder = ImageEncoder(TINY).train()
    before = encoder.backbone.stem[1].running_mean.clone()
    encoder(torch.randn(1, 2, 3, 64, 64) * 5 + 3)
    torch.testing.assert_close(encoder.backbone.stem[1].running_mean, before)
    assert not encoder.backbone.stem[1].training
    assert encoder.neck.training  # the neck's own BatchNorms train as usual


def test_frozen_stages_have_no_trainable_parameters():
    backbone = ResNetBackbone(ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), frozen_stages=1))
    assert not any(p.requires_grad for p in backbone.stem.parameters())
    assert not any(p.requires_grad for p in backbone.stages[0].parameters())
    assert all(p.requires_grad for p in backbone.stages[1].parameters())


def test_bad_depth_is_a_clear_error():
    with pytest.raises(ValueError, match="depth must be one of"):
        ResNetBackbone(ImageEncoderConfig(depth=42))


def test_flashocc_fpn_on_c4_c5_gives_stride_16():
    cfg = ImageEncoderConfig(out_stages=(3, 4), neck="fpn", norm_eval=False)
    encoder = ImageEncoder(cfg).eval()
    assert encoder.stride == 16
    # CustomFPN: laterals 1024->256 and 2048->256 and one 3x3 256->256, all with biases.
    assert count_parameters(encoder.neck) == (1024 * 256 + 256) + (2048 * 256 + 256) + (256 * 256 * 9 + 256)
    with torch.no_grad():
        assert tuple(encoder(torch.zeros(1, 1, 3, 256, 704)).shape) == (1, 1, 256, 16, 44)
