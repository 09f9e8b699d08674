"""The model side of the parity test for DAOcc: its state-dict keys, and golden outputs of a reduced-width model.

    PYTHONPATH=MMSITE python benchmarks/reference_parity/daocc_model.py --reference PATH/TO/DAOcc \\
        [--out tests/golden/reference_parity/daocc_model] [--results docs/results/parity]

``MMSITE`` holds mmcv 1.7.2 (pure Python, without its compiled ops), mmdet 2.28.2, einops and trimesh (imported by
the reference's visualiser). The script imports the reference's own ``mmdet3d`` from a checkout of AlphaPlusTT/DAOcc
at the pinned commit, its compiled ops replaced by :mod:`daocc_ops` (PyTorch definitions of the ones the model runs,
placeholders that raise for the others), and

* builds the paper model of ``configs/nuscenes/occ3d/daocc_occ3d_nus_w_mask.yaml`` with the reference's
  ``build_model``, with and without its detection head (``heads.object`` null), and writes every state-dict key and
  shape, in state-dict order, to ``daocc.json`` and ``daocc_no_detection.json`` under ``--results``;
* builds the same config at reduced width and extent (:data:`REDUCED`: every module type and structural choice kept,
  only channels, ranges, image size and camera count changed), initialises it deterministically, runs it on one fixed
  batch (:func:`make_inputs`) and writes into ``--out``: ``reference.pth`` (an mmcv-style checkpoint
  ``{"state_dict", "meta"}`` of tensors and plain values), ``inputs.npz``, ``stages.npz`` (each stage's output,
  captured by forward hooks, :data:`STAGES`) and ``meta.json`` (provenance, settings, shapes, axis orders, losses).

The config is read as the reference's ``tools/train.py`` reads it with torchpack's ``configs.load(path,
recursive=True)`` from the checkout root: the ``default.yaml`` of every folder from the root down to the config's,
then the config, merged key by key (a mapping merges into a mapping, anything else replaces), here followed by the
overrides; then the reference's own ``mmdet3d.utils.recursive_eval`` resolves the ``${...}`` expressions. This loader
is written here (:func:`load_config`, torchpack itself needs packages the site lacks). Both builds drop the camera
backbone's ``init_cfg`` (a download of torchvision's ResNet-50 weights, which changes no key).

The model runs in eval mode (every BatchNorm on its running statistics, the voxelizer on its test-time
``max_voxels``) except for the flag of the top-level ``BEVFusion`` module itself, which is set to training so that
its ``forward`` takes its loss branch: the heads' forwards, then ``CenterHead.loss`` and ``BEVOCCHead2D.loss`` on the
batch's targets, with gradients enabled, so that the loss dictionary is the one training logs (``loss/<head>/<name>``,
scaled by ``loss_scale``). That flag only chooses that branch and the order in which the two encoders run.
Every run gives identical files: fixed seeds, deterministic algorithms, one CPU thread, fixed zip timestamps.
"""

from __future__ import annotations

import argparse
import copy
import json
import logging
import math
import sys
import warnings
from pathlib import Path

import numpy as np
import torch
import yaml
from torch import nn

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
import daocc_ops  # noqa: E402 - beside this script
from data_side import pinned_checkout  # noqa: E402 - beside this script

from occkit.label_files import save_npz  # noqa: E402 - after the harness's own imports

REPOSITORY = "AlphaPlusTT/DAOcc"
PINNED_COMMIT = "6846432bbc1eff9d2a601900d21f1031df170a8c"
CONFIG = "configs/nuscenes/occ3d/daocc_occ3d_nus_w_mask.yaml"
#: The paper's model (53.82 mIoU in the README's archived results): the same config with the view transform of the
#: paper, ``BEVTransform`` (V1: averaged over the cameras) instead of ``BEVTransformV2`` (the first camera); its
#: parameters are the same tensors, so the reduced model's weights are reused for it.
PAPER_CONFIG = "configs/nuscenes/occ3d/deprecated/daocc_occ3d_nus_w_mask.yaml"
COMMAND = ("PYTHONPATH=MMSITE python benchmarks/reference_parity/daocc_model.py --reference PATH/TO/DAOcc "
           "[--out DIR] [--results DIR]")

