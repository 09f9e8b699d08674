"""Exactness of BEV history alignment: each key frame's ground truth warped into the next key frame of its scene.

For every key frame of a synthetic scene, a BEV map of its Occ3D ground truth: per column, the class of the top
occupied voxel when that class is static (driveable_surface, sidewalk, terrain, manmade, vegetation), one-hot over
those five classes as float channels; a column topped by anything else (a vehicle, a pedestrian, a barrier) or by
nothing is empty. Each map is aligned into the next key frame (``occkit.models.temporal``: ``history_to_current``
from the two ego poses, then ``align_bev``) and compared with that frame's own map over the cells labelled in both
(for the aligned map: valid, and at least half of its bilinear weight from labelled cells):

* ``agreement``: the share of those cells whose class (arg-max) matches;
* ``static_miou``: the IoU of each of the five classes over those cells, averaged over the classes present.

``identity`` is the same with the identity transform (ego motion ignored), the baseline that shows the alignment
matters; ``inverted`` uses the inverse transform (the ego motion applied the wrong way round, the usual sign slip);
``off_by_one_cell`` moves the aligned sampling points one cell (0.4 m) along x, to show what an error of one cell
costs, i.e. that the scores resolve errors smaller than a cell. ``aligned_augmented`` applies one BEV augmentation
to every frame of the scene (a flip of x, then a quarter turn, moved with ``augment_occupancy`` as the data pipeline
moves labels) and passes it as ``prev_aug`` and ``curr_aug``: the scores must not change.

The scenes are small worlds of ``occkit.sim``, one scene per seed with one small camera (the labels do not depend on
the images); the default seeds include bends of up to 3 degrees of yaw per key frame, at 3-5 m per key frame.

    python benchmarks/temporal_alignment.py [--seeds 0 7 10 12 72] [--frames 6] [--density 0.5]
        [--out benchmarks/results/temporal_alignment.json]
"""

from __future__ import annotations

import argparse
import json
import math
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import torch

from occkit.classes import IGNORE_INDEX, OCC3D
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.transforms import augment_occupancy
from occkit.environment import environment_report
from occkit.geometry.grid import OCC3D_GRID
from occkit.models.temporal import align_bev, history_to_current
from occkit.sim.config import SimConfig, WorldConfig
from occkit.sim.generate import simulate_dataset

#: The static classes compared, by their Occ3D names.
STATIC_CLASSES = ("driveable_surface", "sidewalk", "terrain", "manmade", "vegetation")
STATIC_IDS = tuple(OCC3D.index(name) for name in STATIC_CLASSES)
#: What each map is aligned with: the ego motion; none; the ego motion inverted; the ego motion and then one cell
#: (0.4 m) along x; the ego motion under a BEV augmentation of the whole sequence.
VARIANTS = ("aligned", "identity", "inverted", "off_by_one_cell", "aligned_augmented")
#: The Occ3D grid's columns, as (x_min, y_min, x_max, y_max).
BEV_RANGE = (OCC3D_GRID.lower[0], OCC3D_GRID.lower[1], OCC3D_GRID.upper[0], OCC3D_GRID.upper[1])
#: A translation by one cell along x, the size of the error that ``off_by_one_cell`` shows.
ONE_CELL_ALONG_X = torch.eye(4, dtype=torch.float64)
ONE_CELL_ALONG_X[0, 3] = OCC3D_GRID.voxel_size[0]
#: One BEV augmentation for a whole sequence: x flipped, then a quarter turn (exact entries, no cos(pi / 2) residue).
SEQUENCE_AUG = torch.tensor(
    [[0.0, -1.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]], dtype=torch.float64
) @ torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0], dtype=torch.float64))


