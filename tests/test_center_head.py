"""CenterPoint head: targets in occkit's (X, Y) layout, losses, decoding of oracle maps, NMS per task, config."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
import yaml

from occkit.classes import DETECTION_CLASSES
from occkit.config import ConfigError, dump_yaml, from_dict, to_dict
from occkit.models.heads.center import CODE_SIZE, REGRESSION_BRANCHES, CenterHead, CenterHeadConfig

# 40 x 40 cells of 1 m over [-20, 20]: voxel 0.125 m x stride 8.
TINY = CenterHeadConfig(
    in_channels=32,
    share_conv_channels=16,
    head_conv_channels=16,
    point_cloud_range=(-20.0, -20.0, -5.0, 20.0, 20.0, 3.0),
    voxel_size=(0.125, 0.125),
    out_size_factor=8,
    post_center_range=(-25.0, -25.0, -10.0, 25.0, 25.0, 10.0),
)
CLS = {name: i for i, name in enumerate(DETECTION_CLASSES)}


def _boxes(rows: list[tuple]) -> tuple[torch.Tensor, torch.Tensor]:
    """``(name, x, y, z, l, w, h, yaw, vx, vy)`` rows -> boxes (M, 9) and labels (M,)."""
    boxes = torch.tensor([row[1:] for row in rows], dtype=torch.float32).reshape(-1, 9)
    labels = torch.tensor([CLS[row[0]] for row in rows], dtype=torch.long)
    return boxes, labels


def _every_class(offset: float = 0.0, velocity: float = 1.0) -> list[tuple]:
    """One box per detection class, well apart, inside the tiny config's +-20 m."""
    sizes = {"car": (4.5, 1.9, 1.6), "truck": (7.0, 2.5, 3.0), "construction_vehicle": (6.0, 2.8, 3.2),
             "bus": (11.0, 2.9, 3.5), "trailer": (12.0, 2.9, 3.8), "barrier": (0.5, 2.5, 1.0),
             "motorcycle": (2.1, 0.8, 1.5), "bicycle": (1.7, 0.6, 1.3), "pedestrian": (0.7, 0.7, 1.8),
             "traffic_cone": (0.4, 0.4, 1.0)}  # fmt: skip
    rows = []
    for i, name in enumerate(DETECTION_CLASSES):
        x = -15.3 + 7.1 * (i % 5) + offset
        y = -12.6 + 17.2 * (i // 5) + 0.4 * i
        rows.append((name, x, y, 0.2 * i - 1.0, *sizes[name], -3.0 + 0.6 * i, velocity * (i - 4), 0.5 * velocity))
    return rows


def _oracle_outputs(head: CenterHead, targets, size_x: int, size_y: int) -> list[dict[str, torch.Tensor]]:
    """Maps a perfect network would output: peaks only on the heatmap, the regression targets at the centres."""
    names, sizes = zip(*REGRESSION_BRANCHES, strict=True)
    outputs = []
    for target in targets:
        batch = target.heatmap.shape[0]
        maps = torch.zeros(batch, CODE_SIZE, size_x * size_y)
        for b in range(batch):
            mask = target.mask[b]
            maps[b][:, target.indices[b][mask]] = target.boxes[b][mask].T
        out = dict(zip(names, maps.view(batch, CODE_SIZE, size_x, size_y).split(sizes, dim=1), strict=True))
        out["heatmap"] = torch.where(target.heatmap == 1, 10.0, -10.0)
        outputs.append(out)
    return outputs


# ----------------------------------------------------------------------------------------------- config
def test_config_round_trip():
    for cfg in (CenterHeadConfig(), TINY):
        assert from_dict(CenterHeadConfig, to_dict(cfg)) == cfg
        assert from_dict(CenterHeadConfig, yaml.safe_load(dump_yaml(cfg))) == cfg
    assert TINY.bev_shape == (40, 40) and CenterHeadConfig().bev_shape == (180, 180)


def test_config_rejects_bad_class_name():
    with pytest.raises(ValueError, match="'trucks'"):
        CenterHeadConfig(tasks=(("car",), ("trucks", "construction_vehicle")) + CenterHeadConfig().tasks[2:])
    data = to_dict(CenterHeadConfig())
    data["tasks"][5] = ["pedestrian", "cone"]
    with pytest.raises(ConfigError, match="'cone'"):
        from_dict(CenterHeadConfig, data)
    with pytest.raises(ValueError, match="nms_scales"):
        CenterHeadConfig(nms_scales=((1.0,),) * 6)


def test_paper_parameter_count():
    head = CenterHead(CenterHeadConfig())
    count = sum(p.numel() for p in head.parameters())
    # shared 512*64*9 + BN 128; per branch 64*64*9 + BN 128 + 64*9*out + out; 6 tasks x 6 branches, 10 + 10 outputs.
    expected = 512 * 64 * 9 + 128 + 36 * (64 * 64 * 9 + 128) + 577 * (6 * 10 + 10)
    print(f"CenterHead paper config: {count} parameters")
    assert count == expected == 1_667_142


# ----------------------------------------------------------------------------------------------- forward
def test_forward_shapes_and_init():
    head = CenterHead(TINY)
    outputs = head(torch.randn(2, 32, 40, 40))
    assert len(outputs) == 6
    for task, out in zip(TINY.tasks, outputs, strict=True):
        assert out["heatmap"].shape == (2, len(task), 40, 40)
        assert {name: out[name].shape[1] for name, _ in REGRESSION_BRANCHES} == dict(REGRESSION_BRANCHES)
    for task_head in head.task_heads:
        assert torch.all(task_head.branches["heatmap"][-1].bias == -2.19)
        assert torch.all(task_head.branches["reg"][-1].bias == 0)
    with pytest.raises(ValueError, match="40"):
        head(torch.randn(1, 32, 36, 40))


def test_the_prior_initialisation_starts_every_cell_near_the_prior():
    torch.manual_seed(0)
    bev = torch.randn(1, 32, 40, 40)
    spreads = {}
    for std in (None, 0.01):
        head = CenterHead(dataclasses.replace(TINY, heatmap_init_std=std)).train()
        with torch.no_grad():
            probs = torch.cat([out["heatmap"].sigmoid().flatten() for out in head(bev)])
        spreads[std] = (probs.min().item(), probs.max().item())
    prior = 1 / (1 + math.exp(2.19))
    # mmdet3d's Kaiming weights: some cells start almost certain, others almost impossible.
    assert spreads[None][1] > 0.9 and spreads[None][0] < 0.01
    assert prior / 2 < spreads[0.01][0] <= spreads[0.01][1] < 2 * prior


# ----------------------------------------------------------------------------------------------- targets
def test_targets_place_peak_in_the_right_cell_channel_and_task():
    head = CenterHead(TINY)
    boxes, labels = _boxes([
        ("construction_vehicle", -10.2, 15.7, 0.0, 6.0, 2.8, 3.0, 0.0, 0.0, 0.0),  # cell (9, 35)
        ("car", 3.3, -7.6, 0.5, 4.5, 1.9, 1.6, 0.3, 1.0, 2.0),  # cell (23, 12)
        ("car", 25.0, 0.0, 0.0, 4.0, 2.0, 1.5, 0.0, 0.0, 0.0),  # outside the map
        ("truck", 0.5, 0.5, 0.0, 7.0, 2.5, 3.0, 0.0, 0.0, 0.0),  # cell (20, 20)
    ])  # fmt: skip
    targets = head.targets([boxes], [labels], (40, 40))
    car = targets[0]
    assert car.heatmap[0, 0, 23, 12].item() == 1.0
    assert car.heatmap.eq(1).sum().item() == 1
    # x first: the peak is at x index 23, y index 12, not the transpose.
    assert car.heatmap[0, 0, 12, 23].item() == 0.0
    # radius max(2, int(gaussian_radius((4.5, 1.9), 0.1))) = 2: two cells away along x, exp(-0.72 * 4).
    assert car.heatmap[0, 0, 25, 12].item() == pytest.approx(math.exp(-2.88), rel=1e-6)
    assert car.heatmap[0, 0, 26, 12].item() == 0.0
    assert car.mask[0].tolist()[:3] == [True, False, False]
    assert car.indices[0, 0].item() == 23 * 40 + 12
    expected = [0.3, 0.4, 0.5, math.log(4.5), math.log(1.9), math.log(1.6), math.sin(0.3), math.cos(0.3), 1.0, 2.0]
    assert torch.allclose(car.boxes[0, 0], torch.tensor(expected), atol=1e-5)

    trucks = targets[1]  # truck before construction_vehicle, whatever the input order
    assert trucks.heatmap[0, 0, 20, 20].item() == 1.0 and trucks.heatmap[0, 1, 20, 20].item() == 0.0
    assert trucks.heatmap[0, 1, 9, 35].item() == 1.0 and trucks.heatmap[0, 0].eq(1).sum().item() == 1
    assert trucks.indices[0, :2].tolist() == [20 * 40 + 20, 9 * 40 + 35]
    assert trucks.boxes[0, 1, :2].tolist() == pytest.approx([0.8, 0.7], abs=1e-5)
    for other in targets[2:]:
        assert other.heatmap.sum().item() == 0 and not other.mask.any()


def test_targets_are_fast():
    head = CenterHead(CenterHeadConfig())
    g = torch.Generator().manual_seed(0)
    boxes = torch.rand(100, 9, generator=g)
    boxes[:, :2] = boxes[:, :2] * 100 - 50
    boxes[:, 3:6] = boxes[:, 3:6] * 4 + 0.5
    labels = torch.randint(0, 10, (100,), generator=g)
    head.targets([boxes], [labels], (180, 180))
    import time

    start = time.perf_counter()
    targets = head.targets([boxes], [labels], (180, 180))
    assert time.perf_counter() - start < 0.25  # about 10 ms here; a generous bound for slow machines
    assert sum(t.mask.sum().item() for t in targets) == 100


# ----------------------------------------------------------------------------------------------- decoding
def test_decode_of_oracle_maps_recovers_boxes():
    cfg = CenterHeadConfig()
    head = CenterHead(cfg)
    # Spread 2.5x over the +-54 m map so that no two boxes of a task are near enough for NMS.
    rows = [(name, 2.5 * x, 2.5 * y, *rest) for name, x, y, *rest in _every_class()]
    rows.append(("car", 53.7, -53.9, 0.4, 4.0, 1.8, 1.5, 3.1, -2.0, 0.3))  # last cells of the map
    boxes, labels = _boxes(rows)
    rows = [(name, 2.5 * x, 2.5 * y + 7.0, *rest) for name, x, y, *rest in _every_class(1.3, velocity=-0.5)]
    second, second_labels = _boxes(rows[::-1])
    targets = head.targets([boxes, second], [labels, second_labels], (180, 180))
    decoded, scores, decoded_labels = head.decode(_oracle_outputs(head, targets, 180, 180))
    for sample, (truth, truth_labels) in enumerate([(boxes, labels), (second, second_labels)]):
        assert decoded[sample].shape == truth.shape
        assert sorted(decoded_labels[sample].tolist()) == sorted(truth_labels.tolist())
        assert decoded_labels[sample].dtype == torch.int64
        assert (scores[sample] > 0.99).all()
        for box, label in zip(truth, truth_labels, strict=True):
            same = decoded[sample][decoded_labels[sample] == label]
            match = same[(same[:, :2] - box[:2]).norm(dim=1).argmin()]
            assert torch.allclose(match, box, atol=1e-4), (DETECTION_CLASSES[label], match, box)


def _empty_outputs(batch: int = 1) -> list[dict[str, torch.Tensor]]:
    outputs = []
    for task in TINY.tasks:
        out = {name: torch.zeros(batch, channels, 40, 40) for name, channels in REGRESSION_BRANCHES}
        out["rot"][:, 1] = 1.0  # yaw 0
        out["heatmap"] = torch.full((batch, len(task), 40, 40), -10.0)
        outputs.append(out)
    return outputs


def _put(out: dict[str, torch.Tensor], channel: int, ix: int, iy: int, logit: float, size: float) -> None:
    out["heatmap"][0, channel, ix, iy] = logit
    out["reg"][0, :, ix, iy] = 0.5
    out["dim"][0, :, ix, iy] = math.log(size)


def test_decode_nms_per_task():
    head = CenterHead(TINY)
    outputs = _empty_outputs()
    # Cars (circle NMS, 4 m^2 -> 2 m): centres 1 m apart -> one; a third 3 m away stays.
    for ix, logit in ((10, 3.0), (11, 2.0), (13, 1.0)):
        _put(outputs[0], 0, ix, 5, logit, 4.0)
    # Motorcycles (rotated NMS, scale 1): 0.7 m boxes 1 m apart do not overlap -> both kept.
    for ix, logit in ((10, 3.0), (11, 2.0)):
        _put(outputs[4], 0, ix, 15, logit, 0.7)
    # Pedestrians (rotated NMS, l and w x 2.5 -> 1.75 m): 1 m apart, IoU 1.3125 / 4.8125 = 0.27 > 0.2 -> one.
    for ix, logit in ((10, 3.0), (11, 2.0)):
        _put(outputs[5], 0, ix, 25, logit, 0.7)
    # Below the score threshold (sigmoid(-2.5) = 0.076): dropped.
    _put(outputs[3], 0, 30, 30, -2.5, 1.0)
    boxes, scores, labels = head.decode(outputs)
    by_label = {DETECTION_CLASSES[i]: boxes[0][labels[0] == i][:, 0].tolist() for i in labels[0].unique().tolist()}
    assert by_label == {
        "car": [pytest.approx(-9.5), pytest.approx(-6.5)],
        "motorcycle": [pytest.approx(-9.5), pytest.approx(-8.5)],
        "pedestrian": [pytest.approx(-9.5)],
    }
    assert boxes[0][labels[0] == CLS["pedestrian"], 3].item() == pytest.approx(0.7)  # output sizes are unscaled
    assert torch.all(scores[0] > TINY.score_threshold)


def test_decode_of_a_random_network_is_well_formed():
    head = CenterHead(TINY).eval()
    boxes, scores, labels = head.decode(head(torch.randn(2, 32, 40, 40)))
    assert len(boxes) == len(scores) == len(labels) == 2
    for b, s, lab in zip(boxes, scores, labels, strict=True):
        assert b.shape[1] == 9 and b.shape[0] == s.shape[0] == lab.shape[0]
        assert b.shape[0] <= 6 * TINY.post_max_size
        assert torch.all(s > 0.1) and torch.all((lab >= 0) & (lab < 10))
        assert torch.all(b[:, 3:6] > 0) and torch.isfinite(b).all()


# ----------------------------------------------------------------------------------------------- losses
def test_loss_zero_boxes_is_finite():
    head = CenterHead(TINY)
    outputs = head(torch.randn(2, 32, 40, 40))
    empty = [torch.zeros(0, 9), torch.zeros(0, 9)]
    losses = head.loss(outputs, empty, [torch.zeros(0, dtype=torch.long)] * 2)
    assert losses["det_bbox"].item() == 0.0
    assert all(torch.isfinite(v) for v in losses.values())
    (losses["det_heatmap"] + losses["det_bbox"]).backward()
    assert all(torch.isfinite(p.grad).all() for p in head.parameters() if p.grad is not None)


def test_loss_reaches_every_parameter():
    torch.manual_seed(0)
    head = CenterHead(TINY)
    outputs = head(torch.randn(2, 32, 40, 40))
    first, first_labels = _boxes(_every_class())
    # An odd number of boxes per task, so that no bias gradient (a sum of +-1 L1 signs) can cancel exactly.
    keep = {"truck", "bus", "motorcycle", "pedestrian"}
    second, second_labels = _boxes([row for row in _every_class(offset=2.0, velocity=-1.0) if row[0] in keep])
    losses = head.loss(outputs, [first, second], [first_labels, second_labels])
    assert set(losses) >= {"det_heatmap", "det_bbox", "det_heatmap/task5", "det_bbox/task0"}
    total = sum(losses[f"det_heatmap/task{t}"] for t in range(6))
    assert losses["det_heatmap"].item() == pytest.approx(total.item(), rel=1e-6)
    assert not losses["det_bbox/task0"].requires_grad and losses["det_bbox"].requires_grad
    (losses["det_heatmap"] + losses["det_bbox"]).backward()
    for name, p in head.named_parameters():
        assert p.grad is not None and torch.isfinite(p.grad).all() and p.grad.abs().sum() > 0, name


def test_loss_nan_velocities_get_zero_weight():
    head = CenterHead(TINY)
    outputs = head(torch.randn(1, 32, 40, 40))
    boxes, labels = _boxes(_every_class(velocity=float("nan")))
    assert torch.isnan(boxes[:, 7]).all()
    losses = head.loss(outputs, [boxes], [labels])
    assert all(torch.isfinite(v) for v in losses.values())
    assert losses["det_bbox"].item() > 0
    (losses["det_heatmap"] + losses["det_bbox"]).backward()
    for task_head in head.task_heads:
        for p in task_head.branches["vel"].parameters():
            assert torch.count_nonzero(p.grad) == 0  # only the unknown velocities would train this branch
        assert task_head.branches["dim"][-1].weight.grad.abs().sum() > 0
    assert all(torch.isfinite(p.grad).all() for p in head.parameters())


def test_loss_matches_hand_computation_for_one_box():
    head = CenterHead(TINY)
    outputs = [{k: v.detach() for k, v in out.items()} for out in head(torch.randn(1, 32, 40, 40))]
    boxes, labels = _boxes([("car", 3.3, -7.6, 0.5, 4.5, 1.9, 1.6, 0.3, 1.0, 2.0)])
    losses = head.loss(outputs, [boxes], [labels])
    target = head.targets([boxes], [labels], (40, 40))[0]
    pred = torch.cat([outputs[0][name][0, :, 23, 12] for name, _ in REGRESSION_BRANCHES])
    weights = torch.tensor(TINY.code_weights)
    expected_bbox = 0.25 * (weights * (pred - target.boxes[0, 0]).abs()).sum() / (1 + 1e-4)
    assert losses["det_bbox/task0"].item() == pytest.approx(expected_bbox.item(), rel=1e-5)
    p = outputs[0]["heatmap"].sigmoid().clamp(1e-4, 1 - 1e-4)
    t = target.heatmap
    pos = -(p.log() * (1 - p) ** 2)[t == 1].sum()
    neg = -((1 - p).log() * p**2 * (1 - t) ** 4)[t < 1].sum()
    assert losses["det_heatmap/task0"].item() == pytest.approx((pos + neg).item(), rel=1e-4)
    # Tasks without boxes: heatmap loss over num_peaks clamped to 1, no bbox loss.
    assert losses["det_bbox/task1"].item() == 0.0