#: Applied to both builds: the camera backbone's pretrained-weights download is not made (it changes no key).
NO_DOWNLOAD = {"model": {"encoders": {"camera": {"backbone": {"init_cfg": None}}}}}
#: The paper model without its 3D detection head.
NO_DETECTION = {"model": {"heads": {"object": None}}}
#: The reduced-width model: the camera ResNet-50's base width 64 -> 8 (its stem follows), the camera neck's channels
#: / 8, the view transform's, fuser's, decoder's and heads' / 16, the sparse encoder's / 4; the paper's voxel sizes
#: (LiDAR 0.075 x 0.075 x 0.2 m, camera BEV 0.6 m, occupancy 0.4 m) over smaller ranges (LiDAR and BEV +-4.8 m: sparse
#: shape 128 x 128 x 41, a 16 x 16 BEV; occupancy +-4 m: 20 x 20 x 16, 18 classes); 64 x 176 images from 2 cameras.
#: Merged like the YAML files.
REDUCED = {
    "point_cloud_range": [-4.8, -4.8, -5.0, 4.8, 4.8, 3.0],
    "image_size": [64, 176],
    "model": {
        "encoders": {
            "lidar": {"backbone": {"sparse_shape": [128, 128, 41], "base_channels": 4, "output_channels": 32,
                                   "encoder_channels": [[4, 4, 8], [8, 8, 16], [16, 16, 32], [32, 32]]}},
            "camera": {
                "backbone": {"base_channels": 8, "init_cfg": None},
                "neck": {"in_channels": [64, 128, 256], "out_channels": 32},
                "vtransform": {"x": [-4.8, 4.8], "y": [-4.8, 4.8], "xs": 16, "ys": 16, "input_size": [64, 176],
                               "in_channels": 32, "out_channels": 8},
            },
        },
        "fuser": {"in_channels": [80, 64], "out_channels": 32},
        "decoder": {"backbone": {"numC_input": 32, "num_channels": [8, 16, 32]},
                    "neck": {"in_channels": 40, "out_channels": 32}},
        "heads": {
            "object": {"in_channels": 32, "share_conv_channel": 4, "separate_head": {"head_conv": 4},
                       "train_cfg": {"grid_size": [128, 128, 41]}},
            "occ": {"in_dim": 8, "out_dim": 8,
                    "coordinate_transform": {"point_range": [-4.0, 4.0, -4.0, 4.0, 0.0, 0.0], "point_num": [20, 20, 1],
                                             "lidar_point_range": [-4.8, 4.8, -4.8, 4.8], "in_dim": 32,
                                             "out_dim": 8}},
        },
    },
}
NUM_CAMERAS = 2
#: Two cameras with 1600 x 900 images and a 90-degree field of view (focal 800 px), at ego yaw +-35 degrees (their
#: views overlap ahead).
ORIGINAL_SIZE = (900, 1600)
FOCAL, CENTRE = 800.0, (800.0, 450.0)
CAMERA_YAWS_DEG = (35.0, -35.0)
CAMERA_POSITIONS = ((1.50, 0.50, 1.52), (1.50, -0.50, 1.52))
#: The BEV augmentation: ``GlobalRotScaleTrans`` (20 degrees, a small translation, scale 1) then ``RandomFlip3D``'s
#: y flip; the occupancy targets follow the flip only, as in the reference pipeline.
BEV_ROTATION_DEG, BEV_TRANSLATION = 20.0, (0.3, -0.2, 0.1)
#: nuScenes' LiDAR in the ego frame: turned -90 degrees about z, 0.94 m ahead of the rear axle and 1.84 m up.
LIDAR2EGO_YAW_DEG, LIDAR2EGO_TRANSLATION = -90.0, (0.943713, 0.0, 1.84023)
IMAGE_MEAN, IMAGE_STD = (0.485, 0.456, 0.406), (0.229, 0.224, 0.225)
#: Boxes in the augmented LiDAR frame, rows (x, y, z_bottom, x_size, y_size, z_size, yaw, vx, vy), labels of the
#: config's object_classes: car, barrier, pedestrian (three tasks).
BOXES = ((2.2, 1.3, -1.84, 4.2, 1.8, 1.6, 0.4, 1.5, 0.2), (-1.5, 3.2, -1.84, 0.5, 2.0, 1.0, -1.2, 0.0, 0.0),
         (-2.8, -2.5, -1.84, 0.7, 0.7, 1.8, 2.0, 0.6, -0.4))
