"""nuScenes tables -> key-frame index: geometry against the simulator's truth, index files, splits, bad input, CLI."""

from __future__ import annotations

import contextlib
import copy
import dataclasses
import json
import os
import pickle
import re
import shutil
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
import torch
from hypothesis import given, settings
from hypothesis import strategies as st

from occkit.classes import NUSCENES_TO_DETECTION
from occkit.cli import main
from occkit.data.index import (
    INDEX_FORMAT,
    FrameRecord,
    FrameRecords,
    IndexFormatError,
    OutdatedIndexError,
    build_index,
    index_tables,
    load_index,
    read_index_header,
    save_index,
    tables_key,
)
from occkit.data.splits import read_split_file, scene_split, split_scenes
from occkit.data.tables import TableError, load_tables
from occkit.geometry.grid import OCC3D_GRID
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.sim.rig import pose_matrix

VERSION = "v1.0-synth"
TINY = SimConfig(scenes=2, frames=3, image_size=(176, 64), cameras=("CAM_FRONT", "CAM_BACK"))


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("index") / "data"
    simulate_dataset(TINY, root)
    return root


@pytest.fixture(scope="module")
def records(root) -> list[FrameRecord]:
    return build_index(root, VERSION)


@pytest.fixture(scope="module")
def truth(root) -> dict[str, dict]:
    """The simulator's Occ3D-style infos (poses, cameras, label paths) by sample token."""
    infos = json.loads((root / "annotations.json").read_text())["scene_infos"]
    return {token: info for scene in infos.values() for token, info in scene.items()}


@pytest.fixture()
def tables_copy(root, tmp_path) -> Path:
    """A dataset root holding only a copy of the tables, to corrupt."""
    shutil.copytree(root / VERSION, tmp_path / VERSION)
    return tmp_path


def _points(root: Path, path: str) -> np.ndarray:
    return np.fromfile(root / path, dtype=np.float32).reshape(-1, 5)[:, :3].astype(np.float64)


def _apply(transform: np.ndarray, points: np.ndarray) -> np.ndarray:
    return points @ transform[:3, :3].T + transform[:3, 3]


def _share_in_occupied(points_ego: np.ndarray, occupied: np.ndarray) -> float:
    """Share of in-grid points in an occupied voxel; a point on a voxel face counts for both voxels."""
    offsets = np.array([[0, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1], [1, 0, 0], [0, 1, 0], [0, 0, 1]]) * 0.01
    # One call for all offsets: many small torch calls crawl when other processes keep the cores busy.
    shifted = torch.from_numpy((points_ego[None] + offsets[:, None]).reshape(-1, 3))
    index, inside = OCC3D_GRID.world_to_index(shifted)
    index, inside = index.numpy().clip(0, np.array(OCC3D_GRID.shape) - 1), inside.numpy()
    hit = (inside & occupied[index[:, 0], index[:, 1], index[:, 2]]).reshape(len(offsets), -1)
    inside_any = inside.reshape(len(offsets), -1).any(axis=0)
    return float(hit.any(axis=0)[inside_any].mean())


# ----------------------------------------------------------------------------------------------------- structure
def test_records_in_scene_then_time_order(records):
    assert [(r.scene, r.index_in_scene) for r in records] == [(f"scene-000{s}", k) for s in (1, 2) for k in range(3)]
    for previous, current in zip(records, records[1:], strict=False):
        if previous.scene == current.scene:
            assert previous.next == current.token and current.prev == previous.token
            assert previous.timestamp < current.timestamp
    assert records[0].prev == "" and records[2].next == ""
    for record in records:
        assert list(record.cameras) == ["CAM_FRONT", "CAM_BACK"]
        assert record.lidar_path.startswith("samples/LIDAR_TOP/")
        assert record.occ_path == f"gts/{record.scene}/{record.token}/labels.npz"
        assert record.num_boxes > 0 and record.boxes_ego.shape == record.boxes_lidar.shape == (record.num_boxes, 9)


def test_sweeps_newest_first_within_the_scene(root, records):
    for record in records:
        # The simulator has no sweeps before a scene's first key frame, and 9 between key frames.
        assert len(record.sweeps) == (0 if record.index_in_scene == 0 else 10)
        lags = [sweep.time_lag for sweep in record.sweeps]
        assert lags == sorted(lags) and all(lag > 0 for lag in lags)
        for sweep in record.sweeps:
            assert sweep.time_lag == pytest.approx((record.timestamp - sweep.timestamp) / 1e6)
            assert (root / sweep.path).is_file()
    fewer = build_index(root, VERSION, max_sweeps=3)
    assert [len(r.sweeps) for r in fewer] == [0, 3, 3, 0, 3, 3]
    assert fewer[1].sweeps == records[1].sweeps[:3]


def test_sweep_chain_stops_at_the_scene_boundary(root):
    tables = load_tables(root, VERSION)
    lidar = [sd for sd in tables["sample_data"] if "LIDAR_TOP" in sd["filename"]]
    by_scene = defaultdict(list)
    for sd in lidar:
        by_scene[tables.get("sample", sd["sample_token"])["scene_token"]].append(sd)
    first, second = (sorted(rows, key=lambda sd: sd["timestamp"]) for rows in by_scene.values())
    # Chain scene 2's first sweep to scene 1's last one, as one continuous log would.
    second[0]["prev"], first[-1]["next"] = first[-1]["token"], second[0]["token"]
    records = index_tables(tables, max_sweeps=10)
    assert [len(r.sweeps) for r in records if r.scene == "scene-0002"] == [0, 10, 10]


# ----------------------------------------------------------------------------------------------------- geometry
def test_poses_and_cameras_match_the_simulator(records, truth):
    for record in records:
        info = truth[record.token]
        assert record.timestamp == info["timestamp"] and record.occ_path == info["gt_path"]
        ego = info["ego_pose"]
        np.testing.assert_allclose(record.ego2global, pose_matrix(ego["translation"], ego["rotation"]), atol=1e-12)
        for channel, camera in record.cameras.items():
            expected = info["camera_sensor"][channel]
            assert camera.path == expected["img_path"] and (camera.width, camera.height) == TINY.image_size
            np.testing.assert_allclose(camera.intrinsics, expected["intrinsics"])
            extrinsic, pose = expected["extrinsic"], expected["ego_pose"]
            np.testing.assert_allclose(camera.cam2ego, pose_matrix(extrinsic["translation"], extrinsic["rotation"]))
            np.testing.assert_allclose(camera.ego2global, pose_matrix(pose["translation"], pose["rotation"]))
            np.testing.assert_allclose(
                camera.cam2keyego,
                np.linalg.inv(record.ego2global) @ camera.ego2global @ camera.cam2ego,
                atol=1e-9,
            )
            assert camera.timestamp >= record.timestamp  # cameras fire as the LiDAR sweeps past them


