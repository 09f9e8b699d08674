"""Typed containers that flow from the data pipeline to models, losses and metrics.

Shapes follow docs/conventions.md: occupancy ``(X, Y, Z)``, images ``(N, 3, H, W)`` for ``N`` cameras, points
``(P, 5)`` as ``(x, y, z, intensity, time lag)`` in the LiDAR frame. Every geometric augmentation is a matrix:
``img_aug`` maps original to augmented pixels, ``bev_aug`` maps the un-augmented LiDAR frame to the augmented one and
``occ_aug`` does the same for the ego (occupancy) frame, so any stage can map points exactly.
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields

import torch
from torch import Tensor

__all__ = ["Sample", "Batch", "ModelOutput", "OccPrediction"]


@dataclass
class Sample:
    """One key frame, after transforms.

    Camera geometry is given relative to the key frame's ego pose (at the LiDAR timestamp), so the small ego motion
    between the LiDAR and each camera's exposure is already folded into ``cam2ego``.

    With ``DatasetConfig.history = K > 0`` the ``history_*`` fields hold the cameras of the ``K`` earlier key frames
    of the scene, newest first (BEVDet4D-style temporal fusion). They share the sample's augmentation: each camera's
    image augmentation (``history_img_aug[k] == img_aug``) and the one BEV augmentation ``occ_aug`` / ``bev_aug``,
    which moves the whole sequence, so a model aligns history frame ``k`` to the current one with
    ``occ_aug @ inv(ego2global) @ history_ego2global[k] @ inv(occ_aug)`` and nothing per frame is stored. Points,
    boxes, labels and depth maps are the current frame's only.
    """

    token: str
    """nuScenes sample token."""
    scene: str
    """Scene name."""
    images: Tensor | None = None
    """``(N, 3, H, W)`` float32, normalised; None for LiDAR-only pipelines."""
    intrinsics: Tensor | None = None
    """``(N, 3, 3)`` float32 pinhole matrices of the original images."""
    cam2ego: Tensor | None = None
    """``(N, 4, 4)`` float32 camera -> key-frame ego."""
    img_aug: Tensor | None = None
    """``(N, 3, 3)`` float32 original -> augmented pixel map."""
    camera_mask: Tensor | None = None
    """``(N,)`` bool, False for cameras that failed (robustness evaluation); their images are zeroed."""
    lidar2ego: Tensor = field(default_factory=lambda: torch.eye(4))
    """``(4, 4)`` float32 LiDAR -> ego at the key frame."""
    ego2global: Tensor = field(default_factory=lambda: torch.eye(4))
    """``(4, 4)`` float64 key-frame ego -> global."""
    points: Tensor | None = None
    """``(P, 5)`` float32 key frame and sweeps in the (augmented) LiDAR frame: x, y, z, intensity, time lag (s)."""
    bev_aug: Tensor = field(default_factory=lambda: torch.eye(4))
    """``(4, 4)`` float32 LiDAR frame -> augmented LiDAR frame."""
    occ_aug: Tensor = field(default_factory=lambda: torch.eye(4))
    """``(4, 4)`` float32 ego frame -> augmented ego (occupancy) frame."""
    boxes: Tensor | None = None
    """``(M, 9)`` float32 boxes in the augmented LiDAR frame (or the augmented ego frame, with
    ``DatasetConfig.box_frame = "ego"``): x, y, z (centre), l, w, h, yaw, vx, vy."""
    box_labels: Tensor | None = None
    """``(M,)`` int64 indices into ``occkit.classes.DETECTION_CLASSES``."""
    voxel_semantics: Tensor | None = None
    """``(X, Y, Z)`` uint8 occupancy labels in the augmented ego frame (255 = ignore)."""
    mask_camera: Tensor | None = None
    """``(X, Y, Z)`` bool, voxels observed by the cameras."""
    mask_lidar: Tensor | None = None
    """``(X, Y, Z)`` bool, voxels observed by the LiDAR."""
    voxel_flow: Tensor | None = None
    """``(X, Y, Z, 2)`` float32 occupancy flow ``vx, vy`` (m/s) in the augmented ego frame, on request
    (``DatasetConfig.flow``): each voxel's object velocity, zero on static and free voxels."""
    voxel_instances: Tensor | None = None
    """``(X, Y, Z)`` int32 panoptic instance ids (0: stuff or free), on request (``DatasetConfig.instances``)."""
    depth_maps: Tensor | None = None
    """``(N, h, w)`` float32 LiDAR depth per feature cell (0 = none), on request."""
    height_maps: Tensor | None = None
    """``(N, h, w)`` float32 minimum ego-frame height per feature cell (NaN = none), on request."""
    history_tokens: tuple[str, ...] | None = None
    """``K`` earlier sample tokens of the scene, newest first; a padded slot holds this sample's token. None unless
    ``DatasetConfig.history > 0`` (as every ``history_*`` field)."""
    history_images: Tensor | None = None
    """``(K, N, 3, H, W)`` float32 images of the earlier key frames, normalised and augmented as ``images``; failed
    cameras (``camera_mask``) zeroed in every frame."""
    history_intrinsics: Tensor | None = None
    """``(K, N, 3, 3)`` float32 pinhole matrices of the earlier frames' original images."""
    history_cam2ego: Tensor | None = None
    """``(K, N, 4, 4)`` float32 camera -> that history frame's own key-frame ego (its record's ``cam2keyego``)."""
    history_img_aug: Tensor | None = None
    """``(K, N, 3, 3)`` float32 original -> augmented pixel map; every slot equals ``img_aug``."""
    history_ego2global: Tensor | None = None
    """``(K, 4, 4)`` float64 ego pose of each history frame (at its LiDAR key-frame timestamp)."""
    history_padded: Tensor | None = None
    """``(K,)`` bool, True where the scene has too few earlier frames and the slot repeats this frame (its images,
    calibration and pose: the motion to it is the identity)."""


