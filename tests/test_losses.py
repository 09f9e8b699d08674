"""Losses on hand-computed cases."""

from __future__ import annotations

import math

import pytest
import torch
import torch.nn.functional as F

from occkit.losses import (
    CountedVoxels,
    class_weights_from_frequencies,
    counted_affinity_geometric,
    counted_affinity_semantic,
    counted_cross_entropy,
    counted_lovasz_softmax,
    depth_bce,
    drop_free_cross_entropy,
    focal_loss,
    gaussian_focal_loss,
    height_bce,
    lovasz_grad,
    lovasz_softmax,
    masked_cross_entropy,
    scene_class_affinity_geometric,
    scene_class_affinity_semantic,
    weighted_l1_loss,
)
from occkit.models.heads.occupancy import OCC3D_CLASS_FREQUENCIES, OccupancyHead, OccupancyHeadConfig


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


def assert_zero_with_gradient(loss: torch.Tensor, leaf: torch.Tensor) -> None:
    assert isinstance(loss, torch.Tensor) and loss.dim() == 0 and loss.item() == 0
    loss.backward()
    assert leaf.grad is not None and torch.isfinite(leaf.grad).all()


# --- class balance ---------------------------------------------------------------------------------------------------


def test_class_weights_from_frequencies_is_one_over_the_log():
    weights = class_weights_from_frequencies([10, 1000])
    assert weights.dtype == torch.float32
    assert weights.tolist() == pytest.approx([1 / math.log(10.001), 1 / math.log(1000.001)])
    assert class_weights_from_frequencies(torch.tensor([10.0], dtype=torch.float64)).dtype == torch.float64
    head = OccupancyHead(OccupancyHeadConfig(class_balance=True))
    expected = [1.0 / math.log(f + 0.001) for f in OCC3D_CLASS_FREQUENCIES]
    assert head.class_weights.tolist() == pytest.approx(expected, rel=1e-6)
    with pytest.raises(ValueError, match="counts"):
        class_weights_from_frequencies([0.5, 0.5])  # fractions: negative logs


# --- focal loss ------------------------------------------------------------------------------------------------------


def test_focal_loss_by_hand():
    logits, labels = two_voxel_case()
    p0 = 1 / (1 + math.exp(-2.0))
    loss0 = -((1 - p0) ** 2) * math.log(p0)
    loss1 = -(0.5**2) * math.log(0.5)
    logits = logits.double()
    assert focal_loss(logits, labels).item() == pytest.approx((loss0 + loss1) / 2)
    alpha = torch.tensor([1.0, 3.0])
    assert focal_loss(logits, labels, alpha=alpha).item() == pytest.approx((loss0 + 3 * loss1) / 2)
    assert focal_loss(logits, labels, mask=torch.tensor([[False, True]])).item() == pytest.approx(loss1)
    assert focal_loss(logits, torch.tensor([[0, 255]])).item() == pytest.approx(loss0)


def test_focal_loss_without_focusing_is_the_cross_entropy():
    generator = torch.Generator().manual_seed(0)
    logits = torch.randn(2, 5, 3, 4, generator=generator)
    labels = torch.randint(0, 5, (2, 3, 4), generator=generator)
    labels[0, 0] = 255
    expected = masked_cross_entropy(logits, labels, labels != 255)
    assert focal_loss(logits, labels, gamma=0.0).item() == pytest.approx(expected.item(), rel=1e-6)


def test_focal_loss_with_nothing_counted_is_zero():
    logits, labels = two_voxel_case()
    logits.requires_grad_(True)
    assert_zero_with_gradient(focal_loss(logits, labels, mask=torch.zeros(1, 2, dtype=torch.bool)), logits)


# --- Lovasz-softmax --------------------------------------------------------------------------------------------------


def test_lovasz_grad_by_hand():
    # Ground truth [1, 0, 1] in error order: Jaccard losses of the prefixes 1 - 1/2, 1 - 1/3, 1 - 0/3.
    grad = lovasz_grad(torch.tensor([1.0, 0.0, 1.0]))
    assert grad.tolist() == pytest.approx([0.5, 1 / 6, 1 / 3])