def test_key_sweep_points_land_in_occupied_voxels(root, records):
    for record in records:
        occupied = np.load(root / record.occ_path)["semantics"] != 17
        points = _apply(record.lidar2ego, _points(root, record.lidar_path))
        assert _share_in_occupied(points, occupied) >= 0.95


def test_sweeps_map_static_structure_onto_the_key_frame(root, records):
    for record in records:
        occupied = np.load(root / record.occ_path)["semantics"] != 17
        for sweep in record.sweeps[::3]:
            points = _points(root, sweep.path)
            mapped = _apply(record.lidar2ego @ sweep.sweep2lidar, points)
            unmoved = _apply(record.lidar2ego, points)  # as if the ego had stood still
            above_ground = mapped[:, 2] > 0.5  # the ground is occupied wherever a point lands
            share = _share_in_occupied(mapped[above_ground], occupied)
            assert share >= 0.9
            if sweep.time_lag >= 0.3:
                assert share - _share_in_occupied(unmoved[unmoved[:, 2] > 0.5], occupied) >= 0.1


def test_sweep2lidar_maps_a_global_point_consistently(root, records):
    tables = load_tables(root, VERSION)
    by_file = {sd["filename"]: sd for sd in tables["sample_data"]}

    def lidar2global(filename: str) -> np.ndarray:
        sd = by_file[filename]
        pose = tables.get("ego_pose", sd["ego_pose_token"])
        calibration = tables.get("calibrated_sensor", sd["calibrated_sensor_token"])
        return pose_matrix(pose["translation"], pose["rotation"]) @ pose_matrix(
            calibration["translation"], calibration["rotation"]
        )

    point = np.array([[10.0, -4.0, 1.5]])  # a static point in global coordinates, near the ego's path
    for record in records[1:3]:
        key = _apply(np.linalg.inv(lidar2global(record.lidar_path)), point + record.ego2global[:3, 3])
        for sweep in record.sweeps:
            in_sweep = _apply(np.linalg.inv(lidar2global(sweep.path)), point + record.ego2global[:3, 3])
            np.testing.assert_allclose(_apply(sweep.sweep2lidar, in_sweep), key, atol=1e-9)


def test_boxes_lidar_are_boxes_ego_in_the_lidar_frame(records):
    for record in records:
        ego, lidar = record.boxes_ego, record.boxes_lidar
        np.testing.assert_allclose(_apply(np.linalg.inv(record.lidar2ego), ego[:, :3]), lidar[:, :3], atol=1e-9)
        np.testing.assert_allclose(ego[:, 3:6], lidar[:, 3:6])
        lidar_yaw = np.arctan2(record.lidar2ego[1, 0], record.lidar2ego[0, 0])
        np.testing.assert_allclose(np.cos(ego[:, 6] - lidar[:, 6]), np.cos(lidar_yaw), atol=1e-9)
        rotation = record.lidar2ego[:2, :2]
        np.testing.assert_allclose(lidar[:, 7:9] @ rotation.T, ego[:, 7:9], atol=1e-9)


def test_box_velocities_are_finite_differences_of_centres(records):
    """Centred differences of global centres where an instance has annotations on both sides, one-sided at the
    ends, as nuscenes-devkit's box_velocity."""
    seen: dict[str, list[tuple[int, np.ndarray]]] = defaultdict(list)
    for record in records:
        centres = _apply(record.ego2global, record.boxes_ego[:, :3])
        for instance, centre in zip(record.box_instances, centres, strict=True):
            seen[instance].append((record.timestamp, centre))
    checked = 0
    for record in records:
        for i, instance in enumerate(record.box_instances):
            track = seen[instance]
            k = [t for t, _ in track].index(record.timestamp)
            first, last = track[max(k - 1, 0)], track[min(k + 1, len(track) - 1)]
            if first is last:
                assert not record.velocity_valid[i] and (record.boxes_ego[i, 7:9] == 0).all()
                continue
            velocity = (last[1] - first[1]) / ((last[0] - first[0]) / 1e6)
            expected = (np.linalg.inv(record.ego2global[:3, :3]) @ velocity)[:2]
            assert record.velocity_valid[i]
            np.testing.assert_allclose(record.boxes_ego[i, 7:9], expected, atol=1e-6)
            checked += 1
    assert checked > 100


def test_box_labels_follow_the_annotations(root, records):
    tables = load_tables(root, VERSION)
    for record in records:
        annotations = [a for a in tables["sample_annotation"] if a["sample_token"] == record.token]
        assert list(record.box_instances) == [a["instance_token"] for a in annotations]
        assert record.box_num_lidar_pts.tolist() == [a["num_lidar_pts"] for a in annotations]
        assert record.box_valid.tolist() == [a["num_lidar_pts"] + a["num_radar_pts"] > 0 for a in annotations]
        assert list(record.box_visibility) == [a["visibility_token"] for a in annotations]
        for category, name in zip(record.box_categories, record.box_detection_names, strict=True):
            assert name == NUSCENES_TO_DETECTION.get(category)
    assert {n for r in records for n in r.box_detection_names} >= {"car", "pedestrian", None}
    # Boxes seen by a camera alone are annotated too: the world has boxes of both kinds.
    assert {bool(v) for r in records for v in r.box_valid} == {True, False}


def test_a_box_with_radar_points_only_is_valid(tables_copy, records):
    """mmdetection3d's valid_flag counts LiDAR and radar points: (num_lidar_pts + num_radar_pts) > 0."""
    rows = json.loads((tables_copy / VERSION / "sample_annotation.json").read_text())

    def flags(built: list[FrameRecord]) -> dict[str, bool]:
        """Annotation token -> box_valid: a record's boxes are its sample's annotations in table order."""
        by_sample = defaultdict(list)
        for row in rows:
            by_sample[row["sample_token"]].append(row["token"])
        return {token: bool(valid) for record in built
                for token, valid in zip(by_sample[record.token], record.box_valid, strict=True)}  # fmt: skip

    empty = next(row["token"] for row in rows if row["num_lidar_pts"] == 0)
    seen = next(row["token"] for row in rows if row["num_lidar_pts"] > 0)
    changes = {empty: {"num_radar_pts": 3}, seen: {"num_lidar_pts": 0, "num_radar_pts": 0}}
    _edit(tables_copy, "sample_annotation", lambda table: [row.update(changes.get(row["token"], {})) for row in table])
    before, after = flags(records), flags(build_index(tables_copy, VERSION))
    assert not before[empty] and after[empty] and before[seen] and not after[seen]
    assert {token for token in before if before[token] != after[token]} == {empty, seen}


