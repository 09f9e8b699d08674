"""FlashOcc: the official parameter counts, shapes, gradients and learning on a tiny batch."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import fit_batch, parameters_without_gradient

from occkit import zoo
from occkit.models.complexity import count_parameters
from occkit.models.flashocc import FlashOcc, FlashOccConfig


@pytest.mark.parametrize(("name", "official"), [("flashocc_m0", 39.94e6), ("flashocc_m1", 44.74e6)])
def test_parameter_counts_match_the_official_figures(name, official):
    params = count_parameters(zoo.build(name))
    assert abs(params - official) / official < 0.001, params
    # Pinned exactly: a change to any layer shows up here.
    assert params == {"flashocc_m0": 39_938_892, "flashocc_m1": 44_744_312}[name]


def tiny() -> FlashOcc:
    torch.manual_seed(0)
    return zoo.build("flashocc_tiny")


def test_shapes_and_every_parameter_gets_a_gradient(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(image_size=(64, 176))
    features = model.image_encoder(batch.images)
    assert tuple(features.shape) == (2, 2, 64, 4, 11)  # stride 16
    output = model(batch)
    assert tuple(output.occupancy.shape) == (2, 18, 200, 200, 16)
    assert tuple(output.depth.shape) == (2, 2, 22, 4, 11)
    torch.testing.assert_close(output.depth.sum(dim=2), torch.ones(2, 2, 4, 11))
    losses = model.loss(output, batch)
    assert set(losses) == {"occupancy", "lovasz"}
    sum(losses.values()).backward()
    missing = parameters_without_gradient(model)
    assert not missing, f"no gradient for {missing}"


def test_loss_decreases_on_a_fixed_batch(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(batch_size=1, image_size=(64, 176))
    history = fit_batch(model, batch, steps=14)  # about 0.25 of the first after 14 steps
    assert history[-1] < 0.5 * history[0], history


def test_predict_and_failed_cameras(synthetic_batch):
    model = tiny().eval()
    batch = synthetic_batch(num_cameras=3, image_size=(64, 176))
    prediction = model.predict(batch)
    assert prediction.semantics.shape == (2, 200, 200, 16) and prediction.semantics.dtype == torch.uint8
    full = model(batch).occupancy
    batch.camera_mask[:, 0] = False
    assert not torch.equal(full, model(batch).occupancy)


def test_inconsistent_config_is_a_clear_error():
    with pytest.raises(ValueError, match="occupancy.in_channels = 128 must equal bev.neck_channels = 256"):
        dataclasses.replace(FlashOccConfig(), bev=dataclasses.replace(FlashOccConfig().bev, neck_channels=256))


def test_depth_supervision_is_optional_and_trains_the_depth_net(synthetic_batch):
    """depth_weight adds BEVDepth's depth BCE against the LiDAR depth maps; without the maps it is a clear error."""
    torch.manual_seed(0)
    cfg = dataclasses.replace(zoo.experiment("flashocc_tiny").model, depth_weight=3.0)
    model = FlashOcc(cfg).train()
    batch = synthetic_batch(batch_size=1, image_size=(64, 176), depth_stride=16)
    output = model(batch)
    losses = model.loss(output, batch)
    assert "depth" in losses and losses["depth"] > 0
    depth_only = FlashOcc(dataclasses.replace(cfg, depth_weight=1.0))
    depth_only.load_state_dict(model.state_dict())
    torch.testing.assert_close(depth_only.loss(output, batch)["depth"], losses["depth"] / 3.0)
    losses["depth"].backward()
    assert model.view_transform.depth_net.weight.grad.abs().sum() > 0
    batch.depth_maps = None
    with pytest.raises(ValueError, match="FlashOcc's depth loss needs LiDAR depth maps: set data.depth_downsample = 1"):
        model.loss(output, batch)
