"""RayPQ: occkit's counting against SparseOcc's own ``Metric_RayPQ`` on seeded ray-level frames
(``tests/golden/reference_parity/raypq.json``, from ``benchmarks/reference_parity/raypq_golden.py``), and the
voxel-to-ray path on grids whose answer is known."""

from __future__ import annotations

import importlib
import json
from pathlib import Path

import numpy as np
import pytest
from conftest import benchmark_module

from occkit.metrics.rayiou import RayCounts, cast_frame, rayiou
from occkit.metrics.raypq import RayPQCounts, raypq

rayiou_module = importlib.import_module("occkit.metrics.rayiou")  # the package's `rayiou` is the function

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


def test_one_cast_serves_rayiou_and_raypq_and_counts_add_up_over_frames():
    labels, instances = _scene()
    shifted = np.roll(labels, 3, axis=0)
    frames = [(labels, labels, np.array([[0.0, 0.0, 1.5]])), (labels, shifted, np.array([[2.0, -1.0, 1.5], [0, 0, 1]]))]
    by_frame, whole = RayPQCounts(), RayCounts()
    for gt, pred, origins in frames:
        rays = cast_frame(gt, pred, origins)
        by_frame.add_cast(rays, instances, instances)
        counts = RayCounts()
        counts.add_frame(rays)
        whole.merge(counts)
    assert whole.frames == 2 and whole.flow_frames == 0
    expected = rayiou([f[0] for f in frames], [f[1] for f in frames], [f[2] for f in frames])
    assert json.dumps(whole.compute()) == json.dumps(expected)  # NaN classes alike
    reference = RayPQCounts()
    for gt, pred, origins in frames:
        reference.add_frame(gt, pred, instances, instances, origins)
    for name in ("tp", "iou", "fp", "fn"):
        np.testing.assert_array_equal(getattr(by_frame, name), getattr(reference, name))
    doubled = RayCounts()
    doubled.merge(whole)
    doubled.reduce(lambda counts: counts * 2)  # two ranks that counted alike
    assert doubled.tp.dtype == np.int64 and (doubled.tp == 2 * whole.tp).all() and doubled.frames == 4
    assert doubled.scores() == pytest.approx(whole.scores())


def test_eval_preds_reports_raypq_for_predictions_that_carry_instances(tmp_path, monkeypatch):
    from occkit.label_files import write_occ3d_labels
    from occkit.metrics.evaluate import evaluate_predictions, markdown_table, write_prediction

    labels, instances = _scene()
    mask = np.ones_like(labels)
    gts, perfect, semantic_only = tmp_path / "gts", tmp_path / "perfect", tmp_path / "semantic"
    origins = {}
    for index, token in enumerate(("a" * 32, "b" * 32)):
        write_occ3d_labels(gts / "scene-0001" / token / "labels.npz", labels, mask, mask, instances=instances,
                           instance_tokens={1: "x" * 32, 2: "y" * 32})  # fmt: skip
        write_prediction(perfect, token, labels, instances=instances * (index + 3))
        write_prediction(semantic_only, token, labels)
        origins[token] = np.array([[0.0, 0.0, 1.5]])
    kernel, casts = rayiou_module._cast_kernel, []
    monkeypatch.setattr(rayiou_module, "_cast_kernel", lambda *a: casts.append(1) or kernel(*a))
    result = evaluate_predictions(gts, perfect, ray_origins=origins, compute_rayiou=True, workers=1)
    assert len(casts) == 2 * 2  # each grid of the two frames cast once, for RayIoU and RayPQ alike
    assert result["raypq"] == pytest.approx(1.0) and result["raypq@1"] == pytest.approx(1.0)
    assert "RayPQ@2" in markdown_table(result)
    plain = evaluate_predictions(gts, semantic_only, ray_origins=origins, compute_rayiou=True, workers=1)
    assert "raypq" not in plain and plain["rayiou"] == pytest.approx(1.0)
    (perfect / f"{'b' * 32}.npz").unlink()
    write_prediction(perfect, "b" * 32, labels)
    with pytest.raises(ValueError, match="1 of 2 predictions carry instances"):
        evaluate_predictions(gts, perfect, ray_origins=origins, compute_rayiou=True, workers=1)
