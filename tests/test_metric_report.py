"""The printed metric report says why a score is undefined instead of printing a bare ``nan``."""

from __future__ import annotations

import json
import re

import numpy as np

from occkit.label_space import OCC3D_SPACE
from occkit.metrics.evaluate import markdown_table
from occkit.metrics.rayiou import FLOW_CLASSES, rayiou_from_counts


def _result_without_moving_true_positives() -> dict:
    """A flow model's scores over rays where no moving class has a true positive (only driveable surface does)."""
    classes = len(OCC3D_SPACE.taxonomy.classes)
    gt, pred, tp = np.zeros(classes, np.int64), np.zeros(classes, np.int64), np.zeros((3, classes), np.int64)
    surface = OCC3D_SPACE.taxonomy.classes.index("driveable_surface")
    gt[surface] = pred[surface] = tp[:, surface] = 10
    summary = rayiou_from_counts(gt, pred, tp, np.zeros(classes), np.zeros(classes, np.int64))
    per_class = {name: 0.5 for name in OCC3D_SPACE.taxonomy.classes}
    return {"miou": 0.5, "iou": 0.6, "per_class_iou": per_class, "label_space": "occ3d", "mask": "camera",
            "frames": 1, "missing_predictions": 0,
            **{key: summary[key] for key in ("rayiou", "rayiou@1", "rayiou@2", "rayiou@4", "mave", "occ_score")}}


def test_undefined_mave_and_occ_score_are_kept_and_explained():
    result = _result_without_moving_true_positives()
    assert np.isnan(result["mave"]) and np.isnan(result["occ_score"])  # the challenge's value, kept
    for stored in (result, {**result, "mave": None, "occ_score": None}):  # in memory (eval), from JSON (eval-preds)
        table = markdown_table(stored)
        assert re.search(r"\|\s*nan\s*\|", table, re.IGNORECASE) is None  # no bare nan in a cell
        assert "| n/a | n/a |" in table
        assert "mAVE n/a: no true positive of a moving class" in table and all(c in table for c in FLOW_CLASSES)


def test_a_defined_mave_is_printed_as_before():
    table = markdown_table({**_result_without_moving_true_positives(), "mave": 0.25, "occ_score": 0.5})
    assert "| 0.250 | 50.00 |" in table and "n/a" not in table


def test_metrics_json_writes_an_undefined_score_as_null(tmp_path):
    from occkit.metrics.evaluate import write_report

    result = _result_without_moving_true_positives()  # NaN in memory, as evaluate_model returns it
    paths = write_report(result, tmp_path)

    def refuse(constant: str):
        raise AssertionError(f"metrics.json holds a bare {constant}, which is not JSON")

    stored = json.loads(paths["json"].read_text(), parse_constant=refuse)
    assert stored["mave"] is None and stored["occ_score"] is None and stored["rayiou"] == result["rayiou"]
    assert "| n/a | n/a |" in paths["markdown"].read_text()
