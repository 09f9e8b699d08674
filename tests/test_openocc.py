"""The OpenOcc v2 label space: its classes, the world's ``openocc_v2/`` files, RayIoU / mAVE / OccScore on them, and a
flow model trained and scored on them."""

from __future__ import annotations

import dataclasses
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from occkit import zoo
from occkit.classes import OCC3D, OCC3D_TO_OPENOCC, OPENOCC
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.labels import LabelError, read_occ3d_labels, read_openocc_labels
from occkit.engine.evaluate import dataset_ray_origins, evaluate_model
from occkit.label_files import occ3d_to_openocc, write_openocc_labels
from occkit.label_space import OPENOCC_SPACE, label_space
from occkit.metrics.evaluate import evaluate_predictions, write_prediction
from occkit.metrics.rayiou import rayiou
from occkit.models.heads.occupancy import OCC3D_CLASS_FREQUENCIES, class_frequencies

CAMERAS = ("CAM_FRONT", "CAM_BACK")
REPO = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def world(small_world) -> Path:
    return small_world


def test_the_classes_are_the_challenges_and_map_from_occ3d_by_name():
    assert OPENOCC.classes[:3] == ("car", "truck", "trailer") and OPENOCC.empty_index == 16 == OPENOCC.num_classes - 1
    assert "others" not in OPENOCC.classes
    for occ3d_id, name in enumerate(OCC3D.classes):
        expected = "free" if name == "others" else name
        assert OPENOCC.classes[OCC3D_TO_OPENOCC[occ3d_id]] == expected
    space = label_space("openocc")
    assert space.grid.shape == (200, 200, 16) and space.masks == () and space.default_mask is None and space.rayiou
    # The class balance of an OpenOcc head: Occ3D's voxels in OpenOcc's classes, "others" counted as free.
    frequencies = class_frequencies(OPENOCC.num_classes, OPENOCC.empty_index)
    assert sum(frequencies) == sum(OCC3D_CLASS_FREQUENCIES)
    assert frequencies[16] == OCC3D_CLASS_FREQUENCIES[17] + OCC3D_CLASS_FREQUENCIES[0]
    assert frequencies[OPENOCC.index("car")] == OCC3D_CLASS_FREQUENCIES[OCC3D.index("car")]
    with pytest.raises(ValueError, match="not of 5 classes"):
        class_frequencies(5, 4)


def test_the_world_writes_openocc_labels_beside_occ3d(world, tmp_path):
    occ3d = sorted((world / "gts").glob("*/*/labels.npz"))
    openocc = sorted((world / "openocc_v2").glob("*/*/labels.npz"))
    assert len(occ3d) == len(openocc) == 4
    for gt_path, path in zip(occ3d, openocc, strict=True):
        assert path.relative_to(world / "openocc_v2") == gt_path.relative_to(world / "gts")
        with np.load(path) as archive:
            assert sorted(archive.files) == ["flow", "semantics"]  # no visibility mask, as the challenge's
        gt = read_occ3d_labels(gt_path, flow=True)
        labels = read_openocc_labels(path, flow=True)
        assert labels.mask_camera is None and labels.mask_lidar is None
        np.testing.assert_array_equal(labels.semantics, occ3d_to_openocc(gt.semantics))
        np.testing.assert_array_equal(labels.flow, gt.flow)
    # An Occ3D file read as OpenOcc: ids beyond 0..16 are named.
    bad = tmp_path / "bad.npz"
    write_openocc_labels(bad, np.full((200, 200, 16), 17, np.uint8), np.zeros((200, 200, 16, 2), np.float32))
    with pytest.raises(LabelError, match=r"beyond 0\.\.16 of openocc"):
        read_openocc_labels(bad)


