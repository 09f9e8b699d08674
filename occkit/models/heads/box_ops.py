"""Bird's-eye-view box geometry for the CenterPoint head: corners, exact rotated IoU, NMS, Gaussian heatmaps.

Pure functions of tensors, device-agnostic. A BEV box is ``(x, y, l, w, yaw)``: centre, length along the heading,
width across it, and the heading of the length axis measured from +x towards +y (counter-clockwise seen from above),
as occkit's ``(M, 9)`` boxes store them in columns ``0, 1, 3, 4, 6``.

Heatmaps follow occkit's BEV order ``(X, Y)``: ``heatmap[i, j]`` is the cell at x index ``i`` and y index ``j``.
"""

from __future__ import annotations

import functools
import math

import torch
from torch import Tensor

__all__ = [
    "bev_corners",
    "polygon_area",
    "rotated_iou_bev",
    "rotated_nms",
    "circle_nms",
    "gaussian_radius",
    "gaussian_2d",
    "draw_gaussian",
]


# ----------------------------------------------------------------------------------------------- corners, areas
def bev_corners(boxes: Tensor) -> Tensor:
    """Corners of BEV boxes, counter-clockwise.

    Args:
        boxes: ``(..., 5)`` ``x, y, l, w, yaw``; ``l, w > 0``.

    Returns:
        ``(..., 4, 2)`` corners ``(+l/2, +w/2), (-l/2, +w/2), (-l/2, -w/2), (+l/2, -w/2)`` in the box frame, rotated by
        ``yaw`` and moved to the centre: front-left, rear-left, rear-right, front-right.
    """
    x, y, length, width, yaw = boxes.unbind(-1)
    sign_l = boxes.new_tensor([1.0, -1.0, -1.0, 1.0])
    sign_w = boxes.new_tensor([1.0, 1.0, -1.0, -1.0])
    local_x = 0.5 * length[..., None] * sign_l  # (..., 4)
    local_y = 0.5 * width[..., None] * sign_w
    cos, sin = torch.cos(yaw)[..., None], torch.sin(yaw)[..., None]
    corner_x = x[..., None] + cos * local_x - sin * local_y
    corner_y = y[..., None] + sin * local_x + cos * local_y
    return torch.stack([corner_x, corner_y], dim=-1)


def polygon_area(vertices: Tensor, count: Tensor | None = None) -> Tensor:
    """Signed area (shoelace) of polygons, positive when counter-clockwise.

    Args:
        vertices: ``(P, C, 2)`` vertices in order; only the first ``count[p]`` of row ``p`` are used.
        count: ``(P,)`` int64 number of vertices per polygon; None uses all ``C``.

    Returns:
        ``(P,)`` signed areas (0 for fewer than 3 vertices).
    """
    num_polys, capacity, _ = vertices.shape
    if count is None:
        count = torch.full((num_polys,), capacity, dtype=torch.long, device=vertices.device)
    index = torch.arange(capacity, device=vertices.device)[None]  # (1, C)
    valid = index < count[:, None]
    following = torch.where(index + 1 >= count[:, None], torch.zeros_like(index), index + 1)  # (P, C)
    nxt = vertices.gather(1, following[..., None].expand(num_polys, capacity, 2))
    cross = vertices[..., 0] * nxt[..., 1] - nxt[..., 0] * vertices[..., 1]
    return 0.5 * torch.where(valid, cross, torch.zeros_like(cross)).sum(dim=1)


