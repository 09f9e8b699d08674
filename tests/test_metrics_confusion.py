"""Confusion-matrix metrics against the official Occ3D ``Metric_mIoU`` golden outputs, plus the other protocols."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from occkit.classes import OCC3D
from occkit.geometry.grid import OCC3D_GRID
from occkit.metrics import (
    OccupancyMetric,
    confusion_matrix,
    distance_bins,
    geometry_iou,
    iou_from_confusion,
    miou,
    surroundocc_metrics,
)
from occkit.metrics.confusion import _confusion_torch

GOLDEN = Path(__file__).parent / "golden" / "occ3d_metrics"
MODES = {"camera_mask": "mask_camera", "lidar_mask": "mask_lidar", "no_mask": None}


@pytest.fixture(scope="module")
def frames():
    data = np.load(GOLDEN / "all_frames.npz")
    return {key: data[key] for key in ("semantics", "pred", "mask_camera", "mask_lidar")}


@pytest.fixture(scope="module")
def official():
    return json.loads((GOLDEN / "miou_official.json").read_text())["modes"]


def _assert_iou_equal(values, expected) -> None:
    assert len(values) == len(expected)
    for value, reference in zip(values, expected, strict=True):
        if reference is None:
            assert value is None or math.isnan(value)
        else:
            assert value == pytest.approx(reference, abs=1e-12)


def test_per_frame_confusion_matches_official(frames):
    reference = np.load(GOLDEN / "miou_per_frame_confusion_camera_mask.npz")["confusion"]
    for i in range(len(reference)):
        cm = confusion_matrix(frames["semantics"][i], frames["pred"][i], frames["mask_camera"][i])
        assert cm.dtype == np.int64 and cm.shape == (18, 18)
        np.testing.assert_array_equal(cm, reference[i])


@pytest.mark.parametrize("mode", list(MODES))
def test_dataset_metrics_match_official(frames, official, mode):
    mask = None if MODES[mode] is None else frames[MODES[mode]]
    cm = confusion_matrix(frames["semantics"], frames["pred"], mask)
    expected = official[mode]
    np.testing.assert_array_equal(cm, np.asarray(expected["confusion_matrix"]))
    assert cm.sum() == expected["n_evaluated_voxels"]
    _assert_iou_equal(iou_from_confusion(cm).tolist(), expected["per_class_iou"])
    assert miou(cm) == pytest.approx(expected["mIoU"], abs=1e-12)
    assert geometry_iou(cm) == pytest.approx(expected["geometry_iou"]["IoU_occupied"], abs=1e-12)

    sparseocc = expected["sparseocc_old_metrics_variant"]
    _assert_iou_equal(iou_from_confusion(cm, nan_without_gt=True).tolist(), sparseocc["per_class_iou"])
    assert miou(cm, nan_without_gt=True) == pytest.approx(sparseocc["mIoU"], abs=1e-12)

    metric = OccupancyMetric(mask={"camera_mask": "camera", "lidar_mask": "lidar", "no_mask": None}[mode])
    for i in range(0, 20, 5):
        metric.update(
            frames["semantics"][i : i + 5],
            frames["pred"][i : i + 5],
            mask_camera=frames["mask_camera"][i : i + 5],
            mask_lidar=frames["mask_lidar"][i : i + 5],
        )
    result = metric.compute()
    assert result["miou"] == pytest.approx(expected["mIoU"], abs=1e-12)
    assert result["iou"] == pytest.approx(expected["geometry_iou"]["IoU_occupied"], abs=1e-12)
    assert list(result["per_class_iou"]) == list(OCC3D.classes)
    _assert_iou_equal(list(result["per_class_iou"].values()), expected["per_class_iou"])


def test_torch_inputs_and_batches_agree(frames):
    gt, pred, mask = frames["semantics"][:4], frames["pred"][:4], frames["mask_camera"][:4]
    reference = confusion_matrix(gt, pred, mask)
    np.testing.assert_array_equal(
        reference, confusion_matrix(torch.from_numpy(gt), torch.from_numpy(pred), torch.from_numpy(mask))
    )
    np.testing.assert_array_equal(reference, sum(confusion_matrix(gt[i], pred[i], mask[i]) for i in range(4)))
    # The device path (torch.bincount), exercised here on the CPU.
    torch_gt, torch_pred = torch.from_numpy(gt), torch.from_numpy(pred)
    np.testing.assert_array_equal(
        reference, _confusion_torch(torch_gt, torch_pred, torch.from_numpy(mask) != 0, 18, 255)
    )
    np.testing.assert_array_equal(confusion_matrix(gt, pred), _confusion_torch(torch_gt, torch_pred, None, 18, 255))
    # Wider integer dtypes take the generic path and count the same.
    np.testing.assert_array_equal(reference, confusion_matrix(gt.astype(np.int64), pred.astype(np.int32), mask))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_tensors():
    rng = np.random.default_rng(0)
    gt = rng.integers(0, 18, (2, 20, 20, 16), dtype=np.uint8)
    pred = rng.integers(0, 18, (2, 20, 20, 16), dtype=np.uint8)
    mask = rng.integers(0, 2, (2, 20, 20, 16), dtype=np.uint8)
    gt[0, 0, 0] = 255
    cuda = [torch.from_numpy(a).cuda() for a in (gt, pred, mask)]
    np.testing.assert_array_equal(confusion_matrix(*cuda), confusion_matrix(gt, pred, mask))


def test_ignore_index_and_masks():
    rng = np.random.default_rng(1)
    gt = rng.integers(0, 18, (10, 10, 4), dtype=np.uint8)
    pred = rng.integers(0, 18, (10, 10, 4), dtype=np.uint8)
    mask = rng.integers(0, 2, (10, 10, 4)).astype(np.float32)
    gt[0], pred[1] = 255, 255
    cm = confusion_matrix(gt, pred, mask)
    keep = (mask == 1) & (gt != 255) & (pred != 255)
    expected = np.zeros((18, 18), np.int64)
    np.add.at(expected, (gt[keep], pred[keep]), 1)
    np.testing.assert_array_equal(cm, expected)
    # Out-of-range labels outside the mask are never looked at.
    gt[mask == 0] = 200
    np.testing.assert_array_equal(confusion_matrix(gt, pred, mask.astype(bool)), expected)


def test_merge_equals_one_metric():
    rng = np.random.default_rng(2)
    gt = rng.integers(0, 18, (4, 8, 8, 4), dtype=np.uint8)
    pred = rng.integers(0, 18, (4, 8, 8, 4), dtype=np.uint8)
    whole, first, second = (OccupancyMetric(mask=None) for _ in range(3))
    whole.update(gt, pred)
    first.update(gt[:2], pred[:2])
    second.update(gt[2:], pred[2:])
    assert first.merge(second).compute() == whole.compute()
    whole.all_reduce()  # no process group: nothing changes
    np.testing.assert_array_equal(whole.confusion, first.confusion)
    whole.reset()
    assert whole.confusion.sum() == 0
    with pytest.raises(ValueError, match="mask_camera"):
        OccupancyMetric().update(gt, pred)


@pytest.mark.parametrize(
    ("kwargs", "match"),
    [
        ({"gt": np.zeros((4, 4, 2), np.float32)}, "integer"),
        ({"pred": np.full((4, 4, 2), 18, np.uint8), "ignore_index": None}, r"found values \[18\]"),
        ({"pred": np.full((4, 4, 2), 18, np.uint8)}, r"found values \[18\]"),
        ({"gt": np.full((4, 4, 2), 40, np.int64)}, r"found values \[40\]"),
        ({"mask": np.full((4, 4, 2), 2, np.uint8)}, r"0/1.*\[2\]"),
        ({"pred": np.zeros((4, 4, 3), np.uint8)}, "shape mismatch"),
        ({"mask": np.ones((4, 4), bool)}, "mask shape"),
        ({"gt": np.zeros((16, 2), np.uint8), "pred": np.zeros((16, 2), np.uint8)}, "one frame"),
    ],
)
def test_bad_inputs(kwargs, match):
    arguments = {"gt": np.zeros((4, 4, 2), np.uint8), "pred": np.zeros((4, 4, 2), np.uint8), "mask": None}
    arguments.update(kwargs)
    with pytest.raises(ValueError, match=match):
        confusion_matrix(**arguments)


def test_surroundocc_protocol_by_hand():
    # Pairs (gt, pred): (0,0) (1,1) (1,2) (2,2) (255,1 ignored) (0,1) (2,0) (2,2).
    gt = np.array([0, 1, 1, 2, 255, 0, 2, 2], np.uint8).reshape(2, 2, 2)
    pred = np.array([0, 1, 2, 2, 1, 1, 0, 2], np.uint8).reshape(2, 2, 2)
    result = surroundocc_metrics(confusion_matrix(gt, pred, num_classes=17))
    assert result["iou"] == pytest.approx(4 / 6)  # 4 occupied hits, 1 missed, 1 false alarm
    assert result["per_class_iou"][1] == pytest.approx(1 / 3)
    assert result["per_class_iou"][2] == pytest.approx(2 / 4)
    assert np.isnan(result["per_class_iou"][3:]).all()
    assert result["miou"] == pytest.approx((1 / 3 + 1 / 2) / 2)


def test_surroundocc_protocol_matches_the_reference_algorithm(tmp_path):
    # tests/golden/surroundocc_metrics: SurroundOcc's evaluation run step by step on 4 fixed frames (see its README).
    from occkit.classes import SURROUNDOCC
    from occkit.data.labels import read_surroundocc_labels

    folder = Path(__file__).parent / "golden" / "surroundocc_metrics"
    reference = json.loads((folder / "reference.json").read_text())
    inputs = np.load(folder / "inputs.npz")
    total = np.zeros((17, 17), np.int64)
    for frame in range(4):
        np.save(tmp_path / f"{frame}.npy", inputs[f"gt_{frame}"])  # the file layout of SurroundOcc's ground truth
        gt = read_surroundocc_labels(tmp_path / f"{frame}.npy").semantics
        matrix = confusion_matrix(gt, inputs[f"pred_{frame}"], num_classes=17)
        scores = np.array(reference["per_sample_scores"][frame])
        assert [int(matrix[1:, 1:].sum()), int(matrix[1:].sum()), int(matrix[:, 1:].sum())] == scores[0].tolist()
        assert np.array_equal(np.diag(matrix)[1:], scores[1:, 0])
        total += matrix
    result = surroundocc_metrics(total)
    assert abs(result["iou"] - reference["IoU"]) <= 1e-12
    assert abs(result["miou"] - reference["mIoU"]) <= 1e-12
    for index, name in enumerate(SURROUNDOCC.classes[1:], start=1):
        assert abs(result["per_class_iou"][index] - reference[name]) <= 1e-12, name


def test_iou_conventions():
    cm = np.zeros((3, 3), np.int64)
    cm[0, 0], cm[2, 1] = 5, 2  # class 1 only predicted, class 2 only in GT
    iou = iou_from_confusion(cm)
    assert iou.tolist() == [1.0, 0.0, 0.0]
    assert np.isnan(iou_from_confusion(cm, nan_without_gt=True)[1])
    assert np.isnan(iou_from_confusion(np.zeros((3, 3)))).all()
    assert math.isnan(miou(np.zeros((3, 3)), classes=range(2)))


def test_distance_bins():
    bins = distance_bins(OCC3D_GRID, edges=(0, 20, 40))
    assert bins.shape == (2, 200, 200, 16) and bins.dtype == bool
    assert not (bins[0] & bins[1]).any()
    # Voxel 100 is centred at x = 0.2 m; voxel 150 at 20.2 m; the corner voxel at about 56 m is in no bin.
    assert bins[0, 100, 100].all() and bins[1, 150, 100].all() and not bins[:, 0, 0].any()