def test_rayiou_on_openocc_labels_is_occ3ds_by_class_name(world):
    """The same scene in both label spaces gives each class the same RayIoU, and the same mAVE: the free id and the
    moving classes' ids come from the label space. (Occ3D's "others", which OpenOcc makes free, is made free in the
    Occ3D grids too, so that both describe one scene.)"""
    dataset = OccupancyDataset(DatasetConfig(root=str(world), split="all", cameras=(), sweeps=-1, flow=True))
    origins = [dataset_ray_origins(dataset)[record.token] for record in dataset.records]
    grids = [read_occ3d_labels(dataset.label_path(r), flow=True) for r in dataset.records]
    others, free = OCC3D.index("others"), OCC3D.empty_index
    gts = [np.where(g.semantics == others, free, g.semantics).astype(np.uint8) for g in grids]
    # A prediction that moves every grid one voxel along x and halves the flow: errors in depth, class and velocity.
    preds = [np.roll(gt, 1, axis=0) for gt in gts]
    flows = [g.flow for g in grids]
    pred_flows = [np.roll(f, 1, axis=0) * 0.5 for f in flows]
    occ3d = rayiou(gts, preds, origins, flows, pred_flows)
    openocc = rayiou([occ3d_to_openocc(g) for g in gts], [occ3d_to_openocc(p) for p in preds], origins, flows,
                     pred_flows, space=OPENOCC_SPACE)  # fmt: skip
    for threshold in (1, 2, 4):
        for name in OPENOCC.classes[:-1]:
            a = occ3d["per_class"][threshold][OCC3D.index(name)]
            b = openocc["per_class"][threshold][OPENOCC.index(name)]
            assert (np.isnan(a) and np.isnan(b)) or a == b, (threshold, name)
    assert openocc["mave"] == pytest.approx(occ3d["mave"], abs=1e-12) and np.isfinite(openocc["mave"])
    assert len(openocc["counts"]["gt"]) == 17 and len(openocc["per_class"][1]) == 16


def test_eval_preds_scores_openocc_with_rayiou_mave_and_occscore_and_no_mask(world, tmp_path):
    dataset = OccupancyDataset(DatasetConfig(root=str(world), split="all", cameras=(), sweeps=-1,
                                             label_space="openocc", flow=True))  # fmt: skip
    for index, record in enumerate(dataset.records):
        sample = dataset[index]
        write_prediction(tmp_path / "preds", record.token, sample.voxel_semantics.numpy(), sample.voxel_flow.numpy())
    result = evaluate_predictions(world / "openocc_v2", tmp_path / "preds", ray_origins=dataset_ray_origins(dataset),
                                  compute_rayiou=True, space="openocc")  # fmt: skip
    assert result["label_space"] == "openocc" and result["mask"] == "none"
    assert result["miou"] == 1.0 and result["rayiou"] == 1.0 and result["mave"] == 0.0 and result["occ_score"] == 1.0
    with pytest.raises(ValueError, match="cannot be scored under the camera mask"):
        evaluate_predictions(world / "openocc_v2", tmp_path / "preds", mask="camera", space="openocc")
    # The command line names the benchmark in its report.
    out = tmp_path / "report"
    command = [sys.executable, "-m", "occkit", "eval-preds", "--gt", str(world / "openocc_v2"), "--preds",
               str(tmp_path / "preds"), "--out", str(out), "--label-space", "openocc", "--rayiou", "--nuscenes",
               str(world), "--version", "v1.0-synth"]  # fmt: skip
    done = subprocess.run(command, cwd=REPO, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    report = (out / "metrics.md").read_text()
    assert report.startswith("OpenOcc v2 (nuScenes), 4 frames, mask: none") and "| mAVE (m/s) | OccScore |" in report


def test_daocc_tiny_flow_trains_on_openocc_and_is_scored_as_the_challenge(world):
    experiment = zoo.experiment("daocc_tiny_flow_openocc")
    assert experiment.data.label_space == "openocc" and experiment.model.occupancy.num_classes == 17
    assert experiment.model.occupancy.free_index == experiment.model.flow.free_index == 16
    assert not experiment.model.occupancy.use_mask
    data = dataclasses.replace(experiment.data, root=str(world), split="all", cameras=CAMERAS, sweeps=1)
    dataset = OccupancyDataset(data)
    model = zoo.build_from_config(experiment.architecture, experiment.model)
    optimizer = torch.optim.AdamW(model.parameters(), lr=1e-3)
    from occkit.data.collate import collate

    torch.manual_seed(0)
    model.train()
    for step in range(2):  # a few steps on OpenOcc's labels, every voxel in the loss
        batch = collate([dataset[step]])
        assert batch.mask_camera is None and int(batch.voxel_semantics.max()) <= 16
        losses = model.loss(model(batch), batch)
        optimizer.zero_grad()
        sum(losses.values()).backward()
        optimizer.step()
        assert {"occupancy", "flow"} <= set(losses) and all(torch.isfinite(v) for v in losses.values())
    scored = OccupancyDataset(dataclasses.replace(data, augment=False))
    result = evaluate_model(model, scored, ray_origins=dataset_ray_origins(scored))
    assert result["label_space"] == "openocc" and result["mask"] is None
    assert {"rayiou", "mave", "occ_score"} <= set(result) and 0.0 <= result["rayiou"] <= 1.0