# ----------------------------------------------------------------------------------------------- rotated IoU
def _clip_half_plane(poly: Tensor, count: Tensor, start: Tensor, end: Tensor) -> tuple[Tensor, Tensor]:
    """One Sutherland-Hodgman step: keep the part of each polygon left of the directed line ``start -> end``.

    Args:
        poly: ``(P, C, 2)`` polygons, the first ``count[p]`` vertices valid.
        count: ``(P,)`` vertex counts.
        start, end: ``(P, 2)`` the clipping edge of each pair.

    Returns:
        ``(P, C + 4, 2)`` clipped polygons and their ``(P,)`` vertex counts. A convex polygon gains at most one
        vertex per step; the extra room absorbs sign flips of vertices lying on the line (rounding), and any point
        past it would be such a near-duplicate.
    """
    num_polys, capacity, _ = poly.shape
    index = torch.arange(capacity, device=poly.device)[None]  # (1, C)
    valid = index < count[:, None]
    previous = torch.where(index == 0, count[:, None] - 1, index - 1).clamp_min(0)  # (P, C)
    prev = poly.gather(1, previous[..., None].expand(num_polys, capacity, 2))
    direction = (end - start)[:, None, :]  # (P, 1, 2)
    origin = start[:, None, :]

    def side(points: Tensor) -> Tensor:  # > 0 left of the line (inside for a counter-clockwise clip polygon)
        rel = points - origin
        return direction[..., 0] * rel[..., 1] - direction[..., 1] * rel[..., 0]

    side_cur, side_prev = side(poly), side(prev)
    inside_cur, inside_prev = side_cur >= 0, side_prev >= 0
    crossing = inside_cur != inside_prev
    # When the edge crosses the line the two sides have opposite signs, so the denominator is never zero and the
    # parameter lies in [0, 1].
    denom = torch.where(crossing, side_prev - side_cur, torch.ones_like(side_cur))
    t = (side_prev / denom)[..., None]
    intersection = prev + t * (poly - prev)
    emit_intersection = valid & crossing
    emit_current = valid & inside_cur
    # Each input edge (prev -> cur) emits, in order, the crossing point then the current vertex.
    candidates = torch.stack([intersection, poly], dim=2).reshape(num_polys, 2 * capacity, 2)
    emit = torch.stack([emit_intersection, emit_current], dim=2).reshape(num_polys, 2 * capacity)
    out_capacity = capacity + 4
    slot = emit.long().cumsum(dim=1) - 1
    slot = torch.where(emit & (slot < out_capacity), slot, torch.full_like(slot, out_capacity))  # last slot: discard
    out = poly.new_zeros(num_polys, out_capacity + 1, 2)
    out.scatter_(1, slot[..., None].expand(num_polys, 2 * capacity, 2), candidates)
    new_count = emit.sum(dim=1).clamp_max(out_capacity)
    return out[:, :out_capacity], new_count


def _paired_intersection(a: Tensor, b: Tensor) -> Tensor:
    """Overlap area of box ``a[p]`` with box ``b[p]``: ``(P, 5), (P, 5) -> (P,)``."""
    origin = a[:, :2]  # work relative to a's centre: small coordinates, less rounding
    a_local = torch.cat([torch.zeros_like(origin), a[:, 2:4].abs(), a[:, 4:5]], dim=1)
    b_local = torch.cat([b[:, :2] - origin, b[:, 2:4].abs(), b[:, 4:5]], dim=1)
    poly = bev_corners(a_local)  # (P, 4, 2), the subject polygon
    clip = bev_corners(b_local)  # (P, 4, 2), counter-clockwise clip polygon
    count = torch.full((a.shape[0],), 4, dtype=torch.long, device=a.device)
    for edge in range(4):
        poly, count = _clip_half_plane(poly, count, clip[:, edge], clip[:, (edge + 1) % 4])
    return polygon_area(poly, count).clamp_min(0.0)


