"""Label spaces: what an occupancy benchmark's ground truth is, in one object.

A label space names everything that depends on which benchmark the labels come from: the voxel grid, the frame the
labels live in, the taxonomy (classes, the free / empty id), where and how label files are read, and how predictions
are scored. An experiment chooses one (``data.label_space``); the dataset, the occupancy head's classes, the metrics,
``occkit eval`` / ``eval-preds`` / ``predict`` / ``viz`` and the demo all take it from there.

========================  ==================================  ===========================================
                          ``occ3d`` (Occ3D-nuScenes)          ``surroundocc`` (SurroundOcc, nuScenes)
========================  ==================================  ===========================================
grid                      +-40 m, -1..5.4 m, 0.4 m: 200x200x16  +-50 m, -5..3 m, 0.5 m: 200x200x16
frame                     ego at the LiDAR key-frame time     LiDAR (LIDAR_TOP) of the key frame
classes                   18: 0..16 semantic, 17 = free       17: 0 = empty, 1..16 semantic
files                     ``gts/<scene>/<token>/labels.npz``  ``surroundocc/samples/<LiDAR file>.npy``
                          dense semantics + camera/LiDAR      sparse ``(N, 4)`` x, y, z, class rows
                          visibility masks                    (class 0 = noise, ignored)
protocol                  mIoU / IoU under the camera mask    IoU / mIoU on every voxel (no mask)
                          (or LiDAR / none) and RayIoU        RayIoU is not defined
========================  ==================================  ===========================================
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from occkit.classes import OCC3D, SURROUNDOCC, Taxonomy
from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID, VoxelGrid

__all__ = ["LabelSpace", "OCC3D_SPACE", "SURROUNDOCC_SPACE", "LABEL_SPACES", "label_space"]


@dataclass(frozen=True)
class LabelSpace:
    """One benchmark's ground truth: grid, frame, taxonomy, label files and evaluation protocol."""

    name: str
    """Identifier used in configs and checkpoints: ``occ3d`` or ``surroundocc``."""
    grid: VoxelGrid
    """The voxel grid of the labels (and of the occupancy head's output)."""
    frame: Literal["ego", "lidar"]
    """The frame the grid is placed in: the ego frame at the key-frame LiDAR time, or the LiDAR frame."""
    taxonomy: Taxonomy
    """Class names, the free / empty id and colours."""
    label_folder: str
    """Folder under the dataset root that holds the label files (``data.label_root`` can point elsewhere)."""
    masks: tuple[str, ...]
    """Visibility masks the label files carry and the protocol can apply (``camera``, ``lidar``)."""
    default_mask: str | None
    """The mask the benchmark scores under (None: every voxel)."""
    rayiou: bool
    """Whether RayIoU is defined for it (it needs Occ3D's ego-frame labels with a free class)."""

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


OCC3D_SPACE = LabelSpace(name="occ3d", grid=OCC3D_GRID, frame="ego", taxonomy=OCC3D, label_folder="gts",
                         masks=("camera", "lidar"), default_mask="camera", rayiou=True)  # fmt: skip
SURROUNDOCC_SPACE = LabelSpace(name="surroundocc", grid=SURROUNDOCC_GRID, frame="lidar", taxonomy=SURROUNDOCC,
                               label_folder="surroundocc", masks=(), default_mask=None, rayiou=False)  # fmt: skip
LABEL_SPACES: dict[str, LabelSpace] = {space.name: space for space in (OCC3D_SPACE, SURROUNDOCC_SPACE)}


def label_space(name: str | LabelSpace) -> LabelSpace:
    """The label space called ``name`` (a LabelSpace passes through); ValueError lists the known ones."""
    if isinstance(name, LabelSpace):
        return name
    try:
        return LABEL_SPACES[name]
    except KeyError:
        raise ValueError(f"unknown label space {name!r}; known: {', '.join(LABEL_SPACES)}") from None
