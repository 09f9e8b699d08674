"""The synthetic world written as nuScenes + Occ3D: layout, determinism, geometric consistency, bad input."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from occkit.cli import main
from occkit.geometry.grid import OCC3D_GRID
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.sim.rig import LIDAR_TOP, pose_matrix
from occkit.sim.world import WorldConfig
from occkit.sim.writer import TABLE_NAMES

TINY = SimConfig(
    scenes=1,
    frames=1,
    seed=3,
    image_size=(176, 64),
    cameras=("CAM_FRONT", "CAM_BACK"),
    world=WorldConfig(density=0.5),
)


@pytest.fixture(scope="module")
def dataset(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("sim") / "data"
    simulate_dataset(TINY, root)
    return root


def _tables(root: Path, version: str = "v1.0-synth") -> dict[str, list[dict]]:
    return {name: json.loads((root / version / f"{name}.json").read_text()) for name in TABLE_NAMES}


def _files(root: Path) -> dict[str, bytes]:
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_layout_is_nuscenes_and_occ3d(dataset):
    tables = _tables(dataset)
    assert len(tables["scene"]) == 1 and len(tables["sample"]) == 1
    sample = tables["sample"][0]
    channels = {}
    for record in tables["sample_data"]:
        assert (dataset / record["filename"]).is_file()
        sensor = next(c for c in tables["calibrated_sensor"] if c["token"] == record["calibrated_sensor_token"])
        channel = next(s["channel"] for s in tables["sensor"] if s["token"] == sensor["sensor_token"])
        channels[channel] = record
        assert record["sample_token"] == sample["token"] and record["is_key_frame"]
    assert set(channels) == {"CAM_FRONT", "CAM_BACK", "LIDAR_TOP"}
    assert channels["CAM_FRONT"]["filename"].startswith("samples/CAM_FRONT/")
    assert (channels["CAM_FRONT"]["width"], channels["CAM_FRONT"]["height"]) == (176, 64)
    points = np.fromfile(dataset / channels["LIDAR_TOP"]["filename"], dtype=np.float32).reshape(-1, 5)
    assert points.shape[0] > 1000 and set(np.unique(points[:, 4])) <= set(range(32))
    for map_record in tables["map"]:
        assert (dataset / map_record["filename"]).is_file()
    scene_name = tables["scene"][0]["name"]
    with np.load(dataset / "gts" / scene_name / sample["token"] / "labels.npz") as labels:
        assert {k: (v.shape, v.dtype) for k, v in labels.items()} == {
            k: ((200, 200, 16), np.uint8) for k in ("semantics", "mask_lidar", "mask_camera")
        }
    infos = json.loads((dataset / "annotations.json").read_text())
    assert infos["train_split"] == [scene_name] and infos["val_split"] == []


def test_same_arguments_give_identical_bytes(dataset, tmp_path):
    again = tmp_path / "again"
    simulate_dataset(TINY, again)
    assert _files(again) == _files(dataset)


def test_lidar_points_fall_in_occupied_voxels(dataset):
    tables = _tables(dataset)
    sample = tables["sample"][0]
    lidar = next(r for r in tables["sample_data"] if r["filename"].startswith("samples/LIDAR_TOP"))
    calibration = next(c for c in tables["calibrated_sensor"] if c["token"] == lidar["calibrated_sensor_token"])
    lidar2ego = pose_matrix(calibration["translation"], calibration["rotation"])
    assert np.allclose(lidar2ego, LIDAR_TOP.lidar2ego)
    points = np.fromfile(dataset / lidar["filename"], dtype=np.float32).reshape(-1, 5)[:, :3].astype(np.float64)
    ego_points = points @ lidar2ego[:3, :3].T + lidar2ego[:3, 3]
    with np.load(dataset / "gts" / tables["scene"][0]["name"] / sample["token"] / "labels.npz") as labels:
        semantics = labels["semantics"]
    import torch

    index, inside = OCC3D_GRID.world_to_index(torch.from_numpy(ego_points))
    index, inside = index.numpy(), inside.numpy()
    # Points on a voxel face may floor into the free neighbour: accept either side of a face within 1 cm.
    occupied = np.zeros(inside.sum(), dtype=bool)
    for offset in np.array([[0, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1]]):
        nudged = OCC3D_GRID.world_to_index(torch.from_numpy(ego_points[inside] + offset * 0.01))[0].numpy()
        nudged = np.clip(nudged, 0, np.array(OCC3D_GRID.shape) - 1)
        occupied |= semantics[nudged[:, 0], nudged[:, 1], nudged[:, 2]] != 17
    assert inside.sum() > 1000
    assert occupied.mean() >= 0.95


def test_boxes_project_into_the_cameras_that_see_them(dataset):
    tables = _tables(dataset)
    ego_pose = {r["token"]: r for r in tables["ego_pose"]}
    cameras = []
    for record in tables["sample_data"]:
        calibration = next(c for c in tables["calibrated_sensor"] if c["token"] == record["calibrated_sensor_token"])
        if calibration["camera_intrinsic"]:
            pose = ego_pose[record["ego_pose_token"]]
            cam2global = pose_matrix(pose["translation"], pose["rotation"]) @ pose_matrix(
                calibration["translation"], calibration["rotation"]
            )
            cameras.append((np.linalg.inv(cam2global), np.array(calibration["camera_intrinsic"]), record))
    visible = 0
    for annotation in tables["sample_annotation"]:
        if annotation["visibility_token"] not in ("3", "4"):
            continue
        centre = np.array(annotation["translation"])
        hits = []
        for global2cam, intrinsic, record in cameras:
            in_cam = global2cam[:3, :3] @ centre + global2cam[:3, 3]
            if in_cam[2] <= 0:
                continue
            u, v = (intrinsic @ in_cam)[:2] / in_cam[2]
            hits.append(0 <= u < record["width"] and 0 <= v < record["height"])
        visible += 1
        assert any(hits), f"annotation {annotation['token']} is well visible but projects into no camera"
    assert visible > 0


def test_existing_output_needs_overwrite_and_failures_leave_nothing(tmp_path, dataset):
    out = tmp_path / "data"
    out.mkdir()
    (out / "keep.txt").write_text("user data")
    with pytest.raises(FileExistsError, match="not empty; pass --overwrite"):
        simulate_dataset(TINY, out)
    assert (out / "keep.txt").read_text() == "user data"
    broken = dataclasses.replace(TINY, cameras=("CAM_FRONT",))
    object.__setattr__(broken, "jpeg_quality", "bad")  # fails while writing the first image
    with pytest.raises(ValueError, match="quality"):
        simulate_dataset(broken, tmp_path / "never")
    assert not (tmp_path / "never").exists() and not list(tmp_path.glob(".never*"))


def test_config_rejects_bad_values():
    with pytest.raises(ValueError, match="unknown cameras"):
        SimConfig(cameras=("CAM_TOP",))
    with pytest.raises(ValueError, match="at least 16x16"):
        SimConfig(image_size=(8, 8))
    with pytest.raises(ValueError, match="plain folder name"):
        SimConfig(version="../v1.0")


def test_cli_errors_are_one_line(tmp_path, capsys):
    out = tmp_path / "data"
    out.mkdir()
    (out / "x").write_text("")
    assert main(["sim", "--out", str(out), "--frames", "1", "--scenes", "1"]) == 2
    assert "pass --overwrite" in capsys.readouterr().err
    with pytest.raises(SystemExit):
        main(["sim", "--out", str(out), "--image-size", "800by450"])
    assert "must look like 800x450" in capsys.readouterr().err
    assert main(["sim", "--out", str(tmp_path / "d2"), "--set", "world.dense=1"]) == 2
    assert "did you mean 'density'" in capsys.readouterr().err


def test_cli_in_parallel_matches_one_process(tmp_path, capsys):
    # Two scenes in two spawned workers give the same bytes as one process; the summary and preview are written.
    arguments = ["--scenes", "2", "--frames", "1", "--seed", "5", "--image-size", "176x64", "--cameras", "CAM_FRONT"]
    assert (
        main(
            [
                "sim",
                "--out",
                str(tmp_path / "par"),
                "--workers",
                "2",
                *arguments,
                "--json",
                str(tmp_path / "summary.json"),
                "--preview",
                str(tmp_path / "sheet.png"),
            ]
        )
        == 0
    )
    out = capsys.readouterr().out
    assert "wrote 2 scenes, 2 key frames" in out
    summary = json.loads((tmp_path / "summary.json").read_text())
    assert summary["samples"] == 2 and summary["annotations"] > 0
    assert (tmp_path / "sheet.png").stat().st_size > 10_000
    serial = SimConfig(scenes=2, frames=1, seed=5, image_size=(176, 64), cameras=("CAM_FRONT",))
    simulate_dataset(serial, tmp_path / "serial")
    assert _files(tmp_path / "par") == _files(tmp_path / "serial")
    splits = json.loads((tmp_path / "serial" / "splits.json").read_text())
    assert splits == {"train": ["scene-0001"], "val": ["scene-0002"]}