def reference_lovasz(probs: torch.Tensor, labels: torch.Tensor, classes: str) -> float:
    """Berman et al.'s formula, one class at a time: sorted errors dotted with Jaccard-loss increments of prefixes."""
    num_classes = probs.shape[1]
    flat = probs.movedim(1, -1).reshape(-1, num_classes).tolist()
    truth = labels.reshape(-1).tolist()
    losses = []
    for c in range(num_classes):
        pairs = [(abs(float(y == c) - p[c]), y == c) for p, y in zip(flat, truth, strict=True) if y != 255]
        positives = sum(is_c for _, is_c in pairs)
        if classes == "present" and positives == 0:
            continue
        pairs.sort(key=lambda pair: -pair[0])
        # Counting the largest errors as mispredictions one by one: IoU = untouched positives / (positives + false).
        loss, previous, untouched, false_pos = 0.0, 0.0, positives, 0
        for error, is_c in pairs:
            untouched -= is_c
            false_pos += not is_c
            jaccard = 1 - untouched / (positives + false_pos)
            loss += error * (jaccard - previous)
            previous = jaccard
        losses.append(loss)
    return sum(losses) / max(1, len(losses))


def test_lovasz_of_hard_binary_predictions_is_one_minus_iou():
    generator = torch.Generator().manual_seed(1)
    for _ in range(5):
        labels = torch.randint(0, 2, (1, 12), generator=generator)
        predicted = torch.randint(0, 2, (1, 12), generator=generator)
        labels[0, :2] = torch.tensor([0, 1])  # both classes present
        labels[0, 2] = 255
        probs = F.one_hot(predicted, 2).movedim(-1, 1).double()
        counted = labels != 255
        ious = []
        for c in range(2):
            truth, guess = (labels == c) & counted, (predicted == c) & counted
            ious.append((truth & guess).sum().item() / (truth | guess).sum().item())
        expected = sum(1 - iou for iou in ious) / 2
        assert lovasz_softmax(probs, labels).item() == pytest.approx(expected)


def test_lovasz_matches_the_reference_on_soft_probabilities():
    generator = torch.Generator().manual_seed(2)
    probs = torch.randn(2, 4, 3, 5, generator=generator, dtype=torch.float64).softmax(1)
    labels = torch.randint(0, 3, (2, 3, 5), generator=generator)  # class 3 absent
    labels[1, 0, :2] = 255
    for classes in ("present", "all"):
        expected = reference_lovasz(probs, labels, classes)
        assert lovasz_softmax(probs, labels, classes=classes).item() == pytest.approx(expected, rel=1e-9)
    assert lovasz_softmax(probs, labels, classes="all").item() != pytest.approx(lovasz_softmax(probs, labels).item())
    mask = torch.rand(2, 3, 5, generator=generator) > 0.4
    masked_labels = torch.where(mask, labels, torch.full_like(labels, 255))
    expected = reference_lovasz(probs, masked_labels, "present")
    assert lovasz_softmax(probs, labels, mask=mask).item() == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("dtype", [torch.float32, torch.float16, torch.bfloat16])
def test_lovasz_sorts_errors_by_their_bits_in_every_float_type_ties_included(dtype):
    generator = torch.Generator().manual_seed(4)
    # Probabilities on a coarse grid: many equal errors, whose order the bit sort may break differently.
    probs = (torch.rand(1, 4, 40, 30, generator=generator) * 4).round().add(0.5).softmax(1).mul(8).round().div(8)
    labels = torch.randint(0, 4, (1, 40, 30), generator=generator)
    expected = reference_lovasz(probs.double(), labels, "present")
    tolerance = 1e-6 if dtype == torch.float32 else 1e-2  # half precision rounds the probabilities themselves
    assert lovasz_softmax(probs.to(dtype), labels).double().item() == pytest.approx(expected, abs=tolerance)