# ----------------------------------------------------------------------------------------------------- files
META = {"version": VERSION, "root": "x", "max_sweeps": 10}
DOCS = Path(__file__).resolve().parents[1] / "docs" / "data.md"


def _arrays(path: Path) -> dict[str, np.ndarray]:
    with np.load(path) as npz:
        return {name: npz[name] for name in npz.files}


def _write(path: Path, arrays: dict[str, np.ndarray]) -> None:
    """An index file of other arrays (np.savez: the reader takes any .npz)."""
    with open(path, "wb") as stream:
        np.savez(stream, **arrays)


def _point(path: Path, column: str, row: int, text: str) -> None:
    """Make row ``row`` of string column ``column`` of an index file read ``text`` (a string added to its table)."""
    arrays = _arrays(path)
    blob = arrays["strings"].tobytes() + text.encode()
    arrays["strings"] = np.frombuffer(blob, dtype=np.uint8)
    arrays["strings.offsets"] = np.append(arrays["strings.offsets"], len(blob))
    arrays[column] = arrays[column].copy()
    arrays[column][row] = len(arrays["strings.offsets"]) - 2
    _write(path, arrays)


def test_index_file_round_trip(records, tmp_path):
    path = save_index(records, tmp_path / "sub" / "index.npz", META)
    assert list(path.parent.iterdir()) == [path]  # the partial file was renamed
    loaded, meta = load_index(path)
    assert loaded == records and records == loaded and isinstance(loaded, FrameRecords)
    assert meta == {
        "format": INDEX_FORMAT,
        "created_by": meta["created_by"],
        "version": VERSION,
        "root": "x",
        "max_sweeps": 10,
        "frames": len(records),
    }
    assert meta["created_by"].startswith("occkit ")
    record = records[1]
    assert FrameRecord.from_dict(json.loads(json.dumps(record.to_dict()))) == record
    assert record != records[2]
    with pytest.raises(ValueError, match="read-only"):
        record.boxes_ego[0, 0] = 1.0
    with pytest.raises(ValueError, match="read-only"):
        loaded[1].sweeps[0].sweep2lidar[0, 0] = 1.0
    # The same bytes for the same records: no time stamps inside.
    assert save_index(records, tmp_path / "again.npz", META).read_bytes() == path.read_bytes()


def test_loaded_records_act_as_a_list(records, tmp_path):
    loaded, _ = load_index(save_index(records, tmp_path / "index.npz", META))
    assert len(loaded) == len(records) and loaded[1] is loaded[1]  # built once, then kept
    assert loaded[-1] == records[-1] and loaded[1:4] == records[1:4] and list(loaded) == records
    assert loaded != records[:-1] and loaded != records[::-1]
    with pytest.raises(IndexError):
        loaded[len(records)]
    # DataLoader workers that spawn get the dataset pickled.
    assert pickle.loads(pickle.dumps(loaded)) == records
    shorter = dataclasses.replace(loaded[1], sweeps=loaded[1].sweeps[:2])  # as `occkit index --from-info` does
    assert shorter.sweeps == records[1].sweeps[:2] and shorter.cameras == records[1].cameras


def test_index_file_columns_are_the_documented_arrays(records, tmp_path):
    arrays = _arrays(save_index(records, tmp_path / "index.npz", META))
    boxes = [record.num_boxes for record in records]
    assert arrays["boxes_ego"].dtype == np.float64 and arrays["boxes_ego"].shape == (sum(boxes), 9)
    np.testing.assert_array_equal(arrays["boxes.offsets"], np.cumsum([0, *boxes]))
    np.testing.assert_array_equal(arrays["boxes_lidar"], np.concatenate([r.boxes_lidar for r in records]))
    np.testing.assert_array_equal(arrays["ego2global"], np.stack([r.ego2global for r in records]))
    sweeps = [sweep for record in records for sweep in record.sweeps]
    np.testing.assert_array_equal(arrays["sweeps.sweep2lidar"], np.stack([s.sweep2lidar for s in sweeps]))
    cameras = [camera for record in records for camera in record.cameras.values()]
    np.testing.assert_array_equal(arrays["cameras.width"], [camera.width for camera in cameras])
    strings = arrays["strings"].tobytes()
    offsets = arrays["strings.offsets"]
    text = [strings[a:b].decode() for a, b in zip(offsets[:-1], offsets[1:], strict=True)]
    assert [text[code] for code in arrays["token"]] == [record.token for record in records]
    assert [text[code] for code in arrays["cameras.channel"][:2]] == ["CAM_FRONT", "CAM_BACK"]
    assert all(arrays[name].dtype == np.int32 for name in ("token", "occ_path", "sweeps.path", "box_instances"))
    assert json.loads(str(arrays["header"]))["frames"] == len(records)
    documented = DOCS.read_text()
    assert [name for name in arrays if f"`{name}`" not in documented] == []


def test_save_index_needs_the_build_meta(records, tmp_path):
    with pytest.raises(ValueError, match="max_sweeps"):
        save_index(records, tmp_path / "index.npz", {"version": VERSION, "root": "x"})


