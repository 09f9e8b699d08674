"""One key frame at a model's input setting: the reference input of the benchmark and of the ONNX export.

Both need a single, fixed frame: ``occkit bench`` times a model on it and ``occkit export`` makes the fixed-rig
network for its rig. The frame comes from a dataset, or from a small synthetic world simulated for the purpose.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path
from typing import Any

from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.sim.config import SimConfig
from occkit.sim.generate import simulate_dataset
from occkit.types import Batch

__all__ = ["load_key_frame", "load_scene_frames", "simulate_reference_world"]


def load_key_frame(data: DatasetConfig, root: str | Path, index: int | None = None,
                   batch_size: int = 1) -> tuple[Batch, dict[str, Any]]:  # fmt: skip
    """A key frame of ``root`` under ``data``'s input settings with the test transform (no labels, boxes or depth
    targets), repeated ``batch_size`` times, and where it came from (``data``, ``index``, ``token``).

    Args:
        data: a model's training data settings (cameras, sweeps, image size, label space); the root, split and
            augmentation are replaced.
        root: a nuScenes-layout dataset root.
        index: key frame of the whole dataset (split ``all``); None: the last, which has the longest history of
            LiDAR sweeps, so multi-sweep models get all they ask for.

    Raises:
        FileNotFoundError: ``root`` is not a folder.
        ValueError: ``index`` out of range (the message gives the range).
    """
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} does not exist")
    if index is not None and index < 0:
        raise ValueError(f"the sample index must be >= 0, got {index}")
    dataset = _inputs_of(data, root)
    if index is not None and index >= len(dataset):
        raise ValueError(f"--sample {index}: {root} has {len(dataset)} key frames, 0 to {len(dataset) - 1}")
    frame = len(dataset) - 1 if index is None else index
    source = {"data": str(root), "index": frame, "token": dataset.records[frame].token}
    return collate([dataset[frame]] * batch_size), source


def load_scene_frames(data: DatasetConfig, root: str | Path, batch_size: int = 1) -> list[Batch]:
    """Every key frame of the scene of ``root``'s last key frame, in time order, as :func:`load_key_frame` loads one
    (the input of a temporal model's streaming benchmark)."""
    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"dataset root {root} does not exist")
    dataset = _inputs_of(data, root)
    last = len(dataset) - 1
    indices = next(scene for scene in dataset.scene_indices() if last in scene)
    return [collate([dataset[i]] * batch_size) for i in indices]


def _inputs_of(data: DatasetConfig, root: Path) -> OccupancyDataset:
    """``root``'s key frames under ``data``'s input settings: the test transform, no targets, no history frames (a
    temporal model streams its history)."""
    return OccupancyDataset(dataclasses.replace(data, root=str(root), index=None, split="all", augment=False,
                                                occupancy=False, boxes=False, depth_downsample=0, history=0))


def simulate_reference_world(root: str | Path, image_size: tuple[int, int], frames: int, version: str) -> Path:
    """A one-scene synthetic world of ``frames`` key frames at 2 Hz and ``image_size`` (W, H) images in ``root``."""
    simulate_dataset(SimConfig(scenes=1, frames=frames, image_size=image_size, version=version), root, workers=1)
    return Path(root)