def static_top_map(semantics: torch.Tensor) -> torch.Tensor:
    """``(5, X, Y)`` float one-hot of the top occupied voxel's class per column where it is static, else zeros.

    Args:
        semantics: ``(X, Y, Z)`` Occ3D class ids (17 free, 255 ignore).
    """
    labels = semantics.long()
    occupied = (labels != OCC3D.empty_index) & (labels != IGNORE_INDEX)
    height = labels.shape[-1]
    # The highest occupied z: arg-max of the first True along the reversed column.
    top = height - 1 - occupied.flip(-1).int().argmax(-1)
    top_class = labels.gather(-1, top[..., None])[..., 0]
    top_class = torch.where(occupied.any(-1), top_class, torch.full_like(top_class, OCC3D.empty_index))
    ids = torch.tensor(STATIC_IDS)
    return (top_class[None] == ids[:, None, None]).float()


@dataclass
class Counts:
    """Cells compared, cells that agree, and per-class intersections and unions, summed over frame pairs."""

    cells: int = 0
    agree: int = 0
    total_cells: int = 0
    intersection: list[int] = field(default_factory=lambda: [0] * len(STATIC_CLASSES))
    union: list[int] = field(default_factory=lambda: [0] * len(STATIC_CLASSES))

    def add(self, aligned: torch.Tensor, valid: torch.Tensor, current: torch.Tensor) -> None:
        """Add one pair: ``aligned (5, X, Y)`` with ``valid (1, X, Y)`` against ``current (5, X, Y)``."""
        labelled = current.sum(0) > 0.5
        labelled_aligned = valid[0] & (aligned.sum(0) >= 0.5)
        both = labelled & labelled_aligned
        predicted, truth = aligned.argmax(0), current.argmax(0)
        self.cells += int(both.sum())
        self.total_cells += both.numel()
        self.agree += int(((predicted == truth) & both).sum())
        for k in range(len(STATIC_CLASSES)):
            is_p, is_t = (predicted == k) & both, (truth == k) & both
            self.intersection[k] += int((is_p & is_t).sum())
            self.union[k] += int((is_p | is_t).sum())

    def summary(self) -> dict:
        ious = {name: i / u for name, i, u in zip(STATIC_CLASSES, self.intersection, self.union, strict=True) if u}
        return {
            "agreement": round(self.agree / max(self.cells, 1), 4),
            "static_miou": round(sum(ious.values()) / max(len(ious), 1), 4),
            "iou": {name: round(value, 4) for name, value in ious.items()},
            "cells_compared": self.cells,
            "share_of_cells_compared": round(self.cells / max(self.total_cells, 1), 4),
        }


def simulate(seed: int, frames: int, out: Path, density: float = 0.5) -> Path:
    """One scene of ``frames`` key frames for ``seed`` under ``out``; returns the dataset root."""
    config = SimConfig(scenes=1, frames=frames, seed=seed, image_size=(32, 18), cameras=("CAM_FRONT",),
                       world=WorldConfig(density=density))  # fmt: skip
    simulate_dataset(config, out)
    return out


def augment(semantics: torch.Tensor, aug: torch.Tensor = SEQUENCE_AUG) -> torch.Tensor:
    """Occ3D labels moved by a BEV augmentation of the ego frame, as the dataset moves them."""
    return augment_occupancy(semantics, aug, OCC3D_GRID, IGNORE_INDEX, empty=OCC3D.empty_index)


def _yaw(matrix: torch.Tensor) -> float:
    return math.atan2(float(matrix[1, 0]), float(matrix[0, 0]))


