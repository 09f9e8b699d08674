"""DA-Occ's zoo entries: the paper's rows, its ablations and the CPU-sized ``*_tiny`` versions, each a whole
experiment (model, data, schedule) registered by name."""

from __future__ import annotations

import dataclasses

from occkit.data.dataset import DatasetConfig
from occkit.experiment import CPU_TRAIN, Experiment, TrainConfig, cpu_data, reproduces
from occkit.label_space import OCC3D_SPACE
from occkit.models.bev_encoder import BevEncoderConfig
from occkit.models.da_occ import DAOccLossWeights, DirectionAwareOccConfig
from occkit.models.heads.depth import DepthNetConfig
from occkit.models.heads.occupancy import OccupancyHeadConfig
from occkit.models.image_encoder import ImageEncoderConfig
from occkit.models.temporal import TemporalConfig
from occkit.nuscenes import CAMERAS
from occkit.zoo.registry import preset
from occkit.zoo.variants import with_flow_head

PAPER = "DA-Occ (Zhou et al., arXiv 2507.23599)"

#: DA-Occ's optimiser (AdamW 1e-4, weight decay 0.05, 4 samples x 4 GPUs, gradient clip 5) on the schedule of
#: FlashOcc's code base, which it builds on: 24 epochs, 200 warm-up steps from 0.001 of the rate, mmcv's step policy
#: with ``step=[24]`` (constant after the warm-up), MEGVII EMA ramped from 10560 updates.
TRAIN = TrainConfig(epochs=24, batch_size=4, global_batch=16, lr=1e-4, weight_decay=0.05, grad_clip=5.0,
                    warmup_steps=200, warmup_ratio=0.001, lr_policy="step", lr_steps=(24,), ema_decay=0.999,
                    ema_ramp=2000.0, ema_initial_updates=10560)  # fmt: skip

#: The paper's inputs: six cameras, and the key-frame LiDAR sweep for the height (and, in ``da_occ_depth``, depth)
#: targets, training only.
DATA = DatasetConfig(cameras=CAMERAS, sweeps=0, boxes=False, augment=True, depth_downsample=16,
                     label_space=OCC3D_SPACE.name)  # fmt: skip

#: torchvision's ImageNet ResNet-50, the backbone initialisation of FlashOcc's code base.
IMAGENET = "torchvision:IMAGENET1K_V1"


def _paper_model(**changes) -> DirectionAwareOccConfig:
    """The single-frame model with the ImageNet backbone, with ``changes`` to its fields."""
    cfg = DirectionAwareOccConfig()
    return dataclasses.replace(cfg, image=dataclasses.replace(cfg.image, pretrained=IMAGENET), **changes)


def _height_grid(layers: int) -> dict:
    """The fields of a ``layers`` x 32 x 32 height grid over Occ3D's [-1, 5.4] m."""
    model = DirectionAwareOccConfig()
    step = (model.height_range[1] - model.height_range[0]) / layers
    return {"height_range": (model.height_range[0], model.height_range[1], step),
            "height_grid_size": (*model.height_grid_size[:2], layers),
            "height_net": dataclasses.replace(model.height_net, bins=layers)}  # fmt: skip


@preset("da_occ")
@reproduces(PAPER, "Table I, DA-Occ, single frame, R50 256 x 704, camera mask (section IV-C: no depth supervision)",
            "34.38 mIoU, Occ3D-nuScenes val")
def da_occ() -> Experiment:
    """DA-Occ, single frame, without depth supervision: 16 x 32 x 32 height volume, DAC decoders, R50 256 x 704.

    FlashOcc's 1x1 depth net (section IV-C), camera-aware HeightNet with two vertical DACs and its height BCE,
    256-channel BEV neck, fusion and head; ResNet-50 from ImageNet.
    """
    return Experiment("da_occ", _paper_model(), DATA, TRAIN)


@preset("da_occ")
@reproduces(PAPER, "Table I, DA-Occ, single frame, R50 256 x 704, camera mask, read with the method section's "
            "camera-aware DepthNet and its loss formula's 1.0 x depth BCE instead of section IV-C",
            "34.38 mIoU, Occ3D-nuScenes val")