def test_lovasz_with_nothing_counted_is_zero():
    probs = torch.full((1, 3, 4), 1 / 3, requires_grad=True)
    labels = torch.tensor([[0, 1, 2, 255]])
    for classes in ("present", "all"):
        probs.grad = None
        loss = lovasz_softmax(probs, labels, mask=torch.zeros(1, 4, dtype=torch.bool), classes=classes)
        assert_zero_with_gradient(loss, probs)
    with pytest.raises(ValueError, match="classes"):
        lovasz_softmax(probs, labels, classes="some")


def test_lovasz_gradcheck():
    generator = torch.Generator().manual_seed(3)
    probs = torch.rand(1, 3, 2, 3, generator=generator, dtype=torch.float64).requires_grad_(True)
    labels = torch.tensor([[[0, 1, 2], [1, 255, 0]]])
    mask = torch.tensor([[[True, True, True], [True, True, False]]])
    assert torch.autograd.gradcheck(lambda p: lovasz_softmax(p, labels, mask), (probs,))


def test_occupancy_head_adds_a_weighted_lovasz_term_over_the_cross_entropy_voxels():
    generator = torch.Generator().manual_seed(5)
    logits = torch.randn(2, 18, 3, 4, 16, generator=generator)
    labels = torch.randint(0, 18, (2, 3, 4, 16), generator=generator)
    mask = torch.rand(2, 3, 4, 16, generator=generator) > 0.3
    plain = OccupancyHead(OccupancyHeadConfig()).loss(logits, labels, mask)
    assert set(plain) == {"occupancy"}
    terms = OccupancyHead(OccupancyHeadConfig(lovasz_weight=0.5)).loss(logits, labels, mask)
    assert set(terms) == {"occupancy", "lovasz"}
    torch.testing.assert_close(terms["occupancy"], plain["occupancy"])
    torch.testing.assert_close(terms["lovasz"], 0.5 * lovasz_softmax(logits.softmax(dim=1), labels, mask))
    unmasked = OccupancyHead(OccupancyHeadConfig(use_mask=False, lovasz_weight=1.0)).loss(logits, labels, None)
    torch.testing.assert_close(unmasked["lovasz"], lovasz_softmax(logits.softmax(dim=1), labels))


