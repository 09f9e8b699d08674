"""Occupancy flow end to end: the synthetic world's ground truth, reading and augmenting it, the flow head, prediction
files, and mAVE / OccScore against the challenge's algorithm (golden numbers) and through both evaluators."""

from __future__ import annotations

import dataclasses
import json
import math
from pathlib import Path

import numpy as np
import pytest
import torch

from occkit import zoo
from occkit.classes import NUSCENES_TO_OCC3D, OCC3D
from occkit.data.collate import collate
from occkit.data.dataset import DatasetConfig, OccupancyDataset, SampleError
from occkit.data.labels import read_occ3d_labels
from occkit.data.transforms import BevAugConfig
from occkit.engine.evaluate import dataset_ray_origins, evaluate_model
from occkit.geometry.grid import OCC3D_GRID
from occkit.label_files import write_occ3d_labels
from occkit.metrics.evaluate import evaluate_predictions, read_prediction_flow, write_prediction
from occkit.metrics.rayiou import FLOW_CLASSES, cast_rays_exact, occ_score, rayiou
from occkit.models.deployment import deploy
from occkit.models.heads.flow import FlowHead, FlowHeadConfig, MotionConfig, MotionEncoder
from occkit.sim.labels import occupancy_flow_labels, occupancy_labels
from occkit.sim.world import WorldConfig, generate_world

GOLDEN = Path(__file__).parent / "golden" / "occupancy_flow"
FREE = OCC3D.empty_index


@pytest.fixture(scope="module")
def world_root(small_world) -> Path:
    return small_world


def _config(root: Path, **changes) -> DatasetConfig:
    return DatasetConfig(root=str(root), split="all", cameras=("CAM_FRONT", "CAM_BACK"), sweeps=0, flow=True,
                         **changes)  # fmt: skip


# ------------------------------------------------------------------------------------------ ground truth
def _inside_box(centres: np.ndarray, box, pose: np.ndarray, margin: float) -> np.ndarray:
    """Voxel centres (ego) inside ``box`` (global), its footprint grown by ``margin`` (negative: shrunk)."""
    world = centres @ pose[:3, :3].T + pose[:3, 3]
    offset = world[:, :2] - box.center[:2]
    c, s = math.cos(box.yaw), math.sin(box.yaw)
    along, across = offset @ np.array([c, s]), offset @ np.array([-s, c])
    width, length, height = box.size
    return ((np.abs(along) <= length / 2 + margin) & (np.abs(across) <= width / 2 + margin)
            & (world[:, 2] >= -margin) & (world[:, 2] <= height + margin))  # fmt: skip


def test_flow_labels_equal_the_box_velocity_of_every_agent_voxel():
    world = generate_world(7, WorldConfig(duration=4.0, density=0.5))
    t = 2.0
    primitives, pose = world.primitives(t), world.ego_pose(t)
    labels, flow = occupancy_flow_labels(primitives, world.primitive_velocities(t), world.ground, pose)
    assert flow.dtype == np.float32 and flow.shape == (*OCC3D_GRID.shape, 2)
    assert np.array_equal(labels, occupancy_labels(primitives, world.ground, pose))
    centres = OCC3D_GRID.centers(dtype=torch.float64).reshape(-1, 3).numpy()
    flat_labels, flat_flow = labels.reshape(-1), flow.reshape(-1, 2)
    moving = np.abs(flat_flow).sum(axis=1) > 0
    explained = np.zeros_like(moving)
    checked = 0
    half_diagonal = 0.5 * math.sqrt(2) * OCC3D_GRID.voxel_size[0]
    for box in world.boxes(t):
        if not box.velocity.any():
            continue
        expected = (pose[:2, :2].T @ box.velocity).astype(np.float32)  # global -> ego
        cls = NUSCENES_TO_OCC3D[box.category]
        # Voxels well inside the box and of its class belong to it: their flow is its velocity, exactly.
        core = _inside_box(centres, box, pose, -half_diagonal) & (flat_labels == cls)
        assert np.array_equal(flat_flow[core], np.broadcast_to(expected, (int(core.sum()), 2))), box.category
        checked += int(core.sum())
        near = _inside_box(centres, box, pose, half_diagonal)
        explained |= near & (flat_flow == expected).all(axis=1)
    assert checked > 100
    # Every voxel that moves lies at a moving box with that box's velocity; nothing else moves.
    assert moving.any() and not (moving & ~explained).any()
    assert not moving[flat_labels == FREE].any()


