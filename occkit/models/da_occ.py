"""DA-Occ (direction-aware occupancy): LSS with depth scores plus a height-score projection, and DAC decoders.

No public code exists; this follows the paper (Zhou et al., arXiv 2507.23599). Data flow of ``da_occ`` (batch
``B``, 6 cameras at 256 x 704, features 16 x 44)::

    images -> ResNet-50 C4, C5 + FPN -> (B, 6, 256, 16, 44)
      depth net (FlashOcc's 1x1 conv)  -> depth (44 bins) + context (64)
      HeightNet (camera-aware, 2 vertical DACs) -> height scores (16 bins over [-1, 5.4] m)
    depth-score LSS  -> F_bev  (B, 64, 200, 200)  -> BEV encoder -> D_h(F) + D_v(F)          -> (B, 256, 200, 200)
    height-score LSS -> F_3D (B, 64, 16, 32, 32) -> slice along X: F_height (B, 64, 16, 32 * 32) -> D_v (along Z)
        -> heights folded into channels (B, 1024, 32, 32) -> 1x1 conv -> bilinear to 200 x 200 -> (B, 256, 200, 200)
    concat -> 1x1 conv -> channel-to-height head -> (B, 18, 200, 200, 16)

**Depth.** The paper contradicts itself: its figure and loss formula have a BEVDepth-style camera-aware DepthNet
with a depth BCE, while section IV-C says that its single-frame model, like FlashOcc, uses no depth supervision, and
its ablations "remove DepthNet". ``da_occ`` (the single-frame row, 34.38 mIoU) follows IV-C: FlashOcc's 1x1 depth
net (``depth_net: null``) and no depth term. ``da_occ_depth`` follows the figure and the formula (``depth_net``
set, ``loss_weights.depth: 1``).

**HeightNet** keeps the camera-aware structure the paper gives it (DepthNet's, its last two 3x3 conv blocks replaced
by vertical DACs): removing DepthNet takes away the depth branch's network, not HeightNet, and Table III ablates
HeightNet's DACs, which only exist in that structure. It keeps its height BCE against LiDAR heights (training only):
without it the height scores would be unsupervised, and the projection they drive is the paper's contribution.

**Switches** (Tables II and III): ``height_net: null`` removes the height branch (FlashOcc plus the BEV DACs);
``height_net.dac_blocks`` sets how many of HeightNet's last residual blocks are DACs (0: the 3x3 BasicBlocks they
replaced, which is what the paper's ablation takes away); ``bev_horizontal_dac`` and ``bev_vertical_dac`` leave D_h
or D_v out of F_BEV' = D_h(F) + D_v(F) (with both out, F_BEV' = F: the paper adds them on top of FlashOcc's BEV
encoder, and Table III counts what they add, so nothing replaces them); ``height_volume_dac`` makes the D_v on
F_height the identity. ``height_grid_size`` and ``height_range`` set the height grid (Table II: 16 x 32 x 32 or
4 x 32 x 32, Z x X x Y).

**Widths** (the paper gives none): FlashOcc's BEV backbone and context (64 channels, 44 depth bins) with FlashOcc
M1's 256-channel BEV neck, fusion and head. occkit's counter (``occkit bench``'s) gives 274.0 GMACs at 256 x 704 with
six cameras, the paper 276.59 G for its 16 x 32 x 32 setting; M0's 128 channels would give 173.5 G. The counter
agrees with FlashOcc's own figures to 0.5% (M0 153.3 vs 154.1 G, M1 247.7 vs 248.6 G). The two BEV DACs count
4.1 G against the paper's 5.35 G: no standard width matches that (128 channels give 2.1 G), and the paper does not
describe the DAC's arithmetic further.

Other choices the paper leaves open, made here: the height-score projection weights every frustum point by the
height probability of the voxel it falls in (eq. F_3D(v) = sum over points i in v of softmax_Z(H)_i F_i; no depth
factor); F_HEIGHT is reduced to the fusion width at 32 x 32 *before* being brought to 200 x 200 (bilinear), which
costs 0.2% of what reducing at full resolution would; D_h and D_v are single DAC blocks (DAC + BN + ReLU) applied
after FlashOcc's BEV encoder. Loss: 1 x height BCE + 10 x camera-masked CE + 1 x semantic and 1 x geometric
scene-class affinity (MonoScene), the paper's weights, and 1 x depth BCE in ``da_occ_depth``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import ClassVar

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from occkit.geometry.grid import OCC3D_GRID, VoxelGrid
from occkit.losses import (
    counted_affinity_geometric,
    counted_affinity_semantic,
    depth_bce,
    height_bce,
)
from occkit.models.base import FIXED_CALIBRATION_RETIRED, Architecture, OccupancyModel, camera_images
from occkit.models.bev_encoder import BevEncoder, BevEncoderConfig
from occkit.models.dac import DACBlock
from occkit.models.heads.depth import DepthNet, DepthNetConfig, camera_parameters, lidar_target
from occkit.models.heads.flow import FlowHead, FlowHeadConfig, check_motion_input
from occkit.models.heads.occupancy import OccupancyHead, OccupancyHeadConfig
from occkit.models.image_encoder import ImageEncoder, ImageEncoderConfig
from occkit.models.temporal import HISTORY_INPUTS, TemporalConfig, TemporalFusion
from occkit.models.view_transform.lss import (
    PoolingPlan,
    depth_bins,
    fold_height,
    frustum,
    gather_point_weights,
    lift_geometry,
    make_pooling_plan,
    voxel_pool,
)
from occkit.types import Batch, ModelOutput

__all__ = ["DAOccLossWeights", "DirectionAwareOccConfig", "DirectionAwarePlan", "DirectionAwareOcc", "ARCHITECTURE"]


@dataclass(frozen=True)
class DAOccLossWeights:
    """Weights of DA-Occ's loss terms (the paper's formula: 1, 1, 10, 1, 1; its single-frame model: no depth term)."""

    depth: float = 0.0
    """BCE of the depth bins against LiDAR depth: 0 (no term) for the single-frame model, which section IV-C trains
    like FlashOcc without depth supervision; 1 in the loss formula, which ``da_occ_depth`` follows."""
    height: float = 1.0
    """BCE of the height bins against LiDAR height (DHD-style per-patch minimum)."""
    occupancy: float = 10.0
    """Camera-masked cross-entropy."""
    semantic_affinity: float = 1.0
    """MonoScene's semantic scene-class affinity."""
    geometric_affinity: float = 1.0
    """MonoScene's geometric scene-class affinity."""