def test_load_index_names_the_file_on_bad_input(records, tmp_path):
    path = tmp_path / "index.npz"
    path.write_text(json.dumps({"format": "mmdet3d-infos", "records": []}))
    with pytest.raises(IndexFormatError, match=r"index\.npz: not an occkit index \(an occkit-index/3 \.npz file\)"):
        load_index(path)
    save_index(records[:2], path, META)
    _write(path, _arrays(path) | {"header": np.array(json.dumps({"format": "mmdet3d-infos"}))})
    with pytest.raises(IndexFormatError, match=r"index\.npz: not an occkit index \(format 'mmdet3d-infos', expected"):
        load_index(path)
    save_index(records[:2], path, META)
    path.write_bytes(path.read_bytes()[:-100])  # the zip directory is at the end
    with pytest.raises(IndexFormatError, match=r"index\.npz: damaged index file \(BadZipFile"):
        load_index(path)
    save_index(records[:2], path, META)
    arrays = _arrays(path)
    arrays["lidar2ego"] = arrays["lidar2ego"].copy()
    arrays["lidar2ego"][1, 2, 1] = np.nan
    _write(path, arrays)
    with pytest.raises(IndexFormatError, match=r"index\.npz: record 1\.lidar2ego\[2\]: expected a list of 4 finite"):
        load_index(path)
    arrays["lidar2ego"] = arrays["lidar2ego"][:, :3]
    _write(path, arrays)
    with pytest.raises(IndexFormatError, match=r"array 'lidar2ego' is float64 \(2, 3, 4\), expected float64 \(2, 4"):
        load_index(path)
    with pytest.raises(FileNotFoundError, match="missing.npz"):
        load_index(tmp_path / "missing.npz")


def test_values_in_the_columns_name_record_and_field(records, tmp_path):
    path = save_index(records[:3], tmp_path / "index.npz", META)
    arrays = _arrays(path)
    boxes, sweeps, channels = records[0].num_boxes, len(records[0].sweeps), arrays["cameras.channel"]
    cases = [  # array, where, value, message
        ("boxes_ego", (boxes + 2, 4), np.inf, r"record 1\.boxes_ego\[2\]: expected a list of 9 finite numbers, got \["),
        ("sweeps.time_lag", sweeps + 3, np.nan, r"record 1\.sweeps\[3\]\.time_lag: expected a finite number, got nan"),
        ("cameras.intrinsics", (3, 0, 0), np.nan, r"record 1\.cameras\.CAM_BACK\.intrinsics\[0\]: expected a list of"),
        ("box_num_lidar_pts", 1, -4, r"record 0\.box_num_lidar_pts\[1\]: expected a count"),
        ("token", 2, 10**6, r"record 2\.token: expected a string, got string 1000000 of a table of \d+"),
        ("box_categories", 0, -1, r"record 0\.box_categories\[0\]: expected a string, got null"),
        ("cameras.channel", 1, channels[0], r"record 0\.cameras\[1\]\.channel: 'CAM_FRONT' is repeated"),
        ("sweeps.offsets", 1, 99, r"array 'sweeps\.offsets' must start at 0 and never fall"),
    ]  # fmt: skip
    for name, where, value, message in cases:
        changed = arrays[name].copy()
        changed[where] = value
        _write(path, arrays | {name: changed})
        with pytest.raises(IndexFormatError, match=r"^.*index\.npz: " + message):
            load_index(path)
    _write(path, arrays | {"extra": np.zeros(3)})
    with pytest.raises(IndexFormatError, match=r"index\.npz: unknown array\(s\) extra"):
        load_index(path)


def test_a_json_index_of_an_older_occkit_says_how_to_rebuild_it(tmp_path):
    path = tmp_path / "my index.json"
    header = {"format": "occkit-index/1", "created_by": "occkit 0.1.0", "version": VERSION, "root": "data/synth",
              "max_sweeps": 3, "split": "val", "frames": 0}  # fmt: skip
    path.write_text(json.dumps(header)[:-1] + ', "records": [\n\n]}\n')
    message = (
        rf"^{re.escape(str(path))}: a JSON index of an older occkit \(occkit-index/1\); this occkit reads "
        r"occkit-index/3 \(\.npz\): rebuild it with `occkit index --root data/synth --version v1\.0-synth "
        rf"--max-sweeps 3 --split val --out '{re.escape(str(path.with_suffix('.npz')))}'` and point data\.index at "
        rf"{re.escape(str(path.with_suffix('.npz')))}$"
    )
    for read in (load_index, read_index_header):
        with pytest.raises(OutdatedIndexError, match=message):
            read(path)


def test_an_index_of_format_2_says_how_to_rebuild_it(records, tmp_path):
    """Format 2 was a .npz as now, without box_valid: its header names the build to repeat."""
    path = tmp_path / "index.npz"
    meta = {"version": VERSION, "root": "data/synth", "max_sweeps": 4, "from_info": "infos val.pkl"}
    arrays = _arrays(save_index(records[:2], path, meta))
    header = json.loads(str(arrays["header"])) | {"format": "occkit-index/2"}
    del arrays["box_valid"]
    _write(path, arrays | {"header": np.array(json.dumps(header))})
    message = (
        rf"^{re.escape(str(path))}: an index of an older occkit \(occkit-index/2\); this occkit reads "
        r"occkit-index/3 \(\.npz\): rebuild it with `occkit index --root data/synth --version v1\.0-synth "
        rf"--max-sweeps 4 --from-info 'infos val\.pkl' --trust-pickle --out {re.escape(str(path))}`$"
    )
    for read in (load_index, read_index_header):
        with pytest.raises(OutdatedIndexError, match=message):
            read(path)
    # A format that no occkit wrote is no older index.
    _write(path, arrays | {"header": np.array(json.dumps(header | {"format": "occkit-index/9"}))})
    with pytest.raises(IndexFormatError, match=r"not an occkit index \(format 'occkit-index/9', expected") as error:
        load_index(path)
    assert not isinstance(error.value, OutdatedIndexError)


# ----------------------------------------------------------------------------------------------------- fuzz
def _leaves(value, path=()):
    """Every path into a to_dict() tree, with the kind of value there."""
    if isinstance(value, dict):
        for key, item in value.items():
            yield from _leaves(item, (*path, key))
    elif isinstance(value, list):
        yield path, "list"
        for i, item in enumerate(value[:2]):
            yield from _leaves(item, (*path, i))
    else:
        yield path, type(value).__name__


