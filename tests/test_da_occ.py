"""DA-Occ: shapes of every stage, the five loss terms, gradients, learning, failed cameras and cached plans."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import fit_batch, parameters_without_gradient

from occkit import zoo
from occkit.models.da_occ import DirectionAwareOcc, DirectionAwareOccConfig

IMAGE_SIZE = (128, 352)  # the tiny config's input: features 8 x 22, the HeightNet DAC length 8


def tiny(**changes) -> DirectionAwareOcc:
    torch.manual_seed(0)
    _, cfg = zoo.model_config("da_occ_tiny")
    return DirectionAwareOcc(dataclasses.replace(cfg, **changes))


def test_shapes_and_loss_terms(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(image_size=IMAGE_SIZE, depth_stride=16)
    output = model(batch)
    assert tuple(output.occupancy.shape) == (2, 18, 200, 200, 16)
    assert tuple(output.depth.shape) == (2, 2, 22, 8, 22)
    assert tuple(output.height.shape) == (2, 2, 16, 8, 22)
    torch.testing.assert_close(output.height.sum(dim=2), torch.ones(2, 2, 8, 22))
    losses = model.loss(output, batch)
    assert set(losses) == {"depth", "height", "occupancy", "semantic_affinity", "geometric_affinity"}
    assert all(torch.isfinite(v) and v > 0 for v in losses.values())


def test_height_volume_is_sliced_along_x_and_decoded_along_z(synthetic_batch):
    """The vertical DAC on F_height (B, C, Z, X*Y) has kernel length Z: it mixes heights within each column."""
    model = tiny()
    assert model.height_vertical.conv.length == 16
    assert model.height_grid.shape == (32, 32, 16)
    assert model.bev_vertical.conv.length == 200 and model.bev_horizontal.conv.length == 200


def test_every_parameter_gets_a_gradient(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(batch_size=1, image_size=IMAGE_SIZE, depth_stride=16)
    sum(model.loss(model(batch), batch).values()).backward()
    missing = parameters_without_gradient(model)
    assert not missing, f"no gradient for {missing}"


def test_loss_decreases_on_a_fixed_batch(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(batch_size=1, image_size=IMAGE_SIZE, depth_stride=16)
    history = fit_batch(model, batch, steps=12)  # about 0.2 of the first after 12 steps
    assert history[-1] < 0.5 * history[0], history


def test_failed_cameras_and_a_reused_plan(synthetic_batch):
    model = tiny().eval()
    batch = synthetic_batch(num_cameras=3, image_size=IMAGE_SIZE)
    full = model(batch).occupancy
    model.reuse_plan = True  # the inference fast path's fixed calibration
    torch.testing.assert_close(model(batch).occupancy, full, rtol=0, atol=0)
    reused = model.current_plan(batch)
    assert model.current_plan(batch) is reused
    batch.camera_mask[:, 2] = False
    assert model.current_plan(batch) is reused  # one rig: a changed camera mask needs a new plan, by contract
    model.reuse_plan = False
    assert not torch.equal(model(batch).occupancy, full)
    assert model.predict(batch).semantics.dtype == torch.uint8
    model.train()
    assert model.current_plan(batch) is not model.current_plan(batch)  # training always computes the plan


def test_missing_lidar_maps_is_a_clear_error(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(batch_size=1, image_size=IMAGE_SIZE)
    with pytest.raises(ValueError, match="depth_downsample = 16"):
        model.loss(model(batch), batch)


def test_inconsistent_config_is_a_clear_error():
    with pytest.raises(ValueError, match="height_grid_size\\[2\\] = 8 must equal the height_range bins = 16"):
        DirectionAwareOccConfig(height_grid_size=(32, 32, 8))
