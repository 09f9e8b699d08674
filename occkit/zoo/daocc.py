"""DAOcc's zoo entries: the paper's rows, its ablations and the CPU-sized ``*_tiny`` versions, each a whole
experiment (model, data, schedule) registered by name."""

from __future__ import annotations

import dataclasses

from occkit.data.dataset import DatasetConfig
from occkit.experiment import CPU_TRAIN, Experiment, TrainConfig, cpu_data, reproduces
from occkit.label_space import OCC3D_SPACE, SURROUNDOCC_SPACE, LabelSpace
from occkit.models.bev_encoder import BevEncoderConfig
from occkit.models.daocc import DAOccConfig, with_bev_extent
from occkit.models.heads.center import CenterHeadConfig
from occkit.models.heads.occupancy import OccupancyHeadConfig
from occkit.models.image_encoder import ImageEncoderConfig
from occkit.models.lidar_encoder import LidarEncoderConfig
from occkit.models.range_extension import RangeExtensionConfig
from occkit.models.view_transform.projection import ProjectionConfig
from occkit.nuscenes import CAMERAS
from occkit.zoo.registry import preset
from occkit.zoo.variants import in_openocc, with_flow_head

PAPER = "DAOcc (Yang et al., TCSVT 2025)"

#: ResNet-50 pretrained on nuImages (mmdetection3d's HTC R50, COCO then nuImages), which the reference's training
#: command passes for the backbone (its docs/run.md); its configs name torchvision's ImageNet file as a fallback.
NUIMAGES_R50 = ("https://download.openmmlab.com/mmdetection3d/v0.1.0_models/nuimages_semseg/"
                "htc_r50_fpn_coco-20e_20e_nuim/htc_r50_fpn_coco-20e_20e_nuim_20201008_211415-d6c60a2c.pth")

#: DAOcc's schedule (its configs, 8 GPUs x 4): AdamW 2e-4, weight decay 0.01, clip 35, fp16, 6 epochs of CBGS with a
#: per-epoch cosine after 500 warm-up steps from a third of the rate, MEGVII EMA ramped from 10560 updates.
TRAIN = TrainConfig(epochs=6, batch_size=4, global_batch=32, sampler="cbgs", lr=2e-4, weight_decay=0.01,
                    grad_clip=35.0, precision="fp16", warmup_steps=500, warmup_ratio=1.0 / 3.0, lr_policy="cosine",
                    lr_by_epoch=True, min_lr_ratio=1e-3, ema_decay=0.999, ema_ramp=2000.0,
                    ema_initial_updates=10560, val_every=2)  # fmt: skip


def _data(cameras: tuple[str, ...] = CAMERAS, space: LabelSpace = OCC3D_SPACE) -> DatasetConfig:
    """The paper's inputs: 10 LiDAR sweeps (9 before the key frame) and the boxes of the detection head, only those
    with LiDAR or radar points (mmdet3d's use_valid_flag)."""
    return DatasetConfig(cameras=cameras, sweeps=9, boxes=True, augment=True, label_space=space.name,
                         valid_boxes_only=True)  # fmt: skip


def _paper_model() -> DAOccConfig:
    """The paper's model with the nuImages backbone."""
    return dataclasses.replace(DAOccConfig(), image=dataclasses.replace(DAOccConfig().image, pretrained=NUIMAGES_R50))


@preset("daocc")
@reproduces(PAPER, "Table I, DAOcc, R50 256 x 704, camera + LiDAR, camera mask", "53.82 mIoU, Occ3D-nuScenes val")
def daocc() -> Experiment:
    """DAOcc, Occ3D-nuScenes paper setting: ResNet-50 at 256 x 704, 10 LiDAR sweeps, camera mask."""
    return Experiment("daocc", _paper_model(), _data(), TRAIN)


@preset("daocc")
@reproduces(PAPER, "RayIoU comparison, DAOcc trained without the camera mask", "48.2 RayIoU, Occ3D-nuScenes val")
def daocc_no_mask() -> Experiment:
    """DAOcc trained without the camera mask (drop-free cross-entropy over all voxels), scored by RayIoU."""
    model = _paper_model()
    return Experiment("daocc", dataclasses.replace(model, occupancy=dataclasses.replace(model.occupancy,
                                                                                        use_mask=False)),
                      _data(), TRAIN)  # fmt: skip


@preset("daocc")
@reproduces(PAPER, "Table I note, DAOcc trained 24 epochs without CBGS", "53.39 mIoU, Occ3D-nuScenes val")
def daocc_24e() -> Experiment:
    """DAOcc with 24 epochs of plain random order instead of 6 epochs of CBGS."""
    return Experiment("daocc", _paper_model(), _data(), dataclasses.replace(TRAIN, epochs=24, sampler="random"))


@preset("daocc")
@reproduces(PAPER, "ablation, without the 3D detection head",
            "1.56 mIoU below DAOcc at the same schedule, Occ3D-nuScenes val")
def daocc_no_detection() -> Experiment:
    """DAOcc without its auxiliary detection head (the detection-assistance ablation)."""
    return Experiment("daocc", dataclasses.replace(_paper_model(), detection=None),
                      dataclasses.replace(_data(), boxes=False), TRAIN)  # fmt: skip


@preset("daocc")
@reproduces(PAPER, "ablation, without the BEV view range extension (BEV range +-40.8 m instead of +-54 m)",
            "0.5 mIoU below DAOcc at the same schedule, Occ3D-nuScenes val")
def daocc_no_range_extension() -> Experiment:
    """DAOcc whose LiDAR, projection and detection range just covers the +-40 m Occ3D grid (136 x 136 BEV cells of
    0.6 m, the paper's cell size) instead of extending to +-54 m."""
    return Experiment("daocc", with_bev_extent(_paper_model(), 40.8), _data(), TRAIN)