def test_the_world_writes_flow_beside_the_semantics_as_openocc_does(world_root):
    path = next(iter(sorted((world_root / "gts").glob("*/*/labels.npz"))))
    with np.load(path) as archive:
        assert set(archive.files) == {"semantics", "mask_lidar", "mask_camera", "flow", "instances", "instance_ids",
                                      "instance_tokens"}
        assert archive["flow"].dtype == np.float32 and archive["flow"].shape == (200, 200, 16, 2)
    labels = read_occ3d_labels(path, flow=True)
    assert labels.flow is not None and np.abs(labels.flow).max() > 0.1
    assert read_occ3d_labels(path).flow is None  # read only when asked for


def test_labels_without_flow_are_named(tmp_path):
    semantics = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    path = tmp_path / "labels.npz"
    write_occ3d_labels(path, semantics, semantics > 0, semantics > 0)
    with pytest.raises(ValueError, match=rf"{path}: has no flow .*occkit sim"):
        read_occ3d_labels(path, flow=True)
    write_occ3d_labels(path, semantics, semantics > 0, semantics > 0, np.full((*OCC3D_GRID.shape, 2), np.nan))
    with pytest.raises(ValueError, match="flow holds .* not finite"):
        read_occ3d_labels(path, flow=True)


# ------------------------------------------------------------------------------------------ augmentation
def test_a_flipped_sample_has_the_flipped_flow(world_root):
    plain = OccupancyDataset(_config(world_root))[0]
    assert plain.voxel_flow.shape == (200, 200, 16, 2)
    for flip_x, flip_y in ((1.0, 0.0), (0.0, 1.0), (1.0, 1.0)):
        config = _config(world_root, augment=True, bev_aug=BevAugConfig(flip_x=flip_x, flip_y=flip_y))
        flipped = OccupancyDataset(config)[0]
        axes = [axis for axis, p in enumerate((flip_x, flip_y)) if p]
        sign = torch.tensor([-1.0 if flip_x else 1.0, -1.0 if flip_y else 1.0])
        assert torch.equal(flipped.voxel_flow, torch.flip(plain.voxel_flow, dims=axes) * sign)
        assert torch.equal(flipped.voxel_semantics, torch.flip(plain.voxel_semantics, dims=axes))


def test_a_quarter_turn_turns_the_vectors_with_the_voxels(world_root):
    plain = OccupancyDataset(_config(world_root))[0]
    config = _config(world_root, augment=True, bev_aug=BevAugConfig(flip_x=0.0, flip_y=0.0, rotate_deg=(90.0, 90.0)))
    turned = OccupancyDataset(config)[0]
    # A quarter turn about z maps voxel (i, j) to (199 - j, i) on the symmetric grid and (vx, vy) to (-vy, vx).
    expected = torch.rot90(plain.voxel_flow, k=1, dims=(0, 1))
    expected = torch.stack((-expected[..., 1], expected[..., 0]), dim=-1)
    assert torch.equal(turned.voxel_semantics, torch.rot90(plain.voxel_semantics, k=1, dims=(0, 1)))
    torch.testing.assert_close(turned.voxel_flow, expected, atol=1e-5, rtol=0)


def test_flow_needs_occupancy_and_a_label_file_with_flow(world_root, tmp_path):
    with pytest.raises(ValueError, match="flow = true needs occupancy = true"):
        DatasetConfig(flow=True, occupancy=False)
    path = next(iter(sorted((world_root / "gts").glob("*/*/labels.npz"))))
    copy = tmp_path / "gts" / path.parent.parent.name / path.parent.name / "labels.npz"
    labels = read_occ3d_labels(path)
    write_occ3d_labels(copy, labels.semantics, labels.mask_lidar, labels.mask_camera)
    dataset = OccupancyDataset(_config(world_root, label_root=str(tmp_path / "gts")))
    index = next(i for i, r in enumerate(dataset.records) if r.token == path.parent.name)
    with pytest.raises(SampleError, match=f"sample {path.parent.name}: .*labels.npz: has no flow"):
        dataset[index]


