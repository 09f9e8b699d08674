"""CenterPoint detection head (DAOcc's auxiliary 3D detection branch: BEVFusion's / mmdet3d's ``CenterHead``).

A shared conv3x3-BN-ReLU, then one ``SeparateHead`` per task group of classes, each with branches
``reg (2), height (1), dim (3), rot (2), vel (2), heatmap (classes of the task)``. Default values are DAOcc's public
config: a 512 x 180 x 180 BEV over +-54 m (0.075 m voxels, stride 8 -> 0.6 m cells), six task groups.

Layout. occkit's BEV is ``(B, C, X, Y)`` and so are the heatmaps and regression maps ``(B, K, X, Y)``. BEVFusion's
CenterHead already indexes its maps x-first (it draws the Gaussian at ``(x, y)`` swapped into ``(row, col)`` and
flattens ``ind = x * Y + y``), so no conversion is needed: the flat index of cell ``(ix, iy)`` is ``ix * Y + iy``.

Coordinates. With ``cell = voxel_size * out_size_factor``, a box centre sits at the continuous feature coordinate
``c = (x - x_min) / cell_x`` (likewise y); its cell is ``i = floor(c)`` and the regressed sub-cell offset is
``reg = c - i`` in ``[0, 1)``, decoded as ``x = (i + reg) * cell_x + x_min``. This is CenterPoint's convention: the
cell's *corner*, not its centre, is the origin of the offset (no ``+ 0.5``).

Regression target (code size 10) at the centre cell:
``[reg_x, reg_y, z, log l, log w, log h, sin yaw, cos yaw, vx, vy]`` with ``z`` the geometric centre (mmdet3d's
gravity centre). The Gaussian radius uses ``width = w / cell_x`` and ``length = l / cell_y`` (mmdet3d's assignment;
the radius formula is symmetric, so the pairing does not change it). Non-finite target components (unknown, NaN
velocities) get zero weight in the loss.

Differences from the reference, all at its edges: the centre cell is ``floor`` (mmdet3d truncates towards zero, which
keeps centres up to one cell outside the low border, at cell 0 with a negative offset); NaN velocities are left out
of the loss (mmdet3d's dataset replaces them by 0 and regresses towards 0); rotated NMS uses the exact polygon IoU of
:func:`~occkit.models.heads.box_ops.rotated_iou_bev`; decoding takes the top-K over classes x cells in one step (the
same set as mmdet3d's per-class then overall top-K); decoded ``z`` stays the geometric centre (mmdet3d moves it to
the bottom for its box class).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import torch
from torch import Tensor, nn

from occkit.classes import DETECTION_CLASSES
from occkit.losses import gaussian_focal_loss, weighted_l1_loss
from occkit.models.heads.box_ops import circle_nms, draw_gaussian, gaussian_radius, rotated_nms

__all__ = ["CenterHeadConfig", "CenterHead", "SeparateHead", "TaskTargets", "REGRESSION_BRANCHES", "CODE_SIZE",
           "DECODING_FIELDS"]

#: Regression branches of every task head and their output channels, in the order of the regression target.
REGRESSION_BRANCHES: tuple[tuple[str, int], ...] = (("reg", 2), ("height", 1), ("dim", 3), ("rot", 2), ("vel", 2))
#: Length of the regression target.
CODE_SIZE = sum(channels for _, channels in REGRESSION_BRANCHES)

_NMS_TYPES = ("circle", "rotate")

#: The :class:`CenterHeadConfig` fields that only decoding reads (boxes, centres): the same weights serve any value.
DECODING_FIELDS = ("score_threshold", "post_center_range", "max_num", "nms_types", "nms_thresh", "pre_max_size",
                   "post_max_size", "circle_nms_radii", "nms_scales")


@dataclass(frozen=True)
class CenterHeadConfig:
    """CenterPoint head, targets, losses and decoding; defaults are DAOcc's public config."""

    in_channels: int = 512
    """Channels of the input BEV."""
    tasks: tuple[tuple[str, ...], ...] = (
        ("car",),
        ("truck", "construction_vehicle"),
        ("bus", "trailer"),
        ("barrier",),
        ("motorcycle", "bicycle"),
        ("pedestrian", "traffic_cone"),
    )
    """Task groups: each a tuple of occkit.classes.DETECTION_CLASSES names sharing one separate head."""
    share_conv_channels: int = 64
    """Output channels of the shared conv3x3-BN-ReLU."""
    head_conv_channels: int = 64
    """Hidden channels of every branch of a separate head."""
    num_convs: int = 2
    """Convs per branch including the final one (num_convs - 1 conv-BN-ReLU blocks, then the output conv)."""
    final_kernel: int = 3
    """Kernel size of every conv in the separate heads (padding kernel // 2)."""
    init_bias: float = -2.19
    """Initial bias of the heatmap output conv (sigmoid(-2.19) ~ 0.1)."""
    heatmap_init_std: float | None = None
    """None: the heatmap output conv is Kaiming-initialised like every conv (mmdet3d's SeparateHead), which gives
    its logits a spread of several units, so that at the first steps some cells score near 1 and the focal loss is
    in the thousands. A value: normal(0, std) weights instead (RetinaNet's prior initialisation, e.g. 0.01), so
    that every cell starts near ``sigmoid(init_bias)``; a short schedule needs it, because Adam's second moments
    remember those first gradients for about a thousand steps and shrink every later update of the shared BEV."""
    point_cloud_range: tuple[float, float, float, float, float, float] = (-54.0, -54.0, -5.0, 54.0, 54.0, 3.0)
    """x_min, y_min, z_min, x_max, y_max, z_max (m) covered by the BEV; cell (0, 0) starts at (x_min, y_min)."""
    voxel_size: tuple[float, float] = (0.075, 0.075)
    """LiDAR voxel size along x and y (m)."""
    out_size_factor: int = 8
    """BEV stride in voxels: a BEV cell is voxel_size * out_size_factor metres."""
    gaussian_overlap: float = 0.1
    """min_overlap of CenterNet's Gaussian radius."""
    min_radius: int = 2
    """Smallest Gaussian radius (cells)."""
    max_objects: int = 500
    """Regression targets per sample and task (boxes beyond are dropped)."""
    code_weights: tuple[float, ...] = (1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 1.0, 0.2, 0.2)
    """L1 weight of each of the 10 regression components (reg 2, z, log dims 3, sin, cos, velocity 2). A branch whose
    weights are all 0 is not built, as it could never train (Panoptic-FlashOcc's centre head regresses only the
    offset and the height); :meth:`CenterHead.decode` then refuses, :meth:`CenterHead.centres` does not need it."""
    heatmap_loss_weight: float = 1.0
    """Weight of the Gaussian focal loss."""
    bbox_loss_weight: float = 0.25
    """Weight of the L1 regression loss."""
    score_threshold: float = 0.1
    """Decoding keeps scores strictly above this."""
    post_center_range: tuple[float, float, float, float, float, float] = (-61.2, -61.2, -10.0, 61.2, 61.2, 10.0)
    """Decoding keeps box centres (x, y, z) inside this range, bounds included."""
    max_num: int = 500
    """Top-K candidates per task and sample, over classes and cells."""
    nms_types: tuple[str, ...] = ("circle", "rotate", "rotate", "circle", "rotate", "rotate")
    """NMS per task: circle (centre distance) or rotate (BEV rotated IoU)."""
    nms_thresh: float = 0.2
    """Rotated NMS removes boxes with IoU above this."""
    pre_max_size: int = 1000
    """Rotated NMS considers this many top-scoring boxes."""
    post_max_size: int = 83
    """Either NMS keeps at most this many boxes per task and sample."""
    circle_nms_radii: tuple[float, ...] = (4.0, 12.0, 10.0, 1.0, 0.85, 0.175)
    """Per task, mmdet3d's min_radius: circle NMS compares it with the SQUARED centre distance (m^2), so 4 removes
    boxes within 2 m; unused by rotate tasks."""
    nms_scales: tuple[tuple[float, ...], ...] = ((1.0,), (1.0, 1.0), (1.0, 1.0), (1.0,), (1.0, 1.0), (2.5, 4.0))
    """Per task and class, factor on l and w of the boxes given to rotated NMS (the output boxes are unscaled)."""

    def __post_init__(self) -> None:
        if not self.tasks or any(len(task) == 0 for task in self.tasks):
            raise ValueError(f"tasks must be a non-empty tuple of non-empty class tuples, got {self.tasks!r}")
        seen: set[str] = set()
        for task in self.tasks:
            for name in task:
                if name not in DETECTION_CLASSES:
                    raise ValueError(
                        f"tasks: unknown detection class {name!r}; valid classes: {', '.join(DETECTION_CLASSES)}"
                    )
                if name in seen:
                    raise ValueError(f"tasks: class {name!r} appears in more than one place")
                seen.add(name)
        num_tasks = len(self.tasks)
        for key in ("nms_types", "circle_nms_radii", "nms_scales"):
            if len(getattr(self, key)) != num_tasks:
                raise ValueError(f"{key} needs one entry per task ({num_tasks}), got {getattr(self, key)!r}")
        for t, kind in enumerate(self.nms_types):
            if kind not in _NMS_TYPES:
                raise ValueError(f"nms_types[{t}] must be one of {_NMS_TYPES}, got {kind!r}")
        for t, (scales, task) in enumerate(zip(self.nms_scales, self.tasks, strict=True)):
            if len(scales) != len(task):
                raise ValueError(f"nms_scales[{t}] needs one factor per class of task {task!r}, got {scales!r}")
        if len(self.code_weights) != CODE_SIZE:
            raise ValueError(f"code_weights needs {CODE_SIZE} values, got {len(self.code_weights)}")
        if len(self.point_cloud_range) != 6 or len(self.post_center_range) != 6 or len(self.voxel_size) != 2:
            raise ValueError("point_cloud_range and post_center_range need 6 values, voxel_size 2")
        if min(self.voxel_size) <= 0 or self.out_size_factor < 1:
            raise ValueError(f"voxel_size must be positive and out_size_factor >= 1, got {self.voxel_size}, "
                             f"{self.out_size_factor}")  # fmt: skip
        for key in ("in_channels", "share_conv_channels", "head_conv_channels", "num_convs", "max_objects",
                    "max_num", "pre_max_size", "post_max_size"):  # fmt: skip
            if getattr(self, key) < 1:
                raise ValueError(f"{key} must be >= 1, got {getattr(self, key)}")
        if self.final_kernel < 1 or self.final_kernel % 2 == 0:
            raise ValueError(f"final_kernel must be odd, got {self.final_kernel}")

    @property
    def trained_branches(self) -> tuple[str, ...]:
        """The regression branches with a nonzero weight, in :data:`REGRESSION_BRANCHES` order."""
        names, start = [], 0
        for name, channels in REGRESSION_BRANCHES:
            if any(self.code_weights[start:start + channels]):
                names.append(name)
            start += channels
        return tuple(names)

    @property
    def cell_size(self) -> tuple[float, float]:
        """BEV cell size (m) along x and y."""
        return (self.voxel_size[0] * self.out_size_factor, self.voxel_size[1] * self.out_size_factor)

    @property
    def bev_shape(self) -> tuple[int, int]:
        """``(X, Y)`` cells the BEV must have to cover ``point_cloud_range``."""
        cx, cy = self.cell_size
        r = self.point_cloud_range
        return (round((r[3] - r[0]) / cx), round((r[4] - r[1]) / cy))


