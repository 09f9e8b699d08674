"""Check that a dataset written by ``occkit sim`` is real nuScenes, using the official nuscenes-devkit.

nuscenes-devkit pins numpy < 2, so it is not an occkit dependency: run this script in its own environment::

    python -m venv devkit-env && devkit-env/bin/pip install nuscenes-devkit
    devkit-env/bin/python scripts/check_nuscenes_devkit.py --root DATA --version v1.0-synth [--render OUT_DIR]

It loads the tables with ``NuScenes``, then visits every sample: every camera image and LiDAR sweep through
``get_sample_data`` (which also maps every box into the sensor frame), every annotation through ``get_box`` and
``box_velocity``, every key frame's nuScenes-lidarseg labels through ``LidarSegPointCloud`` (one label per point,
every index a category of ``lidarseg_idx2name_mapping``), and every Occ3D ``labels.npz``. With ``--render`` it also
draws one camera and one LiDAR view with boxes, and the LiDAR view coloured by lidarseg, using the devkit's own
renderer. Prints a JSON summary; exits 1 on the first inconsistency.
"""

from __future__ import annotations

import argparse
import json
import os
import sys

import matplotlib

matplotlib.use("Agg")

import numpy as np  # noqa: E402
from nuscenes.nuscenes import NuScenes  # noqa: E402
from nuscenes.utils.data_classes import LidarPointCloud, LidarSegPointCloud  # noqa: E402
from PIL import Image  # noqa: E402


def fail(message: str) -> None:
    print(f"FAILED: {message}", file=sys.stderr)
    sys.exit(1)


def check_sample_data(nusc: NuScenes, token: str, counts: dict) -> None:
    record = nusc.get("sample_data", token)
    path, boxes, intrinsic = nusc.get_sample_data(token)
    if not os.path.exists(path):
        fail(f"sample_data {token}: missing file {path}")
    if record["sensor_modality"] == "camera":
        with Image.open(path) as image:
            if image.size != (record["width"], record["height"]):
                fail(f"{path}: image is {image.size}, table says {(record['width'], record['height'])}")
            image.convert("RGB").load()
        if intrinsic is None or intrinsic.shape != (3, 3):
            fail(f"{path}: no 3x3 camera intrinsic")
        counts["images"] += 1
    else:
        cloud = LidarPointCloud.from_file(path)
        if cloud.points.shape[0] != 4 or cloud.points.shape[1] == 0:
            fail(f"{path}: unexpected point cloud shape {cloud.points.shape}")
        counts["lidar_sweeps"] += 1
        counts["lidar_points"] += cloud.points.shape[1]
    counts["boxes_in_sensor_frames"] += len(boxes)


def check_lidarseg(nusc: NuScenes, sample: dict, counts: dict) -> None:
    token = sample["data"]["LIDAR_TOP"]
    record = nusc.get("lidarseg", token)
    points_path = os.path.join(nusc.dataroot, nusc.get("sample_data", token)["filename"])
    cloud = LidarSegPointCloud(points_path, os.path.join(nusc.dataroot, record["filename"]))
    if cloud.labels.shape != (cloud.points.shape[0],):
        fail(f"lidarseg {token}: {cloud.labels.shape} labels for {cloud.points.shape[0]} points")
    unknown = set(np.unique(cloud.labels).tolist()) - set(nusc.lidarseg_idx2name_mapping)
    if unknown:
        fail(f"lidarseg {token}: indices {sorted(unknown)} name no category")
    counts["lidarseg_frames"] += 1
    counts["lidarseg_points"] += int(cloud.labels.shape[0])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--root", required=True)
    parser.add_argument("--version", default="v1.0-synth")
    parser.add_argument("--render", help="folder for devkit renders of the first sample")
    args = parser.parse_args()

    nusc = NuScenes(version=args.version, dataroot=args.root, verbose=False)
    counts = dict.fromkeys(
        (
            "scenes",
            "samples",
            "images",
            "lidar_sweeps",
            "lidar_points",
            "annotations",
            "boxes_in_sensor_frames",
            "velocities",
            "occ3d_labels",
            "lidarseg_frames",
            "lidarseg_points",
        ),
        0,
    )
    counts["scenes"] = len(nusc.scene)
    for record in nusc.sample_data:
        check_sample_data(nusc, record["token"], counts)
    for scene in nusc.scene:
        token = scene["first_sample_token"]
        while token:
            sample = nusc.get("sample", token)
            counts["samples"] += 1
            if getattr(nusc, "lidarseg", None):
                check_lidarseg(nusc, sample, counts)
            for annotation in sample["anns"]:
                box = nusc.get_box(annotation)
                if not np.all(np.isfinite(box.wlh)) or (box.wlh <= 0).any():
                    fail(f"annotation {annotation}: bad size {box.wlh}")
                velocity = nusc.box_velocity(annotation)
                counts["velocities"] += int(np.isfinite(velocity).all())
                counts["annotations"] += 1
            labels = os.path.join(args.root, "gts", scene["name"], token, "labels.npz")
            with np.load(labels) as gt:
                for key in ("semantics", "mask_lidar", "mask_camera"):
                    if gt[key].shape != (200, 200, 16) or gt[key].dtype != np.uint8:
                        fail(f"{labels}: {key} has {gt[key].shape} {gt[key].dtype}")
            counts["occ3d_labels"] += 1
            token = sample["next"]
        if counts["samples"] == 0:
            fail(f"scene {scene['name']} has no samples")
    if args.render:
        os.makedirs(args.render, exist_ok=True)
        sample = nusc.sample[len(nusc.sample) // 2]
        nusc.render_sample_data(sample["data"]["CAM_FRONT"], out_path=os.path.join(args.render, "devkit_cam_front.png"))
        nusc.render_sample_data(
            sample["data"]["LIDAR_TOP"],
            nsweeps=5,
            underlay_map=True,
            out_path=os.path.join(args.render, "devkit_lidar_top.png"),
        )
        if getattr(nusc, "lidarseg", None):
            nusc.render_sample_data(sample["data"]["LIDAR_TOP"], show_lidarseg=True, show_lidarseg_legend=True,
                                    out_path=os.path.join(args.render, "devkit_lidarseg.png"))
    if counts["lidarseg_frames"] and len(nusc.lidarseg_idx2name_mapping) != 32:
        fail(f"the devkit maps {len(nusc.lidarseg_idx2name_mapping)} lidarseg indices, nuScenes has 32")
    print(json.dumps({"devkit": "ok", **counts}, indent=2))


if __name__ == "__main__":
    main()