# ------------------------------------------------------------------------------------------ head
def test_the_flow_loss_is_an_l1_over_the_occupied_voxels_only():
    config = FlowHeadConfig(in_channels=4, height=2, loss_weight=0.5, balanced=False)
    head = FlowHead(config)
    labels = torch.full((1, 2, 2, 2), FREE, dtype=torch.uint8)
    labels[0, 0, 0, 0], labels[0, 1, 1, 1], labels[0, 0, 1, 1], labels[0, 1, 0, 1] = 4, 11, 13, 255  # ignored last
    flow = torch.zeros(1, 2, 2, 2, 2)
    flow[0, 1, 1, 1] = torch.tensor([0.5, 0.5])
    target = torch.full((1, 2, 2, 2, 2), 100.0)  # huge everywhere that must not count
    target[0, 0, 0, 0], target[0, 1, 1, 1], target[0, 0, 1, 1] = torch.tensor([3.0, -1.0]), 0.0, 0.0
    # One mean over the 3 occupied voxels and both components.
    assert float(head.loss(flow, target, labels)) == pytest.approx(0.5 * (3 + 1 + 0.5 + 0.5) / 6)
    # Balanced: the moving voxel's mean and the two static voxels' mean, averaged.
    balanced = FlowHead(dataclasses.replace(config, balanced=True))
    assert float(balanced.loss(flow, target, labels)) == pytest.approx(0.5 * ((3 + 1) / 2 + (0.5 + 0.5) / 4) / 2)
    out = head(torch.randn(1, 2, 2, 4))  # the occupancy head's per-cell features
    assert out.shape == (1, 2, 2, 2, 2)
    with pytest.raises(ValueError, match="data.flow = true"):
        head.loss(out, None, labels)


def test_the_motion_input_counts_each_sweep_in_its_own_channel():
    encoder = MotionEncoder(MotionConfig(sweeps=2), OCC3D_GRID)
    points = torch.tensor([[[0.1, 0.1, 0.0, 9.0, 0.0],      # key frame, column (100, 100)
                            [0.3, 0.2, 1.0, 9.0, 0.0],      # the same column, higher up
                            [0.1, 0.1, 0.0, 9.0, 0.049],    # first sweep (lag rounds to 1 period)
                            [-39.9, 39.9, 0.0, 9.0, 0.3],   # older than 2 sweeps: the last channel, column (0, 199)
                            [0.1, 0.1, 6.0, 9.0, 0.0],      # above the grid
                            [45.0, 0.1, 0.0, 9.0, 0.0],     # beyond it
                            [0.1, 0.1, 0.0, 9.0, 0.0]]])    # padding past num_points
    counts = encoder.rasterise(points, torch.tensor([6]), torch.eye(4)[None])
    expected = torch.zeros(1, 3, 200, 200)
    expected[0, 0, 100, 100], expected[0, 1, 100, 100], expected[0, 2, 0, 199] = 2, 1, 1
    assert torch.equal(counts, torch.log1p(expected))
    # The points are moved into the grid's frame first: a flip of x moves the count to the mirrored column.
    flip = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))[None]
    assert torch.equal(encoder.rasterise(points, torch.tensor([6]), flip), torch.log1p(expected).flip(2))
    assert encoder(points, torch.tensor([6]), torch.eye(4)[None]).shape == (1, 200, 200, 32)


def test_the_motion_input_lands_on_the_labelled_columns_under_augmentation(world_root):
    experiment = zoo.experiment("daocc_tiny_flow")
    bev_aug = BevAugConfig(flip_x=0.5, flip_y=0.5, rotate_deg=(-22.5, 22.5), scale=(0.95, 1.05))
    data = dataclasses.replace(experiment.data, root=str(world_root), split="all", cameras=("CAM_FRONT", "CAM_BACK"),
                               augment=True, bev_aug=bev_aug)  # fmt: skip
    dataset = OccupancyDataset(data)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    for index in range(len(dataset)):
        batch = collate([dataset[index]])
        counts = model.flow_head.motion.rasterise(batch.points, batch.num_points, model.plan(batch).points_to_grid)
        occupied = ((batch.voxel_semantics != FREE) & (batch.voxel_semantics != OCC3D.ignore_index)).any(-1)
        hit = counts[0, 0] > 0  # key-frame points: they lie on the surfaces the labels were made from
        assert hit.sum() > 1000 and occupied[0][hit].float().mean() > 0.98


def test_camera_only_models_refuse_the_lidar_motion_input():
    for name in ("flashocc_tiny_flow", "da_occ_tiny_flow"):
        model = zoo.experiment(name).model
        with pytest.raises(ValueError, match="flow.motion"):
            dataclasses.replace(model, flow=dataclasses.replace(model.flow, motion=MotionConfig()))


@pytest.mark.parametrize("name", ["flashocc_tiny_flow", "da_occ_tiny_flow", "da_occ_tiny_temporal_flow",
                                  "daocc_tiny_flow"])
