"""Panoptic occupancy: instance centres from the CenterPoint maps, voxels assigned to the nearest centre of their class
(Panoptic-FlashOcc), the panoptic FlashOcc entries, and RayPQ from ``occkit eval``'s scoring."""

from __future__ import annotations

import dataclasses
import importlib
from pathlib import Path

import numpy as np
import pytest
import torch

from occkit import zoo
from occkit.classes import DETECTION_CLASSES, OCC3D
from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.engine.evaluate import dataset_ray_origins, evaluate_model
from occkit.geometry.grid import OCC3D_GRID
from occkit.metrics.rayiou import rayiou
from occkit.metrics.raypq import raypq
from occkit.models.heads.center import CenterHead, CenterHeadConfig
from occkit.models.heads.panoptic import assign_instances
from occkit.viz.palette import class_colors, instance_colors

CAMERAS = ("CAM_FRONT", "CAM_BACK")
CAR, TRUCK, ROAD, FREE = (OCC3D.index(name) for name in ("car", "truck", "driveable_surface", "free"))
rayiou_module = importlib.import_module("occkit.metrics.rayiou")  # the package's `rayiou` is the function
CAST_KERNEL = rayiou_module._cast_kernel


@pytest.fixture(scope="module")
def world(small_world) -> Path:
    return small_world


def _centre(ix: int, iy: int, iz: int) -> list[float]:
    """The metric centre of voxel ``(ix, iy, iz)`` of the Occ3D grid."""
    return [OCC3D_GRID.lower[a] + (i + 0.5) * OCC3D_GRID.voxel_size[a] for a, i in enumerate((ix, iy, iz))]


def test_voxels_join_the_nearest_centre_of_their_class():
    semantics = torch.full((1, 200, 200, 16), FREE, dtype=torch.uint8)
    semantics[0, 100:110, 50:54, 2:4] = CAR  # one car-shaped block, split by two centres
    semantics[0, 20:24, 20:24, 2] = TRUCK  # a truck without a truck centre
    semantics[0, :, :, 0] = ROAD
    centres = [torch.tensor([_centre(101, 51, 2), _centre(108, 52, 3), _centre(21, 21, 2)])]
    labels = [torch.tensor([DETECTION_CLASSES.index("car"), DETECTION_CLASSES.index("car"),
                            DETECTION_CLASSES.index("bus")])]  # fmt: skip
    instances = assign_instances(semantics, centres, labels, OCC3D_GRID)[0]
    assert instances.dtype == torch.int32
    assert (instances[100:105, 50:54, 2:4] == 1).all() and (instances[105:110, 50:54, 2:4] == 2).all()
    # A truck without a truck centre (the bus centre is of another class), the road and free space: instance 0.
    assert (instances[20:24, 20:24, 2] == 0).all() and (instances[:, :, 0] == 0).all()
    assert set(instances.unique().tolist()) == {0, 1, 2}
    # No centre at all: every voxel 0.
    empty = assign_instances(semantics, [torch.zeros(0, 3)], [torch.zeros(0, dtype=torch.long)], OCC3D_GRID)
    assert not empty.any()
    with pytest.raises(ValueError, match="centre and"):
        assign_instances(semantics, [], [], OCC3D_GRID)