@dataclass
class TaskTargets:
    """Training targets of one task for a batch."""

    heatmap: Tensor
    """``(B, K_task, X, Y)`` float32 Gaussian heatmaps, exactly 1 at box centres."""
    boxes: Tensor
    """``(B, max_objects, 10)`` float32 regression targets (may hold NaN where the box value is unknown)."""
    indices: Tensor
    """``(B, max_objects)`` int64 flat cell index ``ix * Y + iy`` of each target."""
    mask: Tensor
    """``(B, max_objects)`` bool, the slots that hold a target."""


class SeparateHead(nn.Module):
    """One branch per output: ``(num_convs - 1) x [conv-BN-ReLU]`` then a conv with bias (mmdet3d's SeparateHead)."""

    def __init__(self, in_channels: int, hidden_channels: int, outputs: dict[str, int], num_convs: int,
                 kernel: int) -> None:  # fmt: skip
        super().__init__()
        self.branches = nn.ModuleDict()
        for name, out_channels in outputs.items():
            layers: list[nn.Module] = []
            channels = in_channels
            for _ in range(num_convs - 1):
                layers += [
                    nn.Conv2d(channels, hidden_channels, kernel, padding=kernel // 2, bias=False),
                    nn.BatchNorm2d(hidden_channels),
                    nn.ReLU(inplace=True),
                ]
                channels = hidden_channels
            layers.append(nn.Conv2d(channels, out_channels, kernel, padding=kernel // 2, bias=True))
            self.branches[name] = nn.Sequential(*layers)

    def forward(self, x: Tensor) -> dict[str, Tensor]:
        return {name: branch(x) for name, branch in self.branches.items()}


class CenterHead(nn.Module):
    """CenterPoint head on a BEV ``(B, C, X, Y)``.

    ``forward(bev) -> list[dict]`` (per task: ``heatmap (B, K_t, X, Y)`` logits, ``reg (B, 2, X, Y)``,
    ``height (B, 1, X, Y)``, ``dim (B, 3, X, Y)`` log sizes, ``rot (B, 2, X, Y)`` sin/cos, ``vel (B, 2, X, Y)``);
    ``targets(boxes, labels, bev_shape)``; ``loss(outputs, boxes, labels)``; ``decode(outputs)`` (boxes);
    ``centres(outputs)`` (object centres, for panoptic occupancy).
    """

    def __init__(self, cfg: CenterHeadConfig) -> None:
        super().__init__()
        self.cfg = cfg
        # mmdet3d's ConvModule with bias="auto" drops the conv bias in front of a norm layer.
        self.shared_conv = nn.Sequential(
            nn.Conv2d(cfg.in_channels, cfg.share_conv_channels, 3, padding=1, bias=False),
            nn.BatchNorm2d(cfg.share_conv_channels),
            nn.ReLU(inplace=True),
        )
        self.task_heads = nn.ModuleList(
            SeparateHead(
                cfg.share_conv_channels,
                cfg.head_conv_channels,
                {**{name: c for name, c in REGRESSION_BRANCHES if name in cfg.trained_branches}, "heatmap": len(task)},
                cfg.num_convs,
                cfg.final_kernel,
            )
            for task in cfg.tasks
        )
        #: Per task, the DETECTION_CLASSES index of each of its classes.
        self.task_class_ids: tuple[tuple[int, ...], ...] = tuple(
            tuple(DETECTION_CLASSES.index(name) for name in task) for task in cfg.tasks
        )
        self.reset_parameters()

    def reset_parameters(self) -> None:
        """Kaiming-normal (fan_out, ReLU) convs with zero bias, unit BN, heatmap output bias ``init_bias`` (and
        normal(0, ``heatmap_init_std``) weights, when set)."""
        for module in self.modules():
            if isinstance(module, nn.Conv2d):
                nn.init.kaiming_normal_(module.weight, mode="fan_out", nonlinearity="relu")
                if module.bias is not None:
                    nn.init.zeros_(module.bias)
            elif isinstance(module, nn.BatchNorm2d):
                nn.init.ones_(module.weight)
                nn.init.zeros_(module.bias)
        for head in self.task_heads:
            nn.init.constant_(head.branches["heatmap"][-1].bias, self.cfg.init_bias)
            if self.cfg.heatmap_init_std is not None:
                nn.init.normal_(head.branches["heatmap"][-1].weight, std=self.cfg.heatmap_init_std)

    # ------------------------------------------------------------------------------------------- forward
    def forward(self, bev: Tensor) -> list[dict[str, Tensor]]:
        """Per task a dict of maps ``(B, channels, X, Y)``: heatmap (logits), reg, height, dim, rot, vel."""
        if bev.dim() != 4 or bev.shape[1] != self.cfg.in_channels:
            raise ValueError(f"CenterHead expects a BEV (B, {self.cfg.in_channels}, X, Y), got {tuple(bev.shape)}")
        self._check_bev_shape(tuple(bev.shape[-2:]))
        shared = self.shared_conv(bev)
        return [head(shared) for head in self.task_heads]

    def _check_bev_shape(self, shape: tuple[int, int]) -> None:
        if tuple(shape) != self.cfg.bev_shape:
            raise ValueError(
                f"BEV of {shape[0]} x {shape[1]} cells, but point_cloud_range {self.cfg.point_cloud_range} at "
                f"{self.cfg.cell_size} m cells (voxel_size x out_size_factor) needs {self.cfg.bev_shape}"
            )

    # ------------------------------------------------------------------------------------------- targets
    def targets(
        self,
        boxes: list[Tensor],
        labels: list[Tensor],
        bev_shape: tuple[int, int],
        device: torch.device | str | None = None,
    ) -> list[TaskTargets]:
        """CenterPoint training targets, one :class:`TaskTargets` per task, on ``device`` (default: that of
        ``boxes[0]``). Built on the CPU with a Python loop over boxes, then moved.

        For each sample, the boxes of a task are taken class by class in the task's class order (mmdet3d's order);
        the ``k``-th of them (``k < max_objects``) fills slot ``k``. A box whose size is not positive and finite, or
        whose centre cell ``floor((x - x_min) / cell_x), floor((y - y_min) / cell_y)`` lies outside the map, leaves
        its slot empty. Otherwise a Gaussian of radius ``max(min_radius, int(gaussian_radius((l / cell_y,
        w / cell_x), gaussian_overlap)))`` is max-merged into its class channel at the centre cell, and the slot
        gets the index ``ix * Y + iy`` and the regression target. Labels of classes in no task are ignored.

        Args:
            boxes: ``B`` tensors ``(M_b, 9)`` x, y, z, l, w, h, yaw, vx, vy in the (augmented) LiDAR frame.
            labels: ``B`` tensors ``(M_b,)`` int64 indices into DETECTION_CLASSES.
            bev_shape: ``(X, Y)`` cells of the heatmaps.
            device: where the targets go.
        """
        if len(boxes) != len(labels):
            raise ValueError(f"{len(boxes)} box tensors but {len(labels)} label tensors")
        size_x, size_y = int(bev_shape[0]), int(bev_shape[1])
        cfg = self.cfg
        cell_x, cell_y = cfg.cell_size
        x_min, y_min = cfg.point_cloud_range[0], cfg.point_cloud_range[1]
        batch, max_objs = len(boxes), cfg.max_objects
        # One buffer each, viewed per task: few large allocations are cheaper than many.
        num_classes = [len(task) for task in cfg.tasks]
        heatmaps = torch.zeros(batch, sum(num_classes), size_x, size_y).split(num_classes, dim=1)
        regression = torch.zeros(len(cfg.tasks), batch, max_objs, CODE_SIZE).unbind(0)
        indices = torch.zeros(len(cfg.tasks), batch, max_objs, dtype=torch.long).unbind(0)
        masks = torch.zeros(len(cfg.tasks), batch, max_objs, dtype=torch.bool).unbind(0)
        for b, (sample_boxes, sample_labels) in enumerate(zip(boxes, labels, strict=True)):
            if sample_boxes.dim() != 2 or sample_boxes.shape[-1] != 9 or sample_labels.shape != sample_boxes.shape[:1]:
                raise ValueError(f"sample {b}: boxes must be (M, 9) with labels (M,), got "
                                 f"{tuple(sample_boxes.shape)} and {tuple(sample_labels.shape)}")  # fmt: skip
            rows = sample_boxes.detach().to("cpu", torch.float64).tolist()
            ids = sample_labels.detach().cpu().tolist()
            per_task: list[list[tuple[int, list[float]]]] = [[] for _ in cfg.tasks]
            for t, class_ids in enumerate(self.task_class_ids):
                for k, cid in enumerate(class_ids):
                    per_task[t].extend((k, row) for row, label in zip(rows, ids, strict=True) if label == cid)
            for t, entries in enumerate(per_task):
                slots, cells, targets = [], [], []
                for slot, (k, row) in enumerate(entries[:max_objs]):
                    x, y, z, length, width, height, yaw, vx, vy = row
                    width_cells, length_cells = width / cell_x, length / cell_y
                    if not (math.isfinite(width_cells) and math.isfinite(length_cells)):
                        continue
                    if not (width_cells > 0 and length_cells > 0):
                        continue
                    coord_x, coord_y = (x - x_min) / cell_x, (y - y_min) / cell_y
                    if not (math.isfinite(coord_x) and math.isfinite(coord_y)):
                        continue
                    ix, iy = math.floor(coord_x), math.floor(coord_y)
                    if not (0 <= ix < size_x and 0 <= iy < size_y):
                        continue
                    radius = gaussian_radius((length_cells, width_cells), cfg.gaussian_overlap)
                    radius = max(cfg.min_radius, int(radius))
                    draw_gaussian(heatmaps[t][b, k], (ix, iy), radius)
                    slots.append(slot)
                    cells.append(ix * size_y + iy)
                    sin, cos = (math.sin(yaw), math.cos(yaw)) if math.isfinite(yaw) else (math.nan, math.nan)
                    targets.append([
                        coord_x - ix, coord_y - iy, z, _log(length), _log(width), _log(height), sin, cos, vx, vy,
                    ])  # fmt: skip
                if slots:
                    slot_index = torch.tensor(slots, dtype=torch.long)
                    regression[t][b, slot_index] = torch.tensor(targets, dtype=torch.float64).float()
                    indices[t][b, slot_index] = torch.tensor(cells, dtype=torch.long)
                    masks[t][b, slot_index] = True
        if device is None:
            device = boxes[0].device if boxes else torch.device("cpu")
        return [
            TaskTargets(heatmap=h.to(device), boxes=r.to(device), indices=i.to(device), mask=m.to(device))
            for h, r, i, m in zip(heatmaps, regression, indices, masks, strict=True)
        ]

    # ------------------------------------------------------------------------------------------- loss
    def loss(self, outputs: list[dict[str, Tensor]], boxes: list[Tensor], labels: list[Tensor]) -> dict[str, Tensor]:
        """CenterPoint losses (computed in float32).

        Per task: heatmap ``gaussian_focal_loss(clamp(sigmoid(logits), 1e-4, 1 - 1e-4), target) / max(num_peaks, 1)``
        (peaks: target cells equal to 1, over the batch); bbox: L1 between the maps gathered at the target cells and
        the targets, weighted by ``mask * code_weights`` (0 for non-finite target values), summed and divided by
        ``num_targets + 1e-4``. Each is multiplied by its loss weight.

        Returns:
            ``det_heatmap`` and ``det_bbox``, the sums over tasks (the training loss is their sum), and detached
            per-task values ``det_heatmap/task{t}``, ``det_bbox/task{t}`` for logging.
        """
        if len(outputs) != len(self.cfg.tasks):
            raise ValueError(f"{len(outputs)} task outputs for {len(self.cfg.tasks)} tasks")
        heatmap = outputs[0]["heatmap"]
        if len(boxes) != heatmap.shape[0]:
            raise ValueError(f"{len(boxes)} box tensors for a batch of {heatmap.shape[0]}")
        size_x, size_y = heatmap.shape[-2:]
        all_targets = self.targets(boxes, labels, (size_x, size_y), device=heatmap.device)
        code_weights = torch.tensor(self.cfg.code_weights, dtype=torch.float32, device=heatmap.device)
        losses: dict[str, Tensor] = {}
        heat_total, bbox_total = heatmap.new_zeros((), dtype=torch.float32), heatmap.new_zeros((), dtype=torch.float32)
        for t, (out, target) in enumerate(zip(outputs, all_targets, strict=True)):
            probs = out["heatmap"].float().sigmoid().clamp(1e-4, 1 - 1e-4)
            num_peaks = target.heatmap.eq(1).sum().float().clamp_min(1.0)
            heat = gaussian_focal_loss(probs, target.heatmap) / num_peaks * self.cfg.heatmap_loss_weight

            maps = out["heatmap"]
            # A branch left out (all its weights 0) regresses zeros: its components weigh nothing in the loss.
            parts = [out[name] if name in out else maps.new_zeros(maps.shape[0], channels, *maps.shape[2:])
                     for name, channels in REGRESSION_BRANCHES]  # fmt: skip
            pred = torch.cat(parts, dim=1).float()  # (B, 10, X, Y)
            pred = pred.flatten(2).transpose(1, 2)  # (B, X * Y, 10), row ix * Y + iy
            pred = pred.gather(1, target.indices[..., None].expand(-1, -1, CODE_SIZE))  # (B, max_objects, 10)
            weight = target.mask[..., None] & torch.isfinite(target.boxes)
            weight = weight.float() * code_weights
            num_targets = target.mask.sum().float()
            bbox = weighted_l1_loss(pred, target.boxes, weight) / (num_targets + 1e-4) * self.cfg.bbox_loss_weight

            losses[f"det_heatmap/task{t}"] = heat.detach()
            losses[f"det_bbox/task{t}"] = bbox.detach()
            heat_total = heat_total + heat
            bbox_total = bbox_total + bbox
        return {"det_heatmap": heat_total, "det_bbox": bbox_total, **losses}

    # ------------------------------------------------------------------------------------------- decoding
    def _candidates(self, out: dict[str, Tensor], peaks: bool) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
        """One task's top ``max_num`` (class, cell) pairs by score over the sigmoid heatmap (with ``peaks``, only
        cells equal to the 3 x 3 max-pool of their class's map), and their centres.

        Returns:
            ``scores``, ``classes`` (index within the task), ``cells`` (flat ``ix * Y + iy``), each ``(B, k)``, by
            decreasing score; ``centres`` ``(B, k, 3)``: ``x = (ix + reg_x) * cell_x + x_min``, ``y`` likewise,
            ``z = height``; ``keep`` ``(B, k)``: above ``score_threshold`` with the centre in ``post_center_range``.
        """
        cfg = self.cfg
        heat = out["heatmap"].float().sigmoid()
        if peaks:
            heat = heat * (nn.functional.max_pool2d(heat, 3, stride=1, padding=1) == heat)
        batch, num_classes, size_x, size_y = heat.shape
        cells = size_x * size_y
        scores, flat = heat.reshape(batch, -1).topk(min(cfg.max_num, num_classes * cells), dim=1)
        classes, cell = flat // cells, flat % cells
        reg = _gather(out["reg"], cell)
        (cell_x, cell_y), (x_min, y_min) = cfg.cell_size, cfg.point_cloud_range[:2]
        x = ((cell // size_y).float() + reg[:, 0]) * cell_x + x_min
        y = ((cell % size_y).float() + reg[:, 1]) * cell_y + y_min
        centres = torch.stack([x, y, _gather(out["height"], cell)[:, 0]], dim=-1)
        low, high = (torch.tensor(bound, device=heat.device) for bound in (cfg.post_center_range[:3],
                                                                            cfg.post_center_range[3:]))  # fmt: skip
        keep = (scores > cfg.score_threshold) & (centres >= low).all(-1) & (centres <= high).all(-1)
        return scores, classes, cell, centres, keep

    @torch.no_grad()
    def decode(self, outputs: list[dict[str, Tensor]]) -> tuple[list[Tensor], list[Tensor], list[Tensor]]:
        """Boxes from the head's maps, per sample, concatenated over tasks in task order.

        Per task: the top ``max_num`` candidates over classes x cells of the sigmoid heatmap, decoded as in
        :meth:`_candidates`, with ``(l, w, h) = exp(dim)``, ``yaw = atan2(sin, cos)``, velocity as predicted; keep
        ``score > score_threshold`` with the centre inside ``post_center_range``; then the task's NMS: circle
        (squared centre distance ``<= circle_nms_radii[t]``) or rotated (BEV IoU ``> nms_thresh`` on the first
        ``pre_max_size`` boxes, l and w scaled by ``nms_scales[t][class]``); at most ``post_max_size`` per task.

        Returns:
            ``boxes`` ``B x (M, 9)`` float32 (x, y, z centre, l, w, h, yaw, vx, vy), ``scores`` ``B x (M,)`` and
            ``labels`` ``B x (M,)`` int64 DETECTION_CLASSES indices.
        """
        cfg = self.cfg
        missing = [name for name, _ in REGRESSION_BRANCHES if name not in cfg.trained_branches]
        if missing:
            raise ValueError(f"decoding boxes needs the {', '.join(missing)} branches, which this head leaves out "
                             "(code_weights 0); centres() gives the object centres")  # fmt: skip
        batch = outputs[0]["heatmap"].shape[0]
        device = outputs[0]["heatmap"].device
        per_sample: list[list[tuple[Tensor, Tensor, Tensor]]] = [[] for _ in range(batch)]
        for t, out in enumerate(outputs):
            scores, cls, cell, centres, keep = self._candidates(out, peaks=False)
            dims, rot, vel = _gather(out["dim"], cell).exp(), _gather(out["rot"], cell), _gather(out["vel"], cell)
            yaw = torch.atan2(rot[:, 0], rot[:, 1])
            decoded = torch.cat([centres, dims.transpose(1, 2), yaw[..., None], vel.transpose(1, 2)], dim=-1)
            class_ids = torch.tensor(self.task_class_ids[t], dtype=torch.long, device=device)
            scales = torch.tensor(cfg.nms_scales[t], dtype=torch.float32, device=device)
            for b in range(batch):
                sel = keep[b]
                box_b, score_b, cls_b = decoded[b, sel], scores[b, sel], cls[b, sel]
                if cfg.nms_types[t] == "circle":
                    kept = circle_nms(box_b[:, :2], score_b, cfg.circle_nms_radii[t], cfg.post_max_size)
                else:
                    bev = box_b[:, [0, 1, 3, 4, 6]].clone()
                    bev[:, 2:4] *= scales[cls_b][:, None]
                    kept = rotated_nms(bev, score_b, cfg.nms_thresh, cfg.pre_max_size, cfg.post_max_size)
                per_sample[b].append((box_b[kept], score_b[kept], class_ids[cls_b[kept]]))
        return _concatenated(per_sample)

    @torch.no_grad()
    def centres(self, outputs: list[dict[str, Tensor]]) -> tuple[list[Tensor], list[Tensor], list[Tensor]]:
        """Object centres from the heatmap, offset and height maps alone (Panoptic-FlashOcc's ``get_centers``).

        Per task: the sigmoid heatmap's peaks (a cell equal to the 3 x 3 max-pool of its class's map), the top
        ``max_num`` of them over classes x cells, decoded and kept as :meth:`decode` does (score above
        ``score_threshold``, centre inside ``post_center_range``). No box NMS: the max-pool is the suppression.

        Returns:
            ``centres`` ``B x (M, 3)`` float32 (x, y, z), ``scores`` ``B x (M,)`` and ``labels`` ``B x (M,)`` int64
            DETECTION_CLASSES indices, by decreasing score within each task, tasks in order.
        """
        if not {"reg", "height"} <= set(self.cfg.trained_branches):
            raise ValueError("centres need the reg and height branches, which this head leaves out (code_weights 0)")
        batch = outputs[0]["heatmap"].shape[0]
        per_sample: list[list[tuple[Tensor, Tensor, Tensor]]] = [[] for _ in range(batch)]
        for t, out in enumerate(outputs):
            scores, cls, _, centres, keep = self._candidates(out, peaks=True)
            class_ids = torch.tensor(self.task_class_ids[t], dtype=torch.long, device=scores.device)
            for b in range(batch):
                per_sample[b].append((centres[b, keep[b]], scores[b, keep[b]], class_ids[cls[b, keep[b]]]))
        return _concatenated(per_sample)


def _gather(maps: Tensor, cell: Tensor) -> Tensor:
    """``(B, C, k)`` float32 values of ``maps (B, C, X, Y)`` at the flat cells ``(B, k)``."""
    maps = maps.float().flatten(2)
    return maps.gather(2, cell[:, None, :].expand(-1, maps.shape[1], -1))


def _concatenated(per_sample: list[list[tuple[Tensor, Tensor, Tensor]]]) -> tuple[list[Tensor], list[Tensor],
                                                                                  list[Tensor]]:  # fmt: skip
    """Per sample, each of the three tensors of every task joined in task order."""
    return tuple([torch.cat([part[i] for part in parts]) for parts in per_sample] for i in range(3))  # type: ignore


def _log(value: float) -> float:
    """``log`` that returns NaN (zero loss weight) instead of raising for non-positive or NaN sizes."""
    return math.log(value) if value > 0 else math.nan
