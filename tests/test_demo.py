"""The demo's yardsticks: the two baselines that need no model, and the one-line summary of what a model learned."""

from __future__ import annotations

import pytest

from occkit.demo import GROUND_CLASSES, baselines, learned


@pytest.fixture(scope="module")
def dataset(tmp_path_factory):
    from occkit.data.dataset import DatasetConfig, OccupancyDataset
    from occkit.sim.generate import SimConfig, simulate_dataset

    root = tmp_path_factory.mktemp("demo") / "world"
    simulate_dataset(SimConfig(scenes=1, frames=2, seed=2, image_size=(176, 99), cameras=("CAM_FRONT",)), root)
    return OccupancyDataset(DatasetConfig(root=str(root), split="all", cameras=(), sweeps=-1, boxes=False))


def test_the_ground_layer_baseline_scores_its_classes_exactly_and_nothing_above(dataset):
    scores = baselines(dataset)
    free, ground = scores["free"], scores["ground"]
    assert free["iou"] == 0.0 and ground["iou"] > 0.3
    for name, iou in ground["per_class_iou"].items():
        if iou is not None and name != "free":
            assert iou == (1.0 if name in GROUND_CLASSES else 0.0), name


def test_what_a_model_learned_is_said_in_one_line():
    ground = {"iou": 0.658}
    ground_only = {"iou": 0.655, "per_class_iou": {"car": 0.004, "driveable_surface": 0.6, "free": 0.9}}
    assert learned(ground_only, ground) == "the ground layer and free space above it, nothing above the ground"
    assert learned({**ground_only, "iou": 0.4}, ground) == "no class above the ground yet"
    objects = {"iou": 0.8, "per_class_iou": {"car": 0.281, "pedestrian": 0.061, "bus": 0.02, "terrain": 0.7}}
    assert learned(objects, ground) == "objects above the ground: car 28, pedestrian 6 IoU"


def test_the_report_shows_the_shipped_weights_and_the_short_runs_beside_both_baselines(tmp_path):
    from occkit.demo import _report

    def scores(miou: float, car: float) -> dict:
        return {"miou": miou, "iou": 0.8, "rayiou": 0.3, "per_class_iou": {"car": car, "driveable_surface": 0.7}}

    baseline = {"free": {"miou": 0.0, "iou": 0.0}, "ground": {"miou": 0.235, "iou": 0.648}}
    shipped = {"daocc_tiny": {**scores(0.536, 0.585), "trained": "2400 steps, card 3fc2621316c9"}}
    trained = {"daocc_tiny": {**scores(0.18, 0.1), "steps": 300, "train_seconds": 390.0, "loss": (40.5, 12.25)}}
    renders = {"shipped": tmp_path / "predictions.png", "trained": tmp_path / "predictions_from_scratch.png"}
    text = _report(tmp_path, shipped, trained, baseline, 900.0, renders).read_text()
    assert "## The shipped weights" in text and "## A short training run from random weights" in text
    assert "| `daocc_tiny` | cameras + LiDAR | 2400 steps, card 3fc2621316c9 | 53.6 | 80.0 | 30.0 |" in text
    assert "| 300 | 6.5 min | 40.50 -> 12.25 | 18.0 | 80.0 | 30.0 |" in text
    assert text.count("the labels' ground layer") == 1 and "| 23.5 | 64.8 |" in text
    assert "- `daocc_tiny`: objects above the ground: car 58 IoU" in text
    assert "| car | 58.5 | 10.0 |" in text  # per class: the shipped weights, then the short run
    assert "![the shipped weights' predictions](predictions.png)" in text