def test_centres_are_the_heatmap_peaks_with_offset_and_height():
    cfg = CenterHeadConfig(in_channels=8, tasks=(DETECTION_CLASSES,), share_conv_channels=4, head_conv_channels=4,
                           point_cloud_range=(-40.0, -40.0, -5.0, 40.0, 40.0, 3.0), voxel_size=(0.1, 0.1),
                           out_size_factor=4, score_threshold=0.3, nms_types=("rotate",), circle_nms_radii=(4.0,),
                           nms_scales=((1.0,) * 10,))  # fmt: skip
    head = CenterHead(cfg)
    heatmap = torch.full((1, 10, 200, 200), -10.0)
    heatmap[0, 0, 120, 80] = 3.0  # a car peak
    heatmap[0, 0, 121, 80] = 2.0  # its neighbour: not a peak under the 3 x 3 max-pool
    heatmap[0, 8, 10, 190] = 1.0  # a pedestrian
    heatmap[0, 8, 50, 50] = -2.0  # below the score threshold (sigmoid 0.12 < 0.3)
    reg = torch.zeros(1, 2, 200, 200)
    reg[0, :, 120, 80] = torch.tensor([0.25, 0.75])
    height = torch.full((1, 1, 200, 200), 0.8)
    outputs = [{"heatmap": heatmap, "reg": reg, "height": height}]
    centres, scores, labels = head.centres(outputs)
    assert labels[0].tolist() == [DETECTION_CLASSES.index("car"), DETECTION_CLASSES.index("pedestrian")]
    torch.testing.assert_close(centres[0][0], torch.tensor([(120.25 * 0.4) - 40.0, (80.75 * 0.4) - 40.0, 0.8]))
    torch.testing.assert_close(centres[0][1], torch.tensor([10 * 0.4 - 40.0, 190 * 0.4 - 40.0, 0.8]))
    assert scores[0][0] > scores[0][1] > 0.3


def test_instance_colours_tell_objects_apart_and_leave_stuff_its_class_colour():
    labels = np.array([CAR, CAR, CAR, ROAD])
    instances = np.array([1, 2, 1, 0])
    colors = instance_colors(labels, instances)
    assert (colors[0] == colors[2]).all() and (colors[0] != colors[1]).any()
    np.testing.assert_array_equal(colors[3], class_colors(labels[3:])[0])
    many = instance_colors(np.full(40, CAR), np.arange(1, 41))
    assert len({tuple(c) for c in many}) == 40


def test_the_panoptic_entries_follow_panoptic_flashocc():
    paper = zoo.experiment("flashocc_pano")
    head = paper.model.instances
    assert head.tasks == (DETECTION_CLASSES,) and head.cell_size == (0.4, 0.4) and head.bev_shape == (200, 200)
    assert head.code_weights[:3] == (1.0, 1.0, 1.0) and not any(head.code_weights[3:])
    assert head.score_threshold == 0.3 and head.in_channels == paper.model.bev.neck_channels == 128
    assert paper.data.box_frame == "ego" and paper.data.instances and paper.model.depth_weight == 1.0
    assert not paper.model.occupancy.use_mask and zoo.paper_row("flashocc_pano") is not None
    assert "3D boxes" in paper.model.training_targets
    tiny = zoo.experiment("flashocc_tiny_pano")
    assert tiny.model.instances.in_channels == tiny.model.bev.neck_channels and tiny.data.box_frame == "ego"


def test_ego_frame_boxes_are_the_lidar_frame_boxes_moved_by_lidar2ego(world):
    config = DatasetConfig(root=str(world), split="all", cameras=(), sweeps=-1, occupancy=False)
    lidar = OccupancyDataset(config)[0]
    ego = OccupancyDataset(dataclasses.replace(config, box_frame="ego"))[0]
    assert len(lidar.boxes) == len(ego.boxes) > 0
    moved = lidar.boxes[:, :3].double() @ lidar.lidar2ego[:3, :3].T.double() + lidar.lidar2ego[:3, 3].double()
    torch.testing.assert_close(ego.boxes[:, :3].double(), moved, atol=1e-4, rtol=0)
    with pytest.raises(ValueError, match="box_frame"):
        DatasetConfig(box_frame="camera")


