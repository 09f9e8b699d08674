"""Losses on hand-computed cases."""

from __future__ import annotations

import math

import pytest
import torch

from occkit.losses import drop_free_cross_entropy, gaussian_focal_loss, masked_cross_entropy, weighted_l1_loss


def two_voxel_case():
    # Logits (B=1, K=2, 2 voxels): voxel 0 -> p(class 0) = 1 / (1 + e^-2); voxel 1 uniform.
    logits = torch.tensor([[[2.0, 0.0], [0.0, 0.0]]])
    labels = torch.tensor([[0, 1]])
    return logits, labels


def test_masked_cross_entropy_averages_over_the_mask():
    logits, labels = two_voxel_case()
    loss0 = math.log(1 + math.exp(-2.0))
    loss1 = math.log(2.0)
    assert masked_cross_entropy(logits, labels).item() == pytest.approx((loss0 + loss1) / 2)
    assert masked_cross_entropy(logits, labels, torch.tensor([[True, False]])).item() == pytest.approx(loss0)
    # A masked-in voxel labelled 255 adds nothing to the sum but still counts in the divisor (mmdet's avg_factor).
    ignored = torch.tensor([[0, 255]])
    assert masked_cross_entropy(logits, ignored, torch.tensor([[True, True]])).item() == pytest.approx(loss0 / 2)


def test_class_weights_normalise_by_the_weight_sum():
    logits, labels = two_voxel_case()
    weights = torch.tensor([1.0, 3.0])
    expected = (1.0 * math.log(1 + math.exp(-2.0)) + 3.0 * math.log(2.0)) / 4.0
    assert masked_cross_entropy(logits, labels, class_weights=weights).item() == pytest.approx(expected)


def test_empty_mask_gives_zero_with_a_gradient():
    logits, labels = two_voxel_case()
    logits.requires_grad_(True)
    loss = masked_cross_entropy(logits, labels, torch.zeros(1, 2, dtype=torch.bool))
    loss.backward()
    assert loss.item() == 0 and logits.grad is not None


def test_drop_free_keeps_every_occupied_voxel_and_a_share_of_free_ones():
    generator = torch.Generator().manual_seed(0)
    labels = torch.full((1, 10000), 17)
    labels[0, :100] = 3
    logits = torch.zeros(1, 18, 10000)
    logits[0, 3, :100] = 50.0  # occupied voxels: loss ~0; free voxels: ln 18 each
    loss = drop_free_cross_entropy(logits, labels, free_index=17, keep_free=0.2, generator=generator)
    kept_free = 0.2 * 9900
    assert loss.item() == pytest.approx(kept_free * math.log(18) / (kept_free + 100), rel=0.03)
    assert drop_free_cross_entropy(logits, labels, 17, keep_free=0.0).item() == pytest.approx(0.0, abs=1e-6)


def test_gaussian_focal_loss_by_hand():
    probs = torch.tensor([0.8, 0.3, 0.1])
    target = torch.tensor([1.0, 0.5, 0.0])
    positive = -math.log(0.8) * 0.2**2
    near = -math.log(0.7) * 0.3**2 * 0.5**4
    far = -math.log(0.9) * 0.1**2
    assert gaussian_focal_loss(probs, target).item() == pytest.approx(positive + near + far, rel=1e-5)


def test_weighted_l1_ignores_unknown_targets():
    pred = torch.tensor([1.0, 2.0, 3.0], requires_grad=True)
    target = torch.tensor([0.5, float("nan"), 2.0])
    weight = torch.tensor([1.0, 0.0, 0.2])
    loss = weighted_l1_loss(pred, target, weight)
    assert loss.item() == pytest.approx(0.5 + 0.2)
    loss.backward()
    assert torch.isfinite(pred.grad).all()