def da_occ_depth() -> Experiment:
    """DA-Occ with depth supervision: da_occ with a camera-aware DepthNet and a 1.0 x depth BCE.

    BEVDepth's DepthNet (ASPP, 44 bins, 64 context channels), as the paper's figure and loss formula describe it.
    """
    model = _paper_model(depth_net=DepthNetConfig(bins=44, context_channels=64),
                         loss_weights=DAOccLossWeights(depth=1.0))  # fmt: skip
    return Experiment("da_occ", model, DATA, TRAIN)


@preset("da_occ")
@reproduces(PAPER, "Occ3D-nuScenes results, DA-Occ, single frame, R50 256 x 704, without the camera visibility mask",
            "31.31 mIoU, Occ3D-nuScenes val")
def da_occ_no_mask() -> Experiment:
    """da_occ trained without the camera visibility mask.

    Drop-free cross-entropy (20% of the free voxels) and scene-class affinities over all voxels.
    """
    model = _paper_model()
    return Experiment("da_occ", dataclasses.replace(model, occupancy=dataclasses.replace(model.occupancy,
                                                                                         use_mask=False)),
                      DATA, TRAIN)  # fmt: skip


@preset("da_occ")
@reproduces(PAPER, "Table II, height grid 4 x 32 x 32 (Z x X x Y) instead of 16 x 32 x 32",
            "1.5 mIoU below the 16 x 32 x 32 row (da_occ), Occ3D-nuScenes val (camera mask)")
def da_occ_height4() -> Experiment:
    """da_occ with a 4 x 32 x 32 height grid: 4 height bins of 1.6 m in HeightNet and the height volume."""
    return Experiment("da_occ", _paper_model(**_height_grid(4)), DATA, TRAIN)


@preset("da_occ")
@reproduces(PAPER, "Table III, without DAC in HeightNet and BEV",
            "1.8 mIoU below da_occ, Occ3D-nuScenes val (camera mask)")
def da_occ_no_dac() -> Experiment:
    """da_occ without the DACs in HeightNet and on the BEV (Table III).

    HeightNet's last two blocks are 3x3 BasicBlocks again and F_BEV' is the encoded BEV itself; the D_v on the
    height volume, which the table does not name, stays.
    """
    model = _paper_model()
    model = dataclasses.replace(model, height_net=dataclasses.replace(model.height_net, dac_blocks=0),
                                bev_horizontal_dac=False, bev_vertical_dac=False)  # fmt: skip
    return Experiment("da_occ", model, DATA, TRAIN)


@preset("da_occ")
@reproduces(PAPER, "Table III, DAC in HeightNet only (without the two BEV DACs)",
            "271.24 GFLOPs (276.59 less the two BEV DACs' 5.35); the text gives its cost, not its mIoU")
def da_occ_dac_height_only() -> Experiment:
    """da_occ without the two BEV DACs: HeightNet keeps its two vertical DACs, F_BEV' is the encoded BEV."""
    return Experiment("da_occ", _paper_model(bev_horizontal_dac=False, bev_vertical_dac=False), DATA, TRAIN)


def _temporal_model(temporal: TemporalConfig) -> DirectionAwareOccConfig:
    """da_occ_depth's model (the temporal rows are trained with depth supervision, section IV-C) with ``temporal``."""
    model = da_occ_depth().model
    return dataclasses.replace(model, temporal=temporal,
                               bev=dataclasses.replace(model.bev, in_channels=temporal.out_channels(64)))


@preset("da_occ")
@reproduces(PAPER, "Table I, DA-Occ with BEV-level temporal fusion, 1 history frame, R50 256 x 704, camera mask",
            "35.77 mIoU at 31.5 FPS, Occ3D-nuScenes val")
def da_occ_1f() -> Experiment:
    """DA-Occ with one history frame, fused as BEVDet4D does: F_bev of the earlier key frame (computed without
    gradient) through ``pre_process``, aligned by ego motion and concatenated with the current one into the BEV
    encoder (128 input channels).

    Depth-supervised like the paper's temporal models (camera-aware DepthNet, 1.0 x depth BCE); the height branch
    stays single-frame.
    """
    model = _temporal_model(TemporalConfig(history=1, fusion="concat"))
    return Experiment("da_occ", model, dataclasses.replace(DATA, history=1), TRAIN)


