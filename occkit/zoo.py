"""Model zoo: names -> configs -> models, plain Python, no registry beyond this table.

    >>> from occkit import zoo
    >>> zoo.names()[:3]
    ['da_occ', 'da_occ_tiny', 'daocc']
    >>> model = zoo.build("daocc_tiny")

Every entry has a YAML twin in ``configs/NAME.yaml``: the whole experiment (``architecture``, ``model``, ``data``,
``train``), written by :func:`config_yaml` and kept equal to :func:`experiment` by a test, so a config file read with
:func:`load_experiment` and a name given to :func:`build` mean the same model.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from torch import nn

from occkit import experiment as _experiment
from occkit.config import ConfigError
from occkit.experiment import Experiment, TrainConfig, experiment_yaml
from occkit.label_space import OCC3D_SPACE, SURROUNDOCC_SPACE

__all__ = ["names", "description", "model_config", "experiment", "build", "build_from_config", "config_yaml",
           "config_class", "experiment_from_dict", "load_experiment", "ARCHITECTURES"]


def _daocc_classes() -> tuple[type, type]:
    from occkit.models.daocc import DAOcc, DAOccConfig

    return DAOccConfig, DAOcc


def _flashocc_classes() -> tuple[type, type]:
    from occkit.models.flashocc import FlashOcc, FlashOccConfig

    return FlashOccConfig, FlashOcc


def _da_occ_classes() -> tuple[type, type]:
    from occkit.models.da_occ import DirectionAwareOcc, DirectionAwareOccConfig

    return DirectionAwareOccConfig, DirectionAwareOcc


#: architecture name -> () -> (config class, model class); imported lazily so ``occkit --help`` stays light.
ARCHITECTURES: dict[str, Callable[[], tuple[type, type]]] = {
    "daocc": _daocc_classes,
    "flashocc": _flashocc_classes,
    "da_occ": _da_occ_classes,
}


# ------------------------------------------------------------------------------------------------ DAOcc entries
def _daocc() -> Any:
    """DAOcc, Occ3D-nuScenes paper setting: ResNet-50 at 256 x 704, 10 LiDAR sweeps, camera mask, 53.8 mIoU."""
    config_class, _ = _daocc_classes()
    return config_class()


def _daocc_surroundocc() -> Any:
    """DAOcc on SurroundOcc: LiDAR-frame +-50 m grid at 0.5 m, 17 classes (0 = empty), drop-free CE, no mask."""
    from occkit.models.heads.occupancy import OccupancyHeadConfig
    from occkit.models.range_extension import RangeExtensionConfig

    space = SURROUNDOCC_SPACE
    return dataclasses.replace(
        _daocc(),
        occ_range=space.grid.point_cloud_range,
        occ_voxel_size=space.grid.voxel_size,
        range_extension=RangeExtensionConfig(label_frame=space.frame),
        occupancy=OccupancyHeadConfig(num_classes=space.num_classes, free_index=space.free_index, use_mask=False),
    )


def _daocc_lidar() -> Any:
    """DAOcc without its camera branch: LiDAR only, asked for by the reference's users."""
    return dataclasses.replace(_daocc(), image=None)


def _daocc_tiny() -> Any:
    """DAOcc's architecture scaled down for CPUs: ResNet-18 (one block per stage), +-43.2 m at 0.15 m voxels with a
    stride-4 sparse encoder (a 144 x 144 BEV of 0.6 m cells, the paper's cell size), narrow channels, and a Lovasz
    term beside the cross-entropy; the Occ3D output grid is unchanged."""
    from occkit.models.bev_encoder import BevEncoderConfig
    from occkit.models.heads.center import CenterHeadConfig
    from occkit.models.heads.occupancy import OccupancyHeadConfig
    from occkit.models.image_encoder import ImageEncoderConfig
    from occkit.models.lidar_encoder import LidarEncoderConfig
    from occkit.models.range_extension import RangeExtensionConfig
    from occkit.models.view_transform.projection import ProjectionConfig

    extent = 43.2
    lidar_range = (-extent, -extent, -5.0, extent, extent, 3.0)
    config_class, _ = _daocc_classes()
    return config_class(
        image=ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), neck_channels=64),
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
        detection=CenterHeadConfig(
            in_channels=64, share_conv_channels=16, head_conv_channels=8, point_cloud_range=lidar_range,
            voxel_size=(0.15, 0.15), out_size_factor=4,
        ),
    )  # fmt: skip