BOX_LABELS = (0, 5, 8)

#: The axis letters of :data:`STAGES` and ``meta.json``.
AXES = {
    "B": "batch (1 sample)",
    "N": "cameras",
    "H W": "image-feature rows and columns",
    "X Y": "BEV maps: the augmented LiDAR frame's x and y, the index growing with the coordinate",
    "X Y Z (occupancy)": "the occupancy grid's x, y, z in the ego frame as the pipeline hands it (flipped with "
                         "occ_aug_matrix); occ_sampled and occ_final_conv are indexed [y, x]",
    "(Z C)": "channels z-major: index z * C + c",
    "(C Z)": "channels c-major: index c * Z + z",
    "K": "occupancy classes (18, 17 = free)",
    "M": "voxels, in the voxelizer's numbering (order of first point)",
    "F": "point features: x, y, z, intensity, time lag",
}
#: Captured stages: name -> (module path in the reduced model, what of its call: ``output``, ``output[i]`` or
#: ``input[i]``, axis order, :data:`AXES`).
STAGES: dict[str, tuple[str, str, str]] = {
    "camera_backbone_0": ("encoders.camera.backbone", "output[0]", "(B N) C H W"),  # ResNet stage 2, stride 8
    "camera_backbone_1": ("encoders.camera.backbone", "output[1]", "(B N) C H W"),  # stage 3, stride 16
    "camera_backbone_2": ("encoders.camera.backbone", "output[2]", "(B N) C H W"),  # stage 4, stride 32
    "camera_neck": ("encoders.camera.neck", "output[0]", "(B N) C H W"),  # the only level BEVFusion uses
    "camera_transfer": ("encoders.camera.vtransform.transfer_conv", "output", "(B N) C H W"),
    "camera_bev": ("encoders.camera.vtransform", "output", "B (Z C) X Y"),
    "lidar_voxel_num_points": ("encoders.lidar.voxelize", "output[2]", "M"),
    "lidar_voxel_features": ("encoders.lidar.backbone", "input[0]", "M F"),  # each voxel's mean point
    "lidar_voxel_coords": ("encoders.lidar.backbone", "input[1]", "M (b x y z)"),
    "lidar_bev": ("encoders.lidar.backbone", "output", "B (C Z) X Y"),
    "fused_bev": ("fuser", "output", "B C X Y"),
    "decoder_backbone_0": ("decoder.backbone", "output[0]", "B C X Y"),
    "decoder_backbone_1": ("decoder.backbone", "output[1]", "B C X Y"),
    "decoder_backbone_2": ("decoder.backbone", "output[2]", "B C X Y"),  # stride 2
    "decoder_bev": ("decoder.neck", "output", "B C X Y"),  # the BEV the heads take
    "occ_sampled": ("heads.occ.coordinate_transform", "output", "B C Y X"),  # CrossCoordinateSample
    "occ_final_conv": ("heads.occ.final_conv", "output", "B C Y X"),
    "occ_logits": ("heads.occ", "output", "B X Y Z K"),
    "object_shared": ("heads.object.shared_conv", "output", "B C X Y"),
}
#: The detection head's raw outputs, stages ``object_task{t}_{name}``, all ``B C X Y``; the heatmap before any
#: sigmoid (``CenterHead.loss`` applies one in place afterwards).
OBJECT_OUTPUTS = ("reg", "height", "dim", "rot", "vel", "heatmap")
#: What ``inputs.npz`` holds: ``BEVFusion.forward``'s arguments, each with a batch axis (B = 1). The view transform
#: (``top_type: lidar``) reads camera2lidar, camera_intrinsics, img_aug_matrix and lidar_aug_matrix; the occupancy
#: head's coordinate sampler lidar_aug_matrix, lidar2ego and occ_aug_matrix; no module of this config reads
#: camera2ego, lidar2camera or lidar2image, which are given consistent with the others.
INPUTS = {
    "img": "(B, N, 3, H, W) images, ImageNet-normalised RGB",
    "points": "(B, P, 5) points x, y, z, intensity, time lag in the augmented LiDAR frame (passed as a list of B)",
    "camera2ego": "(B, N, 4, 4) camera -> ego (camera axes: x right, y down, z ahead)",
    "lidar2ego": "(B, 4, 4) LiDAR -> ego",
    "lidar2camera": "(B, N, 4, 4) LiDAR -> camera",
    "lidar2image": "(B, N, 4, 4) camera_intrinsics @ lidar2camera",
    "camera_intrinsics": "(B, N, 4, 4) the original image's 3 x 3 intrinsics in the top-left block",
    "camera2lidar": "(B, N, 4, 4) camera -> LiDAR (before the BEV augmentation)",
    "img_aug_matrix": "(B, N, 4, 4) ImageAug3D's resize and crop: original image pixels -> input pixels",
    "lidar_aug_matrix": "(B, 4, 4) the BEV augmentation, LiDAR -> augmented LiDAR frame: rotation, translation, "
                        "y flip",
    "occ_aug_matrix": "(B, 4, 4) the occupancy grid's augmentation (the y flip alone)",
    "voxel_semantics": "(B, X, Y, Z) uint8 occupancy classes (17 free, 255 the loss's ignore_index)",
    "mask_camera": "(B, X, Y, Z) uint8 visibility mask weighting the occupancy loss",
    "gt_bboxes_3d": "(B, 3, 9) boxes x, y, z_bottom, x_size, y_size, z_size, yaw, vx, vy in the augmented LiDAR "
                    "frame (LiDARInstance3DBoxes, box_dim 9)",
    "gt_labels_3d": "(B, 3) labels into the config's object_classes",
}
#: What each loss of the forward's dictionary is, in the reference's code (``{t}`` the task; before loss_scale).
LOSS_TERMS = {
    "loss/object/heatmap/task{t}": "CenterHead.loss: mmdet GaussianFocalLoss (alpha 2, gamma 4, mean) of "
                                   "clip_sigmoid(heatmap) (sigmoid clamped to [1e-4, 1 - 1e-4]) against the drawn "
                                   "Gaussian heatmap, avg_factor max(number of peaks == 1, 1)",
    "loss/object/bbox/task{t}": "CenterHead.loss: mmdet L1Loss (loss_weight 0.25, mean) of the 10 box channels (reg, "
                                "height, log dim, sin/cos rot, vel) gathered at the boxes' centre cells, weighted by "
                                "train_cfg.code_weights, avg_factor number of boxes + 1e-4",
    "loss/occ/loss_occ": "BEVOCCHead2D.loss: the reference's CrossEntropyLoss (ignore_index 255, per-voxel weight "
                         "mask_camera, avg_factor mask_camera.sum(), ignored voxels included)",
}
#: How the reference model was called.
CALL = ("model.eval(), then model.training = True on the BEVFusion module alone (every submodule stays in eval mode); "
        "with gradients enabled, model(img, points (a list of B clouds), camera2ego, lidar2ego, lidar2camera, "
        "lidar2image, camera_intrinsics, camera2lidar, img_aug_matrix, lidar_aug_matrix, metas, "
        "gt_bboxes_3d=[LiDARInstance3DBoxes(gt_bboxes_3d[0], box_dim=9)], gt_labels_3d=[gt_labels_3d[0]], "
        "occ_aug_matrix=..., voxel_semantics=..., mask_camera=...). Its forward_single's training branch runs the "
        "encoders (camera, then LiDAR), the fuser and decoder, then heads.object(x, metas) and "
        "CenterHead.loss(gt_bboxes_3d, gt_labels_3d, predictions), and heads.occ(x, lidar_aug_matrix, lidar2ego, "
        "occ_aug_matrix) and BEVOCCHead2D.loss(occ_pred, voxel_semantics, mask_camera); it returns each loss "
        "times loss_scale[head] as 'loss/<head>/<name>'.")


