"""BEV encoder, fuser and channel-to-height head: shapes, layouts and parameter counts."""

from __future__ import annotations

import torch

from occkit.models.bev_encoder import BevEncoder, BevEncoderConfig, ConvFuser
from occkit.models.complexity import count_parameters
from occkit.models.heads.occupancy import OccupancyHead, OccupancyHeadConfig


def test_daocc_bev_encoder_keeps_the_resolution():
    encoder = BevEncoder(BevEncoderConfig()).eval()
    with torch.no_grad():
        assert tuple(encoder(torch.zeros(1, 512, 24, 24)).shape) == (1, 512, 24, 24)
    assert encoder.neck.scale == 2


def test_flashocc_bev_encoder_halves_then_restores():
    cfg = BevEncoderConfig(in_channels=64, strides=(2, 2, 2), channels=(128, 256, 512), neck_channels=256,
                           neck_extra_upsample=2)
    encoder = BevEncoder(cfg).eval()
    assert encoder.neck.scale == 4
    with torch.no_grad():
        assert tuple(encoder(torch.zeros(1, 64, 32, 32)).shape) == (1, 256, 32, 32)


def test_shortcuts_are_biased_convolutions_without_batchnorm():
    encoder = BevEncoder(BevEncoderConfig(in_channels=8, channels=(8, 16, 16), neck_channels=8))
    shortcut = encoder.backbone.stages[1][0].downsample
    assert isinstance(shortcut, torch.nn.Conv2d) and shortcut.bias is not None and shortcut.kernel_size == (3, 3)


def test_fuser_concatenates_in_order():
    fuser = ConvFuser((3, 2), 4)
    assert fuser([torch.zeros(1, 3, 5, 5), torch.zeros(1, 2, 5, 5)]).shape == (1, 4, 5, 5)
    assert fuser.mix[0].in_channels == 5


def test_channel_to_height_layout_is_z_major_then_class():
    cfg = OccupancyHeadConfig(in_channels=4, hidden_channels=4, height=3, num_classes=5)
    head = OccupancyHead(cfg)
    last = head.predictor[-1]
    with torch.no_grad():
        last.weight.zero_()
        last.bias.copy_(torch.tensor([100.0 * z + k for z in range(3) for k in range(5)]))
    logits = head(torch.randn(2, 4, 6, 7))
    assert logits.shape == (2, 5, 6, 7, 3)  # (B, K, X, Y, Z)
    expected = torch.tensor([[100.0 * z + k for z in range(3)] for k in range(5)])  # (K, Z)
    torch.testing.assert_close(logits[1, :, 4, 2, :], expected)


def test_paper_occupancy_head_parameters():
    head = OccupancyHead(OccupancyHeadConfig())
    # conv3x3 128->128 (+bias), Linear 128->256, Linear 256->288.
    assert count_parameters(head) == (128 * 128 * 9 + 128) + (128 * 256 + 256) + (256 * 288 + 288)


def test_the_occupancy_logits_are_float32_under_bf16_autocast():
    """bf16 logits tie where fp32's differ by less than 0.4%: the last projection runs in float32 under bf16 autocast
    (and gives the same values as the head in float32, to the rounding of its bf16 hidden features)."""
    torch.manual_seed(0)
    head = OccupancyHead(OccupancyHeadConfig(in_channels=8, hidden_channels=16, height=4, num_classes=6)).eval()
    bev = torch.randn(1, 8, 10, 12)
    with torch.no_grad():
        exact = head(bev)
        with torch.autocast("cpu", dtype=torch.bfloat16):
            mixed = head(bev)
    assert mixed.dtype == torch.float32 and mixed.shape == exact.shape == (1, 6, 10, 12, 4)
    assert torch.allclose(mixed, exact, atol=0.05) and not torch.equal(mixed, mixed.bfloat16().float())
