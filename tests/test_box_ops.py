"""BEV box geometry: corners, exact rotated IoU, rotated and circle NMS, CenterNet Gaussian targets."""

from __future__ import annotations

import math

import pytest
import torch

from occkit.models.heads.box_ops import (
    bev_corners,
    circle_nms,
    draw_gaussian,
    gaussian_2d,
    gaussian_radius,
    polygon_area,
    rotated_iou_bev,
    rotated_nms,
)


def _box(x, y, l, w, yaw=0.0):
    return [float(x), float(y), float(l), float(w), float(yaw)]


def _random_boxes(n: int, seed: int, spread: float = 1.5) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    boxes = torch.empty(n, 5, dtype=torch.float64)
    boxes[:, :2] = (torch.rand(n, 2, generator=g, dtype=torch.float64) - 0.5) * 2 * spread
    boxes[:, 2:4] = 0.5 + 3.0 * torch.rand(n, 2, generator=g, dtype=torch.float64)
    boxes[:, 4] = (torch.rand(n, generator=g, dtype=torch.float64) - 0.5) * 2 * math.pi
    return boxes


def _inside(points: torch.Tensor, box: torch.Tensor) -> torch.Tensor:
    """``(P, 2)`` points inside one ``(5,)`` box, by rotating them into the box frame."""
    rel = points - box[:2]
    c, s = math.cos(box[4]), math.sin(box[4])
    along = rel[:, 0] * c + rel[:, 1] * s
    across = -rel[:, 0] * s + rel[:, 1] * c
    return (along.abs() <= box[2] / 2) & (across.abs() <= box[3] / 2)


def _raster_iou(a: torch.Tensor, b: torch.Tensor, steps: int = 600) -> float:
    """IoU by counting the centres of a fine grid over both boxes' extent (no polygon code involved)."""
    corners = bev_corners(torch.stack([a, b]))
    lo, hi = corners.reshape(-1, 2).min(0).values, corners.reshape(-1, 2).max(0).values
    u = (torch.arange(steps, dtype=torch.float64) + 0.5) / steps
    xs, ys = lo[0] + u * (hi[0] - lo[0]), lo[1] + u * (hi[1] - lo[1])
    points = torch.stack(torch.meshgrid(xs, ys, indexing="ij"), dim=-1).reshape(-1, 2)
    in_a, in_b = _inside(points, a), _inside(points, b)
    return ((in_a & in_b).sum() / (in_a | in_b).sum()).item()


# ----------------------------------------------------------------------------------------------- corners
def test_corners_counter_clockwise_and_heading():
    corners = bev_corners(torch.tensor([_box(1, 2, 4, 2, math.pi / 2)]))[0]
    # Length along +y after a quarter turn: front-left corner is at (x - w/2, y + l/2).
    assert torch.allclose(corners[0], torch.tensor([0.0, 4.0]), atol=1e-6)
    assert torch.allclose(corners, torch.tensor([[0.0, 4.0], [0.0, 0.0], [2.0, 0.0], [2.0, 4.0]]), atol=1e-6)
    area = polygon_area(corners[None])
    assert area.item() == pytest.approx(8.0, abs=1e-5)  # positive: counter-clockwise


# ----------------------------------------------------------------------------------------------- IoU
def test_iou_identical_is_one():
    boxes = _random_boxes(50, seed=0, spread=40.0).float()
    iou = rotated_iou_bev(boxes, boxes)
    assert torch.allclose(iou.diagonal(), torch.ones(50), atol=1e-5)


def test_iou_disjoint_is_zero():
    a = torch.tensor([_box(0, 0, 2, 2, 0.3)])
    b = torch.tensor([_box(3, 0, 2, 2, 1.1), _box(50, -20, 4, 2, 0.0), _box(0, 2.9, 2, 1, 0.0)])
    assert torch.equal(rotated_iou_bev(a, b), torch.zeros(1, 3))


def test_iou_axis_aligned_matches_formula():
    boxes = _random_boxes(40, seed=1, spread=2.0)
    boxes[:, 4] = 0.0
    iou = rotated_iou_bev(boxes, boxes)
    lo = boxes[:, :2] - boxes[:, 2:4] / 2
    hi = boxes[:, :2] + boxes[:, 2:4] / 2
    overlap = (torch.minimum(hi[:, None], hi[None]) - torch.maximum(lo[:, None], lo[None])).clamp_min(0).prod(-1)
    area = boxes[:, 2] * boxes[:, 3]
    expected = overlap / (area[:, None] + area[None] - overlap)
    assert torch.allclose(iou, expected, atol=1e-9)
    # Swapping l and w while turning by 90 degrees is the same box.
    turned = boxes[:, [0, 1, 3, 2, 4]].clone()
    turned[:, 4] = math.pi / 2
    assert torch.allclose(rotated_iou_bev(turned, boxes), expected, atol=1e-9)