@dataclass
class Batch:
    """``B`` samples collated; per-sample lists where sizes differ (boxes), padding plus lengths for points."""

    tokens: list[str]
    scenes: list[str]
    images: Tensor | None = None
    """``(B, N, 3, H, W)``."""
    intrinsics: Tensor | None = None
    """``(B, N, 3, 3)``."""
    cam2ego: Tensor | None = None
    """``(B, N, 4, 4)``."""
    img_aug: Tensor | None = None
    """``(B, N, 3, 3)``."""
    camera_mask: Tensor | None = None
    """``(B, N)`` bool, cameras that work; None: all of them."""
    lidar2ego: Tensor | None = None
    """``(B, 4, 4)``."""
    ego2global: Tensor | None = None
    """``(B, 4, 4)`` float64."""
    points: Tensor | None = None
    """``(B, P_max, 5)`` zero padded."""
    num_points: Tensor | None = None
    """``(B,)`` int64 valid rows of ``points``."""
    bev_aug: Tensor | None = None
    """``(B, 4, 4)``."""
    occ_aug: Tensor | None = None
    """``(B, 4, 4)``."""
    boxes: list[Tensor] | None = None
    """``B`` tensors ``(M_b, 9)``."""
    box_labels: list[Tensor] | None = None
    """``B`` tensors ``(M_b,)``."""
    voxel_semantics: Tensor | None = None
    """``(B, X, Y, Z)`` uint8."""
    mask_camera: Tensor | None = None
    """``(B, X, Y, Z)`` bool."""
    mask_lidar: Tensor | None = None
    """``(B, X, Y, Z)`` bool."""
    voxel_flow: Tensor | None = None
    """``(B, X, Y, Z, 2)`` float32 m/s."""
    voxel_instances: Tensor | None = None
    """``(B, X, Y, Z)`` int32 panoptic instance ids."""
    depth_maps: Tensor | None = None
    """``(B, N, h, w)``."""
    height_maps: Tensor | None = None
    """``(B, N, h, w)``."""
    history_tokens: list[tuple[str, ...]] | None = None
    """``B`` tuples of ``K`` earlier sample tokens, newest first (padded slots: the sample's own token)."""
    history_images: Tensor | None = None
    """``(B, K, N, 3, H, W)``."""
    history_intrinsics: Tensor | None = None
    """``(B, K, N, 3, 3)``."""
    history_cam2ego: Tensor | None = None
    """``(B, K, N, 4, 4)`` camera -> the history frame's own ego."""
    history_img_aug: Tensor | None = None
    """``(B, K, N, 3, 3)``."""
    history_ego2global: Tensor | None = None
    """``(B, K, 4, 4)`` float64."""
    history_padded: Tensor | None = None
    """``(B, K)`` bool, slots that repeat the current frame."""

    def __len__(self) -> int:
        return len(self.tokens)

    def to(self, device: torch.device | str, non_blocking: bool = False) -> Batch:
        """A copy with every tensor moved to ``device`` (float64 poses keep their dtype)."""
        moved = {}
        for f in fields(self):
            value = getattr(self, f.name)
            if isinstance(value, Tensor):
                value = value.to(device, non_blocking=non_blocking)
            elif isinstance(value, list) and value and isinstance(value[0], Tensor):
                value = [v.to(device, non_blocking=non_blocking) for v in value]
            moved[f.name] = value
        return Batch(**moved)


@dataclass
class ModelOutput:
    """What a model's ``forward`` returns: raw head outputs, consumed by its ``loss`` and ``predict``."""

    occupancy: Tensor
    """``(B, K, X, Y, Z)`` occupancy logits."""
    detection: list[dict[str, Tensor]] | None = None
    """CenterPoint maps per task group (``heatmap``, ``reg``, ``height``, ``dim``, ``rot``, ``vel``), each
    ``(B, C, X', Y')``; None when the detection branch is absent or not run."""
    depth: Tensor | None = None
    """``(B, N, D, h, w)`` depth distributions of LSS models."""
    height: Tensor | None = None
    """``(B, N, Z, h, w)`` height distributions of DA-Occ."""
    flow: Tensor | None = None
    """``(B, X, Y, Z, 2)`` predicted occupancy flow ``vx, vy`` (m/s, ego frame) of models with a flow head."""
    history_state: Tensor | None = None
    """``(B, C, X, Y)`` of temporal models: what a stream keeps of this frame for the next ones
    (:class:`~occkit.models.temporal.StreamMemory`)."""


@dataclass
class OccPrediction:
    """What a model predicts for a batch."""

    semantics: Tensor
    """``(B, X, Y, Z)`` uint8 class ids (17 = free for Occ3D)."""
    flow: Tensor | None = None
    """``(B, X, Y, Z, 2)`` float32 occupancy flow (m/s, ego frame) of models with a flow head."""
    instances: Tensor | None = None
    """``(B, X, Y, Z)`` int32 panoptic instance ids of models with an instance head (0: stuff or free)."""
    boxes: list[Tensor] | None = None
    """Optional ``B`` tensors ``(M_b, 9)`` in the LiDAR frame."""
    box_scores: list[Tensor] | None = None
    """Optional ``B`` tensors ``(M_b,)``."""
    box_labels: list[Tensor] | None = None
    """Optional ``B`` tensors ``(M_b,)`` int64."""