def test_flow_entries_train_on_flow_and_predict_it(world_root, name):
    experiment = zoo.experiment(name)
    assert experiment.data.flow and experiment.model.flow is not None
    data = dataclasses.replace(experiment.data, root=str(world_root), split="all", cameras=("CAM_FRONT", "CAM_BACK"))
    batch = collate([OccupancyDataset(data)[i] for i in range(2)])
    torch.manual_seed(0)
    model = zoo.build_from_config(experiment.architecture, experiment.model).train()
    memory = model.stream() if model.temporal is not None else None
    output = model(batch, memory=memory) if memory is not None else model(batch)
    losses = model.loss(output, batch)
    assert output.flow.shape == (2, 200, 200, 16, 2) and losses["flow"] > 0
    sum(losses.values()).backward()
    assert model.flow_head.predictor[-1].weight.grad.abs().sum() > 0
    if model.flow_head.motion is not None:
        assert model.flow_head.motion.cnn[0].weight.grad.abs().sum() > 0
    model.eval()
    prediction = model.predict(batch, memory=model.stream()) if memory is not None else model.predict(batch)
    assert prediction.flow.shape == (2, 200, 200, 16, 2)


# ------------------------------------------------------------------------------------------ metric
def test_mave_and_occscore_equal_the_challenge_algorithm_on_the_golden_frames():
    with np.load(GOLDEN / "inputs.npz") as archive:
        inputs = {key: archive[key] for key in archive.files}
    reference = json.loads((GOLDEN / "reference.json").read_text())
    origins = [inputs["origins"][i, : inputs["n_origins"][i]] for i in range(len(inputs["semantics"]))]
    flow_gt, flow_pred = _golden_flows(inputs)
    result = rayiou(inputs["semantics"], inputs["pred"], origins, flow_gt, flow_pred)
    assert result["counts"]["gt"] == reference["counts"]["gt_cnt"]
    assert result["counts"]["ave_count"] == reference["counts"]["ave_count"]["2"]
    for key in ("rayiou", "mave", "occ_score"):
        assert result[key] == pytest.approx(reference[key], abs=1e-9), key
    ave = [None if math.isnan(v) else v for v in result["ave_per_class"]]
    assert ave == pytest.approx(reference["ave_per_class"], abs=1e-9)
    flow_ids = [OCC3D.index(name) for name in FLOW_CLASSES]
    sums = reference["counts"]["ave_sum"]["2"]
    assert [result["counts"]["ave_sum"][c] for c in flow_ids] == pytest.approx([sums[c] for c in flow_ids], abs=1e-9)
    zero = rayiou(inputs["semantics"], inputs["pred"], origins, flow_gt, [np.zeros_like(f) for f in flow_pred])
    for key in ("mave", "occ_score"):
        assert zero[key] == pytest.approx(reference["zero_flow"][key], abs=1e-9), key
    # No true-positive ray of a moving class: mAVE and OccScore are NaN, as the reference's.
    slot = int(inputs["edge_slot"])
    edge = rayiou([inputs["semantics"][slot]], [inputs["edge_pred"]], [origins[slot]], [flow_gt[slot]],
                  [flow_pred[slot]])  # fmt: skip
    assert edge["rayiou"] == pytest.approx(reference["edge_cases"]["no_flow_tp"]["rayiou"], abs=1e-12)
    assert math.isnan(edge["mave"]) and math.isnan(edge["occ_score"]) and reference["edge_cases"]["no_flow_tp"][
        "occ_score"] is None  # fmt: skip
    perfect = rayiou(inputs["semantics"], inputs["semantics"], origins, flow_gt, flow_gt)
    assert (perfect["rayiou"], perfect["mave"], perfect["occ_score"]) == (1.0, 0.0, 1.0)


def _golden_flows(inputs: dict) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """The dense flows of the golden inputs (stored dense or as voxel indices and values)."""
    if "flow_gt" in inputs:
        return list(inputs["flow_gt"]), list(inputs["flow_pred"])
    dense = {}
    for kind in ("gt", "pred"):
        flows = np.zeros((len(inputs["semantics"]), *OCC3D_GRID.shape, 2), np.float32)
        index, values = inputs[f"flow_{kind}_index"], inputs[f"flow_{kind}_values"]
        flows[tuple(index.T)] = values
        dense[kind] = list(flows)
    return dense["gt"], dense["pred"]


