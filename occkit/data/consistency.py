"""Geometric consistency of a written dataset, measured from the files alone.

Two checks that a dataset's sensors and labels agree, usable on any nuScenes + Occ3D layout:

* :func:`lidar_in_occupied` - the share of key-frame LiDAR points inside the grid that fall in (or on the face of)
  an occupied voxel of that key frame's labels, after mapping LiDAR -> ego with the calibration;
* :func:`boxes_in_cameras` - for annotations with visibility above 60%, whether the box centre projects into
  at least one camera image through the written poses and intrinsics.

``python -m occkit.data.consistency DATA_ROOT [--version V]`` prints both as JSON.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
import torch

from occkit.data.labels import read_occ3d_labels
from occkit.data.tables import NuScenesTables, load_tables
from occkit.geometry.se3 import transform_from_quaternion
from occkit.label_space import OCC3D_SPACE

__all__ = ["lidar_in_occupied", "boxes_in_cameras"]


def _pose_matrix(translation, rotation_wxyz) -> np.ndarray:
    """``(4, 4)`` float64 matrix of a nuScenes record's translation and (w, x, y, z) quaternion."""
    rotation = torch.as_tensor(rotation_wxyz, dtype=torch.float64)
    return transform_from_quaternion(rotation, torch.as_tensor(translation, dtype=torch.float64)).numpy()

# A point exactly on a voxel face floors into the upper voxel; it also touches the lower one.
_FACE_TOLERANCE = 0.01


def _key_frame_records(tables: NuScenesTables, modality: str) -> list[tuple[dict, dict]]:
    """(sample_data, calibrated_sensor) pairs of the key frames of one sensor modality."""
    calibration = {c["token"]: c for c in tables["calibrated_sensor"]}
    modality_of = {s["token"]: s["modality"] for s in tables["sensor"]}
    pairs = []
    for record in tables["sample_data"]:
        sensor = calibration[record["calibrated_sensor_token"]]
        if record["is_key_frame"] and modality_of[sensor["sensor_token"]] == modality:
            pairs.append((record, sensor))
    return pairs


def lidar_in_occupied(root: str | Path, version: str) -> dict:
    """Share of in-grid key-frame LiDAR points that lie in or on an occupied voxel, overall and per key frame."""
    root = Path(root)
    tables = load_tables(root, version)
    scene_of = {s["token"]: s["name"] for s in tables["scene"]}
    sample_scene = {s["token"]: scene_of[s["scene_token"]] for s in tables["sample"]}
    hits = total = 0
    per_frame = []
    offsets = np.array([[0, 0, 0], [-1, 0, 0], [0, -1, 0], [0, 0, -1]]) * _FACE_TOLERANCE
    upper = np.array(OCC3D_SPACE.grid.shape) - 1
    for record, calibration in _key_frame_records(tables, "lidar"):
        points = np.fromfile(root / record["filename"], dtype=np.float32).reshape(-1, 5)[:, :3].astype(np.float64)
        lidar2ego = _pose_matrix(calibration["translation"], calibration["rotation"])
        ego = torch.from_numpy(points @ lidar2ego[:3, :3].T + lidar2ego[:3, 3])
        _, inside = OCC3D_SPACE.grid.world_to_index(ego)
        ego = ego[inside]
        labels = root / OCC3D_SPACE.label_folder / sample_scene[record["sample_token"]] / record["sample_token"] / \
            "labels.npz"  # fmt: skip
        occupied = read_occ3d_labels(labels, record["sample_token"]).semantics != OCC3D_SPACE.free_index
        found = np.zeros(ego.shape[0], dtype=bool)
        for offset in offsets:
            index = OCC3D_SPACE.grid.world_to_index(ego + torch.from_numpy(offset))[0].numpy().clip(0, upper)
            found |= occupied[index[:, 0], index[:, 1], index[:, 2]]
        hits += int(found.sum())
        total += int(found.size)
        per_frame.append(float(found.mean()) if found.size else float("nan"))
    return {
        "points_in_grid": total,
        "share_in_occupied": hits / max(total, 1),
        "worst_key_frame": float(np.nanmin(per_frame)) if per_frame else float("nan"),
        "key_frames": len(per_frame),
    }


def boxes_in_cameras(root: str | Path, version: str) -> dict:
    """How many annotations seen at more than 60% visibility have their centre inside some camera image."""
    tables = load_tables(Path(root), version)
    poses = {p["token"]: p for p in tables["ego_pose"]}
    cameras_of: dict[str, list] = {}
    for record, calibration in _key_frame_records(tables, "camera"):
        pose = poses[record["ego_pose_token"]]
        cam2global = _pose_matrix(pose["translation"], pose["rotation"]) @ _pose_matrix(
            calibration["translation"], calibration["rotation"]
        )
        intrinsic = np.array(calibration["camera_intrinsic"])
        size = (record["width"], record["height"])
        cameras_of.setdefault(record["sample_token"], []).append((np.linalg.inv(cam2global), intrinsic, size))
    checked = inside = 0
    misses = []
    for annotation in tables["sample_annotation"]:
        if annotation["visibility_token"] not in ("3", "4"):
            continue
        centre = np.array(annotation["translation"])
        seen = False
        for global2cam, intrinsic, (width, height) in cameras_of[annotation["sample_token"]]:
            in_camera = global2cam[:3, :3] @ centre + global2cam[:3, 3]
            if in_camera[2] > 0:
                u, v = (intrinsic @ in_camera)[:2] / in_camera[2]
                seen |= bool(0 <= u < width and 0 <= v < height)
        checked += 1
        inside += int(seen)
        if not seen:
            misses.append(annotation["token"])
    return {"visible_boxes": checked, "centre_in_a_camera": inside, "misses": misses[:20]}


def main() -> None:
    parser = argparse.ArgumentParser(description="Consistency of a written nuScenes + Occ3D dataset.")
    parser.add_argument("root", type=Path)
    parser.add_argument("--version", default="v1.0-synth")
    args = parser.parse_args()
    report = {"lidar": lidar_in_occupied(args.root, args.version), "boxes": boxes_in_cameras(args.root, args.version)}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
