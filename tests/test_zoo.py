"""Every zoo entry builds, matches its YAML twin, trains one step and predicts in its own label space.

The paper entries run at their own input size on one sample with two cameras (the camera count is free, the image
size is fixed by the depth frustum) and 2000 LiDAR points, so that the whole zoo fits in the suite's time budget.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import torch
from conftest import make_batch, parameters_without_gradient

from occkit import zoo
from occkit.label_space import label_space
from occkit.models.complexity import count_parameters

CONFIGS = Path(__file__).resolve().parents[1] / "configs"


@pytest.mark.parametrize("name", zoo.names())
def test_every_zoo_entry_builds_and_matches_its_yaml(name):
    model = zoo.build(name)
    assert count_parameters(model) > 0
    path = CONFIGS / f"{name}.yaml"
    assert path.read_text() == zoo.config_yaml(name), f"{path} is stale: regenerate it with scripts/write_configs.py"
    assert zoo.load_experiment(path) == zoo.experiment(name)


@pytest.mark.parametrize("name", zoo.names())
def test_every_zoo_entry_trains_a_step_and_predicts_its_label_space(name):
    experiment = zoo.experiment(name)
    space = label_space(experiment.data.label_space)
    batch = make_batch(
        batch_size=1,
        num_cameras=min(2, len(experiment.data.cameras)),
        image_size=tuple(experiment.data.image_aug.final_size),
        num_points=2000,
        depth_stride=experiment.data.depth_downsample,
        space=space,
    )
    torch.manual_seed(0)
    model = zoo.build(name).train()

    losses = model.loss(model(batch), batch)
    assert losses and all(torch.isfinite(value) for value in losses.values()), losses
    sum(losses.values()).backward()
    missing = parameters_without_gradient(model)
    if not experiment.data.cameras:  # a LiDAR-only model holds no camera branch to leave without gradient
        assert not any(name.startswith(("image", "view")) for name, _ in model.named_parameters())
    assert not missing, f"{name}: no gradient for {missing}"

    model.eval()
    with torch.no_grad():
        prediction = model.predict(batch)
    semantics = prediction.semantics
    assert semantics.dtype == torch.uint8 and tuple(semantics.shape) == (1, *space.grid.shape)
    assert int(semantics.max()) < space.num_classes
