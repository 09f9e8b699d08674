"""The shipped weights still score what their cards say: each shipped entry, loaded with ``weights="synthetic"``, is
scored on the held-out scene of a small world simulated here, and must stay within :data:`MIOU_TOLERANCE` /
:data:`IOU_TOLERANCE` below its card's scores on the demo world.

A different, smaller world than the card's: the scores move with the scenes, so the tolerances are set from what the
shipped weights measured on this world (0.3 to 1.0 mIoU and 4 to 15 IoU points below their cards). A silent loss of
accuracy (a changed layer, a broken loader, weights that no longer load into the right parameters) drops a model far
below them: a model that learned nothing scores about 0 mIoU.
"""

from __future__ import annotations

import dataclasses

import pytest

from occkit import zoo
from occkit.engine.evaluate import evaluation_dataset, score_model
from occkit.shipped import SYNTHETIC, card, shipped_entries

#: The small world: two scenes of six key frames at the demo's image size, a seed neither the demo nor the training
#: world uses; the second scene is held out.
WORLD = {"scenes": 2, "frames": 6, "image_size": (400, 225), "seed": 7}
#: How far below its card's mIoU / geometry IoU (fractions) an entry may score on this world.
MIOU_TOLERANCE = 0.03
IOU_TOLERANCE = 0.20


@pytest.fixture(scope="module")
def world(synthetic_world):
    return synthetic_world(**WORLD)


@pytest.mark.parametrize("entry", shipped_entries())
def test_the_shipped_weights_score_their_card_on_a_fresh_world(entry, world):
    described = card(entry)
    experiment = zoo.experiment(entry)
    experiment = dataclasses.replace(experiment, data=dataclasses.replace(experiment.data, root=str(world)))
    model = zoo.build(entry, weights=SYNTHETIC).eval()
    scores = score_model(model, evaluation_dataset(experiment, world, "val"), rayiou=False)
    expected = described.scores
    assert scores["miou"] >= expected["miou"] - MIOU_TOLERANCE, (entry, scores["miou"], expected["miou"])
    assert scores["iou"] >= expected["iou"] - IOU_TOLERANCE, (entry, scores["iou"], expected["iou"])


def test_every_family_of_the_demo_ships_weights():
    from occkit.demo import DEMO_MODELS

    assert set(DEMO_MODELS) <= set(shipped_entries())