def test_flow_is_read_where_the_ray_stops():
    labels = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    labels[110, 100, 2] = 4  # a car voxel 4 m ahead of an origin at the grid centre
    label, distance, voxel = cast_rays_exact(labels, np.array([[0.2, 0.2, 0.0]]), voxels=True)
    hits = label == 4
    assert hits.any() and (voxel[hits] == [110, 100, 2]).all()
    missed = ~hits
    assert (labels[tuple(voxel[missed].T)] == FREE).all()  # the last voxel inside the grid, free
    gt_flow = np.zeros((*OCC3D_GRID.shape, 2), np.float32)
    gt_flow[110, 100, 2] = (3.0, 4.0)
    origins = [np.array([[0.2, 0.2, 0.0]])]
    perfect = rayiou([labels], [labels], origins, [gt_flow], [gt_flow])
    still = rayiou([labels], [labels], origins, [gt_flow], [np.zeros_like(gt_flow)])
    assert perfect["mave"] == 0.0 and perfect["occ_score"] == pytest.approx(0.9 * perfect["rayiou"] + 0.1)
    assert still["mave"] == pytest.approx(5.0) and still["occ_score"] == pytest.approx(0.9 * still["rayiou"])
    # Without a true-positive ray of a moving class mAVE is undefined, and OccScore with it (the reference's NaN).
    empty = np.full(OCC3D_GRID.shape, FREE, np.uint8)
    none = rayiou([labels], [empty], origins, [gt_flow], [gt_flow])
    assert math.isnan(none["mave"]) and math.isnan(none["occ_score"])
    assert math.isnan(occ_score(0.5, float("nan"))) and occ_score(0.5, 3.0) == pytest.approx(0.45)
    assert len(FLOW_CLASSES) == 8


def test_eval_preds_reports_mave_when_predictions_carry_flow(world_root, tmp_path):
    dataset = OccupancyDataset(_config(world_root))
    origins = dataset_ray_origins(dataset)
    gts, gt_flows, preds, pred_flows = [], [], tmp_path / "preds", []
    preds.mkdir()
    rng = np.random.default_rng(0)
    for i, record in enumerate(dataset.records):
        sample = dataset[i]
        semantics, flow = sample.voxel_semantics.numpy(), sample.voxel_flow.numpy()
        noisy = (flow + rng.normal(0, 0.5, flow.shape) * (flow != 0)).astype(np.float32)
        write_prediction(preds, record.token, semantics, noisy)
        gts.append(semantics), gt_flows.append(flow), pred_flows.append(noisy)
    assert np.array_equal(read_prediction_flow(preds / f"{dataset.records[0].token}.npz"), pred_flows[0])
    result = evaluate_predictions(world_root / "gts", preds, ray_origins=origins, compute_rayiou=True, workers=2)
    direct = rayiou(gts, gts, [origins[r.token] for r in dataset.records], gt_flows, pred_flows)
    assert 0.1 < result["mave"] < 1.0
    assert result["mave"] == pytest.approx(direct["mave"], rel=1e-12)
    assert result["occ_score"] == pytest.approx(direct["occ_score"], rel=1e-12)
    # A mix of predictions with and without flow is an error; none carrying flow gives RayIoU alone.
    write_prediction(preds, dataset.records[0].token, gts[0])
    with pytest.raises(ValueError, match="predictions carry flow"):
        evaluate_predictions(world_root / "gts", preds, ray_origins=origins, compute_rayiou=True)


def test_evaluating_a_flow_model_reports_mave_and_occscore(world_root, tmp_path):
    experiment = zoo.experiment("flashocc_tiny_flow")
    data = dataclasses.replace(experiment.data, root=str(world_root), split="all", cameras=("CAM_FRONT", "CAM_BACK"),
                               sweeps=-1, augment=False)  # fmt: skip
    dataset = OccupancyDataset(data)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    result = evaluate_model(model, dataset, ray_origins=dataset_ray_origins(dataset), predictions=tmp_path)
    assert {"mave", "occ_score", "rayiou"} <= set(result)
    with np.load(next(tmp_path.glob("*.npz"))) as archive:
        assert archive["flow"].shape == (200, 200, 16, 2)
    # On labels read without flow the model is scored as any other.
    plain = OccupancyDataset(dataclasses.replace(data, flow=False))
    without = evaluate_model(model, plain, ray_origins=dataset_ray_origins(plain))
    assert "rayiou" in without and "mave" not in without


def test_the_fixed_rig_network_leaves_a_motion_flow_head_out_by_name(world_root):
    experiment = zoo.experiment("daocc_tiny_flow")
    data = dataclasses.replace(experiment.data, root=str(world_root), split="all", cameras=("CAM_FRONT", "CAM_BACK"),
                               augment=False)  # fmt: skip
    batch = collate([OccupancyDataset(data)[0]])
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    with pytest.raises(ValueError, match="flow_head = None"):
        deploy(model, batch)