@preset("daocc")
@reproduces(PAPER, "SurroundOcc benchmark, DAOcc R50 256 x 704", "45.0 IoU, 30.5 mIoU, SurroundOcc nuScenes val")
def daocc_surroundocc() -> Experiment:
    """DAOcc on SurroundOcc: LiDAR-frame +-50 m grid at 0.5 m, 17 classes (0 = empty), drop-free CE, no mask, no
    image resize or rotation (the reference's SurroundOcc config)."""
    space = SURROUNDOCC_SPACE
    model = dataclasses.replace(
        _paper_model(),
        occ_range=space.grid.point_cloud_range,
        occ_voxel_size=space.grid.voxel_size,
        range_extension=RangeExtensionConfig(label_frame=space.frame),
        occupancy=OccupancyHeadConfig(num_classes=space.num_classes, free_index=space.free_index, use_mask=False),
    )
    data = _data(space=space)
    data = dataclasses.replace(data, image_aug=dataclasses.replace(data.image_aug, resize_range=(0.0, 0.0),
                                                                   rotate_deg=(0.0, 0.0)))  # fmt: skip
    return Experiment("daocc", model, data, TRAIN)


@preset("daocc")
def daocc_lidar() -> Experiment:
    """DAOcc without its camera branch: LiDAR only, asked for by the reference's users (no paper row)."""
    return Experiment("daocc", dataclasses.replace(DAOccConfig(), image=None), _data(cameras=()), TRAIN)


@preset("daocc")
def daocc_tiny() -> Experiment:
    """DAOcc's architecture scaled down for CPUs: ResNet-18 (one block per stage), +-43.2 m at 0.15 m voxels with a
    stride-4 sparse encoder (a 144 x 144 BEV of 0.6 m cells, the paper's cell size), narrow channels, a Lovasz
    term beside the cross-entropy, and the detection heatmap's prior initialisation; the Occ3D output grid is
    unchanged."""
    extent = 43.2
    lidar_range = (-extent, -extent, -5.0, extent, extent, 3.0)
    model = DAOccConfig(
        image=ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), norm_eval=False, neck_channels=64),
        view=ProjectionConfig(point_cloud_range=lidar_range, grid_size=(144, 144, 4), in_channels=64, out_channels=16),
        lidar=LidarEncoderConfig(
            point_cloud_range=lidar_range,
            voxel_size=(0.15, 0.15, 0.2),
            max_voxels_train=60000,
            max_voxels_test=80000,
            base_channels=8,
            encoder_channels=((8, 8, 16), (16, 16, 32), (32, 32)),
            downsample_paddings=((1, 1, 1), (1, 1, 1)),
            output_channels=16,
        ),
        fusion_channels=32,
        bev=BevEncoderConfig(in_channels=32, blocks=(1, 1, 1), strides=(1, 2, 2), channels=(32, 64, 128),
                             neck_channels=64),
        range_extension=RangeExtensionConfig(bev_range=(-extent, -extent, extent, extent), in_channels=64,
                                             out_channels=32),
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, class_balance=True, lovasz_weight=1.0),
        # RetinaNet's prior initialisation of the heatmap output: with mmdet3d's Kaiming weights the first steps'
        # focal loss is in the thousands, and in a schedule of a few hundred steps Adam's memory of those gradients
        # keeps the shared BEV from learning occupancy (measured in docs/training.md).
        detection=CenterHeadConfig(
            in_channels=64, share_conv_channels=16, head_conv_channels=8, point_cloud_range=lidar_range,
            voxel_size=(0.15, 0.15), out_size_factor=4, heatmap_init_std=0.01,
        ),
    )  # fmt: skip
    return Experiment("daocc", model, cpu_data(_data()), CPU_TRAIN)


@preset("daocc")
def daocc_surroundocc_tiny() -> Experiment:
    """daocc_tiny on SurroundOcc's labels: the LiDAR-frame +-50 m grid at 0.5 m with 17 classes (0 = empty), a
    +-50.4 m BEV of 0.6 m cells (168 x 168) so that the grid lies inside it, drop-free CE and Lovasz, no mask."""
    cfg, space = with_bev_extent(daocc_tiny().model, 50.4), SURROUNDOCC_SPACE
    model = dataclasses.replace(
        cfg,
        occ_range=space.grid.point_cloud_range,
        occ_voxel_size=space.grid.voxel_size,
        range_extension=dataclasses.replace(cfg.range_extension, label_frame=space.frame),
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, num_classes=space.num_classes,
                                      free_index=space.free_index, use_mask=False, lovasz_weight=1.0),
    )  # fmt: skip
    return Experiment("daocc", model, cpu_data(_data(space=space)), CPU_TRAIN)


@preset("daocc")
def daocc_tiny_flow() -> Experiment:
    """daocc_tiny with an occupancy flow head (two velocities per voxel, channel-to-height on the range-extended BEV,
    L1 on the occupied voxels), trained on labels that carry flow (``data.flow``). The head also reads the LiDAR motion
    input: the key frame and its 4 sweeps, one BEV channel each, where a moving object shows its motion within one
    sample (``data.sweeps = 0`` leaves the key frame alone)."""
    return with_flow_head(daocc_tiny(), motion=True)


@preset("daocc")
def daocc_tiny_flow_openocc() -> Experiment:
    """daocc_tiny_flow on OpenOcc v2's labels (``occkit sim --openocc`` writes them beside Occ3D's): 17 classes with
    free = 16, no visibility mask, scored as the CVPR 2024 challenge scores them (RayIoU, mAVE, OccScore)."""
    return in_openocc(daocc_tiny_flow())