def _daocc_surroundocc_tiny() -> Any:
    """daocc_tiny on SurroundOcc's labels: the LiDAR-frame +-50 m grid at 0.5 m with 17 classes (0 = empty), a
    +-50.4 m BEV of 0.6 m cells (168 x 168) so that the grid lies inside it, drop-free CE and Lovasz, no mask."""
    from occkit.models.heads.occupancy import OccupancyHeadConfig

    cfg, space = _daocc_tiny(), SURROUNDOCC_SPACE
    extent = 50.4
    lidar_range = (-extent, -extent, -5.0, extent, extent, 3.0)
    return dataclasses.replace(
        cfg,
        occ_range=space.grid.point_cloud_range,
        occ_voxel_size=space.grid.voxel_size,
        view=dataclasses.replace(cfg.view, point_cloud_range=lidar_range, grid_size=(168, 168, 4)),
        lidar=dataclasses.replace(cfg.lidar, point_cloud_range=lidar_range),
        range_extension=dataclasses.replace(cfg.range_extension, bev_range=(-extent, -extent, extent, extent),
                                            label_frame=space.frame),
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, num_classes=space.num_classes,
                                      free_index=space.free_index, use_mask=False, lovasz_weight=1.0),
        detection=dataclasses.replace(cfg.detection, point_cloud_range=lidar_range),
    )  # fmt: skip


def _flashocc_m0() -> Any:
    """FlashOcc M0: ResNet-50 C4/C5 + FPN at 256 x 704, 44 depth bins, 64 x 200 x 200 BEV, 128-channel C2H head;
    31.95 mIoU, 39.94 M parameters."""
    config_class, _ = _flashocc_classes()
    return config_class()


def _flashocc_m1() -> Any:
    """FlashOcc M1: M0 with 88 depth bins (0.5 m) and a 256-channel BEV neck and head; 32.08 mIoU, 44.74 M
    parameters."""
    from occkit.models.heads.occupancy import OccupancyHeadConfig
    from occkit.models.view_transform.lss import LSSConfig

    cfg = _flashocc_m0()
    return dataclasses.replace(
        cfg,
        lss=LSSConfig(depth_range=(1.0, 45.0, 0.5)),
        bev=dataclasses.replace(cfg.bev, neck_channels=256),
        occupancy=OccupancyHeadConfig(in_channels=256, hidden_channels=256),
    )


def _flashocc_tiny() -> Any:
    """FlashOcc's architecture scaled down for CPUs: ResNet-18 (one block per stage) C4/C5 at 128 x 352, 22 depth
    bins, 16 context channels, narrow BEV encoder, and a Lovasz term beside the cross-entropy (as daocc_tiny); the
    Occ3D output grid is unchanged."""
    from occkit.models.bev_encoder import BevEncoderConfig
    from occkit.models.heads.occupancy import OccupancyHeadConfig
    from occkit.models.image_encoder import ImageEncoderConfig
    from occkit.models.view_transform.lss import LSSConfig

    config_class, _ = _flashocc_classes()
    return config_class(
        image=ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), out_stages=(3, 4), norm_eval=False, neck="fpn",
                                 neck_channels=64),
        lss=LSSConfig(image_size=(128, 352), depth_range=(1.0, 45.0, 2.0), in_channels=64, context_channels=16),
        bev=BevEncoderConfig(in_channels=16, strides=(2, 2, 2), channels=(32, 64, 128), blocks=(1, 1, 1),
                             neck_channels=32, neck_extra_upsample=2),
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, class_balance=True, lovasz_weight=1.0),
    )  # fmt: skip


# ---------------------------------------------------------------------------------------------- DA-Occ entries
def _da_occ() -> Any:
    """DA-Occ, single frame: ResNet-50 at 256 x 704, camera-aware DepthNet and HeightNet (two vertical DACs),
    depth-score BEV plus a 16 x 32 x 32 height-score volume, DAC decoders; 34.38 mIoU in the paper."""
    config_class, _ = _da_occ_classes()
    return config_class()


