"""DAOcc end to end on tiny synthetic batches: shapes at every stage, gradients, learning, variants, the zoo."""

from __future__ import annotations

import dataclasses

import pytest
import torch
from conftest import fit_batch, parameters_without_gradient

from occkit import zoo
from occkit.config import ConfigError
from occkit.models.complexity import count_macs, count_parameters
from occkit.models.daocc import DAOcc, DAOccConfig, with_bev_extent
from occkit.types import OccPrediction
from occkit.zoo import load_experiment


def tiny(**changes) -> DAOcc:
    torch.manual_seed(0)
    _, cfg = zoo.model_config("daocc_tiny")
    return DAOcc(dataclasses.replace(cfg, **changes))


def test_shapes_at_every_stage(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch()
    features = model.image_encoder(batch.images)
    assert tuple(features.shape) == (2, 2, 64, 8, 22)
    plan = model.view_transform.plan(batch.intrinsics, batch.cam2ego, batch.img_aug, batch.lidar2ego,
                                     batch.bev_aug, image_size=(64, 176))
    camera_bev = model.view_transform(features, plan)
    assert tuple(camera_bev.shape) == (2, 16 * 4, 144, 144)
    lidar_bev = model.lidar_encoder(batch.points, batch.num_points)
    assert tuple(lidar_bev.shape) == (2, 16 * 5, 144, 144)  # z: 41 -> 21 -> 11, then conv_out -> 5
    assert model.lidar_encoder.out_channels == 16 * 5
    bev = model.bev_encoder(model.fuser([camera_bev, lidar_bev]))
    assert tuple(bev.shape) == (2, 64, 144, 144)
    occ_bev = model.range_extension(bev, model.plan(batch).range_grid)
    assert tuple(occ_bev.shape) == (2, 32, 200, 200)
    output = model(batch)
    assert tuple(output.occupancy.shape) == (2, 18, 200, 200, 16)
    assert len(output.detection) == 6
    assert tuple(output.detection[0]["heatmap"].shape) == (2, 1, 144, 144)
    assert tuple(output.detection[5]["heatmap"].shape) == (2, 2, 144, 144)


def test_every_parameter_gets_a_gradient(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(batch_size=1)  # an odd number of boxes per task: L1 signs at a bias cannot cancel
    losses = model.loss(model(batch), batch)
    assert set(losses) == {"occupancy", "lovasz", "det_heatmap", "det_bbox"}
    sum(losses.values()).backward()
    missing = parameters_without_gradient(model)
    assert not missing, f"no gradient for {missing}"
    assert all(torch.isfinite(p.grad).all() for p in model.parameters() if p.grad is not None)


def test_loss_decreases_on_a_fixed_batch(synthetic_batch):
    model = tiny().train()
    batch = synthetic_batch(batch_size=1)
    # With the heatmap's prior initialisation the first loss is the occupancy terms' (about 6), not a focal loss in
    # the thousands that collapses at once: it falls at every step, by about a third in 6 steps.
    history = fit_batch(model, batch, steps=6)
    assert all(later < earlier for earlier, later in zip(history[:-1], history[1:], strict=True)), history
    assert history[-1] < 0.8 * history[0], history


def test_lidar_only_variant_has_no_camera_branch_and_trains(synthetic_batch):
    model = tiny(image=None).train()
    assert model.image_encoder is None and model.view_transform is None
    batch = synthetic_batch(batch_size=1)
    batch.images = None
    sum(model.loss(model(batch), batch).values()).backward()
    assert not parameters_without_gradient(model)
    assert model.eval().predict(batch).semantics.shape == (1, 200, 200, 16)


def test_failed_cameras_and_empty_lidar(synthetic_batch):
    model = tiny().eval()
    batch = synthetic_batch(num_cameras=3)
    full = model(batch).occupancy
    batch.camera_mask[:, 1] = False
    masked = model(batch).occupancy
    assert torch.isfinite(masked).all() and not torch.equal(full, masked)
    batch.num_points.zero_()
    assert torch.isfinite(model(batch).occupancy).all()
    one_camera = synthetic_batch(num_cameras=1)
    assert model(one_camera).occupancy.shape == (2, 18, 200, 200, 16)


def test_detection_branch_is_detachable(synthetic_batch):
    model = tiny().eval()
    batch = synthetic_batch(batch_size=1)
    assert model(batch).detection is None  # inference skips it
    prediction = model.predict(batch, boxes=True)
    assert isinstance(prediction, OccPrediction) and prediction.semantics.dtype == torch.uint8
    assert len(prediction.boxes) == 1 and prediction.boxes[0].shape[1] == 9
    with_head = count_macs(model, lambda: model(batch, detect=True)).total
    before = count_parameters(model)
    model.remove_detection()
    assert count_parameters(model) < before
    assert count_macs(model, lambda: model(batch)).total < with_head
    assert model.predict(batch, boxes=True).boxes is None


def test_inconsistent_channels_are_clear_errors():
    _, cfg = zoo.model_config("daocc_tiny")
    with pytest.raises(ValueError, match="bev.in_channels = 32 must equal fusion_channels = 64"):
        dataclasses.replace(cfg, fusion_channels=64)
    with pytest.raises(ValueError, match="camera branch"):
        DAOccConfig(image=None, lidar=None)


def test_zoo_errors_name_the_problem(tmp_path):
    with pytest.raises(KeyError, match="unknown model 'daoc'"):
        zoo.build("daoc")
    bad = tmp_path / "bad.yaml"
    bad.write_text(zoo.config_yaml("daocc_tiny").replace("fusion_channels:", "fusion_channel:"))
    with pytest.raises(ConfigError, match="fusion_channel"):
        load_experiment(bad)


@pytest.mark.parametrize("detection", [True, False])
def test_bev_extent_keeps_the_cell_size_and_every_branch_in_step(synthetic_batch, detection):
    _, cfg = zoo.model_config("daocc_tiny")
    cfg = cfg if detection else dataclasses.replace(cfg, detection=None)
    narrow = with_bev_extent(cfg, 40.8)  # the BVRE ablation: the BEV just covers the +-40 m grid
    assert narrow.view.grid_size == (136, 136, cfg.view.grid_size[2])  # 0.6 m cells, as daocc_tiny's 144 over 86.4 m
    assert narrow.lidar.point_cloud_range == narrow.view.point_cloud_range == (-40.8, -40.8, -5.0, 40.8, 40.8, 3.0)
    assert narrow.range_extension.bev_range == (-40.8, -40.8, 40.8, 40.8)
    assert (narrow.detection is None) == (not detection)
    torch.manual_seed(0)
    model = DAOcc(narrow).train()  # the detection head runs in training only
    with torch.no_grad():
        output = model(synthetic_batch(batch_size=1))
    assert tuple(output.occupancy.shape) == (1, 18, 200, 200, 16)
    if detection:
        assert tuple(output.detection[0]["heatmap"].shape) == (1, 1, 136, 136)