def test_iou_square_and_square_turned_45_degrees():
    # Both squares have inradius 1; their intersection is the regular octagon of inradius 1, area 8 tan(pi/8)
    # = 8 (sqrt 2 - 1); union 8 - that; IoU = (sqrt 2 - 1) / (2 - sqrt 2) = 1 / sqrt 2.
    a = torch.tensor([_box(5, -3, 2, 2, 0.0)], dtype=torch.float64)
    b = torch.tensor([_box(5, -3, 2, 2, math.pi / 4)], dtype=torch.float64)
    assert rotated_iou_bev(a, b).item() == pytest.approx(1 / math.sqrt(2), abs=1e-12)
    assert rotated_iou_bev(a.float(), b.float()).item() == pytest.approx(1 / math.sqrt(2), abs=1e-6)


def test_iou_symmetric_and_bounded():
    a, b = _random_boxes(30, seed=2), _random_boxes(20, seed=3)
    ab, ba = rotated_iou_bev(a, b), rotated_iou_bev(b, a)
    assert torch.allclose(ab, ba.T, atol=1e-12)
    assert (ab >= 0).all() and (ab <= 1).all()
    assert rotated_iou_bev(a[:0], b).shape == (0, 20)


def test_iou_matches_rasterised_estimate():
    a, b = _random_boxes(25, seed=4), _random_boxes(25, seed=5)
    iou = rotated_iou_bev(a, b)
    checked = 0
    for i in range(25):
        expected = _raster_iou(a[i], b[i])
        assert iou[i, i].item() == pytest.approx(expected, abs=0.01), (a[i], b[i])
        checked += expected > 0.05
    assert checked >= 10  # most pairs really overlap


def test_iou_float32_far_from_origin():
    a, b = _random_boxes(10, seed=6), _random_boxes(10, seed=7)
    shift = torch.tensor([50.0, -50.0, 0.0, 0.0, 0.0], dtype=torch.float64)
    near = rotated_iou_bev(a, b)
    far = rotated_iou_bev((a + shift).float(), (b + shift).float())
    assert torch.allclose(far.double(), near, atol=1e-4)


# ----------------------------------------------------------------------------------------------- NMS
def test_rotated_nms_greedy():
    boxes = torch.tensor([
        _box(0, 0, 4, 2),  # 0: IoU 7/9 with box 1
        _box(0.5, 0, 4, 2),  # 1: best
        _box(0, 0, 4, 2, math.pi / 2),  # 2: crosses box 1, IoU 4 / 12 = 1/3
        _box(20, 0, 4, 2),  # 3: far from the others
        _box(21.5, 0, 4, 2),  # 4: IoU 5 / 11 with box 3
        _box(2.5, 0, 4, 2),  # 5: IoU 1/3 with box 1, 1/15 with box 2
    ])  # fmt: skip
    scores = torch.tensor([0.9, 0.95, 0.8, 0.7, 0.6, 0.5])
    assert rotated_nms(boxes, scores, 0.2).tolist() == [1, 3]
    assert rotated_nms(boxes, scores, 0.4).tolist() == [1, 2, 3, 5]
    assert rotated_nms(boxes, scores, 0.2, post_max_size=1).tolist() == [1]
    assert rotated_nms(boxes, scores, 0.2, pre_max_size=2).tolist() == [1]  # candidates: boxes 1 and 0
    assert rotated_nms(boxes[:0], scores[:0], 0.2).tolist() == []


def test_rotated_nms_removed_boxes_do_not_suppress():
    # b overlaps a (IoU 5/11) and is removed; c overlaps b (IoU 1/3) but not a (IoU 1/15), so c stays.
    boxes = torch.tensor([_box(0, 0, 4, 2), _box(1.5, 0, 4, 2), _box(3.5, 0, 4, 2)])
    assert rotated_nms(boxes, torch.tensor([0.9, 0.8, 0.7]), 0.2).tolist() == [0, 2]