def _da_occ_tiny() -> Any:
    """DA-Occ's architecture scaled down for CPUs: ResNet-18 (one block per stage) C4/C5 at 128 x 352, 22 depth
    bins, 32-channel depth and height nets without ASPP, narrow BEV encoder; Occ3D output grid unchanged."""
    from occkit.models.bev_encoder import BevEncoderConfig
    from occkit.models.heads.depth import DepthNetConfig
    from occkit.models.heads.occupancy import OccupancyHeadConfig
    from occkit.models.image_encoder import ImageEncoderConfig

    config_class, _ = _da_occ_classes()
    net = {"in_channels": 64, "mid_channels": 32, "residual_blocks": 2, "feature_height": 8, "aspp": False}
    return config_class(
        image=ImageEncoderConfig(depth=18, blocks=(1, 1, 1, 1), out_stages=(3, 4), norm_eval=False, neck="fpn",
                                 neck_channels=64),
        depth_range=(1.0, 45.0, 2.0),
        depth_net=DepthNetConfig(bins=22, context_channels=16, **net),
        height_net=DepthNetConfig(bins=16, context_channels=0, dac_blocks=2, **net),
        bev=BevEncoderConfig(in_channels=16, strides=(2, 2, 2), channels=(32, 64, 128), blocks=(1, 1, 1),
                             neck_channels=32, neck_extra_upsample=2),
        fusion_channels=32,
        occupancy=OccupancyHeadConfig(in_channels=32, hidden_channels=32, class_balance=True),
    )  # fmt: skip


# ----------------------------------------------------------------------- data and training settings per family
def _data(family: str, tiny: bool) -> Any:
    """Training-split dataset settings: the paper's inputs, or the CPU demo's small ones for tiny entries."""
    from occkit.data.dataset import DatasetConfig
    from occkit.data.transforms import ImageAugConfig
    from occkit.nuscenes import CAMERAS

    sweeps = {"daocc": 9, "daocc_lidar": 9, "daocc_surroundocc": 9, "flashocc": -1, "da_occ": 0}[family]
    cameras = () if family == "daocc_lidar" else CAMERAS
    space = (SURROUNDOCC_SPACE if family == "daocc_surroundocc" else OCC3D_SPACE).name
    if not tiny:
        return DatasetConfig(cameras=cameras, sweeps=sweeps, boxes=family.startswith("daocc"), augment=True,
                             depth_downsample=16 if family == "da_occ" else 0, label_space=space)  # fmt: skip
    return DatasetConfig(
        root="data/demo", cameras=CAMERAS,
        sweeps=min(sweeps, 4), boxes=family.startswith("daocc"), augment=True,
        image_aug=ImageAugConfig(final_size=(128, 352), rotate_deg=(0.0, 0.0)),
        depth_downsample=16 if family == "da_occ" else 0, label_space=space,
    )  # fmt: skip


def _train(family: str, tiny: bool) -> TrainConfig:
    """The papers' schedules (DAOcc: AdamW 2e-4, clip 35, fp16; FlashOcc: 1e-4, clip 5; DA-Occ: 1e-4, wd 0.05),
    or a short CPU schedule for tiny entries."""

    if tiny:
        return TrainConfig(epochs=5, batch_size=1, lr=2e-3, warmup_steps=50, grad_clip=35.0, ema_decay=0.0,
                           workers=1, val_every=0, log_every=10)  # fmt: skip
    if family.startswith("daocc"):
        return TrainConfig(epochs=24, batch_size=4, lr=2e-4, grad_clip=35.0, precision="fp16")
    if family == "flashocc":
        return TrainConfig(epochs=24, batch_size=4, lr=1e-4, grad_clip=5.0, warmup_steps=200, warmup_ratio=0.001)
    return TrainConfig(epochs=24, batch_size=4, lr=1e-4, weight_decay=0.05, grad_clip=5.0)