@dataclass(frozen=True)
class DirectionAwareOccConfig:
    """DA-Occ, single frame without depth supervision, the paper's 16 x 32 x 32 height grid."""

    #: Keys of older versions, skipped on load (see :func:`occkit.config.from_dict`).
    RETIRED_KEYS: ClassVar[dict[str, str]] = {"fixed_calibration": FIXED_CALIBRATION_RETIRED}

    image: ImageEncoderConfig = field(
        default_factory=lambda: ImageEncoderConfig(out_stages=(3, 4), norm_eval=False, neck="fpn")
    )
    """ResNet-50 C4 + C5 with BEVDet's FPN, 256 channels at stride 16."""
    feature_stride: int = 16
    """Stride of the image features."""
    depth_range: tuple[float, float, float] = (1.0, 45.0, 1.0)
    """Depth bins (min, max, step), metres."""
    height_range: tuple[float, float, float] = (OCC3D_GRID.point_cloud_range[2], OCC3D_GRID.point_cloud_range[5],
                                                OCC3D_GRID.voxel_size[2])  # fmt: skip
    """Height bins (min, max, step), metres in the ego frame: one per voxel layer of the height grid."""
    occ_range: tuple[float, float, float, float, float, float] = OCC3D_GRID.point_cloud_range
    """Occupancy grid extent, ego frame (Occ3D's grid)."""
    bev_size: tuple[int, int] = OCC3D_GRID.shape[:2]
    """BEV cells (X, Y) of the depth-score projection and the output."""
    height_grid_size: tuple[int, int, int] = (32, 32, 16)
    """Voxels (X, Y, Z) of the height-score projection (the paper's Z x X x Y = 16 x 32 x 32)."""
    depth_net: DepthNetConfig | None = None
    """None: FlashOcc's depth net, one 1x1 conv from the image features to the depth bins and ``bev.in_channels``
    context channels, unsupervised (the single-frame model of the paper's section IV-C). A DepthNetConfig: BEVDepth's
    camera-aware DepthNet of the paper's figure, whose context_channels must equal ``bev.in_channels``."""
    height_net: DepthNetConfig | None = field(
        default_factory=lambda: DepthNetConfig(bins=16, context_channels=0, dac_blocks=2)
    )
    """HeightNet: the camera-aware DepthNet's structure for height bins, its last ``dac_blocks`` residual blocks
    vertical DACs (0: the 3x3 conv blocks they replace). None: no height branch (no height-score projection, height
    volume, its DAC, reduction and fusion), i.e. FlashOcc with the BEV DACs."""
    bev: BevEncoderConfig = field(
        default_factory=lambda: BevEncoderConfig(
            in_channels=64, strides=(2, 2, 2), channels=(128, 256, 512), neck_channels=256, neck_extra_upsample=2
        )
    )
    """FlashOcc's BEV encoder on F_bev with M1's 256-channel neck (the width that matches the paper's MACs);
    ``in_channels`` is the context width lifted by the depth net."""
    bev_horizontal_dac: bool = True
    """D_h on the encoded BEV (along y). Off: left out of F_BEV' = D_h(F) + D_v(F); with both off F_BEV' = F."""
    bev_vertical_dac: bool = True
    """D_v on the encoded BEV (along x). Off: left out of the sum, as ``bev_horizontal_dac``."""
    height_volume_dac: bool = True
    """D_v along Z on the sliced height volume F_height. Off: the identity."""
    fusion_channels: int = 256
    """Channels of the fused BEV (and of F_HEIGHT after its 1x1 reduction)."""
    occupancy: OccupancyHeadConfig = field(
        default_factory=lambda: OccupancyHeadConfig(in_channels=256, hidden_channels=256)
    )
    """Channel-to-height head (FlashOcc M1's width)."""
    flow: FlowHeadConfig | None = None
    """Occupancy flow head on the occupancy head's input (the data then loads flow: ``data.flow = true``); None:
    no flow, as the paper."""
    loss_weights: DAOccLossWeights = field(default_factory=DAOccLossWeights)
    """Weights of the loss terms; a weight of 0 leaves its term (and its LiDAR target) out."""
    temporal: TemporalConfig | None = None
    """BEV-level history (the paper's temporal rows): F_bev fused with earlier frames' before the BEV encoder, whose
    ``in_channels`` is then ``temporal.out_channels(context)``; the height branch stays single-frame. None: a single
    frame."""

    @property
    def sensors(self) -> tuple[str, ...]:
        """The sensors the model reads at inference (LiDAR, where the data loads it, only supervises)."""
        return ("cameras",)

    @property
    def training_targets(self) -> tuple[str, ...]:
        """What supervises the model in training beside the occupancy labels (never an input at inference)."""
        targets = ("LiDAR depth",) if self.loss_weights.depth else ()
        return targets + (("LiDAR heights",) if self.height_net is not None and self.loss_weights.height else ())

    @property
    def output_grid(self) -> VoxelGrid:
        """The grid the model predicts on: :attr:`occ_range` cut into the BEV's cells and the occupancy head's
        ``height`` layers (checked against the label space's grid by ``experiment.check_label_space``)."""
        return VoxelGrid.from_shape(self.occ_range, (*self.bev_size, self.occupancy.height))

    @property
    def depth_bins(self) -> int:
        """Bins of :attr:`depth_range` (as many as the frustum has)."""
        return int(depth_bins(self.depth_range).numel())

    @property
    def context_channels(self) -> int:
        """C of F_bev: ``bev.in_channels``, or its share of one frame when the encoder takes a fused history."""
        if self.temporal is None or self.temporal.fusion == "recurrent":
            return self.bev.in_channels
        extra = self.temporal.history if self.temporal.with_valid else 0
        return (self.bev.in_channels - extra) // (self.temporal.history + 1)

    @property
    def height_bins(self) -> int:
        """Bins of :attr:`height_range`."""
        return _bins(self.height_range)

    def __post_init__(self) -> None:
        checks = {
            "occupancy.in_channels": (self.occupancy.in_channels, self.fusion_channels, "fusion_channels"),
            "fusion_channels": (self.fusion_channels, self.bev.neck_channels, "bev.neck_channels"),
        }
        check_motion_input(self.flow, lidar=False)
        if self.flow is not None:
            checks["flow.in_channels"] = (self.flow.in_channels, self.occupancy.hidden_channels,
                                          "occupancy.hidden_channels")  # fmt: skip
        nets = {"depth_net": (self.depth_net, self.depth_bins), "height_net": (self.height_net, self.height_bins)}
        for name, (net, bins) in nets.items():
            if net is not None:
                checks[f"{name}.in_channels"] = (net.in_channels, self.image.neck_channels, "image.neck_channels")
                checks[f"{name}.bins"] = (net.bins, bins, f"the {name[:-4]}_range bins")
        context = self.context_channels
        if self.temporal is not None and self.temporal.fusion == "concat":
            # The encoder takes (K + 1) frames of context (+ K valid masks): its width fixes the context's.
            frames, masks = self.temporal.history + 1, self.temporal.history if self.temporal.with_valid else 0
            if (self.bev.in_channels - masks) % frames or context < 1:
                raise ValueError(f"bev.in_channels = {self.bev.in_channels} must be {frames} x the context channels"
                                 + (f" + {masks}" if masks else "") + f" (temporal: the current frame and "
                                 f"{frames - 1} earlier ones concatenated" + (", with their valid masks)" if masks
                                                                              else ")"))  # fmt: skip
        if self.depth_net is not None:
            checks["depth_net.context_channels"] = (self.depth_net.context_channels, context,
                                                    "the context channels (bev.in_channels without temporal)")
        if self.height_net is not None:
            checks["height_grid_size[2]"] = (self.height_grid_size[2], self.height_bins, "the height_range bins")
        for key, (value, wanted, source) in checks.items():
            if value != wanted:
                raise ValueError(f"{key} = {value} must equal {source} = {wanted}")