def test_terms_of_one_gather_equal_the_terms_gathered_each_on_its_own():
    generator = torch.Generator().manual_seed(6)
    grid = torch.randn(2, 5, 3, 4, 18, generator=generator, dtype=torch.float64)  # classes innermost, as the heads
    labels = torch.randint(0, 18, (2, 5, 3, 4), generator=generator)
    labels[0, 0] = 255
    mask = torch.rand(2, 5, 3, 4, generator=generator) > 0.3
    weights = torch.rand(18, generator=generator, dtype=torch.float64) + 0.5

    def separate(logits):
        return [masked_cross_entropy(logits, labels, mask, weights), masked_cross_entropy(logits, labels, mask),
                lovasz_softmax(logits, labels, mask, from_logits=True),
                scene_class_affinity_semantic(logits, labels, mask),
                scene_class_affinity_geometric(logits, labels, 17, mask)]  # fmt: skip

    def shared(logits):
        voxels = CountedVoxels(logits, labels, mask)
        return [counted_cross_entropy(voxels, weights), counted_cross_entropy(voxels), counted_lovasz_softmax(voxels),
                counted_affinity_semantic(voxels), counted_affinity_geometric(voxels, 17)]  # fmt: skip

    gradients = []
    for terms_of in (separate, shared):
        leaf = grid.clone().requires_grad_(True)
        terms = terms_of(leaf.movedim(-1, 1))
        sum(terms).backward()
        gradients.append((torch.stack(terms).detach(), leaf.grad))
    torch.testing.assert_close(gradients[0][0], gradients[1][0], rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(gradients[0][1], gradients[1][1], rtol=1e-12, atol=1e-12)
    with pytest.raises(ValueError, match="logits"):
        counted_cross_entropy(CountedVoxels(grid.movedim(-1, 1).softmax(1), labels, mask, from_logits=False))


# --- scene-class affinity (MonoScene) --------------------------------------------------------------------------------


def affinity_case():
    # Four voxels, three classes; logits are log-probabilities, so the softmax gives these numbers back exactly.
    probs = torch.tensor(
        [[0.7, 0.2, 0.1], [0.1, 0.6, 0.3], [0.2, 0.2, 0.6], [0.5, 0.25, 0.25]], dtype=torch.float64
    )  # (voxel, class)
    logits = probs.log().T.unsqueeze(0)  # (B=1, K=3, 4)
    labels = torch.tensor([[0, 1, 0, 255]])  # the last voxel is ignored
    return logits, labels


def test_semantic_scene_class_affinity_by_hand():
    logits, labels = affinity_case()
    # Class 0 (voxels 0, 2): precision 0.9 / (0.7 + 0.1 + 0.2), recall 0.9 / 2, specificity (1 - 0.1) / 1.
    loss0 = -math.log(0.9) - math.log(0.45) - math.log(0.9)
    # Class 1 (voxel 1): precision 0.6 / (0.2 + 0.6 + 0.2), recall 0.6 / 1, specificity (0.8 + 0.8) / 2.
    loss1 = -math.log(0.6) - math.log(0.6) - math.log(0.8)
    # Class 2 is absent from the counted labels: not averaged in.
    assert scene_class_affinity_semantic(logits, labels).item() == pytest.approx((loss0 + loss1) / 2)


def test_geometric_scene_class_affinity_by_hand():
    logits, labels = affinity_case()
    # Free = class 0: occupied probabilities 0.3, 0.9, 0.8; only voxel 1 is occupied.
    precision, recall, specificity = 0.9 / 2.0, 0.9 / 1.0, (0.7 + 0.2) / 2
    expected = -math.log(precision) - math.log(recall) - math.log(specificity)
    assert scene_class_affinity_geometric(logits, labels, free_index=0).item() == pytest.approx(expected)
    # Free = class 2, absent: all three voxels occupied (probabilities 0.9, 0.7, 0.4), so precision is 1 and the
    # specificity term, with no free voxel, is skipped.
    precision, recall = 2.0 / 2.0, 2.0 / 3
    expected = -math.log(precision) - math.log(recall)
    assert scene_class_affinity_geometric(logits, labels, free_index=2).item() == pytest.approx(expected)


def test_scene_class_affinity_mask_equals_dropping_the_voxels():
    logits, labels = affinity_case()
    mask = torch.tensor([[True, True, False, True]])
    kept = [0, 1, 3]
    semantic = scene_class_affinity_semantic(logits[..., kept], labels[..., kept])
    assert scene_class_affinity_semantic(logits, labels, mask).item() == pytest.approx(semantic.item())
    geometric = scene_class_affinity_geometric(logits[..., kept], labels[..., kept], 0)
    assert scene_class_affinity_geometric(logits, labels, 0, mask).item() == pytest.approx(geometric.item())


def test_scene_class_affinity_with_nothing_counted_is_zero():
    logits, labels = affinity_case()
    logits.requires_grad_(True)
    empty = torch.zeros(1, 4, dtype=torch.bool)
    assert_zero_with_gradient(scene_class_affinity_semantic(logits, labels, empty), logits)
    logits.grad = None
    assert_zero_with_gradient(scene_class_affinity_geometric(logits, labels, 0, empty), logits)


def test_scene_class_affinity_gradcheck():
    generator = torch.Generator().manual_seed(4)
    logits = torch.randn(1, 3, 2, 3, generator=generator, dtype=torch.float64).requires_grad_(True)
    labels = torch.tensor([[[0, 1, 2], [1, 255, 0]]])
    mask = torch.tensor([[[True, True, True], [True, True, False]]])
    assert torch.autograd.gradcheck(lambda x: scene_class_affinity_semantic(x, labels, mask), (logits,))
    assert torch.autograd.gradcheck(lambda x: scene_class_affinity_geometric(x, labels, 2, mask), (logits,))


# --- depth and height bins -------------------------------------------------------------------------------------------


def test_depth_bce_by_hand():
    # Bins (1, 5, 1): [1, 2), [2, 3), [3, 4), [4, 5). One camera, 1 x 6 pixels, the same probabilities everywhere.
    probs = torch.tensor([0.1, 0.6, 0.2, 0.1]).view(1, 1, 4, 1, 1).expand(1, 1, 4, 1, 6)
    depth = torch.tensor([2.5, 0.0, 5.0, 0.5, float("inf"), 1.0]).view(1, 1, 1, 6)
    in_bin_1 = -math.log(0.9) - math.log(0.6) - math.log(0.8) - math.log(0.9)
    in_bin_0 = -math.log(0.1) - math.log(0.4) - math.log(0.8) - math.log(0.9)
    # Valid: 2.5 (bin 1) and 1.0 (bin 0); no LiDAR (0), at max (5.0), below min (0.5) and inf are skipped.
    loss = depth_bce(probs, depth, (1.0, 5.0, 1.0))
    assert loss.item() == pytest.approx((in_bin_1 + in_bin_0) / 2, rel=1e-6)


def test_depth_bce_matches_bevdepth_labels():
    # BEVDepth: bin (d - (min - step)) / step of D + 1 classes, class 0 (out of range) dropped, loss / num_valid.
    generator = torch.Generator().manual_seed(5)
    low, high, step, num_bins = 1.0, 9.0, 0.5, 16
    probs = torch.randn(2, 3, num_bins, 4, 5, generator=generator, dtype=torch.float64).softmax(2)
    depth = torch.rand(2, 3, 4, 5, generator=generator, dtype=torch.float64) * 10
    depth[0, 0] = 0.0
    shifted = (depth - (low - step)) / step
    shifted = torch.where((shifted < num_bins + 1) & (shifted >= 0), shifted, torch.zeros_like(shifted))
    labels = F.one_hot(shifted.long(), num_bins + 1)[..., 1:].reshape(-1, num_bins).double()
    preds = probs.permute(0, 1, 3, 4, 2).reshape(-1, num_bins)
    valid = labels.max(1).values > 0
    expected = F.binary_cross_entropy(preds[valid], labels[valid], reduction="none").sum() / max(1.0, valid.sum())
    assert 0 < valid.sum() < valid.numel()
    assert depth_bce(probs, depth, (low, high, step)).item() == pytest.approx(expected.item(), rel=1e-9)


def test_height_bce_keeps_ground_height_and_skips_nan():
    bins = (-1.0, 5.4, 0.4)  # 16 bins; height 0 lies in bin 2, [-0.2, 0.2)
    probs = torch.full((1, 1, 16, 1, 3), 0.1)
    height = torch.tensor([0.0, float("nan"), 5.4]).view(1, 1, 1, 3)
    expected = -math.log(0.1) - 15 * math.log(0.9)
    assert height_bce(probs, height, bins).item() == pytest.approx(expected, rel=1e-6)
    with pytest.raises(ValueError, match="16 bins"):
        height_bce(torch.full((1, 1, 15, 1, 3), 0.1), height, bins)


def test_binned_bce_without_valid_pixels_is_zero():
    probs = torch.full((1, 2, 4, 2, 2), 0.25, requires_grad=True)
    assert_zero_with_gradient(depth_bce(probs, torch.zeros(1, 2, 2, 2), (1.0, 5.0, 1.0)), probs)
    probs.grad = None
    assert_zero_with_gradient(height_bce(probs, torch.full((1, 2, 2, 2), float("nan")), (0.0, 2.0, 0.5)), probs)


def test_depth_bce_saturated_probabilities_stay_finite():
    logits = torch.tensor([200.0, 0.0, 0.0, 0.0]).view(1, 1, 4, 1, 1).requires_grad_(True)
    loss = depth_bce(logits.softmax(2), torch.tensor([3.5]).view(1, 1, 1, 1), (1.0, 5.0, 1.0))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(logits.grad).all()


def test_depth_bce_gradcheck():
    generator = torch.Generator().manual_seed(6)
    probs = (torch.rand(1, 2, 4, 1, 2, generator=generator, dtype=torch.float64) * 0.9 + 0.05).requires_grad_(True)
    depth = torch.tensor([[[[1.5, 0.0]], [[4.2, 3.0]]]], dtype=torch.float64)
    assert torch.autograd.gradcheck(lambda p: depth_bce(p, depth, (1.0, 5.0, 1.0)), (probs,))