def test_circle_nms_squared_distance_semantics():
    centres = torch.tensor([[0.0, 0.0], [1.5, 0.0], [3.0, 0.0], [0.0, -2.0], [0.0, -2.01]])
    scores = torch.tensor([0.9, 0.8, 0.7, 0.6, 0.5])
    # thresh 4 m^2, i.e. within 2 m of a kept box: box 0 removes box 1 (d^2 = 2.25) and box 3 (d^2 = 4, bound
    # included) but not box 4 (d^2 = 4.04); box 2 (d^2 = 9) stays although box 1 (removed) was within 2 m of it.
    assert circle_nms(centres, scores, 4.0).tolist() == [0, 2, 4]
    assert circle_nms(centres, scores, 4.0, post_max_size=2).tolist() == [0, 2]
    # thresh 2 m^2: 1.5 m apart survives (2.25 > 2), so only box 4 (0.01 m from box 3) goes.
    assert circle_nms(centres, scores, 2.0).tolist() == [0, 1, 2, 3]
    # Visiting order follows the scores: box 2 first removes box 1; box 0 is 3 m from box 2 and stays.
    assert circle_nms(centres[:3], torch.tensor([0.1, 0.2, 0.3]), 4.0).tolist() == [2, 0]
    assert circle_nms(centres[:0], scores[:0], 4.0).tolist() == []


# ----------------------------------------------------------------------------------------------- Gaussians
def test_gaussian_radius_pinned():
    # h = w = 10, overlap 0.1: r1 = (20 + sqrt(400 - 4 * 900 / 11)) / 2 = 14.264, r2 = (40 + sqrt(160)) / 2 = 26.32,
    # r3 = (-4 + sqrt(16 + 144)) / 2 = sqrt(40) - 2 = 4.3246 -> the smallest.
    assert gaussian_radius((10, 10), 0.1) == pytest.approx(math.sqrt(40) - 2, abs=1e-12)
    # DAOcc car 4.5 x 1.9 m at 0.6 m cells: (7.5, 3.1667) cells -> r3 = (-2.1333 + sqrt(4.55111 + 34.2)) / 2 = 2.045853.
    length, width = 4.5 / 0.6, 1.9 / 0.6
    b3, c3 = -0.2 * (length + width), -0.9 * length * width
    expected = (b3 + math.sqrt(b3 * b3 - 1.6 * c3)) / 2
    assert gaussian_radius((length, width), 0.1) == pytest.approx(expected, abs=1e-12)
    assert gaussian_radius((length, width), 0.1) == pytest.approx(2.045853, abs=1e-6)
    # Symmetric in (h, w). Overlap 0.7 on 10 x 10: a3 = 2.8, b3 = -28, c3 = -30, r3 = (-28 + sqrt(784 + 336)) / 2.
    assert gaussian_radius((3.0, 7.0), 0.1) == pytest.approx(gaussian_radius((7.0, 3.0), 0.1), rel=1e-14)
    assert gaussian_radius((10, 10), 0.7) == pytest.approx((-28 + math.sqrt(1120)) / 2, abs=1e-12)


def test_gaussian_kernel_values():
    g1 = gaussian_2d(1)  # sigma 0.5: exp(-2 d^2)
    assert g1.shape == (3, 3)
    assert g1[1, 1].item() == 1.0
    assert g1[0, 1].item() == pytest.approx(math.exp(-2), rel=1e-12)
    assert g1[0, 0].item() == pytest.approx(math.exp(-4), rel=1e-12)
    g2 = gaussian_2d(2)  # sigma 5/6: exp(-0.72 d^2)
    assert g2[2, 3].item() == pytest.approx(math.exp(-0.72), rel=1e-12)
    assert g2[0, 0].item() == pytest.approx(math.exp(-5.76), rel=1e-12)


def test_draw_gaussian_max_merge_and_borders():
    heat = torch.zeros(6, 8)
    heat[3, 5] = 0.5
    draw_gaussian(heat, (2, 4), 2)
    assert heat[2, 4].item() == 1.0
    assert heat[3, 4].item() == pytest.approx(math.exp(-0.72), rel=1e-6)  # x neighbour
    assert heat[2, 6].item() == pytest.approx(math.exp(-2.88), rel=1e-6)  # two cells along y
    assert heat[3, 5].item() == 0.5  # max-merge keeps the larger 0.5 > exp(-1.44) = 0.237
    assert heat[5, 4].item() == 0.0 and heat[2, 7].item() == 0.0  # beyond the radius
    corner = torch.zeros(4, 4)
    draw_gaussian(corner, (0, 0), 1)  # cropped to the quadrant inside the map
    assert corner[0, 0].item() == 1.0 and corner[1, 1].item() == pytest.approx(math.exp(-4), rel=1e-6)
    assert corner[2:].sum().item() == 0.0 and corner[:, 2:].sum().item() == 0.0
    edge = torch.zeros(4, 4)
    draw_gaussian(edge, (3, 3), 3)
    assert edge[3, 3].item() == 1.0 and edge.min().item() > 0
