"""Contact sheets of a written dataset: the six cameras and a bird's-eye view of the occupancy labels.

Reads only what ``occkit sim`` wrote (``annotations.json``, the JPEGs and ``labels.npz``), so it shows exactly
what a reader of the dataset gets.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from occkit.data.labels import read_occ3d_labels
from occkit.figure import new_figure, save_figure
from occkit.viz.bev import bev_image
from occkit.viz.cameras import SURROUND_LAYOUT

__all__ = ["contact_sheet"]


def contact_sheet(root: str | Path, out: str | Path, samples: int = 3, scene: str | None = None) -> Path:
    """Write a PNG with ``samples`` key frames (evenly spread over one scene): cameras and a BEV per row.

    Args:
        root: dataset root written by ``occkit sim``.
        out: PNG path.
        samples: key frames to show.
        scene: scene name (default: the first scene).
    """
    from PIL import Image

    root = Path(root)
    infos = json.loads((root / "annotations.json").read_text())["scene_infos"]
    scene = scene or sorted(infos)[0]
    if scene not in infos:
        raise KeyError(f"{root / 'annotations.json'} has no scene {scene!r}; scenes: {', '.join(sorted(infos))}")
    frames = list(infos[scene].values())
    chosen = [frames[i] for i in np.linspace(0, len(frames) - 1, min(samples, len(frames))).round().astype(int)]

    figure = new_figure(20, 4.4 * len(chosen), dpi=100)
    grid = figure.add_gridspec(2 * len(chosen), 4, width_ratios=(1, 1, 1, 1.15), wspace=0.02, hspace=0.02)
    for row, frame in enumerate(chosen):
        for line, names in enumerate(SURROUND_LAYOUT):
            for column, name in enumerate(names):
                axis = figure.add_subplot(grid[2 * row + line, column])
                axis.set_axis_off()
                camera = frame["camera_sensor"].get(name)
                if camera is None:
                    continue
                with Image.open(root / camera["img_path"]) as image:
                    axis.imshow(np.asarray(image.convert("RGB")))
                axis.text(4, 4, name, fontsize=8, va="top", color="white", backgroundcolor=(0, 0, 0, 0.5))
        labels = read_occ3d_labels(root / frame["gt_path"])  # checked from the headers, as every label reader
        bev = bev_image(labels.semantics, labels.mask_camera)
        axis = figure.add_subplot(grid[2 * row : 2 * row + 2, 3])
        axis.imshow(bev, interpolation="nearest")
        axis.text(
            2, 2, f"Occ3D labels seen by the cameras\nts {frame['timestamp']}", fontsize=8, va="top", color="white"
        )
        axis.set_axis_off()
    return save_figure(figure, out, tight=True)
