"""Info pickles of BEVDet / FlashOcc and mmdetection3d v2 -> occkit records: both layouts against the index built
from the tables, defaults, refusal of untrusted pickles, errors, CLI."""

from __future__ import annotations

import copy
import dataclasses
import math
import pickle
from pathlib import Path

import numpy as np
import pytest

from occkit.classes import NUSCENES_TO_DETECTION
from occkit.cli import main
from occkit.data.index import FrameRecord, build_index, load_index, read_index_header
from occkit.data.interop import (
    DEFAULT_IMAGE_SIZE,
    IGNORED_CATEGORY,
    MMDET3D_NUSCENES_CLASSES,
    InfoFileError,
    UntrustedPickleError,
    convert_infos,
    import_info_file,
)
from occkit.data.tables import load_tables
from occkit.sim.generate import SimConfig, simulate_dataset
from occkit.sim.rig import pose_matrix

VERSION = "v1.0-synth"
TINY = SimConfig(scenes=1, frames=2, image_size=(176, 64), cameras=("CAM_FRONT", "CAM_BACK"))


@pytest.fixture(scope="module")
def root(tmp_path_factory) -> Path:
    root = tmp_path_factory.mktemp("interop") / "data"
    simulate_dataset(TINY, root)
    return root


@pytest.fixture(scope="module")
def records(root) -> list[FrameRecord]:
    return build_index(root, VERSION)


@pytest.fixture(scope="module")
def bevdet(root, records) -> dict:
    return _bevdet_infos(root, records)