def test_a_panoptic_flashocc_predicts_instances_and_is_scored_with_raypq(world, tmp_path, monkeypatch):
    experiment = zoo.experiment("flashocc_tiny_pano")
    data = dataclasses.replace(experiment.data, root=str(world), split="all", cameras=CAMERAS, augment=False)
    dataset = OccupancyDataset(data)
    sample = dataset[0]
    assert sample.voxel_instances is not None and sample.voxel_instances.dtype == torch.int32
    assert sample.voxel_instances.max() > 0 and sample.boxes is not None
    torch.manual_seed(0)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    batch = collate([sample])
    losses = model.loss(model(batch), batch)
    assert {"occupancy", "det_heatmap", "det_bbox"} <= set(losses)
    model.eval()
    # A heatmap bias that makes every cell a candidate: each thing voxel joins a centre of its class.
    with torch.no_grad():
        model.instance_head.task_heads[0].branches["heatmap"][-1].bias.fill_(5.0)
        prediction = model.predict(batch)
    assert prediction.instances.shape == (1, 200, 200, 16) and prediction.instances.dtype == torch.int32
    things = torch.isin(prediction.semantics, torch.tensor([OCC3D.index(n) for n in ("car", "truck", "bus")]))
    assert (prediction.instances[~things & (prediction.semantics == ROAD)] == 0).all()
    casts = []
    monkeypatch.setattr(rayiou_module, "_cast_kernel", lambda *a: casts.append(1) or CAST_KERNEL(*a))
    origins = dataset_ray_origins(dataset)
    result = evaluate_model(model, dataset, ray_origins=origins, predictions=tmp_path)
    assert len(casts) == 2 * len(dataset)  # each grid cast once, for RayIoU and RayPQ alike
    monkeypatch.undo()
    # The same scores as the metrics' own functions on the written predictions.
    labels = [dataset[i] for i in range(len(dataset))]
    written = [np.load(tmp_path / f"{sample.token}.npz") for sample in labels]
    assert written[0]["instances"].shape == (200, 200, 16)
    gts = [sample.voxel_semantics.numpy() for sample in labels]
    preds = [archive["semantics"] for archive in written]
    rays = [origins[sample.token] for sample in labels]
    expected = raypq(gts, preds, [sample.voxel_instances.numpy() for sample in labels],
                     [archive["instances"] for archive in written], rays)  # fmt: skip
    assert {key: result[key] for key in ("raypq", "raypq@1", "raypq@2", "raypq@4")} == pytest.approx(
        {key: expected[key] for key in ("raypq", "raypq@1", "raypq@2", "raypq@4")}, nan_ok=True)
    assert result["rayiou"] == pytest.approx(rayiou(gts, preds, rays)["rayiou"])


def test_daocc_becomes_panoptic_from_its_detection_head(world):
    from occkit.models.daocc import DAOccConfig

    experiment = zoo.experiment("daocc_tiny")
    data = dataclasses.replace(experiment.data, root=str(world), split="all", cameras=CAMERAS, augment=False,
                               instances=True)  # fmt: skip
    batch = collate([OccupancyDataset(data)[0]])
    torch.manual_seed(0)
    model = zoo.build_from_config("daocc", dataclasses.replace(experiment.model, panoptic=True)).eval()
    with torch.no_grad():
        for head in model.detection_head.task_heads:  # every cell a candidate centre
            head.branches["heatmap"][-1].bias.fill_(5.0)
        prediction = model.predict(batch)
    assert prediction.instances is not None and prediction.instances.shape == (1, 200, 200, 16)
    stuff = ~torch.isin(prediction.semantics, torch.tensor([OCC3D.index(n) for n in ("car", "truck", "bus",
                        "construction_vehicle", "trailer", "motorcycle", "bicycle", "pedestrian")]))  # fmt: skip
    assert not prediction.instances[stuff].any()
    with pytest.raises(ValueError, match="detection is None"):
        DAOccConfig(detection=None, panoptic=True)


def test_a_checkpoint_loads_under_other_prediction_settings_only():
    from occkit.config import to_dict
    from occkit.engine.checkpoint import check_compatible

    experiment = zoo.experiment("daocc_tiny")
    payload = {"architecture": "daocc", "experiment": experiment.to_dict()}
    model = experiment.model
    decoding = dataclasses.replace(model, panoptic=True,
                                   detection=dataclasses.replace(model.detection, score_threshold=0.3))  # fmt: skip
    check_compatible(payload, "daocc", to_dict(decoding), "step.pt")  # the same weights predict differently
    with pytest.raises(ValueError, match="detection_loss_weight"):
        check_compatible(payload, "daocc", to_dict(dataclasses.replace(model, detection_loss_weight=0.1)), "step.pt")
