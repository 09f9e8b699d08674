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