# ----------------------------------------------------------------------------------------------------- writers
def _writer_sensor2lidar(
    sensor2ego: np.ndarray, ego2global: np.ndarray, key_lidar2ego: np.ndarray, key_ego2global: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """obtain_sensor2top's ``sensor2lidar_rotation`` / ``_translation``, in its row-vector form."""
    # A row p maps as p @ R.T + t at each step: sensor -> ego -> global -> key ego -> key LiDAR.
    to_key_ego, to_lidar = np.linalg.inv(key_ego2global[:3, :3]).T, np.linalg.inv(key_lidar2ego[:3, :3]).T
    rows = sensor2ego[:3, :3].T @ ego2global[:3, :3].T @ to_key_ego @ to_lidar
    offset = sensor2ego[:3, 3] @ ego2global[:3, :3].T + ego2global[:3, 3] - key_ego2global[:3, 3]
    offset = (offset @ to_key_ego - key_lidar2ego[:3, 3]) @ to_lidar
    return rows.T, offset  # the writer stores the transpose of the row-vector matrix


def _sensor_info(tables, sd: dict, key_lidar2ego: np.ndarray, key_ego2global: np.ndarray, prefix: str) -> dict:
    """One ``cams`` / ``sweeps`` item as obtain_sensor2top lays it out."""
    calibration = tables.get("calibrated_sensor", sd["calibrated_sensor_token"])
    pose = tables.get("ego_pose", sd["ego_pose_token"])
    sensor2ego = pose_matrix(calibration["translation"], calibration["rotation"])
    ego2global = pose_matrix(pose["translation"], pose["rotation"])
    rotation, translation = _writer_sensor2lidar(sensor2ego, ego2global, key_lidar2ego, key_ego2global)
    return {
        "data_path": prefix + sd["filename"],
        "type": "lidar",
        "sample_data_token": sd["token"],
        "sensor2ego_translation": calibration["translation"],
        "sensor2ego_rotation": calibration["rotation"],
        "ego2global_translation": pose["translation"],
        "ego2global_rotation": pose["rotation"],
        "timestamp": sd["timestamp"],
        "sensor2lidar_rotation": rotation,
        "sensor2lidar_translation": translation,
    }


def _bevdet_infos(root: Path, records: list[FrameRecord]) -> dict:
    """``bevdetv2-nuscenes_infos_*.pkl`` content for ``records``: poses from the tables, boxes from the records."""
    tables = load_tables(root, VERSION)
    by_file = {sd["filename"]: sd for sd in tables["sample_data"]}
    infos = []
    for i, record in enumerate(records):
        # Both path styles of the field: the scripts' ./data/nuscenes and an absolute root.
        prefix = "./data/nuscenes/" if i % 2 == 0 else f"{root}/"
        lidar = by_file[record.lidar_path]
        calibration = tables.get("calibrated_sensor", lidar["calibrated_sensor_token"])
        pose = tables.get("ego_pose", lidar["ego_pose_token"])
        lidar2ego = pose_matrix(calibration["translation"], calibration["rotation"])
        ego2global = pose_matrix(pose["translation"], pose["rotation"])
        cams = {}
        for channel, camera in record.cameras.items():
            sd = by_file[camera.path]
            cams[channel] = _sensor_info(tables, sd, lidar2ego, ego2global, prefix) | {"type": channel}
            cams[channel]["cam_intrinsic"] = np.array(
                tables.get("calibrated_sensor", sd["calibrated_sensor_token"])["camera_intrinsic"]
            )
        velocity = np.where(record.velocity_valid[:, None], record.boxes_lidar[:, 7:9], np.nan)
        names = [NUSCENES_TO_DETECTION.get(category, category) for category in record.box_categories]
        infos.append(
            {
                "lidar_path": prefix + record.lidar_path,
                "token": record.token,
                "sweeps": [_sensor_info(tables, by_file[s.path], lidar2ego, ego2global, prefix) for s in record.sweeps],
                "cams": cams,
                "lidar2ego_translation": calibration["translation"],
                "lidar2ego_rotation": calibration["rotation"],
                "ego2global_translation": pose["translation"],
                "ego2global_rotation": pose["rotation"],
                "timestamp": record.timestamp,
                "gt_boxes": record.boxes_lidar[:, :7].copy(),
                "gt_names": np.array(names),
                "gt_velocity": velocity,
                "num_lidar_pts": np.array(record.box_num_lidar_pts),
                "num_radar_pts": np.zeros(record.num_boxes, dtype=np.int64),
                "valid_flag": np.array(record.box_num_lidar_pts) > 0,
                "ann_infos": ([], []),
                "scene_token": record.scene_token,
                "scene_name": record.scene,
                "occ_path": f"gts/{record.scene}/{record.token}",
            }
        )
    return {"infos": infos, "metadata": {"version": VERSION}}


def _matrix(rotation, translation) -> list:
    return pose_matrix(translation, rotation).tolist()


def _inverse(rotation: np.ndarray, translation: np.ndarray) -> list:
    matrix = np.eye(4)
    matrix[:3, :3], matrix[:3, 3] = rotation.T, -rotation.T @ translation
    return matrix.tolist()


def _v2_infos(bevdet: dict, flashocc_keys: bool) -> dict:
    """update_infos_to_v2's rewrite of ``bevdet`` (float64; the writer rounds matrices to float32)."""
    data_list = []
    for i, info in enumerate(bevdet["infos"]):
        entry = {
            "sample_idx": i,
            "token": info["token"],
            "timestamp": info["timestamp"] / 1e6,
            "ego2global": _matrix(info["ego2global_rotation"], info["ego2global_translation"]),
            "lidar_points": {
                "num_pts_feats": 5,
                "lidar_path": Path(info["lidar_path"]).name,
                "lidar2ego": _matrix(info["lidar2ego_rotation"], info["lidar2ego_translation"]),
            },
            "lidar_sweeps": [
                {
                    "lidar_points": {
                        "lidar2ego": _matrix(s["sensor2ego_rotation"], s["sensor2ego_translation"]),
                        "lidar2sensor": _inverse(s["sensor2lidar_rotation"], s["sensor2lidar_translation"]),
                        "lidar_path": s["data_path"],
                    },
                    "ego2global": _matrix(s["ego2global_rotation"], s["ego2global_translation"]),
                    "timestamp": s["timestamp"] / 1e6,
                    "sample_data_token": s["sample_data_token"],
                }
                for s in info["sweeps"]
            ],
            "images": {
                channel: {
                    "img_path": Path(cam["data_path"]).name,
                    "cam2img": cam["cam_intrinsic"].tolist(),
                    "sample_data_token": cam["sample_data_token"],
                    "timestamp": cam["timestamp"] / 1e6,
                    "cam2ego": _matrix(cam["sensor2ego_rotation"], cam["sensor2ego_translation"]),
                    "lidar2cam": _inverse(cam["sensor2lidar_rotation"], cam["sensor2lidar_translation"]),
                }
                for channel, cam in info["cams"].items()
            },
            "instances": [
                {
                    "bbox_3d": box.tolist(),
                    "bbox_label": _v2_label(name),
                    "bbox_label_3d": _v2_label(name),
                    "velocity": velocity.tolist(),
                    "num_lidar_pts": points,
                    "num_radar_pts": radar,
                    "bbox_3d_isvalid": valid,  # numpy's bool, as the writer indexes valid_flag
                }
                for box, name, velocity, points, radar, valid in zip(
                    info["gt_boxes"], info["gt_names"], info["gt_velocity"], info["num_lidar_pts"],
                    info["num_radar_pts"], info["valid_flag"], strict=True,
                )  # fmt: skip
            ],
            "cam_instances": {},
        }
        if not entry["lidar_sweeps"]:
            del entry["lidar_sweeps"]  # clear_data_info_unused_keys drops empty lists
        if flashocc_keys:
            entry.update({key: info[key] for key in ("scene_token", "scene_name", "occ_path")})
        data_list.append(entry)
    names = {name for info in bevdet["infos"] for name in info["gt_names"]}
    categories = {name: i for i, name in enumerate(MMDET3D_NUSCENES_CLASSES)}
    categories |= {name: -1 for name in names if name not in categories}
    metainfo = {"categories": categories, "dataset": "nuscenes", "version": VERSION, "info_version": "1.1"}
    return {"metainfo": metainfo, "data_list": data_list}


def _v2_label(name: str) -> int:
    return MMDET3D_NUSCENES_CLASSES.index(name) if name in MMDET3D_NUSCENES_CLASSES else -1


def _dump(data, path: Path) -> Path:
    with open(path, "wb") as stream:
        pickle.dump(data, stream)
    return path


# ----------------------------------------------------------------------------------------------------- checks
def _expected(record: FrameRecord, ignored: str | None = None, scene: bool = True) -> FrameRecord:
    """``record`` as an info file can give it back: no instance or visibility tokens, detection classes as
    categories (nuScenes categories for the others, or ``ignored`` where the file keeps no name)."""
    categories = [
        name if name is not None else (ignored or category)
        for category, name in zip(record.box_categories, record.box_detection_names, strict=True)
    ]
    changes = {"box_categories": categories, "box_instances": [""] * record.num_boxes}
    changes["box_visibility"] = [""] * record.num_boxes
    if not scene:
        changes.update(scene="", scene_token="", prev="", next="", index_in_scene=0, occ_path=None)
    return dataclasses.replace(record, **changes)


def _assert_close(actual, expected, where: str = "record", tol: float = 1e-9) -> None:
    """Equal, floats to ``tol``."""
    if isinstance(expected, dict):
        assert list(actual) == list(expected), where
        for key in expected:
            _assert_close(actual[key], expected[key], f"{where}.{key}", tol)
    elif isinstance(expected, list):
        assert len(actual) == len(expected), where
        for i, (a, e) in enumerate(zip(actual, expected, strict=True)):
            _assert_close(a, e, f"{where}[{i}]", tol)
    elif isinstance(expected, float):
        assert math.isclose(actual, expected, rel_tol=0, abs_tol=tol), f"{where}: {actual} != {expected}"
    else:
        assert actual == expected, f"{where}: {actual!r} != {expected!r}"


def _assert_records(actual: list[FrameRecord], expected: list[FrameRecord], tol: float = 1e-9) -> None:
    assert len(actual) == len(expected)
    for i, (a, e) in enumerate(zip(actual, expected, strict=True)):
        _assert_close(a.to_dict(), e.to_dict(), f"record {i}", tol)


# ----------------------------------------------------------------------------------------------------- layouts
def test_bevdet_infos_give_the_index_records(root, records, bevdet, tmp_path):
    assert [len(r.sweeps) for r in records] == [0, 10] and all(r.num_boxes for r in records)
    imported = import_info_file(_dump(bevdet, tmp_path / "infos.pkl"), root, VERSION, trust_pickle=True)
    _assert_records(imported, [_expected(r) for r in records])
    assert imported[1].boxes_lidar.shape == records[1].boxes_lidar.shape and not imported[1].velocity_valid.all()


@pytest.mark.parametrize("flashocc_keys", [True, False], ids=["flashocc-keys", "plain"])
def test_mmdet3d_v2_infos_give_the_index_records(root, records, bevdet, tmp_path, flashocc_keys):
    data = _v2_infos(bevdet, flashocc_keys)
    imported = import_info_file(_dump(data, tmp_path / "v2.pkl"), root, VERSION, trust_pickle=True)
    _assert_records(imported, [_expected(r, IGNORED_CATEGORY, scene=flashocc_keys) for r in records])


def test_valid_flags_come_from_the_file_or_from_the_lidar_points(root, bevdet):
    """``valid_flag`` / ``bbox_3d_isvalid`` are mmdetection3d's ``(num_lidar_pts + num_radar_pts) > 0``, taken as the
    file has them; a file without them gets ``num_lidar_pts > 0``."""
    data = copy.deepcopy(bevdet)
    first = data["infos"][0]
    # Box 0 seen by radar alone: valid by the file's flag, not by its LiDAR points.
    first["num_lidar_pts"][0], first["num_radar_pts"][0], first["valid_flag"][0] = 0, 5, True
    flags = [info["valid_flag"].tolist() for info in data["infos"]]
    lidar = [(info["num_lidar_pts"] > 0).tolist() for info in data["infos"]]
    assert flags != lidar and {flag for row in flags for flag in row} == {True, False}
    v2 = _v2_infos(data, flashocc_keys=True)
    for layout in (data, v2):
        assert [record.box_valid.tolist() for record in convert_infos(layout, root)] == flags
    for info in data["infos"]:
        del info["valid_flag"]
    for entry in v2["data_list"]:
        for instance in entry["instances"]:
            del instance["bbox_3d_isvalid"]
    for layout in (data, v2):
        assert [record.box_valid.tolist() for record in convert_infos(layout, root)] == lidar


@pytest.mark.parametrize(
    "layout, edit, message",
    [
        ("bevdet", lambda entry: entry.update(valid_flag=np.ones(len(entry["gt_boxes"]), dtype=np.int64)),
         r"\.valid_flag: expected booleans of shape \(\d+\), got int64"),
        ("bevdet", lambda entry: entry.update(valid_flag=entry["valid_flag"][:-1]),
         r"\.valid_flag: expected booleans of shape \(\d+\), got bool of shape"),
        ("mmdet3d-v2", lambda entry: entry["instances"][2].update(bbox_3d_isvalid=1),
         r"\.instances\[2\]\.bbox_3d_isvalid: expected booleans of shape \(\), got int64"),
    ],
)  # fmt: skip
def test_bad_valid_flags_name_the_entry_and_key(root, bevdet, layout, edit, message):
    data = copy.deepcopy(bevdet) if layout == "bevdet" else _v2_infos(bevdet, flashocc_keys=True)
    edit((data["infos"] if layout == "bevdet" else data["data_list"])[1])
    with pytest.raises(InfoFileError, match=r"^info file: entry 1 \(token '\w+'\)" + message):
        convert_infos(data, root)


def test_mmdet3d_v2_float32_matrices_stay_close(root, records, bevdet):
    data = _v2_infos(bevdet, flashocc_keys=True)

    def rounded(item: dict, *keys: str) -> None:
        for key in keys:  # the writer rounds every matrix to float32 before listing it
            item[key] = np.float32(item[key]).tolist()

    for entry in data["data_list"]:
        rounded(entry, "ego2global")
        rounded(entry["lidar_points"], "lidar2ego")
        for sweep in entry.get("lidar_sweeps", []):
            rounded(sweep["lidar_points"], "lidar2ego", "lidar2sensor")
        for image in entry["images"].values():
            rounded(image, "cam2ego", "lidar2cam")
    _assert_records(convert_infos(data, root), [_expected(r, IGNORED_CATEGORY) for r in records], tol=1e-4)


def test_sweep_transform_follows_the_writers_row_convention(root, bevdet):
    # The simulated ego drives straight, so its sweeps do not turn: turn and tilt one sweep's ego pose.
    data = copy.deepcopy(bevdet)
    info, sweep = data["infos"][1], data["infos"][1]["sweeps"][0]
    sweep["ego2global_rotation"] = list(np.array([0.98, 0.03, -0.02, 0.2]) / np.linalg.norm([0.98, 0.03, -0.02, 0.2]))
    sensor2ego = pose_matrix(sweep["sensor2ego_translation"], sweep["sensor2ego_rotation"])
    ego2global = pose_matrix(sweep["ego2global_translation"], sweep["ego2global_rotation"])
    key_lidar2ego = pose_matrix(info["lidar2ego_translation"], info["lidar2ego_rotation"])
    key_ego2global = pose_matrix(info["ego2global_translation"], info["ego2global_rotation"])
    rotation, translation = _writer_sensor2lidar(sensor2ego, ego2global, key_lidar2ego, key_ego2global)
    sweep["sensor2lidar_rotation"], sweep["sensor2lidar_translation"] = rotation, translation
    expected = np.linalg.inv(key_lidar2ego) @ np.linalg.inv(key_ego2global) @ ego2global @ sensor2ego
    assert np.abs(expected[:3, :3] - expected[:3, :3].T).max() > 0.1  # the transposed rotation would differ
    for layout in (data, _v2_infos(data, flashocc_keys=True)):
        np.testing.assert_allclose(convert_infos(layout, root)[1].sweeps[0].sweep2lidar, expected, atol=1e-9)


def test_defaults_for_keys_a_file_lacks(root, records, bevdet, tmp_path):
    data = copy.deepcopy(bevdet)
    for info in data["infos"]:
        del info["occ_path"]
    # No occ_path: the Occ3D layout's labels.npz where it exists.
    assert [r.occ_path for r in convert_infos(data, root)] == [r.occ_path for r in records]
    for info, record in zip(data["infos"], records, strict=True):
        for key in ("scene_token", "scene_name", "gt_boxes", "gt_names", "gt_velocity", "num_lidar_pts"):
            del info[key]
        info["lidar_path"] = f"elsewhere/{record.lidar_path}"
        for item in [*info["sweeps"], *info["cams"].values()]:  # paths under the old root would be absolute here
            item["data_path"] = item["data_path"].replace(f"{root}/", "./data/nuscenes/")
    bare = convert_infos(data, tmp_path)  # a root without the images or labels
    for record, original in zip(bare, records, strict=True):
        assert (record.scene, record.prev, record.next, record.index_in_scene) == ("", "", "", 0)
        assert record.occ_path is None and record.num_boxes == 0 and record.boxes_ego.shape == (0, 9)
        assert {(c.width, c.height) for c in record.cameras.values()} == {DEFAULT_IMAGE_SIZE}
        # Relative paths under neither the root nor data/nuscenes are kept as they are.
        assert record.lidar_path == f"elsewhere/{original.lidar_path}"
        assert record.cameras["CAM_FRONT"].path == original.cameras["CAM_FRONT"].path


@pytest.mark.parametrize(
    "edit, message",
    [
        # Absolute paths elsewhere and '..' would read outside the root.
        (lambda info: info.update(lidar_path="/elsewhere/a.pcd.bin"), r"record field lidar_path: .* absolute path"),
        (lambda info: info["cams"]["CAM_BACK"].update(data_path="../x.jpg"), r"cameras\.CAM_BACK\.path: .*'\.\.'"),
        (lambda info: info["sweeps"][0].update(data_path="samples/../../x"), r"sweeps\[0\]\.path: .*'\.\.'"),
        (lambda info: info.update(occ_path="/gts/a"), r"occ_path: .* absolute path"),
        # Tokens and scene names become file names.
        (lambda info: info.update(token="../../escape_tok"), r"\.token: '\.\./\.\./escape_tok' is not a safe name"),
        (lambda info: info.update(scene_name="../../../escape_scene"), r"\.scene_name: .* is not a safe name"),
        (lambda info: info.update(scene_token="/abs"), r"\.scene_token: '/abs' is not a safe name"),
        # A zero quaternion is no rotation (normalising it gives NaN).
        (lambda info: info.update(ego2global_rotation=[0.0, 0.0, 0.0, 0.0]), r"ego2global_rotation: quaternion"),
    ],
)
def test_unsafe_names_paths_and_rotations_name_the_entry(root, bevdet, edit, message):
    data = copy.deepcopy(bevdet)
    edit(data["infos"][1])
    with pytest.raises(InfoFileError, match=r"info file: entry 1 .*" + message):
        convert_infos(data, root)


# ----------------------------------------------------------------------------------------------------- errors
def test_untrusted_pickle_is_refused_before_loading(root, tmp_path):
    marker = tmp_path / "ran"

    class Payload:
        def __reduce__(self):
            import os

            return os.mkdir, (str(marker),)

    path = _dump({"infos": [Payload()]}, tmp_path / "infos.pkl")
    refusal = r"runs any code.*pass --trust-pickle only for files from a source you trust"
    with pytest.raises(UntrustedPickleError, match=refusal) as error:
        import_info_file(path, root)
    assert str(path) in str(error.value) and not marker.exists()


@pytest.mark.parametrize(
    "layout, drop, message",
    [
        ("bevdet", ("lidar2ego_rotation",), r"entry 1 \(token '{token}'\): no key 'lidar2ego_rotation' .*"),
        ("bevdet", ("cams", "CAM_BACK", "sensor2ego_translation"), r"entry 1 .*\.cams\.CAM_BACK: no key"),
        ("mmdet3d-v2", ("images", "CAM_BACK", "lidar2cam"), r"entry 1 .*\.images\.CAM_BACK: no key 'lidar2cam'"),
    ],
)
def test_missing_key_names_the_file_entry_key_and_writer(root, bevdet, tmp_path, layout, drop, message):
    data = copy.deepcopy(bevdet) if layout == "bevdet" else _v2_infos(bevdet, flashocc_keys=True)
    entry = (data["infos"] if layout == "bevdet" else data["data_list"])[1]
    parent = entry
    for key in drop[:-1]:
        parent = parent[key]
    del parent[drop[-1]]
    path = _dump(data, tmp_path / "infos.pkl")
    with pytest.raises(InfoFileError, match=message.format(token=entry["token"])) as error:
        import_info_file(path, root, trust_pickle=True)
    writer = "nuscenes_converter.py" if layout == "bevdet" else "update_infos_to_v2.py"
    assert str(error.value).startswith(f"{path}: ") and writer in str(error.value)


def test_unknown_or_unreadable_files(root, bevdet, tmp_path):
    with pytest.raises(InfoFileError, match=r"unknown info file layout: expected .*'infos'.*'data_list'.*'foo'"):
        import_info_file(_dump({"foo": 1}, tmp_path / "a.pkl"), root, trust_pickle=True)
    with pytest.raises(InfoFileError, match="got a list"):
        import_info_file(_dump(bevdet["infos"], tmp_path / "b.pkl"), root, trust_pickle=True)
    truncated = tmp_path / "c.pkl"
    truncated.write_bytes(pickle.dumps(bevdet)[:100])
    with pytest.raises(InfoFileError, match="not a readable pickle"):
        import_info_file(truncated, root, trust_pickle=True)
    with pytest.raises(InfoFileError, match=r"written for nuScenes 'v1.0-synth', not 'v1.0-trainval'"):
        convert_infos(bevdet, root, version_hint="v1.0-trainval")
    with pytest.raises(FileNotFoundError, match="does not exist"):
        import_info_file(tmp_path / "missing.pkl", root)


# ----------------------------------------------------------------------------------------------------- CLI
def test_cli_index_from_info(root, records, bevdet, tmp_path, capsys):
    path = _dump(bevdet, tmp_path / "bevdetv2-nuscenes_infos_val.pkl")
    out = tmp_path / "index.npz"
    command = ["index", "--root", str(root), "--version", VERSION, "--out", str(out), "--from-info", str(path)]
    assert main(command) == 2
    assert "--trust-pickle only for files from a source you trust" in capsys.readouterr().err and not out.exists()
    assert main([*command, "--trust-pickle", "--split", "val"]) == 2
    assert "leave out --split" in capsys.readouterr().err
    assert main([*command, "--trust-pickle", "--max-sweeps", "3"]) == 0
    assert "converted 2 key frames of 1 scene(s)" in capsys.readouterr().out
    loaded, header = load_index(out)
    assert header["version"] == VERSION and header["max_sweeps"] == 3 and header["from_info"] == str(path)
    expected = [dataclasses.replace(_expected(r), sweeps=r.sweeps[:3]) for r in records]
    _assert_records(loaded, expected)
    assert read_index_header(out)["frames"] == 2