@preset("da_occ")
@reproduces(PAPER, "Table I, DA-Occ with BEV-level temporal fusion, 16 frames, R50 256 x 704, camera mask",
            "39.3 mIoU at 27.7 FPS, Occ3D-nuScenes val")
def da_occ_16f() -> Experiment:
    """DA-Occ with 16 history frames stacked, as the public 16-frame model of its code base stacks them (FlashOcc's
    ``panoptic-flashocc-r50-depth4d-longterm16f``, BEVDepth4D): F_bev of each of the 16 earlier key frames (computed
    without gradient) through ``pre_process``, aligned by ego motion and concatenated with the current one into the
    BEV encoder (17 x 64 = 1088 input channels). The paper's 16-frame row cites SparseOcc's fusion, which also reads
    every frame's features rather than a carried state. Depth-supervised as da_occ_1f.
    """
    model = _temporal_model(TemporalConfig(history=16, fusion="concat"))
    return Experiment("da_occ", model, dataclasses.replace(DATA, history=16), TRAIN)


@preset("da_occ")
def da_occ_16f_recurrent() -> Experiment:
    """da_occ_16f's long history at constant cost per frame, a variant of occkit's: a recurrent BEV state
    (VideoBEV-style, one BasicBlock on [F_bev, aligned state, valid mask]) carried from frame to frame instead of 16
    stacked frames.

    Trained as it runs, on streams: each scene's frames in time order, 4 streams per GPU, the state carried from
    step to step without gradient (SOLOFusion's streaming training); the state spans every earlier frame of the
    scene, the paper's 16 and more. Depth-supervised as da_occ_1f.
    """
    model = _temporal_model(TemporalConfig(fusion="recurrent", history=0, with_valid=True))
    return Experiment("da_occ", model, DATA, dataclasses.replace(TRAIN, sampler="streams"))


@preset("da_occ")
def da_occ_tiny() -> Experiment:
    """DA-Occ's architecture (da_occ's design, no depth supervision) scaled down for CPUs.

    ResNet-18 (one block per stage) C4/C5 at 128 x 352, FlashOcc's 1x1 depth net (22 bins, 16 context channels), a
    32-channel camera-aware HeightNet without ASPP, narrow BEV encoder; Occ3D output grid unchanged.
    """
    model = DirectionAwareOccConfig(
        image=ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), out_stages=(3, 4), norm_eval=False, neck="fpn",
                                 neck_channels=64),
        depth_range=(1.0, 45.0, 2.0),
        height_net=DepthNetConfig(in_channels=64, mid_channels=32, bins=16, context_channels=0, residual_blocks=2,
                                  dac_blocks=2, feature_height=8, aspp=False),
        bev=BevEncoderConfig(in_channels=16, strides=(2, 2, 2), channels=(32, 64, 128), blocks=(1, 1, 1),
                             neck_channels=32, neck_extra_upsample=2),
        fusion_channels=32,
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, class_balance=True),
    )  # fmt: skip
    return Experiment("da_occ", model, cpu_data(DATA), CPU_TRAIN)


@preset("da_occ")
def da_occ_tiny_temporal() -> Experiment:
    """da_occ_tiny with da_occ_16f_recurrent's BEV history, trained on streams of each scene's frames in order and
    streamed at inference; no depth supervision, so that against da_occ_tiny only the history differs."""
    model = dataclasses.replace(da_occ_tiny().model, temporal=TemporalConfig(fusion="recurrent", history=0,
                                                                             with_valid=True))
    return Experiment("da_occ", model, cpu_data(DATA), dataclasses.replace(CPU_TRAIN, sampler="streams"))


@preset("da_occ")
def da_occ_tiny_flow() -> Experiment:
    """da_occ_tiny with an occupancy flow head (two velocities per voxel, channel-to-height, L1 on the occupied
    voxels), trained on labels that carry flow (``data.flow``): the single-frame side of the flow comparison."""
    return with_flow_head(da_occ_tiny())


@preset("da_occ")
def da_occ_tiny_temporal_flow() -> Experiment:
    """da_occ_tiny_temporal with the flow head of da_occ_tiny_flow: its recurrent BEV history lets the head see
    motion, which a single frame shows only through poses and context."""
    return with_flow_head(da_occ_tiny_temporal())


