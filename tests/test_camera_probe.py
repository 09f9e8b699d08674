"""benchmarks/camera_probe.py: each oracle puts into the model exactly what it names, in training and prediction."""

import argparse
import importlib.util
from pathlib import Path

import pytest
import torch

from occkit import zoo

REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def probe_module():
    """benchmarks/camera_probe.py as a module (benchmarks/ is not a package)."""
    spec = importlib.util.spec_from_file_location("benchmarks_camera_probe", REPO / "benchmarks" / "camera_probe.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def _probed(probe_module, probe: str):
    args = argparse.Namespace(data=Path("unused"), steps=1, lr=2e-3, stride=16, seed=0)
    experiment = probe_module.probe_experiment(probe, args)
    torch.manual_seed(0)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    probe_module.attach(probe, model)
    seen = {}
    model.bev_encoder.register_forward_pre_hook(lambda _, inputs: seen.update(bev=inputs[0]))
    return model, seen


@pytest.mark.parametrize("mode", ["train", "predict"])
def test_oracle_depth_is_one_hot_at_the_lidar_depth_and_predicted_elsewhere(probe_module, synthetic_batch, mode):
    batch = synthetic_batch(batch_size=1, num_cameras=2, depth_stride=16)
    model, _ = _probed(probe_module, "oracle-depth")
    model.train(mode == "train")
    depth = model(batch).depth if mode == "train" else model.forward(batch).depth  # (B, N, D, h, w)
    low, _, step = model.view_transform.cfg.depth_range
    index = ((batch.depth_maps - low) / step).floor().long()
    valid = (batch.depth_maps > 0) & (index >= 0) & (index < depth.shape[2])
    assert valid.any() and (~valid).any()
    oracle = torch.nn.functional.one_hot(index[valid], depth.shape[2]).float()
    torch.testing.assert_close(depth.permute(0, 1, 3, 4, 2)[valid], oracle)
    unknown = depth.permute(0, 1, 3, 4, 2)[~valid]
    assert (unknown.max(-1).values < 0.99).all()  # a fresh model's spread-out prediction


def test_true_occupancy_feeds_the_labels_to_the_bev_encoder_in_prediction_too(probe_module, synthetic_batch):
    batch = synthetic_batch(batch_size=1, num_cameras=2)
    model, seen = _probed(probe_module, "true-occupancy")
    model.eval().predict(batch)
    occupied = (batch.voxel_semantics != model.cfg.occupancy.free_index).float().permute(0, 3, 1, 2)
    torch.testing.assert_close(seen["bev"], occupied)


def test_geometry_probe_ignores_the_image_content(probe_module, synthetic_batch):
    model, seen = _probed(probe_module, "geometry-4z")
    model.eval()
    bevs = []
    for seed in (0, 1):  # the same rig, points and depth maps; other images
        batch = synthetic_batch(batch_size=1, num_cameras=2, depth_stride=16)
        batch.images = torch.rand(batch.images.shape, generator=torch.Generator().manual_seed(seed))
        model.predict(batch)
        bevs.append(seen["bev"])
    assert bevs[0].abs().sum() > 0
    torch.testing.assert_close(bevs[0], bevs[1])