class _Node(dict):
    """torchpack's ``Config``: a dict whose keys also read as attributes (the configs' ``${a.b}`` expressions)."""

    def __getattr__(self, key: str):
        if key not in self:
            raise AttributeError(key)
        return self[key]


def _merge(into: _Node, other: dict) -> None:
    """torchpack's ``Config.update``: mappings merge recursively, any other value replaces."""
    for key, value in other.items():
        if isinstance(value, dict):
            if not isinstance(into.get(key), _Node):
                into[key] = _Node()
            _merge(into[key], value)
        else:
            into[key] = copy.deepcopy(value)


def load_config(checkout: Path, config: str, *overrides: dict):
    """The reference's ``config`` as ``tools/train.py`` builds it, with ``overrides`` merged before ``${...}`` is
    resolved, as an mmcv ``Config``."""
    from mmcv import Config
    from mmdet3d.utils import recursive_eval

    merged = _Node()
    for file in [checkout / folder / "default.yaml" for folder in reversed(Path(config).parents)] + [checkout / config]:
        if file.is_file():
            _merge(merged, yaml.safe_load(file.read_text()))
    for override in overrides:
        _merge(merged, override)
    return Config(recursive_eval(merged), filename=str(checkout / config))


def build(checkout: Path, config: str, *overrides: dict) -> nn.Module:
    from mmdet3d.models import build_model

    return build_model(load_config(checkout, config, *overrides).model)