def _bins(value_range: tuple[float, float, float]) -> int:
    return round((value_range[1] - value_range[0]) / value_range[2])


@dataclass
class DirectionAwarePlan:
    """DA-Occ's calibration-only tensors."""

    camera_params: Tensor | None
    """``(B, N, 27)`` camera parameters of the camera-aware depth and height nets; None when there are none."""
    z_bins: Tensor | None
    """``(B, N, D, h, w)`` int64 height bin of every frustum point; None without a height branch."""
    bev: PoolingPlan
    """Depth-score pooling onto the ``X x Y x 1`` BEV."""
    height: PoolingPlan | None
    """Height-score pooling onto the ``X' x Y' x Z`` height volume; None without a height branch."""


class DirectionAwareOcc(OccupancyModel):
    """``forward(batch) -> ModelOutput`` (occupancy, depth, height); ``loss(output, batch)``; ``predict(batch)``.

    Plan: :class:`DirectionAwarePlan`. Inputs: ``images``.
    """

    def __init__(self, cfg: DirectionAwareOccConfig) -> None:
        super().__init__()
        self.cfg = cfg
        self.bev_grid = VoxelGrid.from_shape(cfg.occ_range, (*cfg.bev_size, 1))
        self.height_grid = VoxelGrid.from_shape(cfg.occ_range, cfg.height_grid_size)
        self.image_encoder = ImageEncoder(cfg.image)
        context, channels, (x, y) = cfg.context_channels, cfg.fusion_channels, cfg.bev_size
        # Both kinds of depth net are ``depth_net``: a checkpoint of either finds its weights under that name.
        self.depth_net: nn.Module = (nn.Conv2d(cfg.image.neck_channels, cfg.depth_bins + context, 1)
                                     if cfg.depth_net is None else DepthNet(cfg.depth_net))  # fmt: skip
        self.height_net = None if cfg.height_net is None else DepthNet(cfg.height_net)
        if cfg.temporal is not None:
            x_min, y_min, _, x_max, y_max, _ = cfg.occ_range
            self.temporal = TemporalFusion(cfg.temporal, context, (x_min, y_min, x_max, y_max), cfg.bev_size)
        self.bev_encoder = BevEncoder(cfg.bev)
        # A switched-off DAC builds nothing: its attribute is None (or the identity), so its parameters are absent.
        self.bev_horizontal = DACBlock(channels, y, "h") if cfg.bev_horizontal_dac else None  # D_h: along y (dim 3)
        self.bev_vertical = DACBlock(channels, x, "v") if cfg.bev_vertical_dac else None  # D_v: along x (dim 2)
        if self.height_net is not None:
            z = cfg.height_grid_size[2]
            # D_v on F_height (B, C, Z, X*Y): along Z.
            self.height_vertical = DACBlock(context, z, "v") if cfg.height_volume_dac else nn.Identity()
            self.height_reduce = nn.Conv2d(context * z, channels, 1)
            self.fuse = nn.Conv2d(2 * channels, channels, 1)
        self.occupancy_head = OccupancyHead(cfg.occupancy)
        if cfg.flow is not None:
            self.flow_head = FlowHead(cfg.flow)

    @property
    def camera_aware(self) -> bool:
        """Whether a camera-aware net (the depth-supervised DepthNet or HeightNet) reads the camera parameters."""
        return self.cfg.depth_net is not None or self.height_net is not None

    def plan(self, batch: Batch) -> DirectionAwarePlan:
        images = camera_images(batch, "DA-Occ")
        points_uvd = frustum(tuple(images.shape[-2:]), self.cfg.feature_stride, self.cfg.depth_range,
                             device=images.device)
        points = lift_geometry(points_uvd, batch.intrinsics.float(), batch.cam2ego.float(), batch.img_aug.float(),
                               batch.occ_aug.float())  # (B, N, D, h, w, 3)
        camera_params = (camera_parameters(batch.intrinsics, batch.img_aug, batch.occ_aug, batch.cam2ego)
                         if self.camera_aware else None)  # fmt: skip
        bev = make_pooling_plan(points, self.bev_grid, batch.camera_mask)
        if self.height_net is None:
            return DirectionAwarePlan(camera_params=camera_params, z_bins=None, bev=bev, height=None)
        z_bins = self.height_grid.world_to_index(points)[0][..., 2].clamp(0, self.cfg.height_grid_size[2] - 1)
        return DirectionAwarePlan(camera_params=camera_params, z_bins=z_bins, bev=bev,
                                  height=make_pooling_plan(points, self.height_grid, batch.camera_mask))

    def inputs(self, batch: Batch) -> dict[str, Tensor]:
        return {"images": camera_images(batch, "DA-Occ")}

    def _depth(self, features: Tensor, plan: DirectionAwarePlan) -> tuple[Tensor, Tensor]:
        """``(M, C_in, h, w)`` -> depth logits ``(M, D, h, w)`` and context ``(M, C, h, w)``."""
        if isinstance(self.depth_net, DepthNet):
            return self.depth_net(features, plan.camera_params)
        out = self.depth_net(features)  # (M, D + C, h, w)
        return out[:, : self.cfg.depth_bins], out[:, self.cfg.depth_bins :]

    def _bev_decoder(self, bev: Tensor) -> Tensor:
        """F_BEV' = D_h(F) + D_v(F) over the DACs switched on; F itself when both are off. ``(B, C, X, Y)``."""
        branches = [dac(bev) for dac in (self.bev_horizontal, self.bev_vertical) if dac is not None]
        if not branches:
            return bev
        return branches[0] if len(branches) == 1 else branches[0] + branches[1]

    def _lift(self, features: Tensor, plan: DirectionAwarePlan) -> tuple[Tensor, Tensor, Tensor]:
        """Image features ``(B, N, C_in, h, w)`` -> F_bev ``(B, C, X, Y)``, depth ``(B, N, D, h, w)`` and context
        ``(B, N, C, h, w)``."""
        batch_size, cameras = features.shape[:2]
        depth_logits, context = self._depth(features.flatten(0, 1), plan)
        depth = depth_logits.softmax(dim=1).unflatten(0, (batch_size, cameras))  # (B, N, D, h, w)
        context = context.unflatten(0, (batch_size, cameras))  # (B, N, C, h, w)
        return fold_height(voxel_pool(depth, context, plan.bev)), depth, context

    def frame_bev(self, images: Tensor, plan: DirectionAwarePlan) -> Tensor:
        return self._lift(self.image_encoder(images), plan)[0]

    def network(self, inputs: Mapping[str, Tensor], plan: DirectionAwarePlan) -> ModelOutput:
        features = self.image_encoder(inputs["images"])  # (B, N, C, h, w)
        batch_size, cameras = features.shape[:2]
        bev, depth, context = self._lift(features, plan)  # F_bev (B, C, X, Y)
        state = None
        if self.temporal is not None:  # BEV-level history, before the encoder
            bev, state = self.temporal(bev, *(inputs[name] for name in HISTORY_INPUTS))
        bev = self._bev_decoder(self.bev_encoder(bev))  # F_BEV' (B, C', X, Y)
        if self.height_net is None:  # FlashOcc with the BEV DACs
            logits, flow = self.occupancy_and_flow(self.occupancy_head, bev)
            return ModelOutput(occupancy=logits, depth=depth, history_state=state, flow=flow)

        height_logits, _ = self.height_net(features.flatten(0, 1), plan.camera_params)
        height = height_logits.softmax(dim=1).unflatten(0, (batch_size, cameras))  # (B, N, Z, h, w)
        volume = voxel_pool(gather_point_weights(height, plan.z_bins), context, plan.height)  # F_3D (B, C, Z, X, Y)
        c, z, x, y = volume.shape[1:]
        sliced = self.height_vertical(volume.reshape(batch_size, c, z, x * y))  # F_height (B, C, Z, X*Y), DAC on Z
        folded = sliced.reshape(batch_size, c, z, x, y).transpose(1, 2).reshape(batch_size, z * c, x, y)
        heights = F.interpolate(self.height_reduce(folded), size=bev.shape[-2:], mode="bilinear", align_corners=False)

        logits, flow = self.occupancy_and_flow(self.occupancy_head, self.fuse(torch.cat([heights, bev], dim=1)))
        return ModelOutput(occupancy=logits, depth=depth, height=height, history_state=state, flow=flow)

    def loss(self, output: ModelOutput, batch: Batch) -> dict[str, Tensor]:
        """DA-Occ's weighted loss terms: the occupancy CE and the scene-class affinities, the height BCE with a height
        branch, the depth BCE with a depth weight (only the depth-supervised variant)."""
        if batch.voxel_semantics is None:
            raise ValueError("the occupancy loss needs batch.voxel_semantics")
        w = self.cfg.loss_weights
        labels = batch.voxel_semantics
        losses: dict[str, Tensor] = {}
        if w.depth:
            maps = lidar_target(batch.depth_maps, output.depth, "depth", "DA-Occ", self.cfg.feature_stride)
            losses["depth"] = w.depth * depth_bce(output.depth, maps, self.cfg.depth_range)
        if self.height_net is not None and w.height:
            maps = lidar_target(batch.height_maps, output.height, "height", "DA-Occ", self.cfg.feature_stride)
            losses["height"] = w.height * height_bce(output.height, maps, self.cfg.height_range)
        # One gather of the counted voxels serves the head's terms and the affinities (without the visibility mask,
        # the affinities, like the head's drop-free CE, count every voxel).
        voxels = self.occupancy_head.counted_voxels(output.occupancy, labels, batch.mask_camera)
        # The head's own loss: its class balance and optional Lovasz term apply as in the other models.
        losses.update({name: (w.occupancy if name == "occupancy" else 1.0) * term for name, term
                       in self.occupancy_head.loss(output.occupancy, labels, batch.mask_camera, voxels).items()})
        losses["semantic_affinity"] = w.semantic_affinity * counted_affinity_semantic(voxels)
        losses["geometric_affinity"] = w.geometric_affinity * counted_affinity_geometric(
            voxels, self.cfg.occupancy.free_index
        )
        losses.update(self.flow_losses(output, batch))
        return losses


ARCHITECTURE = Architecture(
    name="da_occ",
    config=DirectionAwareOccConfig,
    model=DirectionAwareOcc,
    stages={
        "image_encoder": ("image_encoder",),
        "view_transform": ("depth_net", "height_net"),
        # DA-Occ's decoders: the DACs on F_bev and on the height volume, its reduction and the fusing 1x1 conv.
        "fusion_bev_encoder": ("temporal", "bev_encoder", "bev_horizontal", "bev_vertical", "height_vertical",
                               "height_reduce", "fuse"),
        "heads": ("occupancy_head", "flow_head"),
    },
)  # fmt: skip