def rotated_iou_bev(a: Tensor, b: Tensor) -> Tensor:
    """Exact BEV IoU of rotated boxes (intersection of convex quadrilaterals by Sutherland-Hodgman clipping).

    Only pairs whose circumscribed circles meet are clipped (all at once, vectorised); the others have IoU 0.
    Computed in float32 or wider, relative to each pair's first centre.

    Args:
        a: ``(M, 5)`` ``x, y, l, w, yaw``.
        b: ``(N, 5)``.

    Returns:
        ``(M, N)`` IoU in ``[0, 1]``; 0 where the union is empty (zero-size boxes) or a box has NaN values.
    """
    if a.dim() != 2 or a.shape[-1] != 5 or b.dim() != 2 or b.shape[-1] != 5:
        raise ValueError(f"boxes must be (M, 5) and (N, 5) x, y, l, w, yaw; got {tuple(a.shape)} and {tuple(b.shape)}")
    dtype = torch.promote_types(torch.promote_types(a.dtype, b.dtype), torch.float32)
    a, b = a.to(dtype), b.to(dtype)
    iou = a.new_zeros(a.shape[0], b.shape[0])
    if iou.numel() == 0:
        return iou
    half_diag_a = 0.5 * torch.hypot(a[:, 2], a[:, 3])
    half_diag_b = 0.5 * torch.hypot(b[:, 2], b[:, 3])
    dist_sq = (a[:, None, 0] - b[None, :, 0]) ** 2 + (a[:, None, 1] - b[None, :, 1]) ** 2
    reach = half_diag_a[:, None] + half_diag_b[None, :]
    near = dist_sq <= reach * reach * (1 + 1e-6)
    i, j = near.nonzero(as_tuple=True)
    if i.numel() == 0:
        return iou
    inter = _paired_intersection(a[i], b[j])
    area_a = (a[:, 2] * a[:, 3]).abs()
    area_b = (b[:, 2] * b[:, 3]).abs()
    union = area_a[i] + area_b[j] - inter
    value = torch.where(union > 0, inter / union.clamp_min(torch.finfo(dtype).tiny), torch.zeros_like(inter))
    iou[i, j] = value.clamp(0.0, 1.0)
    return iou


# ----------------------------------------------------------------------------------------------- NMS
def _greedy_keep(suppresses: Tensor, post_max_size: int | None) -> list[int]:
    """Greedy pass over candidates sorted by score: ``suppresses[i, j]`` says a kept ``i`` removes ``j``."""
    rows = suppresses.cpu()
    removed = [False] * rows.shape[0]
    keep: list[int] = []
    for i in range(rows.shape[0]):
        if removed[i]:
            continue
        keep.append(i)
        if post_max_size is not None and len(keep) >= post_max_size:
            break
        for j in rows[i].nonzero().flatten().tolist():
            removed[j] = True
    return keep


def _sorted_order(scores: Tensor) -> Tensor:
    return torch.sort(scores, descending=True, stable=True).indices


def rotated_nms(
    boxes: Tensor,
    scores: Tensor,
    iou_threshold: float,
    pre_max_size: int | None = None,
    post_max_size: int | None = None,
) -> Tensor:
    """Greedy NMS on BEV rotated IoU, highest score first (mmdet3d's ``nms_gpu`` semantics).

    Boxes are sorted by score; the first ``pre_max_size`` are candidates; each kept box removes every later one with
    IoU ``> iou_threshold``; at most ``post_max_size`` are kept.

    Args:
        boxes: ``(M, 5)`` ``x, y, l, w, yaw``.
        scores: ``(M,)``.

    Returns:
        ``(K,)`` int64 indices into ``boxes``, by decreasing score.
    """
    if boxes.shape[0] != scores.shape[0]:
        raise ValueError(f"{boxes.shape[0]} boxes but {scores.shape[0]} scores")
    order = _sorted_order(scores)
    if pre_max_size is not None:
        order = order[:pre_max_size]
    if order.numel() == 0:
        return order
    candidates = boxes[order]
    over = rotated_iou_bev(candidates, candidates) > iou_threshold
    keep = _greedy_keep(over, post_max_size)
    return order[torch.tensor(keep, dtype=torch.long, device=order.device)]


def circle_nms(centres: Tensor, scores: Tensor, thresh: float, post_max_size: int | None = None) -> Tensor:
    """Greedy centre-distance NMS, exactly as mmdet3d's ``circle_nms``.

    Boxes are visited by decreasing score; a kept box removes every later box whose **squared** centre distance is
    ``<= thresh``. mmdet3d passes its per-task ``min_radius`` as ``thresh`` unchanged, so ``min_radius = 4`` removes
    boxes within 2 m (the value is in m^2, the effective radius is its square root).

    Args:
        centres: ``(M, 2)`` BEV centres ``x, y``.
        scores: ``(M,)``.
        thresh: squared-distance threshold (m^2).
        post_max_size: keep at most this many.

    Returns:
        ``(K,)`` int64 indices into ``centres``, by decreasing score.
    """
    if centres.shape[0] != scores.shape[0]:
        raise ValueError(f"{centres.shape[0]} centres but {scores.shape[0]} scores")
    order = _sorted_order(scores)
    if order.numel() == 0:
        return order
    points = centres[order]
    dist_sq = ((points[:, None, :] - points[None, :, :]) ** 2).sum(dim=-1)
    keep = _greedy_keep(dist_sq <= thresh, post_max_size)
    return order[torch.tensor(keep, dtype=torch.long, device=order.device)]


