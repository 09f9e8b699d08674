"""Label spaces: what an occupancy benchmark's ground truth is, in one object.

A label space names everything that depends on which benchmark the labels come from: the voxel grid, the frame the
labels live in, the taxonomy (classes, the free / empty id), where and how label files are read, and how predictions
are scored. An experiment chooses one (``data.label_space``); the dataset, the occupancy head's classes, the metrics,
``occkit eval`` / ``eval-preds`` / ``predict`` / ``viz`` and the demo all take it from there.

========  ==================================  ===================================  ===============================
          ``occ3d`` (Occ3D-nuScenes)          ``surroundocc`` (SurroundOcc)        ``openocc`` (OpenOcc v2)
========  ==================================  ===================================  ===============================
grid      +-40 m, -1..5.4 m, 0.4 m:           +-50 m, -5..3 m, 0.5 m: 200x200x16   Occ3D's
          200x200x16
frame     ego at the LiDAR key-frame time     LiDAR (LIDAR_TOP) of the key frame   Occ3D's
classes   18: 0..16 semantic, 17 = free       17: 0 = empty, 1..16 semantic        17: 0..15 semantic (no
                                                                                   ``others``), 16 = free
files     ``gts/<scene>/<token>/labels.npz``  ``surroundocc/samples/<LiDAR         ``openocc_v2/<scene>/<token>/
          dense semantics + camera/LiDAR      file>.npy``: sparse ``(N, 4)``       labels.npz``: dense semantics
          visibility masks                    x, y, z, class rows (0 = noise)      and flow, no visibility mask
protocol  mIoU / IoU under the camera mask    IoU / mIoU on every voxel (no mask)  RayIoU, mAVE and OccScore (the
          (or LiDAR / none) and RayIoU        RayIoU is not defined                CVPR 2024 challenge); mIoU on
                                                                                   every voxel
========  ==================================  ===================================  ===============================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from occkit.classes import OCC3D, OPENOCC, SURROUNDOCC, Taxonomy
from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid

__all__ = ["LabelSpace", "OCC3D_SPACE", "SURROUNDOCC_SPACE", "OPENOCC_SPACE", "LABEL_SPACES", "label_space"]


@dataclass(frozen=True)
class LabelSpace:
    """One benchmark's ground truth: grid, frame, taxonomy, label files and evaluation protocol."""

    name: str
    """Identifier used in configs and checkpoints: ``occ3d``, ``surroundocc`` or ``openocc``."""
    title: str
    """The benchmark's name as papers print it, for reports."""
    grid: VoxelGrid
    """The voxel grid of the labels (and of the occupancy head's output)."""
    frame: Literal["ego", "lidar"]
    """The frame the grid is placed in: the ego frame at the key-frame LiDAR time, or the LiDAR frame."""
    taxonomy: Taxonomy
    """Class names, the free / empty id and colours."""
    label_folder: str
    """Folder under the dataset root that holds the label files (``data.label_root`` can point elsewhere)."""
    layout: Literal["token_tree", "lidar_files"]
    """How the label files are named: ``<scene>/<token>/labels.npz`` (a tree a folder listing pairs with sample
    tokens), or after each key frame's LiDAR file (pairing them needs the dataset's tables)."""
    masks: tuple[str, ...]
    """Visibility masks the label files carry and the protocol can apply (``camera``, ``lidar``)."""
    default_mask: str | None
    """The mask the benchmark scores under (None: every voxel)."""
    rayiou: bool
    """Whether RayIoU is defined for it (it needs Occ3D's ego-frame grid with a free class)."""

    @property
    def num_classes(self) -> int:
        return self.taxonomy.num_classes

    @property
    def free_index(self) -> int:
        """The free (Occ3D) or empty (SurroundOcc) class id."""
        return self.taxonomy.empty_index

    @property
    def ignore_index(self) -> int:
        return self.taxonomy.ignore_index

    @property
    def semantic_ids(self) -> tuple[int, ...]:
        """The classes mIoU averages: every id but free / empty."""
        return self.taxonomy.semantic_ids

    def check_mask(self, mask: str | None) -> str | None:
        """``mask`` if the protocol can apply it, else ValueError naming the label space."""
        if mask is not None and mask not in self.masks:
            allowed = ", ".join(self.masks) if self.masks else "none (its labels carry no visibility mask)"
            raise ValueError(f"{self.name} labels cannot be scored under the {mask} mask; masks: {allowed}")
        return mask


OCC3D_SPACE = LabelSpace(name="occ3d", title="Occ3D-nuScenes", grid=OCC3D_GRID, frame="ego", taxonomy=OCC3D,
                         label_folder="gts", layout="token_tree", masks=("camera", "lidar"), default_mask="camera",
                         rayiou=True)  # fmt: skip
SURROUNDOCC_SPACE = LabelSpace(name="surroundocc", title="SurroundOcc-nuScenes", grid=SURROUNDOCC_GRID, frame="lidar",
                               taxonomy=SURROUNDOCC, label_folder="surroundocc", layout="lidar_files", masks=(),
                               default_mask=None, rayiou=False)  # fmt: skip
OPENOCC_SPACE = LabelSpace(name="openocc", title="OpenOcc v2 (nuScenes)", grid=OCC3D_GRID, frame="ego",
                           taxonomy=OPENOCC, label_folder="openocc_v2", layout="token_tree", masks=(),
                           default_mask=None, rayiou=True)  # fmt: skip
LABEL_SPACES: dict[str, LabelSpace] = {
    space.name: space for space in (OCC3D_SPACE, SURROUNDOCC_SPACE, OPENOCC_SPACE)
}


def label_space(name: str | LabelSpace) -> LabelSpace:
    """The label space called ``name`` (a LabelSpace passes through); ValueError lists the known ones."""
    if isinstance(name, LabelSpace):
        return name
    try:
        return LABEL_SPACES[name]
    except KeyError:
        raise ValueError(f"unknown label space {name!r}; known: {', '.join(LABEL_SPACES)}") from None