_WRONG = {
    "str": st.one_of(st.integers(), st.floats(), st.booleans(), st.lists(st.text(), max_size=2)),
    "int": st.one_of(st.floats(), st.text(max_size=3), st.booleans(), st.none(), st.lists(st.integers(), max_size=2)),
    "float": st.one_of(
        st.text(max_size=3), st.booleans(), st.none(), st.just(float("nan")), st.just(float("inf")), st.just([1.0])
    ),
    "bool": st.one_of(st.integers(), st.text(max_size=3), st.none(), st.floats()),
    "list": st.one_of(st.text(max_size=3), st.integers(), st.none(), st.dictionaries(st.text(max_size=2), st.none())),
    "NoneType": st.one_of(st.integers(), st.booleans(), st.lists(st.none(), max_size=2)),
}
_JSON = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=4),
    lambda children: st.lists(children, max_size=3) | st.dictionaries(st.text(max_size=4), children, max_size=3),
    max_leaves=8,
)


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_from_dict_rejects_wrong_types_naming_the_field(records, data):
    valid = records[1].to_dict()
    leaves = [(path, kind) for path, kind in _leaves(valid) if path]
    path, kind = data.draw(st.sampled_from(leaves))
    if path[0] == "box_detection_names" and len(path) == 2:
        kind = "NoneType" if valid["box_detection_names"][path[1]] is None else "detection"
    wrong = data.draw(
        _WRONG.get(kind, st.one_of(st.integers(), st.booleans(), st.lists(st.integers(), max_size=1))), label="wrong"
    )
    broken = copy.deepcopy(valid)
    target = broken
    for key in path[:-1]:
        target = target[key]
    target[path[-1]] = wrong
    with pytest.raises(IndexFormatError) as error:
        FrameRecord.from_dict(broken, "index.json: record 7")
    message = str(error.value)
    assert message.startswith("index.json: record 7")
    assert str(next(key for key in reversed(path) if isinstance(key, str))) in message


@settings(max_examples=200, deadline=None)
@given(value=_JSON, key=st.sampled_from(["token", "sweeps", "cameras", "boxes_ego", "velocity_valid", "occ_path"]))
def test_from_dict_gives_index_errors_only(records, value, key):
    broken = records[1].to_dict()
    broken[key] = value
    with contextlib.suppress(IndexFormatError):
        FrameRecord.from_dict(broken)
    with pytest.raises(IndexFormatError):
        FrameRecord.from_dict(value)


@pytest.fixture(scope="module")
def small_index(records, tmp_path_factory) -> tuple[dict[str, np.ndarray], Path]:
    """The arrays of an index file of three frames, and a file to write changed ones to."""
    folder = tmp_path_factory.mktemp("fuzz")
    return _arrays(save_index(records[:3], folder / "good.npz", META)), folder / "index.npz"


_VALUES = {
    "f": st.sampled_from([np.nan, np.inf, -1.0, 0.0, 1e300]),
    "i": st.one_of(st.integers(-3, 3), st.sampled_from([2**31 - 1, -(2**31), 10**6])),
    "u": st.integers(0, 255),
    "b": st.booleans(),
    "U": st.text(max_size=8),
}


@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_load_index_gives_index_errors_only(small_index, data):
    """Any array dropped, retyped, cut short or given another value: the file loads (and every record reads) or
    IndexFormatError says why."""
    arrays, path = small_index
    arrays = dict(arrays)
    name = data.draw(st.sampled_from(sorted(arrays)), label="array")
    array = arrays[name].copy()
    change = data.draw(st.sampled_from(["drop", "dtype", "shorter", "value"]), label="change")
    if change == "drop":
        del arrays[name]
    elif change == "dtype" and array.dtype.kind != "U":
        arrays[name] = array.astype(data.draw(st.sampled_from([np.int32, np.int64, np.float64, np.uint8, np.bool_])))
    elif change == "shorter" and array.ndim:
        arrays[name] = array[:-1]
    elif array.size:
        flat = array.reshape(-1)
        flat[data.draw(st.integers(0, flat.size - 1), label="at")] = data.draw(_VALUES[array.dtype.kind], label="value")
        arrays[name] = flat.reshape(array.shape)
    _write(path, arrays)
    with contextlib.suppress(IndexFormatError):
        loaded, _ = load_index(path)
        assert len(list(loaded)) == 3


def test_from_dict_missing_and_unknown_keys(records):
    data = records[0].to_dict()
    del data["sweeps"]
    with pytest.raises(IndexFormatError, match="record: missing sweeps"):
        FrameRecord.from_dict(data)
    data = records[0].to_dict() | {"extra": 1}
    with pytest.raises(IndexFormatError, match="unknown key.*extra"):
        FrameRecord.from_dict(data)
    data = records[0].to_dict()
    data["box_instances"] = data["box_instances"][:-1]
    with pytest.raises(IndexFormatError, match="one length"):
        FrameRecord.from_dict(data)


# ----------------------------------------------------------------------------------------------------- table errors
def _edit(folder: Path, table: str, edit) -> None:
    path = folder / VERSION / f"{table}.json"
    rows = json.loads(path.read_text())
    edit(rows)
    path.write_text(json.dumps(rows))


def test_missing_folders_and_tables(tables_copy):
    with pytest.raises(FileNotFoundError, match="v1.0-mini does not exist; version folders found: v1.0-synth"):
        load_tables(tables_copy, "v1.0-mini")
    with pytest.raises(FileNotFoundError, match="dataset root"):
        load_tables(tables_copy / "nowhere", VERSION)
    (tables_copy / VERSION / "map.json").unlink()
    with pytest.raises(TableError, match=r"v1\.0-synth/map\.json: table is missing"):
        load_tables(tables_copy, VERSION)


def test_corrupt_json_names_the_file(tables_copy):
    (tables_copy / VERSION / "sample.json").write_text('[{"token": ')
    with pytest.raises(TableError, match=r"v1\.0-synth/sample\.json: not valid JSON"):
        load_tables(tables_copy, VERSION)
    (tables_copy / VERSION / "sample.json").write_text('{"token": "a"}')
    with pytest.raises(TableError, match=r"v1\.0-synth/sample\.json: expected a JSON list"):
        load_tables(tables_copy, VERSION)


def test_missing_field_names_file_and_record(tables_copy):
    _edit(tables_copy, "sample_data", lambda rows: rows[17].pop("calibrated_sensor_token"))
    with pytest.raises(
        TableError, match=r"^v1\.0-synth/sample_data\.json: record 17 has no 'calibrated_sensor_token'$"
    ):
        load_tables(tables_copy, VERSION)


def test_repeated_and_dangling_tokens(tables_copy):
    _edit(tables_copy, "ego_pose", lambda rows: rows.append(dict(rows[3])))
    with pytest.raises(TableError, match=r"ego_pose\.json: record \d+ repeats token"):
        load_tables(tables_copy, VERSION)
    _edit(tables_copy, "ego_pose", lambda rows: rows.pop())
    _edit(tables_copy, "sample_data", lambda rows: rows[0].update(ego_pose_token="f" * 32))
    message = r"sample_data\.json: record \w+\.ego_pose_token refers to ego_pose token 'f{32}', which "
    with pytest.raises(TableError, match=message):
        build_index(tables_copy, VERSION)