_ZOO: dict[str, tuple[str, Callable[[], Any], str]] = {
    # name: (architecture, model factory, data/training family)
    "daocc": ("daocc", _daocc, "daocc"),
    "daocc_lidar": ("daocc", _daocc_lidar, "daocc_lidar"),
    "daocc_surroundocc": ("daocc", _daocc_surroundocc, "daocc_surroundocc"),
    "daocc_surroundocc_tiny": ("daocc", _daocc_surroundocc_tiny, "daocc_surroundocc"),
    "daocc_tiny": ("daocc", _daocc_tiny, "daocc"),
    "flashocc_m0": ("flashocc", _flashocc_m0, "flashocc"),
    "flashocc_m1": ("flashocc", _flashocc_m1, "flashocc"),
    "flashocc_tiny": ("flashocc", _flashocc_tiny, "flashocc"),
    "da_occ": ("da_occ", _da_occ, "da_occ"),
    "da_occ_tiny": ("da_occ", _da_occ_tiny, "da_occ"),
}


def names() -> list[str]:
    """Zoo entry names, sorted."""
    return sorted(_ZOO)


def _entry(name: str) -> tuple[str, Callable[[], Any], str]:
    if name not in _ZOO:
        raise KeyError(f"unknown model {name!r}; the zoo has: {', '.join(names())}")
    return _ZOO[name]


def description(name: str) -> str:
    """One paragraph on what the entry is."""
    return " ".join((_entry(name)[1].__doc__ or "").split())


def model_config(name: str) -> tuple[str, Any]:
    """``(architecture, config)`` of a zoo entry."""
    architecture, factory, _ = _entry(name)
    return architecture, factory()


def experiment(name: str) -> Experiment:
    """The full experiment (model, data, training) of a zoo entry, as ``configs/NAME.yaml`` holds it."""
    architecture, factory, family = _entry(name)
    tiny = name.endswith("_tiny")
    return Experiment(architecture, factory(), _data(family, tiny), _train(family, tiny))


def config_class(architecture: str) -> type:
    """The model config dataclass of ``architecture``."""
    if architecture not in ARCHITECTURES:
        raise ConfigError(f"architecture: unknown {architecture!r}; known: {', '.join(sorted(ARCHITECTURES))}")
    return ARCHITECTURES[architecture]()[0]


def experiment_from_dict(data: Any, where: str = "experiment", overrides: Sequence[str] = ()) -> Experiment:
    """Check and build an experiment of any zoo architecture from plain data (a checkpoint's, a YAML file's);
    ``overrides`` are ``section.key=value`` strings. Errors name ``where`` and the key."""
    classes = {name: classes()[0] for name, classes in ARCHITECTURES.items()}
    return _experiment.experiment_from_dict(data, classes, where, overrides)


def load_experiment(source: str | Path, overrides: Sequence[str] = ()) -> Experiment:
    """The experiment of a YAML file, or of the zoo entry of that name when no such file exists, with overrides.

    Raises:
        ConfigError: the file or an override is invalid (the message names the file and the key).
        FileNotFoundError: neither a file nor a zoo name.
    """
    path = Path(source)
    if not path.exists() and str(source) in _ZOO:
        return experiment_from_dict(experiment(str(source)).to_dict(), f"zoo entry {source}", overrides)
    if not path.exists():
        raise FileNotFoundError(f"config {source} does not exist (zoo names: {', '.join(names())})")
    return experiment_from_dict(_experiment.read_experiment_file(path), str(path), overrides)


def build_from_config(architecture: str, cfg: Any) -> nn.Module:
    """The model of ``architecture`` built from ``cfg``."""
    config_class(architecture)  # an unknown name is a ConfigError
    _, model_class = ARCHITECTURES[architecture]()
    return model_class(cfg)


def build(name: str) -> nn.Module:
    """A freshly initialised model of the zoo entry ``name``."""
    return build_from_config(*model_config(name))


def config_yaml(name: str) -> str:
    """The text of ``configs/NAME.yaml``: a description, then the commented experiment."""
    header = f"# {name}: {description(name)}\n# occkit train --config configs/{name}.yaml --out runs/{name}"
    return experiment_yaml(experiment(name), header)
