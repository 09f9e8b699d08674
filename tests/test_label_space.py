"""Label spaces end to end: SurroundOcc labels read, augmented, trained on, scored and drawn; mixing spaces refused.

One small synthetic world written with ``--surroundocc`` (Occ3D labels and SurroundOcc labels side by side) serves
every test: 2 scenes x 2 key frames, 2 cameras at 176 x 99.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
import torch

from occkit.classes import SURROUNDOCC
from occkit.cli import main
from occkit.data.dataset import DatasetConfig, OccupancyDataset
from occkit.data.transforms import BevAugConfig
from occkit.label_space import OCC3D_SPACE, SURROUNDOCC_SPACE
from occkit.sim.generate import SimConfig, simulate_dataset

CAMERAS = ("CAM_FRONT", "CAM_BACK")
#: A two-step daocc_surroundocc_tiny run on the world's two cameras at its image size.
TRAIN = ("--config", "daocc_surroundocc_tiny", "--device", "cpu", "--no-progress",
         "--set", "data.cameras=[CAM_FRONT, CAM_BACK]", "--set", "data.image_aug.final_size=[64, 176]",
         "--set", "data.sweeps=0", "--set", "train.max_steps=2", "--set", "train.workers=0",
         "--set", "train.log_every=1")  # fmt: skip


@pytest.fixture(scope="module")
def world(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("label_space") / "world"
    simulate_dataset(SimConfig(scenes=2, frames=2, seed=3, image_size=(176, 99), cameras=CAMERAS, surroundocc=True),
                     root)  # fmt: skip
    return root


@pytest.fixture(scope="module")
def run(world, tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("label_space") / "run"
    assert main(["train", *TRAIN, "--out", str(out), "--set", f"data.root={world}"]) == 0
    return out


def _dataset(world: Path, **options) -> OccupancyDataset:
    defaults = {"root": str(world), "split": "all", "cameras": (), "sweeps": 0, "boxes": False,
                "label_space": "surroundocc"}  # fmt: skip
    return OccupancyDataset(DatasetConfig(**{**defaults, **options}))


def test_the_world_writes_surroundoccs_layout(world):
    files = sorted((world / "surroundocc" / "samples").iterdir())
    assert len(files) == 4 and all(f.name.endswith(".pcd.bin.npy") and "LIDAR_TOP" in f.name for f in files)
    rows = np.load(files[0])
    assert rows.ndim == 2 and rows.shape[1] == 4 and np.issubdtype(rows.dtype, np.integer)
    assert (rows[:, :3] >= 0).all() and (rows[:, :3] < np.array(SURROUNDOCC_SPACE.grid.shape)).all()


def test_the_dataset_reads_surroundocc_labels_without_masks(world):
    sample = _dataset(world)[0]
    semantics = sample.voxel_semantics.numpy()
    assert semantics.shape == SURROUNDOCC_SPACE.grid.shape and sample.mask_camera is None
    present = set(np.unique(semantics).tolist())
    assert present <= set(range(SURROUNDOCC.num_classes)) | {SURROUNDOCC.ignore_index}
    assert SURROUNDOCC.empty_index in present and len(present - {0, 255}) >= 3  # empty, and some classes


def test_a_bev_flip_moves_surroundocc_labels_as_it_moves_the_points(world):
    """LiDAR-frame labels flip with the points: a flip of the LiDAR x axis mirrors the grid's axis 0."""
    plain = _dataset(world, sweeps=0)
    flipped = _dataset(world, augment=True, bev_aug=BevAugConfig(flip_x=1.0, flip_y=0.0))
    a, b = plain[1], flipped[1]
    assert torch.equal(b.bev_aug[:3, :3], torch.diag(torch.tensor([-1.0, 1.0, 1.0])))  # the LiDAR frame's x
    np.testing.assert_array_equal(b.voxel_semantics.numpy(), a.voxel_semantics.numpy()[::-1])
    torch.testing.assert_close(b.points[:, 0], -a.points[:, 0])
    # The points of an occupied voxel stay on occupied voxels of the same class.
    grid = SURROUNDOCC_SPACE.grid
    for sample in (a, b):
        index, inside = grid.world_to_index(sample.points[:, :3].double())
        labels = sample.voxel_semantics[tuple(index[inside].T)]
        assert (labels != SURROUNDOCC.empty_index).float().mean() > 0.5


def test_train_eval_and_eval_preds_score_surroundocc(world, run, tmp_path):
    out = tmp_path / "eval"
    assert main(["eval", "--ckpt", str(run / "best.pt"), "--data", str(world), "--split", "all", "--out", str(out),
                 "--workers", "0", "--device", "cpu", "--save-predictions"]) == 0  # fmt: skip
    metrics = json.loads((out / "metrics.json").read_text())  # every frame: eval-preds scores the whole label tree
    assert metrics["label_space"] == "surroundocc" and metrics["mask"] is None
    assert 0.0 <= metrics["iou"] <= 1.0 and 0.0 <= metrics["miou"] <= 1.0
    assert set(metrics["per_class_iou"]) <= set(SURROUNDOCC.classes) and "car" in metrics["per_class_iou"]
    assert "rayiou" not in metrics
    again = tmp_path / "again"
    assert main(["eval-preds", "--preds", str(out / "predictions"), "--gt", str(world / "surroundocc"),
                 "--label-space", "surroundocc", "--nuscenes", str(world), "--version", "v1.0-synth",
                 "--out", str(again)]) == 0  # fmt: skip
    scored = json.loads((again / "metrics.json").read_text())
    assert scored["miou"] == pytest.approx(metrics["miou"], abs=1e-12)
    assert scored["iou"] == pytest.approx(metrics["iou"], abs=1e-12)


