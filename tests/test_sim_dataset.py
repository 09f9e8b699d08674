"""The synthetic world written as nuScenes + Occ3D: layout, determinism, geometric consistency, bad input."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import numpy as np
import pytest

from occkit.classes import NUSCENES_TO_OCC3D
from occkit.cli import main
from occkit.data.consistency import boxes_in_cameras, lidar_in_occupied
from occkit.data.tables import load_tables
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.sim.rig import LIDAR_TOP
from occkit.sim.world import WorldConfig

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
    return load_tables(root, version).tables


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
        objects = labels["instance_ids"].shape[0]
        assert {k: (v.shape, v.dtype.str) for k, v in labels.items()} == {
            **{k: ((200, 200, 16), "|u1") for k in ("semantics", "mask_lidar", "mask_camera")},
            "flow": ((200, 200, 16, 2), "<f4"),  # OpenOcc v2's occupancy flow
            "instances": ((200, 200, 16), "<i4"),  # panoptic: each voxel's object, 0 for stuff
            "instance_ids": ((objects,), "<i4"),
            "instance_tokens": ((objects,), "<U64"),
        }
    infos = json.loads((dataset / "annotations.json").read_text())
    assert infos["train_split"] == [scene_name] and infos["val_split"] == []


def test_lidarseg_labels_every_key_frame_point_as_nuscenes_does(dataset):
    tables = _tables(dataset)
    rows = json.loads((dataset / "v1.0-synth" / "lidarseg.json").read_text())
    key_lidar = [r for r in tables["sample_data"] if r["fileformat"] == "pcd" and r["is_key_frame"]]
    assert [r["token"] for r in rows] == [r["token"] for r in key_lidar]
    assert all(r["sample_data_token"] == r["token"] for r in rows)
    categories = {r["index"]: r["name"] for r in tables["category"]}
    for row, lidar in zip(rows, key_lidar, strict=True):
        assert row["filename"] == f"lidarseg/v1.0-synth/{row['token']}_lidarseg.bin"
        labels = np.fromfile(dataset / row["filename"], dtype=np.uint8)
        points = np.fromfile(dataset / lidar["filename"], dtype=np.float32).reshape(-1, 5)
        assert labels.shape == (len(points),) and 0 not in labels  # every return hit something: no noise
        # The lidarseg category agrees with the Occ3D class of the voxel each point lies in, as far as the exact
        # labels' priorities allow (a point on a car's roof edge may fall in the voxel a pedestrian wins).
        names = {categories[int(i)] for i in np.unique(labels)}
        assert {"flat.driveable_surface", "static.manmade"} <= names
        occ3d = np.array([NUSCENES_TO_OCC3D[categories[int(i)]] for i in labels])
        with np.load(dataset / "gts" / tables["scene"][0]["name"] / lidar["sample_token"] / "labels.npz") as gt:
            semantics = gt["semantics"]
        ego = points[:, :3].astype(np.float64) @ LIDAR_TOP.lidar2ego[:3, :3].T + LIDAR_TOP.lidar2ego[:3, 3]
        index = np.floor((ego - np.array([-40.0, -40.0, -1.0])) / 0.4).astype(int)
        inside = ((index >= 0) & (index < [200, 200, 16])).all(axis=1)
        agree = semantics[tuple(index[inside].T)] == occ3d[inside]
        assert agree.mean() > 0.9


def test_same_arguments_give_identical_bytes(dataset, tmp_path):
    again = tmp_path / "again"
    simulate_dataset(TINY, again)
    assert _files(again) == _files(dataset)


def test_lidar_points_fall_in_occupied_voxels(dataset):
    report = lidar_in_occupied(dataset, "v1.0-synth")
    assert report["key_frames"] == 1 and report["points_in_grid"] > 1000
    assert report["share_in_occupied"] >= 0.95


def test_visible_boxes_project_into_a_camera(dataset):
    report = boxes_in_cameras(dataset, "v1.0-synth")
    assert report["visible_boxes"] > 0
    assert report["centre_in_a_camera"] == report["visible_boxes"], report["misses"]


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
