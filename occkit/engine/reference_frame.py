"""One key frame at a model's input setting: the reference input of the benchmark and of the ONNX export.

Both need a single, fixed frame: ``occkit bench`` times a model on it and ``occkit export`` makes the fixed-rig
network for its rig. The frame comes from a dataset, or from a small synthetic world simulated for the purpose;
:func:`load_reference_frame` takes it from either, and each caller passes its own :class:`SyntheticWorld`.
"""

from __future__ import annotations

import dataclasses
import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.sim.config import SimConfig
from occkit.sim.generate import simulate_dataset
from occkit.types import Batch

__all__ = ["SyntheticWorld", "ReferenceFrame", "load_reference_frame", "simulate_reference_world"]


@dataclass(frozen=True)
class SyntheticWorld:
    """The one-scene synthetic world (key frames at 2 Hz) a reference frame is taken from when no dataset is given."""

    image_size: tuple[int, int]
    """(W, H) of its camera images."""
    frames: int
    """Key frames of its scene."""
    folder: Path | None = None
    """Where it is simulated on first use and kept for later loads; None: a temporary folder, gone after the load."""


@dataclass(frozen=True)
class ReferenceFrame:
    """A loaded reference frame."""

    batch: Batch
    """The key frame, repeated ``batch_size`` times."""
    source: dict[str, Any]
    """Where it came from: ``data`` (the dataset root, or the synthetic world), ``index``, ``token``; with the scene
    also ``scene`` (its name) and ``frames`` (its key frames)."""
    scene: list[Batch]
    """Every key frame of its scene in time order, each as ``batch`` is (the stream a temporal model runs over);
    empty unless asked for."""


def load_reference_frame(data: DatasetConfig, root: str | Path | None, world: SyntheticWorld,
                         index: int | None = None, batch_size: int = 1, scene: bool = False,
                         log: Callable[[str], None] | None = None) -> ReferenceFrame:  # fmt: skip
    """A key frame under ``data``'s input settings with the test transform (no labels, boxes or depth targets).

    Args:
        data: a model's data settings (cameras, sweeps, image size, label space); the root, split and augmentation
            are replaced.
        root: a nuScenes-layout dataset root; None: ``world``, simulated first unless its folder holds it already.
        world: the synthetic world taken when ``root`` is None.
        index: key frame of the whole dataset (split ``all``); None: the last, which has the longest history of
            LiDAR sweeps, so multi-sweep models get all they ask for.
        batch_size: copies of the frame (and of each scene frame) per batch.
        scene: also load every key frame of the frame's scene.
        log: told when a world is simulated into its folder (it takes a while once).

    Raises:
        FileNotFoundError: ``root`` is not a folder.
        ValueError: ``index`` out of range (the message gives the range).
    """
    if index is not None and index < 0:
        raise ValueError(f"the sample index must be >= 0, got {index}")
    if root is not None:
        if not Path(root).is_dir():
            raise FileNotFoundError(f"dataset root {root} does not exist")
        return _load(data, Path(root), str(root), index, batch_size, scene)
    width, height = world.image_size
    if world.folder is not None:
        if not world.folder.exists():
            if log is not None:
                log(f"simulating a one-scene {width}x{height} world of {world.frames} key frames into "
                    f"{world.folder} (once)")  # fmt: skip
            simulate_reference_world(world.folder, world.image_size, world.frames, data.version)
        return _load(data, world.folder, str(world.folder), index, batch_size, scene)
    with tempfile.TemporaryDirectory() as folder:
        simulate_reference_world(Path(folder) / "world", world.image_size, world.frames, data.version)
        # The frames are read into memory here, before the folder goes.
        return _load(data, Path(folder) / "world", f"synthetic world (1 scene of {world.frames} key frames, "
                     f"{width}x{height}), generated", index, batch_size, scene)  # fmt: skip


def _load(data: DatasetConfig, root: Path, name: str, index: int | None, batch_size: int,
          scene: bool) -> ReferenceFrame:  # fmt: skip
    """The frame of :func:`load_reference_frame` from the dataset at ``root``, whose ``source`` calls it ``name``."""
    dataset = _inputs_of(data, root)
    if index is not None and index >= len(dataset):
        raise ValueError(f"--sample {index}: {root} has {len(dataset)} key frames, 0 to {len(dataset) - 1}")
    frame = len(dataset) - 1 if index is None else index
    record = dataset.records[frame]
    source: dict[str, Any] = {"data": name, "index": frame, "token": record.token}
    frames = []
    if scene:
        order = next(indices for indices in dataset.scene_indices() if frame in indices)
        frames = [collate([dataset[i]] * batch_size) for i in order]
        source.update(scene=record.scene, frames=len(frames))
    return ReferenceFrame(collate([dataset[frame]] * batch_size), source, frames)


def _inputs_of(data: DatasetConfig, root: Path) -> OccupancyDataset:
    """``root``'s key frames under ``data``'s input settings: the test transform, no targets, no history frames (a
    temporal model streams its history)."""
    inputs = dataclasses.replace(data, root=str(root), index=None, split="all", augment=False, occupancy=False,
                                 boxes=False, depth_downsample=0, history=0)  # fmt: skip
    return OccupancyDataset(inputs)


def simulate_reference_world(root: str | Path, image_size: tuple[int, int], frames: int, version: str) -> Path:
    """A one-scene synthetic world of ``frames`` key frames at 2 Hz and ``image_size`` (W, H) images in ``root``."""
    simulate_dataset(SimConfig(scenes=1, frames=frames, image_size=image_size, version=version), root, workers=1)
    return Path(root)
