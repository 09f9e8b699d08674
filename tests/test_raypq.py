"""RayPQ: occkit's counting against SparseOcc's own ``Metric_RayPQ`` on seeded ray-level frames
(``tests/golden/reference_parity/raypq.json``, from ``benchmarks/reference_parity/raypq_golden.py``), and the
voxel-to-ray path on grids whose answer is known."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from conftest import benchmark_module

from occkit.metrics.raypq import RayPQCounts, raypq

GOLDEN = Path(__file__).parent / "golden" / "reference_parity" / "raypq.json"


def test_counts_and_scores_equal_sparseoccs_own_metric():
    golden = json.loads(GOLDEN.read_text())
    assert golden["repository"] == "MCG-NJU/SparseOcc" and len(golden["commit"]) == 40
    frames = benchmark_module("reference_parity/raypq_golden.py").frames
    counts = RayPQCounts()
    for seed in golden["seeds"]:
        rays = frames(seed)
        counts.add_rays(rays["sem_pred"], rays["sem_gt"], rays["inst_pred"], rays["inst_gt"], rays["l1_error"])
    assert counts.tp.tolist() == golden["counts"]["tp"]
    assert counts.fp.tolist() == golden["counts"]["fp"] and counts.fn.tolist() == golden["counts"]["fn"]
    np.testing.assert_allclose(counts.iou, golden["counts"]["iou"], rtol=0, atol=1e-9)
    scores = counts.compute()
    for key, value in golden["result"].items():
        assert scores[key.lower()] == pytest.approx(value, abs=1e-9), key


def _scene() -> tuple[np.ndarray, np.ndarray]:
    """Free space with a road layer and two cars (instances 1 and 2) around the ego."""
    labels = np.full((200, 200, 16), 17, dtype=np.uint8)
    instances = np.zeros((200, 200, 16), dtype=np.int32)
    labels[:, :, 1] = 11  # driveable surface
    labels[110:120, 95:105, 2:6], instances[110:120, 95:105, 2:6] = 4, 1
    labels[80:90, 120:126, 2:6], instances[80:90, 120:126, 2:6] = 4, 2
    return labels, instances


def test_a_perfect_prediction_scores_one_and_merged_cars_lose_one_of_them():
    labels, instances = _scene()
    origins = [np.array([[0.0, 0.0, 1.5]])]
    perfect = raypq([labels], [labels], [instances], [instances * 7], origins)  # ids need not be the same numbers
    assert perfect["raypq"] == pytest.approx(1.0)
    merged = raypq([labels], [labels], [instances], [np.where(instances > 0, 1, 0)], origins)
    car = merged["per_class"][1][4]
    # One of the two cars matches the merged segment (IoU > 0.5 with the larger car) or neither does: never both.
    assert car < 1.0 and merged["per_class"][1][11] == pytest.approx(1.0)