def key_shapes(model: nn.Module) -> dict[str, list[int]]:
    return {key: list(value.shape) for key, value in model.state_dict().items()}


def initialise(model: nn.Module, sparse_convolution: type) -> None:
    """Every learned parameter and BatchNorm buffer drawn anew from the global generator, in module order: weights
    ~ N(0, 1 / fan_in) (fan_in the input channels times the kernel size, for spconv's (k..., in, out) weights too),
    biases ~ U(-0.1, 0.1); BatchNorm weight ~ U(0.5, 1.5), bias ~ U(-0.1, 0.1), running_mean ~ U(-0.1, 0.1),
    running_var ~ U(0.5, 1.5). Fixed geometry (the view transform's and the coordinate sampler's reference points)
    and the BatchNorm step counters are left as built."""
    with torch.no_grad():
        for module in model.modules():
            if isinstance(module, nn.modules.batchnorm._BatchNorm):
                module.weight.uniform_(0.5, 1.5)
                module.bias.uniform_(-0.1, 0.1)
                module.running_mean.uniform_(-0.1, 0.1)
                module.running_var.uniform_(0.5, 1.5)
                continue
            for parameter in module.parameters(recurse=False):
                if not parameter.requires_grad:
                    continue
                if parameter.dim() == 1:
                    parameter.uniform_(-0.1, 0.1)
                    continue
                if isinstance(module, sparse_convolution):
                    fan_in = parameter.numel() // parameter.shape[-1]
                else:
                    fan_in = parameter.numel() // parameter.shape[0]
                parameter.normal_(0.0, 1.0 / math.sqrt(fan_in))


