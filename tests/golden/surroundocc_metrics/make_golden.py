"""Make the SurroundOcc metric golden data: fixed inputs and the numbers of SurroundOcc's own evaluation algorithm.

    python tests/golden/surroundocc_metrics/make_golden.py

The evaluation is written out here step by step as SurroundOcc runs it (``weiyithu/SurroundOcc``, commit d9cfca5b:
``LoadOccupancy`` in ``projects/mmdet3d_plugin/datasets/pipelines/loading.py``, ``gt_to_voxel`` and
``evaluation_semantic`` in ``projects/mmdet3d_plugin/datasets/evaluation_metrics.py``, and the reduction in
``CustomNuScenesOccDataset.evaluate`` of ``projects/mmdet3d_plugin/datasets/nuscenes_occupancy_dataset.py``), in
numpy only and independent of occkit, so that occkit's metric can be held against it. Deterministic: running it again
rewrites identical files.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

HERE = Path(__file__).parent
OCC_SIZE = (200, 200, 16)  # SurroundOcc's nuScenes grid: +-50 m, -5..3 m, 0.5 m voxels
CLASS_NUM = 17  # 0 = empty (geometry IoU), 1..16 semantic
CLASS_NAMES = ("barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
               "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat", "sidewalk", "terrain",
               "manmade", "vegetation")  # fmt: skip


# ----------------------------------------------------------------------------------------------------- inputs
def _scene(rng: np.random.Generator) -> np.ndarray:
    """A dense ``OCC_SIZE`` scene of classes 0..16: ground, walls, trees and objects of every class."""
    dense = np.zeros(OCC_SIZE, np.uint8)
    ground = rng.choice([11, 12, 13, 14], size=(8, 8), p=[0.5, 0.1, 0.2, 0.2])
    dense[:, :, 3] = np.kron(ground, np.ones((25, 25), np.uint8))
    for _ in range(30):  # buildings and vegetation
        x, y = rng.integers(0, 190, 2)
        w, d, h = rng.integers(3, 12, 3)
        dense[x : x + w, y : y + d, 4 : 4 + h] = rng.choice([15, 16])
    for cls in range(1, 11):  # objects on the ground, every class at least twice
        for _ in range(2 + int(rng.integers(0, 3))):
            x, y = rng.integers(10, 190, 2)
            w, d, h = rng.integers(1, 6, 3)
            dense[x : x + w, y : y + d, 4 : 4 + h] = cls
    return dense


def _sparse_gt(dense: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """SurroundOcc's file layout: ``(N, 4)`` rows of x, y, z index and class of the occupied voxels; a few rows carry
    class 0, the noise that ``LoadOccupancy`` turns into 255 (ignored)."""
    occupied = np.argwhere(dense > 0)
    rows = np.concatenate([occupied, dense[tuple(occupied.T)][:, None]], axis=1).astype(np.int64)
    noise = rng.choice(len(rows), size=len(rows) // 50, replace=False)
    rows[noise, 3] = 0
    return rows


def _prediction(dense: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """A dense prediction: the scene shifted by a voxel in places, some classes confused, false positives added."""
    pred = dense.copy()
    pred[:100] = np.roll(dense[:100], 1, axis=2)
    flip = rng.random(OCC_SIZE) < 0.05
    pred[flip & (pred > 0)] = rng.integers(1, CLASS_NUM, size=int((flip & (pred > 0)).sum()))
    extra = rng.random(OCC_SIZE) < 0.002
    pred[extra] = rng.integers(1, CLASS_NUM, size=int(extra.sum()))
    return pred


# ----------------------------------------------------------------------------------------------------- reference
def load_occupancy(occ: np.ndarray) -> np.ndarray:
    """``LoadOccupancy(use_semantic=True)``: float32 rows, class 0 (noise) becomes 255."""
    occ = occ.astype(np.float32)
    occ[..., 3][occ[..., 3] == 0] = 255
    return occ


def gt_to_voxel(gt: np.ndarray) -> np.ndarray:
    """``gt_to_voxel``: a dense float64 grid of zeros with each row's class written at its index."""
    voxel = np.zeros(OCC_SIZE)
    voxel[gt[:, 0].astype(int), gt[:, 1].astype(int), gt[:, 2].astype(int)] = gt[:, 3]
    return voxel


def evaluation_semantic(pred: np.ndarray, gt: np.ndarray) -> np.ndarray:
    """``evaluation_semantic`` for one sample: ``(17, 3)`` of (true positives, GT count, prediction count); row 0 is
    occupied vs empty, row j the class j; voxels whose GT is 255 are left out."""
    gt_i = gt_to_voxel(gt)
    mask = gt_i != 255
    score = np.zeros((CLASS_NUM, 3))
    for j in range(CLASS_NUM):
        if j == 0:
            score[j][0] += ((gt_i[mask] != 0) * (pred[mask] != 0)).sum()
            score[j][1] += (gt_i[mask] != 0).sum()
            score[j][2] += (pred[mask] != 0).sum()
        else:
            score[j][0] += ((gt_i[mask] == j) * (pred[mask] == j)).sum()
            score[j][1] += (gt_i[mask] == j).sum()
            score[j][2] += (pred[mask] == j).sum()
    return score


def evaluate(scores: list[np.ndarray]) -> dict:
    """``CustomNuScenesOccDataset.evaluate`` (use_semantic): the mean of the per-sample scores, IoU per row,
    mIoU the plain mean over rows 1..16."""
    results = np.stack(scores, axis=0).mean(0)
    ious = []
    for i in range(CLASS_NUM):
        tp, p, g = results[i, 0], results[i, 1], results[i, 2]
        ious.append(tp / (p + g - tp))
    out = {"IoU": ious[0]}
    out.update({name: ious[i + 1] for i, name in enumerate(CLASS_NAMES)})
    out["mIoU"] = float(np.mean(np.array(ious)[1:]))
    return {key: float(value) for key, value in out.items()}


def main() -> None:
    rng = np.random.default_rng(20231105)
    arrays, scores = {}, []
    for frame in range(4):
        dense = _scene(rng)
        gt, pred = _sparse_gt(dense, rng), _prediction(dense, rng)
        arrays[f"gt_{frame}"], arrays[f"pred_{frame}"] = gt.astype(np.int16), pred
        scores.append(evaluation_semantic(pred, load_occupancy(gt)))
    np.savez_compressed(HERE / "inputs.npz", **arrays)
    result = {"per_sample_scores": [s.tolist() for s in scores], **evaluate(scores)}
    (HERE / "reference.json").write_text(json.dumps(result, indent=2) + "\n")
    print(json.dumps({k: v for k, v in result.items() if k != "per_sample_scores"}, indent=2))


if __name__ == "__main__":
    main()