def test_without_labels_occ_path_is_none_and_unknown_scenes_fail(tables_copy):
    records = build_index(tables_copy, VERSION, scenes=["scene-0002"])
    assert [r.scene for r in records] == ["scene-0002"] * 3 and all(r.occ_path is None for r in records)
    with pytest.raises(TableError, match=r"1 scene\(s\) are not in v1\.0-synth/scene\.json: scene-0404"):
        build_index(tables_copy, VERSION, scenes=["scene-0001", "scene-0404"])
    with pytest.raises(ValueError, match="max_sweeps"):
        build_index(tables_copy, VERSION, max_sweeps=-1)


# ----------------------------------------------------------------------------------------------------- splits
def test_official_splits():
    counts = {name: len(scene_split(name)) for name in ("train", "val", "test", "mini_train", "mini_val")}
    assert counts == {"train": 700, "val": 150, "test": 150, "mini_train": 8, "mini_val": 2}
    train, val, test = (set(scene_split(name)) for name in ("train", "val", "test"))
    assert not train & val and not (train | val) & test
    assert set(scene_split("mini_train") + scene_split("mini_val")) <= train | val
    assert "scene-0003" in val and "scene-0061" in scene_split("mini_train")
    with pytest.raises(ValueError, match="official splits: train, val, test, mini_train, mini_val"):
        scene_split("trainval")


def test_split_scenes_per_version(root, tmp_path):
    assert split_scenes(tmp_path, "v1.0-trainval", "val") == scene_split("val")
    assert split_scenes(tmp_path, "v1.0-mini", "train") == scene_split("mini_train")
    assert split_scenes(tmp_path, "v1.0-mini", "mini_val") == scene_split("mini_val")
    assert split_scenes(tmp_path, "v1.0-test", "test") == scene_split("test")
    with pytest.raises(ValueError, match="unknown split 'test' for v1.0-trainval; valid: train, val"):
        split_scenes(tmp_path, "v1.0-trainval", "test")
    with pytest.raises(ValueError, match="has no official splits"):
        split_scenes(tmp_path, VERSION, "train")
    # The synthetic dataset's splits.json decides, whatever the version.
    written = json.loads((root / "splits.json").read_text())
    assert split_scenes(root, VERSION, "train") == written["train"] == ["scene-0001"]
    assert split_scenes(root, "v1.0-trainval", "val") == written["val"] == ["scene-0002"]
    with pytest.raises(ValueError, match=r"splits\.json: no split 'test'; the file has 'train', 'val'"):
        split_scenes(root, VERSION, "test")


def test_read_split_file(tmp_path):
    path = tmp_path / "mine.json"
    path.write_text(json.dumps(["scene-0001", "scene-0002"]))
    assert read_split_file(path) == ["scene-0001", "scene-0002"]
    with pytest.raises(ValueError, match="one list of scenes"):
        read_split_file(path, "train")
    path.write_text(json.dumps({"train": ["scene-0001"], "val": [3]}))
    assert read_split_file(path, "train") == ["scene-0001"]
    with pytest.raises(ValueError, match=r"mine\.json: val: expected a list of scene names"):
        read_split_file(path, "val")
    with pytest.raises(ValueError, match="no split given; the file has 'train', 'val'"):
        read_split_file(path)
    path.write_text("[")
    with pytest.raises(ValueError, match=r"mine\.json: not valid JSON"):
        read_split_file(path)
    with pytest.raises(FileNotFoundError, match="nope.json"):
        read_split_file(tmp_path / "nope.json")


# ----------------------------------------------------------------------------------------------------- CLI
def test_cli_index_end_to_end(root, records, tmp_path, capsys):
    out = tmp_path / "val.npz"
    assert main(["index", "--root", str(root), "--version", VERSION, "--out", str(out), "--split", "val"]) == 0
    summary = capsys.readouterr().out.strip().splitlines()[-1]
    assert summary.startswith("indexed 3 key frames of 1 scene(s) (val)") and str(out) in summary
    loaded, meta = load_index(out)
    assert loaded == records[3:] and meta["split"] == "val" and meta["max_sweeps"] == 10
    assert meta["root"] == str(root) and meta["version"] == VERSION

    custom = tmp_path / "custom.json"
    custom.write_text(json.dumps(["scene-0001"]))
    args = ["index", "--root", str(root), "--version", VERSION, "--out", str(out), "--split-file", str(custom)]
    assert main([*args, "--max-sweeps", "2"]) == 0
    loaded, meta = load_index(out)
    assert [r.token for r in loaded] == [r.token for r in records[:3]] and meta["max_sweeps"] == 2
    assert max(len(r.sweeps) for r in loaded) == 2