def _rotation_z(degrees: float) -> torch.Tensor:
    angle = math.radians(degrees)
    c, s = math.cos(angle), math.sin(angle)
    return torch.tensor([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _transform(rotation: torch.Tensor, translation) -> torch.Tensor:
    matrix = torch.eye(4)
    matrix[:3, :3] = rotation
    matrix[:3, 3] = torch.tensor(translation, dtype=torch.float32)
    return matrix


def _points(generator: torch.Generator) -> torch.Tensor:
    """2000 LiDAR-like points (x, y, z, intensity, time lag) in the augmented LiDAR frame, inside the reduced range,
    shuffled: ground rings dense enough that neighbouring voxels are active together, two vertical surfaces, a
    scatter, and 25 points in one voxel (more than the voxelizer keeps: 10)."""

    def uniform(count: int, low: float, high: float) -> torch.Tensor:
        return torch.rand(count, generator=generator) * (high - low) + low

    parts = []
    for radius, count in ((1.6, 220), (2.3, 260), (3.1, 300), (4.0, 320)):
        angle = torch.arange(count) * (2 * math.pi / count) + uniform(count, 0.0, 0.01)
        parts.append(torch.stack([radius * torch.cos(angle), radius * torch.sin(angle), uniform(count, -1.87, -1.81)],
                                 dim=1))
    # Vertical surfaces at x = 1.3 and y = 4.2.
    parts.append(torch.stack([uniform(300, 1.28, 1.32), uniform(300, 0.5, 2.2), uniform(300, -1.8, -0.3)], dim=1))
    parts.append(torch.stack([uniform(250, -3.5, 0.5), uniform(250, 4.18, 4.22), uniform(250, -1.8, 1.0)], dim=1))
    parts.append(torch.stack([uniform(325, -4.7, 4.7), uniform(325, -4.7, 4.7), uniform(325, -4.9, 2.9)], dim=1))
    parts.append(torch.stack([uniform(25, -0.51, -0.46), uniform(25, -0.74, -0.69), uniform(25, -1.79, -1.62)], dim=1))
    xyz = torch.cat(parts)
    xyz = xyz[torch.randperm(len(xyz), generator=generator)]  # the pipeline's PointShuffle
    intensity = torch.floor(torch.rand(len(xyz), generator=generator) ** 2 * 60.0)
    lag = torch.randint(0, 10, (len(xyz),), generator=generator).float() * 0.05
    return torch.cat([xyz, intensity[:, None], lag[:, None]], dim=1)


def make_inputs() -> dict[str, torch.Tensor]:
    """One batch (B = 1) as the reference's data pipeline hands it to ``BEVFusion.forward``."""
    generator = torch.Generator().manual_seed(0)
    intrinsics = torch.eye(4)
    intrinsics[:3, :3] = torch.tensor([[FOCAL, 0.0, CENTRE[0]], [0.0, FOCAL, CENTRE[1]], [0.0, 0.0, 1.0]])
    optical = torch.tensor([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])  # camera axes (right, down, ahead)
    camera2ego = torch.stack([_transform(_rotation_z(yaw) @ optical, position)
                              for yaw, position in zip(CAMERA_YAWS_DEG, CAMERA_POSITIONS, strict=True)])
    lidar2ego = _transform(_rotation_z(LIDAR2EGO_YAW_DEG), LIDAR2EGO_TRANSLATION)
    camera2lidar = torch.linalg.inv(lidar2ego) @ camera2ego
    lidar2camera = torch.linalg.inv(camera2lidar)
    # DAOcc's test-time ImageAug3D: resize to the input width (1600 -> 176: 0.11), crop the bottom rows.
    height, width = REDUCED["image_size"]
    resize = float(width) / float(ORIGINAL_SIZE[1])
    resized_width, resized_height = int(ORIGINAL_SIZE[1] * resize), int(ORIGINAL_SIZE[0] * resize)
    crop = (int(max(0, resized_width - width) / 2), resized_height - height)
    img_aug = torch.eye(4)
    img_aug[:2, :2] *= resize
    img_aug[:2, 3] = -torch.tensor(crop, dtype=torch.float32)
    flip_y = torch.diag(torch.tensor([1.0, -1.0, 1.0]))
    lidar_aug = _transform(flip_y @ _rotation_z(BEV_ROTATION_DEG), (flip_y @ torch.tensor(BEV_TRANSLATION)).tolist())
    occ_aug = _transform(flip_y, (0.0, 0.0, 0.0))
    pixels = torch.rand(NUM_CAMERAS, 3, height, width, generator=generator)
    images = (pixels - torch.tensor(IMAGE_MEAN)[:, None, None]) / torch.tensor(IMAGE_STD)[:, None, None]
    grid = REDUCED["model"]["heads"]["occ"]["coordinate_transform"]["point_num"][:2]
    semantics = torch.full((*grid, 16), 17, dtype=torch.uint8)  # free
    semantics[..., :2] = torch.randint(11, 15, (*grid, 2), generator=generator, dtype=torch.uint8)  # ground classes
    semantics[12:17, 10:13, 2:6] = 4  # a car
    semantics[3:5, 15:19, 2:5] = 1  # a barrier
    semantics[6, 4, 2:7] = 7  # a pedestrian
    semantics.view(-1)[torch.randperm(semantics.numel(), generator=generator)[:4]] = 255  # the config's ignore_index
    mask_camera = (torch.rand(*grid, 16, generator=generator) < 0.6).to(torch.uint8)
    return {
        "img": images[None].contiguous(),
        "points": _points(generator)[None],
        "camera2ego": camera2ego[None],
        "lidar2ego": lidar2ego[None],
        "lidar2camera": lidar2camera[None],
        "lidar2image": (intrinsics @ lidar2camera)[None],
        "camera_intrinsics": intrinsics.expand(NUM_CAMERAS, 4, 4)[None].contiguous(),
        "camera2lidar": camera2lidar[None],
        "img_aug_matrix": img_aug.expand(NUM_CAMERAS, 4, 4)[None].contiguous(),
        "lidar_aug_matrix": lidar_aug[None],
        "occ_aug_matrix": occ_aug[None],
        "voxel_semantics": semantics[None],
        "mask_camera": mask_camera[None],
        "gt_bboxes_3d": torch.tensor(BOXES, dtype=torch.float32)[None],
        "gt_labels_3d": torch.tensor(BOX_LABELS, dtype=torch.int64)[None],
    }


def _pick(what: str, args: tuple, output):
    """``output``, ``output[i]`` or ``input[i]`` of a module call."""
    if what == "output":
        return output
    source, index = what.rstrip("]").split("[")
    return (output if source == "output" else args)[int(index)]


def run(model: nn.Module, inputs: dict[str, torch.Tensor]) -> tuple[dict[str, np.ndarray], dict[str, float]]:
    """:data:`CALL` on ``inputs``: every stage's output (cloned as its module returns, before anything downstream
    can change it in place) and the loss dictionary the forward returns."""
    from mmdet3d.core.bbox import LiDARInstance3DBoxes

    stages: dict[str, torch.Tensor] = {}
    modules = dict(model.named_modules())

    def stage_hook(name: str, what: str):
        def hook(module, args, output):
            stages[name] = _pick(what, args, output).detach().clone()

        return hook

    def object_hook(module, args, output):
        for task, (predictions,) in enumerate(output):
            for key in OBJECT_OUTPUTS:
                stages[f"object_task{task}_{key}"] = predictions[key].detach().clone()

    handles = [modules[path].register_forward_hook(stage_hook(name, what)) for name, (path, what, _) in STAGES.items()]
    handles.append(modules["heads.object"].register_forward_hook(object_hook))
    model.eval()
    model.training = True  # BEVFusion.forward's loss branch; every submodule stays in eval mode
    try:
        losses = model(
            inputs["img"], list(inputs["points"]), inputs["camera2ego"], inputs["lidar2ego"], inputs["lidar2camera"],
            inputs["lidar2image"], inputs["camera_intrinsics"], inputs["camera2lidar"], inputs["img_aug_matrix"],
            inputs["lidar_aug_matrix"], [{"box_type_3d": LiDARInstance3DBoxes}],
            gt_bboxes_3d=[LiDARInstance3DBoxes(boxes, box_dim=boxes.shape[-1]) for boxes in inputs["gt_bboxes_3d"]],
            gt_labels_3d=list(inputs["gt_labels_3d"]), occ_aug_matrix=inputs["occ_aug_matrix"],
            voxel_semantics=inputs["voxel_semantics"], mask_camera=inputs["mask_camera"])
    finally:
        model.eval()
        for handle in handles:
            handle.remove()
    return ({name: value.numpy() for name, value in stages.items()},
            {name: float(value.detach()) for name, value in losses.items()})


def describe(stages: dict[str, np.ndarray]) -> dict[str, dict]:
    """Where each stage comes from, its axis order and shape."""
    described = {}
    for name, array in stages.items():
        if name in STAGES:
            path, what, layout = STAGES[name]
        else:
            task, key = name.removeprefix("object_task").split("_", 1)
            path, what, layout = "heads.object", f"output[{task}][0][{key!r}]", "B C X Y"
        described[name] = {"module": path, "of": what, "layout": layout, "shape": list(array.shape),
                           "dtype": str(array.dtype)}
    return described


def _write_keys(path: Path, header: dict, keys: dict[str, list[int]]) -> None:
    """``header`` and ``{"keys": keys}`` as one JSON object, a key and its shape on each line, in state-dict order."""
    path.parent.mkdir(parents=True, exist_ok=True)
    head = json.dumps(header, indent=1)[:-2]  # without the closing brace, to append "keys"
    rows = ",\n".join(f"  {json.dumps(key)}: {json.dumps(shape)}" for key, shape in keys.items())
    path.write_text(f'{head},\n "keys": {{\n{rows}\n }}\n}}\n')


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--reference", type=Path, required=True, help=f"a checkout of {REPOSITORY}")
    parser.add_argument("--out", type=Path, default=Path("tests/golden/reference_parity/daocc_model"),
                        help="folder of the reduced model's goldens")
    parser.add_argument("--results", type=Path, default=Path("docs/results/parity"),
                        help="folder of the paper model's state-dict keys")
    args = parser.parse_args()
    commit = pinned_checkout(args.reference, REPOSITORY, PINNED_COMMIT)
    reference = {"repository": REPOSITORY, "commit": commit, "config": CONFIG}
    torch.use_deterministic_algorithms(True)
    torch.set_num_threads(1)  # CPU reductions in an order independent of the machine's core count
    sys.path.insert(0, str(args.reference.resolve()))
    with daocc_ops.installed(), warnings.catch_warnings():
        warnings.simplefilter("ignore", FutureWarning)  # torch.cuda.amp's deprecated decorators in the reference
        # SparseConvTensor.dense indexes with a list, which torch still reads as a tuple but warns about.
        warnings.filterwarnings("ignore", message="Using a non-tuple sequence for multidimensional indexing")
        from mmcv.utils import get_logger
        from mmdet3d.ops.spconv.conv import SparseConvolution

        get_logger("mmcv").setLevel(logging.WARNING)  # mmcv logs every parameter's initialisation at INFO
        for name, overrides in (("daocc", [NO_DOWNLOAD]), ("daocc_no_detection", [NO_DOWNLOAD, NO_DETECTION])):
            keys = key_shapes(build(args.reference, CONFIG, *overrides))
            if key_shapes(build(args.reference, PAPER_CONFIG, *overrides)) != keys:
                raise SystemExit(f"{PAPER_CONFIG} no longer has the state-dict keys of {CONFIG}")
            _write_keys(args.results / f"{name}.json", {"reference": reference, "overrides": overrides}, keys)
            print(f"{name}: {len(keys)} state-dict keys -> {args.results / name}.json")

        torch.manual_seed(0)
        model = build(args.reference, CONFIG, REDUCED)
        initialise(model, SparseConvolution)
        state = {key: value.detach().clone() for key, value in model.state_dict().items()}
        inputs = make_inputs()
        stages, losses = run(model, inputs)
        loss_scale = dict(model.loss_scale)
        paper_model = build(args.reference, PAPER_CONFIG, REDUCED)
        paper_model.load_state_dict(state, strict=True)
        paper_stages, paper_losses = run(paper_model, inputs)
    meta = {
        "reference": reference, "command": COMMAND, "overrides": REDUCED, "call": CALL,
        "initialisation": " ".join(initialise.__doc__.split()), "loss_scale": loss_scale, "losses": losses,
        "loss_terms": LOSS_TERMS,
        "inputs": {name: {"meaning": INPUTS[name], "shape": list(value.shape),
                          "dtype": str(value.dtype).removeprefix("torch.")} for name, value in inputs.items()},
        "stages": describe(stages), "axes": AXES,
        "state_dict": {"keys": len(state), "values": sum(value.numel() for value in state.values())},
        "paper_view_transform": {"config": PAPER_CONFIG, "stages": "stages_paper.npz", "losses": paper_losses,
                                 "differs": "encoders.camera.vtransform is BEVTransform (V1) instead of "
                                            "BEVTransformV2; same weights, same inputs"},
    }
    args.out.mkdir(parents=True, exist_ok=True)
    checkpoint = {"state_dict": state, "meta": {"reference": reference, "overrides": REDUCED}}
    torch.save(checkpoint, args.out / "reference.pth")
    save_npz(args.out / "inputs.npz", **{name: value.numpy() for name, value in inputs.items()})
    save_npz(args.out / "stages.npz", **stages)
    save_npz(args.out / "stages_paper.npz", **paper_stages)
    (args.out / "meta.json").write_text(json.dumps(meta, indent=1, sort_keys=True) + "\n")
    for name, value in losses.items():
        print(f"{name} = {value:.6f}")
    print(f"wrote {len(stages)} stages of {REPOSITORY}@{commit[:12]} to {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
