"""FlashOcc's zoo entries: the paper's rows, its ablations and the CPU-sized ``*_tiny`` versions, each a whole
experiment (model, data, schedule) registered by name."""

from __future__ import annotations

import dataclasses

from occkit.classes import DETECTION_CLASSES
from occkit.data.dataset import DatasetConfig
from occkit.experiment import CPU_TRAIN, Experiment, TrainConfig, cpu_data, reproduces
from occkit.label_space import OCC3D_SPACE
from occkit.models.bev_encoder import BevEncoderConfig
from occkit.models.flashocc import FlashOccConfig
from occkit.models.heads.center import CenterHeadConfig
from occkit.models.heads.occupancy import OccupancyHeadConfig
from occkit.models.image_encoder import ImageEncoderConfig
from occkit.models.temporal import TemporalConfig
from occkit.models.view_transform.lss import LSSConfig
from occkit.nuscenes import CAMERAS
from occkit.zoo.registry import preset
from occkit.zoo.variants import with_flow_head

PAPER = "FlashOcc (Yu et al., 2023), Table 2 and its code's README"
PANOPTIC_PAPER = "Panoptic-FlashOcc (Yu et al., 2024), its code's config panoptic-flashocc-r50-depth-tiny-pano.py"

#: FlashOcc's schedule (its configs): AdamW 1e-4, weight decay 0.01, clip 5, 24 epochs at a global batch of 16, mmcv's
#: step policy with ``step=[24]`` (constant after 200 warm-up steps from 0.001 of the rate), MEGVII EMA.
TRAIN = TrainConfig(epochs=24, batch_size=4, global_batch=16, lr=1e-4, weight_decay=0.01, grad_clip=5.0,
                    warmup_steps=200, warmup_ratio=0.001, lr_policy="step", lr_steps=(24,), ema_decay=0.999,
                    ema_ramp=2000.0, ema_initial_updates=10560, load_from="ckpts/bevdet-r50-cbgs.pth")  # fmt: skip

#: The paper's inputs: six cameras, no LiDAR.
DATA = DatasetConfig(cameras=CAMERAS, sweeps=-1, boxes=False, augment=True, label_space=OCC3D_SPACE.name)

#: torchvision's ImageNet ResNet-50 (mmcv's ``torchvision://resnet50``), under the BEVDet checkpoint FlashOcc loads.
IMAGENET = "torchvision:IMAGENET1K_V1"


def _paper_model() -> FlashOccConfig:
    """M0 as the reference builds it; its pooling rounds voxel indices towards zero as the reference's ``.long()``
    does, so that its checkpoints give the reference's outputs (tests/test_reference_parity_models.py)."""
    cfg = FlashOccConfig()
    return dataclasses.replace(cfg, image=dataclasses.replace(cfg.image, pretrained=IMAGENET),
                               lss=dataclasses.replace(cfg.lss, truncate_indices=True))  # fmt: skip


@preset("flashocc")
@reproduces(PAPER, "M0: FlashOcc (1f), R50 256 x 704, with BEVDet detection pretraining, camera mask",
            "31.95 mIoU, Occ3D-nuScenes val")
def flashocc_m0() -> Experiment:
    """FlashOcc M0: ResNet-50 C4/C5 + FPN at 256 x 704, 44 depth bins, 64 x 200 x 200 BEV, 128-channel C2H head;
    39.94 M parameters; starts from BEVDet's detection checkpoint (bevdet-r50-cbgs.pth)."""
    return Experiment("flashocc", _paper_model(), DATA, TRAIN)


@preset("flashocc")
@reproduces(PAPER, "M1: FlashOcc (1f), R50 256 x 704, with BEVDet detection pretraining, camera mask",
            "32.08 mIoU, Occ3D-nuScenes val")
def flashocc_m1() -> Experiment:
    """FlashOcc M1: M0 with 88 depth bins (0.5 m) and a 256-channel BEV neck and head; 44.74 M parameters."""
    cfg = _paper_model()
    model = dataclasses.replace(
        cfg,
        lss=dataclasses.replace(cfg.lss, depth_range=(1.0, 45.0, 0.5)),
        bev=dataclasses.replace(cfg.bev, neck_channels=256),
        occupancy=OccupancyHeadConfig(in_channels=256, hidden_channels=256),
    )
    return Experiment("flashocc", model, DATA, TRAIN)


@preset("flashocc")
def flashocc_m0_4d() -> Experiment:
    """FlashOcc M0 with BEVDet4D's history: one earlier key frame, each frame's LSS BEV through ``pre_process`` (one
    BasicBlock), the earlier one aligned by ego motion and concatenated into the BEV encoder (128 input channels).

    FlashOcc publishes its temporal models with BEVStereo4D's stereo depth (M2, 37.84 mIoU), which occkit does not
    implement; this row, M0 plus BEVDet4D's history without stereo, is not in the paper. The earlier frame runs
    without gradient and is padded with the current one at the start of a scene, as in BEVDet4D.
    """
    cfg = _paper_model()
    model = dataclasses.replace(cfg, temporal=TemporalConfig(history=1, fusion="concat"),
                                bev=dataclasses.replace(cfg.bev, in_channels=2 * cfg.bev.in_channels))  # fmt: skip
    return Experiment("flashocc", model, dataclasses.replace(DATA, history=1), TRAIN)