def test_rayiou_on_surroundocc_and_mixed_spaces_are_one_line_errors(world, run, tmp_path, capsys):
    assert main(["eval-preds", "--preds", str(tmp_path), "--gt", str(world / "surroundocc"), "--label-space",
                 "surroundocc", "--nuscenes", str(world), "--rayiou", "--out", str(tmp_path / "e")]) == 2  # fmt: skip
    assert "RayIoU is not defined for surroundocc" in capsys.readouterr().err
    # A SurroundOcc model scored on Occ3D labels.
    assert main(["eval", "--ckpt", str(run / "best.pt"), "--data", str(world), "--out", str(tmp_path / "mixed"),
                 "--workers", "0", "--device", "cpu", "--set", "data.label_space=occ3d"]) == 2  # fmt: skip
    error = capsys.readouterr().err.strip().splitlines()
    assert len(error) == 1 and "label_space" in error[0] and "occ3d" in error[0]


def test_viz_draws_surroundocc_labels_and_predictions_in_the_lidar_frame(world, run, tmp_path):
    out = tmp_path / "viz"
    assert main(["viz", "--data", str(world), "--ckpt", str(run / "best.pt"), "--frames", "1", "--dpi", "40",
                 "--out", str(out)]) == 0  # fmt: skip
    index = json.loads((out / "index.json").read_text())
    (frame,) = index["frames"]
    assert {"bev_gt", "voxels_gt", "compare", "voxels_pred", "cameras_gt", "cameras_pred"} <= set(frame["files"])
    assert set(frame["scores"]) == {"miou", "iou"}
    with pytest.raises(ValueError, match="predicts surroundocc labels, not occ3d"):
        from occkit.model_source import ModelSource
        from occkit.viz.run import VizConfig, render_frames

        render_frames(VizConfig(data=str(world), out=str(tmp_path / "v2"), model=ModelSource(ckpt=str(run / "best.pt")),
                                label_space="occ3d"), progress=lambda _: None)  # fmt: skip


def test_surroundocc_voxels_project_through_lidar2ego(world):
    """A SurroundOcc voxel centre is a LiDAR-frame point: the camera overlay must apply lidar2ego."""
    from occkit.viz.cameras import voxel_centres_in_ego

    sample = _dataset(world)[0]
    grid = SURROUNDOCC_SPACE.grid
    index = np.array([[150, 100, 8]])
    lidar = (torch.tensor(index, dtype=torch.float64) + 0.5) * grid.size_tensor(dtype=torch.float64) + \
        grid.lower_tensor(dtype=torch.float64)  # fmt: skip
    expected = lidar @ sample.lidar2ego[:3, :3].double().T + sample.lidar2ego[:3, 3].double()
    torch.testing.assert_close(voxel_centres_in_ego(index, None, grid, sample.lidar2ego), expected.float())


def test_the_zoo_and_the_demo_use_the_spaces_grids():
    from occkit import zoo

    _, surroundocc = zoo.model_config("daocc_surroundocc_tiny")
    assert surroundocc.occ_range == SURROUNDOCC_SPACE.grid.point_cloud_range
    assert surroundocc.occupancy.num_classes == SURROUNDOCC_SPACE.num_classes
    assert zoo.experiment("daocc_surroundocc_tiny").data.label_space == "surroundocc"
    _, occ3d = zoo.model_config("daocc_tiny")
    assert occ3d.occ_range == OCC3D_SPACE.grid.point_cloud_range and occ3d.occupancy.free_index == 17


@pytest.mark.parametrize("entry", ["flashocc_tiny", "da_occ_tiny", "daocc_tiny"])
def test_a_model_whose_grid_differs_from_its_label_space_is_refused(entry):
    """Every architecture says where it predicts (``output_grid``), and an experiment whose model predicts on another
    grid than its labels' is refused in one message naming both grids: a FlashOcc BEV of +-51.2 m, a DA-Occ height
    grid cut into 8 layers, a DAOcc of 0.5 m voxels."""
    import dataclasses

    from occkit import zoo
    from occkit.config import ConfigError
    from occkit.experiment import check_label_space

    _, model = zoo.model_config(entry)
    assert model.output_grid == OCC3D_SPACE.grid
    check_label_space(model, "occ3d")
    if entry == "flashocc_tiny":
        wider = dataclasses.replace(model.lss, point_cloud_range=(-51.2, -51.2, -1.0, 51.2, 51.2, 5.4))
        other = dataclasses.replace(model, lss=wider)
    elif entry == "da_occ_tiny":
        other = dataclasses.replace(model, occupancy=dataclasses.replace(model.occupancy, height=8))
    else:
        other = dataclasses.replace(model, occ_voxel_size=(0.5, 0.5, 0.4))
    with pytest.raises(ConfigError, match=r"the model predicts on VoxelGrid.* but occ3d labels are on"):
        check_label_space(other, "occ3d")