def test_cli_index_bad_input_is_one_line(root, tmp_path, capsys):
    out = str(tmp_path / "index.npz")
    assert main(["index", "--root", str(root), "--version", VERSION, "--out", out, "--split", "test"]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("occkit index: error:") and "no split 'test'" in error and "\n" not in error
    assert main(["index", "--root", str(tmp_path / "none"), "--version", VERSION, "--out", out]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert not Path(out).exists()


# ----------------------------------------------------------------------------------------------------- hostile tables
def _rename(folder: Path, table: str, field: str, old: str, new: str) -> None:
    """Replace ``old`` by ``new`` in ``field`` of every record of ``table`` (a token and its references)."""
    _edit(folder, table, lambda rows: [row.update({field: new}) for row in rows if row.get(field) == old])


def _rename_sample(folder: Path, old: str, new: str) -> None:
    """A sample token renamed consistently in every table that refers to it."""
    _rename(folder, "sample", "token", old, new)
    for field in ("prev", "next"):
        _rename(folder, "sample", field, old, new)
    for table in ("sample_data", "sample_annotation"):
        _rename(folder, table, "sample_token", old, new)
    for field in ("first_sample_token", "last_sample_token"):
        _rename(folder, "scene", field, old, new)


@pytest.mark.parametrize("token", ["../../escape_tok", "/escape_tok", "", ".hidden", "a" * 129, "a/b", "tok\n"])
def test_unsafe_sample_tokens_are_refused_at_build(tables_copy, records, token):
    _rename_sample(tables_copy, records[4].token, token)
    with pytest.raises(TableError, match=r"^v1\.0-synth/sample\.json: record '.*\.token: .* is not a safe name"):
        build_index(tables_copy, VERSION)


def test_unsafe_scene_names_and_tokens_are_refused_at_build(tables_copy, records):
    _rename(tables_copy, "scene", "name", "scene-0002", "../../../escape_scene")
    with pytest.raises(TableError, match=r"scene\.json: record \w+\.name: '\.\./\.\./\.\./escape_scene' is not a safe"):
        build_index(tables_copy, VERSION)
    _rename(tables_copy, "scene", "name", "../../../escape_scene", "scene-0002")
    old = records[0].scene_token
    _rename(tables_copy, "scene", "token", old, "/abs")
    _rename(tables_copy, "sample", "scene_token", old, "/abs")
    with pytest.raises(TableError, match=r"scene\.json: record '/abs'\.token: '/abs' is not a safe name"):
        build_index(tables_copy, VERSION)


def test_cli_index_refuses_an_escaping_token(tables_copy, records, tmp_path, capsys):
    _rename_sample(tables_copy, records[4].token, "../../escape_tok")
    out = tmp_path / "index.npz"
    assert main(["index", "--root", str(tables_copy), "--version", VERSION, "--out", str(out)]) == 2
    error = capsys.readouterr().err.strip()
    assert error.startswith("occkit index: error: v1.0-synth/sample.json: record '../../escape_tok'.token:")
    assert "\n" not in error and not out.exists()


def test_unsafe_file_paths_are_refused_at_build(tables_copy, records):
    for bad in ("/etc/passwd", "samples/../../outside.pcd.bin", "samples\\x.pcd.bin"):
        _rename(tables_copy, "sample_data", "filename", records[1].lidar_path, bad)
        with pytest.raises(TableError, match=r"sample_data\.json: record \w+\.filename: "):
            build_index(tables_copy, VERSION)
        _rename(tables_copy, "sample_data", "filename", bad, records[1].lidar_path)
    assert [r.lidar_path for r in build_index(tables_copy, VERSION)] == [r.lidar_path for r in records]


@pytest.mark.parametrize(
    "field, value, message",
    [
        ("token", "../../escape_tok", r"\.token: '\.\./\.\./escape_tok' is not a safe name"),
        ("token", "/abs/tok", r"\.token: '/abs/tok' is not a safe name"),
        ("scene", "../../../escape_scene", r"\.scene: .* is not a safe name"),
        ("scene_token", "a/b", r"\.scene_token: 'a/b' is not a safe name"),
        ("prev", "..", r"\.prev: '\.\.' is not a safe name"),
        ("lidar_path", "/etc/passwd", r"\.lidar_path: '/etc/passwd' is an absolute path"),
        ("occ_path", "gts/../../x/labels.npz", r"\.occ_path: .* has a '\.\.' component"),
        ("occ_path", "", r"\.occ_path: expected a relative path"),
    ],
)
def test_index_files_refuse_unsafe_names_and_paths(records, tmp_path, field, value, message):
    path = tmp_path / "index.npz"
    broken = dataclasses.replace(records[1], **{field: value})
    with pytest.raises(IndexFormatError, match=r"index\.npz: record 1 \(sample .*\)" + message):
        save_index([records[0], broken], path, META)
    assert list(tmp_path.iterdir()) == []
    save_index(records[:2], path, META)
    _point(path, field, 1, value)
    with pytest.raises(IndexFormatError, match=r"index\.npz: record 1" + message):
        load_index(path)


def test_index_files_refuse_unsafe_sweep_and_camera_paths(records, tmp_path):
    path = save_index(records[:2], tmp_path / "index.npz", META)
    _point(path, "sweeps.path", len(records[0].sweeps) + 2, "../sweeps/x.pcd.bin")
    with pytest.raises(IndexFormatError, match=r"index\.npz: record 1\.sweeps\[2\]\.path: .*'\.\.' component"):
        load_index(path)
    path = save_index(records[:2], tmp_path / "index.npz", META)
    _point(path, "cameras.path", 3, "C:/images/x.jpg")
    with pytest.raises(IndexFormatError, match=r"index\.npz: record 1\.cameras\.CAM_BACK\.path: .* absolute path"):
        load_index(path)


def test_from_dict_refuses_unsafe_sweep_and_camera_paths(records):
    data = records[1].to_dict()
    data["sweeps"][2]["path"] = "../sweeps/x.pcd.bin"
    with pytest.raises(IndexFormatError, match=r"^here\.sweeps\[2\]\.path: .*'\.\.' component"):
        FrameRecord.from_dict(data, "here")
    data = records[1].to_dict()
    data["cameras"]["CAM_BACK"]["path"] = "C:/images/x.jpg"
    with pytest.raises(IndexFormatError, match=r"^here\.cameras\.CAM_BACK\.path: .* absolute path"):
        FrameRecord.from_dict(data, "here")
    # Records of info files without a scene keep empty scene names.
    data = records[1].to_dict() | {"scene": "", "scene_token": "", "prev": "", "next": ""}
    assert FrameRecord.from_dict(data).scene == ""


def test_unknown_references_name_file_record_and_field(tables_copy, records):
    # A sample of an unknown scene was dropped without a word.
    _edit(tables_copy, "sample", lambda rows: rows[4].update(scene_token="e" * 32))
    with pytest.raises(TableError, match=r"sample\.json: record \w+\.scene_token refers to scene token 'e{32}', which"):
        build_index(tables_copy, VERSION)
    _edit(tables_copy, "sample", lambda rows: rows[4].update(scene_token=records[4].scene_token))
    cases = [
        ("sample_data", "sample_token", "sample"),
        ("sample_annotation", "sample_token", "sample"),
        ("sample", "prev", "sample"),
        ("sample_data", "calibrated_sensor_token", "calibrated_sensor"),
        ("sample_data", "ego_pose_token", "ego_pose"),
    ]
    for table, field, target in cases:
        path = tables_copy / VERSION / f"{table}.json"
        original = path.read_text()
        _edit(tables_copy, table, lambda rows, field=field: rows[-1].update({field: "d" * 32}))
        message = rf"^v1\.0-synth/{table}\.json: record \w+\.{field} refers to {target} token 'd{{32}}', which "
        with pytest.raises(TableError, match=message + rf"v1\.0-synth/{target}\.json does not have$"):
            build_index(tables_copy, VERSION)
        path.write_text(original)


def _first(folder: Path, table: str, where=lambda row: True) -> dict:
    return next(row for row in json.loads((folder / VERSION / f"{table}.json").read_text()) if where(row))


@pytest.mark.parametrize("table", ["ego_pose", "calibrated_sensor", "sample_annotation"])
@pytest.mark.parametrize("rotation", [[0, 0, 0, 0], [0.0, 1e-9, 0.0, 0.0]])
def test_zero_quaternions_are_errors_naming_the_record(tables_copy, table, rotation):
    used = _first(tables_copy, table, lambda row: table != "calibrated_sensor" or row["camera_intrinsic"] == [])
    _edit(tables_copy, table, lambda rows: [row.update(rotation=rotation) for row in rows if row is not None and
                                            row["token"] == used["token"]])  # fmt: skip
    message = rf"^v1\.0-synth/{table}\.json: record {used['token']}\.rotation: .* has norm .*: not a rotation"
    with pytest.raises(TableError, match=message):
        build_index(tables_copy, VERSION)


def test_quaternions_of_other_norms_are_normalised(tables_copy, records):
    _edit(tables_copy, "ego_pose", lambda rows: [row.update(rotation=[2 * q for q in row["rotation"]]) for row in rows])
    scaled = build_index(tables_copy, VERSION)
    for a, b in zip(scaled, records, strict=True):
        np.testing.assert_allclose(a.ego2global, b.ego2global, atol=1e-12)


@pytest.mark.parametrize(
    "table, field, value, expected",
    [
        ("ego_pose", "translation", "1.0, 2.0, 3.0", "a list of 3 finite numbers"),
        ("ego_pose", "translation", ["1", "2", "x"], "a list of 3 finite numbers"),
        ("ego_pose", "translation", [1.0, 2.0], "a list of 3 finite numbers"),
        ("ego_pose", "rotation", [1.0, 0.0, 0.0], "a list of 4 finite numbers"),
        ("calibrated_sensor", "translation", [1.0, float("nan"), 0.0], "a list of 3 finite numbers"),
        ("sample_annotation", "size", [1.0, 2.0, [3.0]], "a list of 3 finite numbers"),
        ("sample_annotation", "num_lidar_pts", "12", "an integer"),
        ("sample_annotation", "num_lidar_pts", -1, "a count >= 0"),
        ("sample_annotation", "num_radar_pts", 2.0, "an integer"),
        ("sample_annotation", "num_radar_pts", -3, "a count >= 0"),
        ("sample_annotation", "visibility_token", 4, "a string"),
        ("sample_data", "timestamp", "1700000000500000", "an integer"),
        ("sample_data", "width", 1600.0, "an integer"),
        ("sample", "timestamp", None, "an integer"),
    ],
)
def test_wrongly_typed_fields_name_file_record_and_field(tables_copy, table, field, value, expected):
    def used(row: dict) -> bool:
        return table != "sample_data" or "CAM_FRONT" in row["filename"]

    record = _first(tables_copy, table, used)
    _edit(tables_copy, table, lambda rows: [row.update({field: value}) for row in rows if row == record])
    message = rf"^v1\.0-synth/{table}\.json: record {record['token']}\.{field}: expected {expected}, got "
    with pytest.raises(TableError, match=message):
        build_index(tables_copy, VERSION)


def test_camera_intrinsics_and_token_types(tables_copy):
    camera = _first(tables_copy, "calibrated_sensor", lambda row: row["camera_intrinsic"] != [])
    _edit(tables_copy, "calibrated_sensor", lambda rows: [row.update(camera_intrinsic=[[1, 0, 0], [0, 1, 0]])
                                                          for row in rows if row == camera])  # fmt: skip
    with pytest.raises(TableError, match=rf"calibrated_sensor\.json: record {camera['token']}\.camera_intrinsic: "):
        build_index(tables_copy, VERSION)
    # A reference that is no token at all (a list cannot even be looked up).
    _edit(tables_copy, "sample_data", lambda rows: rows[3].update(sample_token=["x"]))
    with pytest.raises(TableError, match=r"sample_data\.json: record '\w+'\.sample_token: expected a token, got \["):
        load_tables(tables_copy, VERSION)
    _edit(tables_copy, "sample_data", lambda rows: rows[3].update(sample_token="x"))
    _edit(tables_copy, "sensor", lambda rows: rows[0].update(token=["x"]))
    with pytest.raises(TableError, match=r"sensor\.json: record 0: token must be a string, got \['x'\]"):
        load_tables(tables_copy, VERSION)


# ----------------------------------------------------------------------------------------------------- cache key
def test_tables_key_follows_the_content_not_the_modification_time(tables_copy):
    key = tables_key(tables_copy, VERSION, 10)
    assert key.startswith("sha256:") and key == tables_key(tables_copy, VERSION, 10)
    assert tables_key(tables_copy, VERSION, 9) != key
    path = tables_copy / VERSION / "scene.json"
    stat = path.stat()
    path.write_text(path.read_text().replace("scene-0002", "scene-0003"))  # same size
    os.utime(path, ns=(stat.st_atime_ns, stat.st_mtime_ns))
    assert path.stat().st_size == stat.st_size and path.stat().st_mtime_ns == stat.st_mtime_ns
    assert tables_key(tables_copy, VERSION, 10) != key


def test_read_index_header(records, tmp_path):
    path = save_index(records[:2], tmp_path / "index.npz", META | {"max_sweeps": 3})
    assert read_index_header(path) == load_index(path)[1]
    # The header alone is read: a damaged column does not stop it.
    _write(path, _arrays(path) | {"boxes_ego": np.zeros(3)})
    assert read_index_header(path)["max_sweeps"] == 3
    path.write_text('{"format": "occkit-index/3", "records": []}')
    with pytest.raises(IndexFormatError, match=r"index\.npz: not an occkit index \(an occkit-index/3 \.npz file\)"):
        read_index_header(path)


def test_save_index_refuses_nan_and_leaves_no_partial_file(records, tmp_path):
    pose = records[1].ego2global.copy()
    pose[0, 0] = np.nan  # what a zero quaternion gave before it was an error
    broken = dataclasses.replace(records[1], ego2global=pose)
    message = rf"index\.npz: record 1 \(sample {broken.token}\)\.ego2global\[0\]: expected a list of 4 finite numbers"
    with pytest.raises(ValueError, match=message):
        save_index([records[0], broken], tmp_path / "index.npz", META)
    assert list(tmp_path.iterdir()) == []