def _instance_head(in_channels: int, **changes: object) -> CenterHeadConfig:
    """Panoptic-FlashOcc's instance-centre head (its config's ``Centerness_Head``): one task of the 10 detection
    classes on the BEV encoder's output at 0.4 m cells (0.1 m x 4), 64 shared and branch channels; the heatmap and the
    centre's offset and height are trained (``task_specific_weight = [1, 1, 0, 0, 0]``: box size, yaw and velocity at
    zero weight); centres above 0.3 (its box coder's threshold), at most 500."""
    head = CenterHeadConfig(
        in_channels=in_channels, tasks=(DETECTION_CLASSES,), share_conv_channels=64, head_conv_channels=64,
        point_cloud_range=(-40.0, -40.0, -5.0, 40.0, 40.0, 3.0), voxel_size=(0.1, 0.1), out_size_factor=4,
        code_weights=(1.0, 1.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0), score_threshold=0.3, max_num=500,
        nms_types=("rotate",), circle_nms_radii=(4.0,), post_max_size=500,
        nms_scales=((1.0, 0.7, 0.7, 0.4, 0.55, 1.1, 1.0, 1.0, 1.5, 3.5),),
    )  # fmt: skip
    return dataclasses.replace(head, **changes)


#: What a panoptic entry loads beside the images: the boxes in the ego frame (the centre head's targets, mmdet3d's
#: valid flag) and the labels' instance ids (RayPQ's ground truth).
PANOPTIC_DATA = dataclasses.replace(DATA, boxes=True, box_frame="ego", valid_boxes_only=True, instances=True)


@preset("flashocc")
@reproduces(PANOPTIC_PAPER, "Panoptic-FlashOcc (1f), R50 256 x 704, depth supervision, no camera mask",
            "34.82 RayIoU, 12.89 RayPQ, Occ3D-nuScenes val")
def flashocc_pano() -> Experiment:
    """Panoptic-FlashOcc, single frame: FlashOcc M0 with the instance-centre head on its 128-channel BEV, LiDAR depth
    supervision of the depth bins (weight 1), class-balanced cross-entropy over every voxel (no camera mask), and
    voxels of thing classes assigned to the nearest centre of their class. The reference lifts with BEVDepth's
    camera-aware DepthNet and trains the occupancy with a sigmoid focal loss; this entry keeps FlashOcc's 1x1 depth
    net and occkit's drop-free cross-entropy (docs/reproducing.md)."""
    cfg = _paper_model()
    model = dataclasses.replace(
        cfg, depth_weight=1.0, instances=_instance_head(cfg.bev.neck_channels),
        occupancy=dataclasses.replace(cfg.occupancy, use_mask=False, class_balance=True),
    )  # fmt: skip
    data = dataclasses.replace(PANOPTIC_DATA, sweeps=0, depth_downsample=cfg.lss.feature_stride)
    # Its config starts from BEVDet4D-Depth's detection checkpoint.
    train = dataclasses.replace(TRAIN, load_from="ckpts/bevdet-r50-4d-depth-cbgs.pth")
    return Experiment("flashocc", model, data, train)


@preset("flashocc")
def flashocc_tiny() -> Experiment:
    """FlashOcc's architecture scaled down for CPUs: ResNet-18 (one block per stage) C4/C5 at 128 x 352, 22 depth
    bins, 16 context channels, narrow BEV encoder, and a Lovasz term beside the cross-entropy (as daocc_tiny); the
    Occ3D output grid is unchanged."""
    model = FlashOccConfig(
        image=ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), out_stages=(3, 4), norm_eval=False, neck="fpn",
                                 neck_channels=64),
        lss=LSSConfig(image_size=(128, 352), depth_range=(1.0, 45.0, 2.0), in_channels=64, context_channels=16),
        bev=BevEncoderConfig(in_channels=16, strides=(2, 2, 2), channels=(32, 64, 128), blocks=(1, 1, 1),
                             neck_channels=32, neck_extra_upsample=2),
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, class_balance=True, lovasz_weight=1.0),
    )  # fmt: skip
    return Experiment("flashocc", model, cpu_data(DATA), CPU_TRAIN)


@preset("flashocc")
def flashocc_tiny_flow() -> Experiment:
    """flashocc_tiny with an occupancy flow head (two velocities per voxel, channel-to-height, L1 on the occupied
    voxels), trained on labels that carry flow (``data.flow``, which the synthetic world writes): the CVPR 2024
    occupancy-and-flow task at CPU size, scored with mAVE and OccScore."""
    return with_flow_head(flashocc_tiny())


@preset("flashocc")
def flashocc_tiny_pano() -> Experiment:
    """flashocc_tiny with Panoptic-FlashOcc's instance-centre head (16 shared and branch channels, the heatmap's prior
    initialisation of the short schedules): panoptic occupancy at CPU size, scored with RayPQ (``occkit eval
    --rayiou``) against the synthetic world's exact instance labels."""
    tiny = flashocc_tiny()
    model = dataclasses.replace(tiny.model, instances=_instance_head(tiny.model.bev.neck_channels,
                                                                     share_conv_channels=16, head_conv_channels=16,
                                                                     heatmap_init_std=0.01))  # fmt: skip
    return Experiment("flashocc", model, cpu_data(PANOPTIC_DATA), CPU_TRAIN)