def measure_dataset(root: Path) -> list[dict]:
    """One row per scene of the dataset at ``root``: its ego motion and the counts of every variant."""
    dataset = OccupancyDataset(DatasetConfig(root=str(root), split="all", cameras=(), sweeps=-1, boxes=False))
    by_token = {record.token: i for i, record in enumerate(dataset.records)}
    scenes: dict[str, list[int]] = {}
    for i, record in enumerate(dataset.records):
        scenes.setdefault(record.scene, []).append(i)
    rows = []
    for scene, indices in sorted(scenes.items()):
        counts = {name: Counts() for name in VARIANTS}
        yaws, steps = [], []
        for i in sorted(indices, key=lambda i: dataset.records[i].index_in_scene):
            if not dataset.records[i].next:
                continue
            prev, curr = dataset[i], dataset[by_token[dataset.records[i].next]]
            history, current = static_top_map(prev.voxel_semantics), static_top_map(curr.voxel_semantics)
            current_to_history = history_to_current(prev.ego2global[None], curr.ego2global[None])
            transforms = {
                "aligned": current_to_history,
                "identity": torch.eye(4, dtype=torch.float64)[None],
                "inverted": torch.linalg.inv(current_to_history),
                "off_by_one_cell": ONE_CELL_ALONG_X @ current_to_history,
            }
            for name, transform in transforms.items():
                aligned, valid = align_bev(history[None], transform, BEV_RANGE)
                counts[name].add(aligned[0], valid[0], current)
            # Both frames augmented alike, as a sequence is; the labels moved by the data pipeline's own function.
            aug = SEQUENCE_AUG[None]
            transform = history_to_current(prev.ego2global[None], curr.ego2global[None], aug, aug)
            aligned, valid = align_bev(static_top_map(augment(prev.voxel_semantics))[None], transform, BEV_RANGE)
            counts["aligned_augmented"].add(aligned[0], valid[0], static_top_map(augment(curr.voxel_semantics)))
            yaws.append(abs(math.degrees(_yaw(current_to_history[0]))))
            steps.append(float(torch.linalg.vector_norm(current_to_history[0, :2, 3])))
        pairs = len(yaws)
        rows.append({
            "scene": scene,
            "pairs": pairs,
            "yaw_deg_per_key_frame": {"mean": round(sum(yaws) / max(pairs, 1), 2), "max": round(max(yaws), 2)},
            "metres_per_key_frame": round(sum(steps) / max(pairs, 1), 2),
            **{name: c.summary() for name, c in counts.items()},
        })  # fmt: skip
    return rows


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 7, 10, 12, 72])
    parser.add_argument("--frames", type=int, default=6)
    parser.add_argument("--density", type=float, default=0.5)
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/temporal_alignment.json"))
    args = parser.parse_args()

    rows = []
    start = time.perf_counter()
    for seed in args.seeds:
        with tempfile.TemporaryDirectory() as folder:
            root = simulate(seed, args.frames, Path(folder) / "data", args.density)
            for row in measure_dataset(root):
                rows.append({"seed": seed, **row})
        row = rows[-1]
        print(
            f"seed {seed:3d}: yaw {row['yaw_deg_per_key_frame']['mean']:.2f} deg and "
            f"{row['metres_per_key_frame']:.2f} m per key frame; agreement aligned {row['aligned']['agreement']:.4f} "
            f"(static mIoU {row['aligned']['static_miou']:.4f}), identity {row['identity']['agreement']:.4f} "
            f"({row['identity']['static_miou']:.4f}), inverted {row['inverted']['agreement']:.4f}, "
            f"off by one cell {row['off_by_one_cell']['agreement']:.4f} ({row['off_by_one_cell']['static_miou']:.4f}), "
            f"aligned+augmented {row['aligned_augmented']['agreement']:.4f}"
        )
    worst = {name: min(row[name]["agreement"] for row in rows) for name in VARIANTS}
    best = {name: max(row[name]["agreement"] for row in rows) for name in VARIANTS}
    results = {
        "what": __doc__.split("\n\n")[0],
        "settings": {"seeds": args.seeds, "frames": args.frames, "density": args.density,
                     "static_classes": list(STATIC_CLASSES), "bev_range": list(BEV_RANGE)},  # fmt: skip
        "scenes": rows,
        "agreement_worst_scene": worst,
        "agreement_best_scene": best,
        "seconds": round(time.perf_counter() - start, 1),
        "environment": {k: environment_report()[k] for k in ("occkit", "python", "packages", "devices")},
    }
    print(f"aligned, worst scene: {worst['aligned']:.4f}; identity, best scene: {best['identity']:.4f}; "
          f"inverted, best scene: {best['inverted']:.4f}")
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(results, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