# ----------------------------------------------------------------------------------------------- Gaussian targets
def gaussian_radius(det_size: tuple[float, float], min_overlap: float = 0.5) -> float:
    """Gaussian radius (cells) of a box of ``det_size = (height, width)`` cells, CenterNet's formula as in mmdet3d.

    The smallest of three quadratic "roots" for the cases where one or both corners of a shifted box stay inside
    the ground truth. It reproduces the original code exactly, including its departure from the textbook root
    (``(b + sqrt(b^2 - 4ac)) / 2`` in every case, not ``/ 2a``), which CenterPoint's targets were trained with.
    Symmetric in height and width. Computed in float64.
    """
    height, width = float(det_size[0]), float(det_size[1])
    o = float(min_overlap)
    b1 = height + width
    c1 = width * height * (1 - o) / (1 + o)
    r1 = (b1 + math.sqrt(b1**2 - 4 * c1)) / 2
    a2 = 4.0
    b2 = 2 * (height + width)
    c2 = (1 - o) * width * height
    r2 = (b2 + math.sqrt(b2**2 - 4 * a2 * c2)) / 2
    a3 = 4 * o
    b3 = -2 * o * (height + width)
    c3 = (o - 1) * width * height
    r3 = (b3 + math.sqrt(b3**2 - 4 * a3 * c3)) / 2
    return min(r1, r2, r3)


@functools.lru_cache(maxsize=64)
def _gaussian_kernel(radius: int) -> Tensor:
    diameter = 2 * radius + 1
    sigma = diameter / 6
    offsets = torch.arange(diameter, dtype=torch.float64) - radius
    kernel = torch.exp(-(offsets[:, None] ** 2 + offsets[None, :] ** 2) / (2 * sigma * sigma))
    kernel[kernel < torch.finfo(torch.float64).eps * kernel.max()] = 0
    return kernel


def gaussian_2d(radius: int) -> Tensor:
    """``(2r + 1, 2r + 1)`` float64 Gaussian, ``sigma = (2r + 1) / 6``, peak exactly 1 (mmdet3d's ``gaussian_2d``)."""
    return _gaussian_kernel(int(radius)).clone()


def draw_gaussian(heatmap: Tensor, centre: tuple[int, int], radius: int) -> Tensor:
    """Max-merge a Gaussian of ``radius`` cells into ``heatmap`` at integer ``centre``, in place (mmdet3d's
    ``draw_heatmap_gaussian``, in occkit's ``(X, Y)`` order).

    Args:
        heatmap: ``(X, Y)`` float tensor, any device.
        centre: ``(ix, iy)`` integer cell; the Gaussian is cropped at the borders.
        radius: integer radius in cells (``>= 0``).

    Returns:
        ``heatmap``, with ``heatmap[ix + dx, iy + dy] = max(old, exp(-(dx^2 + dy^2) / (2 sigma^2)))`` for
        ``|dx|, |dy| <= radius``.
    """
    radius = int(radius)
    ix, iy = int(centre[0]), int(centre[1])
    size_x, size_y = heatmap.shape
    kernel = _gaussian_kernel(radius)
    lo_x, hi_x = min(ix, radius), min(size_x - ix, radius + 1)
    lo_y, hi_y = min(iy, radius), min(size_y - iy, radius + 1)
    if lo_x + hi_x <= 0 or lo_y + hi_y <= 0 or ix < -radius or iy < -radius:
        return heatmap
    region = heatmap[ix - lo_x : ix + hi_x, iy - lo_y : iy + hi_y]
    patch = kernel[radius - lo_x : radius + hi_x, radius - lo_y : radius + hi_y]
    if min(region.shape) > 0 and min(patch.shape) > 0:
        torch.maximum(region, patch.to(device=heatmap.device, dtype=heatmap.dtype), out=region)
    return heatmap
