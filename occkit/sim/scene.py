"""One simulated scene: sensors over time, labels per key frame, and the nuScenes rows that describe them.

Called by :func:`occkit.sim.generate.simulate_dataset` in a worker process per scene; writes the scene's
files under the dataset root and returns its table rows, so the parent can write the tables in scene order.
"""

from __future__ import annotations

import math
import time
from collections import defaultdict
from collections.abc import Callable
from contextlib import contextmanager
from pathlib import Path
from typing import NamedTuple

import numpy as np

from occkit.geometry.grid import OCC3D_GRID, SURROUNDOCC_GRID
from occkit.geometry.visibility import camera_visibility, lidar_visibility
from occkit.label_files import occ3d_to_openocc, write_occ3d_labels, write_openocc_labels, write_surroundocc_labels
from occkit.nuscenes import CAMERAS
from occkit.sim.config import (
    FIRST_TIMESTAMP_US,
    KEY_FRAME_INTERVAL_US,
    SWEEP_INTERVAL_US,
    SWEEPS_PER_KEY_FRAME,
    SimConfig,
    camera_time_offsets_us,
    scene_name,
)
from occkit.sim.labels import occupancy_flow_labels, surroundocc_labels
from occkit.sim.lidar import lidarseg_labels, scan_lidar
from occkit.sim.primitives import Primitives
from occkit.sim.raytrace import cast_rays
from occkit.sim.render import render_camera
from occkit.sim.rig import LIDAR_TOP, CameraSpec, camera_rig, yaw_quaternion
from occkit.sim.world import BoxState, World, generate_world
from occkit.sim.writer import (
    make_token,
    write_jpeg,
    write_lidarseg,
    write_png,
    write_points,
)

__all__ = ["simulate_scene", "ANNOTATION_RANGE"]

#: Objects farther than this from the ego (m, in the ground plane) are not annotated, as in nuScenes.
ANNOTATION_RANGE = 60.0


class _Sweep(NamedTuple):
    points: np.ndarray  # (N, 5) float32 in the LiDAR frame
    instance: np.ndarray  # (N,) int32 object hit by each point, -1 for the ground
    ego2global: np.ndarray  # (4, 4)
    filename: str  # relative to the dataset root


class _StageTimer:
    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    @contextmanager
    def __call__(self, stage: str):
        start = time.perf_counter()
        yield
        self.seconds[stage] += time.perf_counter() - start


def _child_seed(*parts: int) -> int:
    return int(np.random.SeedSequence(list(parts)).generate_state(1)[0])


class _SceneWriter:
    """Accumulates the rows of one scene and writes its files."""

    def __init__(self, config: SimConfig, index: int, root: Path, world: World) -> None:
        self.config = config
        self.root = root
        self.world = world
        self.name = scene_name(index)
        self.log_name = f"synth-{config.seed:04d}-{index + 1:04d}"
        self.first_timestamp = FIRST_TIMESTAMP_US + index * 100_000_000
        # Global coordinates are written shifted so the map raster starts at (0, 0), as nuScenes map masks do.
        self.offset = np.array([-world.ground.origin[0], -world.ground.origin[1], 0.0])
        self.rows: dict[str, list[dict]] = defaultdict(list)
        self.calibration: dict[str, str] = {}

    def token(self, *parts: object) -> str:
        return make_token(self.config.version, self.config.seed, self.name, *parts)

    def shared_token(self, table: str, name: str) -> str:
        return make_token(self.config.version, table, name)

    # --------------------------------------------------------------------------------------- log, map, sensors
    def write_log_and_map(self) -> None:
        log_token, map_token = self.token("log"), self.token("map")
        self.rows["log"].append(
            {
                "token": log_token,
                "logfile": self.log_name,
                "vehicle": "synth-ego",
                "date_captured": "2026-01-01",
                "location": self.world.location,
            }
        )
        filename = f"maps/{map_token}.png"
        # nuScenes map masks: 255 on drivable area, rows from north to south, 0.1 m per pixel from the origin.
        drivable = (self.world.ground.semantics == 11).astype(np.uint8) * 255
        write_png(self.root / filename, np.ascontiguousarray(np.flipud(drivable.T)))
        self.rows["map"].append(
            {"token": map_token, "log_tokens": [log_token], "category": "semantic_prior", "filename": filename}
        )

    def calibrate(self, channel: str, translation, rotation, intrinsics) -> str:
        token = self.token("calibrated_sensor", channel)
        self.calibration[channel] = token
        self.rows["calibrated_sensor"].append(
            {
                "token": token,
                "sensor_token": self.shared_token("sensor", channel),
                "translation": [float(v) for v in translation],
                "rotation": [float(v) for v in rotation],
                "camera_intrinsic": [[float(v) for v in row] for row in intrinsics] if intrinsics is not None else [],
            }
        )
        return token

    # --------------------------------------------------------------------------------------- sample data
    def pose_record(self, ego2global: np.ndarray) -> dict:
        yaw = float(np.arctan2(ego2global[1, 0], ego2global[0, 0]))
        return {
            "translation": [float(v) for v in ego2global[:3, 3] + self.offset],
            "rotation": [float(v) for v in yaw_quaternion(yaw)],
        }

    def add_sample_data(
        self,
        channel: str,
        timestamp: int,
        ego2global: np.ndarray,
        key_frame: int | None,
        sample: int,
        filename: str,
        size: tuple[int, int] | None,
    ) -> str:
        token = self.token("sample_data", channel, timestamp)
        # nuScenes gives each sample_data's ego pose the sample_data's own token.
        self.rows["ego_pose"].append({"token": token, "timestamp": timestamp, **self.pose_record(ego2global)})
        width, height = size if size is not None else (0, 0)
        self.rows["sample_data"].append(
            {
                "token": token,
                "sample_token": self.token("sample", sample),
                "ego_pose_token": token,
                "calibrated_sensor_token": self.calibration[channel],
                "timestamp": timestamp,
                "fileformat": "jpg" if size is not None else "pcd",
                "is_key_frame": key_frame is not None,
                "height": height,
                "width": width,
                "filename": filename,
                "prev": "",
                "next": "",
            }
        )
        return token

    def add_lidarseg(self, token: str, labels: np.ndarray) -> None:
        """Write the lidarseg labels of the LiDAR sample_data ``token`` and its row (whose token is the same)."""
        filename = f"lidarseg/{self.config.version}/{token}_lidarseg.bin"
        write_lidarseg(self.root / filename, labels)
        self.rows["lidarseg"].append({"token": token, "sample_data_token": token, "filename": filename})

    def link_sample_data(self) -> None:
        by_channel: dict[str, list[dict]] = defaultdict(list)
        channel_of = {token: channel for channel, token in self.calibration.items()}
        for row in self.rows["sample_data"]:
            by_channel[channel_of[row["calibrated_sensor_token"]]].append(row)
        ordered = []
        for channel in self.calibration:
            rows = sorted(by_channel[channel], key=lambda r: r["timestamp"])
            _link(rows)
            ordered.extend(rows)
        self.rows["sample_data"] = ordered
        order = {row["token"]: i for i, row in enumerate(ordered)}
        self.rows["ego_pose"].sort(key=lambda r: order[r["token"]])


def _link(rows: list[dict]) -> None:
    for previous, current in zip(rows, rows[1:], strict=False):
        previous["next"] = current["token"]
        current["prev"] = previous["token"]


class _View(NamedTuple):
    """One camera image of a key frame, as rendered."""

    camera: CameraSpec
    ego2global: np.ndarray
    primitives: Primitives  # the world at the camera's timestamp
    instance: np.ndarray  # (H, W) object seen at each pixel


_RAYS_PER_VIEW = 4000


def _box_visibility(box: BoxState, views: list[_View], stride: int = 2) -> str:
    """nuScenes visibility token: the share of the object's image pixels that are not occluded, over all cameras.

    The unoccluded silhouette is ray cast against the object's own solids alone, inside the rectangle around its
    projected corners (extended above and below the image), and compared with the pixels where the full render shows
    it; both are counted on every ``stride``-th pixel or coarser (at most about 4000 rays per camera), which is
    plenty for the 20%-wide bins.
    """
    corners = _box_corners(box)
    unoccluded = visible = 0
    for view in views:
        camera = view.camera
        cam2global = view.ego2global @ camera.cam2ego
        global2cam = np.linalg.inv(cam2global)
        in_camera = corners @ global2cam[:3, :3].T + global2cam[:3, 3]
        front = in_camera[:, 2] > 0.1
        if not front.any():
            continue
        # Rows above and below the image count as unseen, as parts outside every image do in nuScenes; columns
        # need no extension, since the rig's images overlap all around.
        width, height = camera.width, camera.height
        u0, v0, u1, v1 = 0, -height, width, 2 * height
        if front.all():  # otherwise the box reaches behind the camera and may cover any pixel
            uv = in_camera[:, :2] / in_camera[:, 2:3] @ camera.K[:2, :2].T + camera.K[:2, 2]
            u0, v0 = np.floor(uv.min(axis=0)).clip((0, -height), (width, 2 * height)).astype(int)
            u1, v1 = np.ceil(uv.max(axis=0)).clip((0, -height), (width, 2 * height)).astype(int)
        if u1 <= u0 or v1 <= v0:
            continue
        # Coarser sampling for large silhouettes keeps near objects cheap; the bins need only about 1% precision.
        step = max(stride, math.ceil(math.sqrt((u1 - u0) * (v1 - v0) / _RAYS_PER_VIEW)))
        v, u = np.mgrid[v0:v1:step, u0:u1:step]
        in_image = (v >= 0) & (v < height)
        visible += int((view.instance[v[in_image], u[in_image]] == box.instance).sum())
        pixel_centres = np.stack((u.ravel() + 0.5, v.ravel() + 0.5, np.ones(u.size)), axis=-1)
        directions = pixel_centres @ np.linalg.inv(camera.K).T @ cam2global[:3, :3].T
        directions /= np.linalg.norm(directions, axis=-1, keepdims=True)
        own = view.primitives.select(view.primitives.instance == box.instance)
        hits = cast_rays(cam2global[:3, 3], directions, 1e4, own, None)
        unoccluded += int((hits.primitive >= 0).sum())
    ratio = visible / unoccluded if unoccluded > 0 else 0.0
    for token, upper in (("1", 0.4), ("2", 0.6), ("3", 0.8)):
        if ratio < upper:
            return token
    return "4"


def _box_corners(box: BoxState) -> np.ndarray:
    """``(8, 3)`` global corners of a box (size w, l, h; yaw about z)."""
    width, length, height = box.size
    signs = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], dtype=np.float64)
    local = signs * np.array([length / 2, width / 2, height / 2])
    cos, sin = np.cos(box.yaw), np.sin(box.yaw)
    rotation = np.array([[cos, -sin, 0.0], [sin, cos, 0.0], [0.0, 0.0, 1.0]])
    return local @ rotation.T + box.center


def simulate_scene(config: SimConfig, index: int, root: Path, progress: Callable[[int], None] | None = None) -> dict:
    """Simulate scene ``index`` of ``config``, write its files under ``root`` and return its rows and timings."""
    timer = _StageTimer()
    world_seed = _child_seed(config.seed, index)
    with timer("world"):
        world = generate_world(world_seed, config.world_config())
    scene = _SceneWriter(config, index, Path(root), world)
    scene.write_log_and_map()

    width, height = config.image_size
    cameras = [camera for camera in camera_rig(width, height) if camera.name in config.cameras]
    for camera in cameras:
        scene.calibrate(camera.name, camera.translation, camera.rotation, camera.intrinsics)
    scene.calibrate(LIDAR_TOP.name, LIDAR_TOP.translation, LIDAR_TOP.rotation, None)
    offsets = camera_time_offsets_us(tuple(c.name for c in cameras))
    lidar2ego = LIDAR_TOP.lidar2ego

    sweeps: dict[int, _Sweep] = {}
    num_sweeps = (config.frames - 1) * SWEEPS_PER_KEY_FRAME + 1

    def sweep(j: int) -> _Sweep:
        """Sweep j, scanned and written the first time it is asked for."""
        if j not in sweeps:
            timestamp = scene.first_timestamp + j * SWEEP_INTERVAL_US
            t = j * SWEEP_INTERVAL_US / 1e6
            ego2global = world.ego_pose(t)
            with timer("lidar"):
                scan = scan_lidar(
                    LIDAR_TOP,
                    ego2global,
                    world.primitives(t),
                    world.ground,
                    _child_seed(world_seed, 1, j),
                    config.lidar_dropout,
                )
            key_frame = j // SWEEPS_PER_KEY_FRAME if j % SWEEPS_PER_KEY_FRAME == 0 else None
            folder = "samples" if key_frame is not None else "sweeps"
            filename = f"{folder}/LIDAR_TOP/{scene.log_name}__LIDAR_TOP__{timestamp}.pcd.bin"
            with timer("write"):
                write_points(scene.root / filename, scan.points)
            # A sweep belongs to the next key frame, so the devkit interpolates boxes between it and the previous one.
            sample = -(-j // SWEEPS_PER_KEY_FRAME)
            token = scene.add_sample_data(LIDAR_TOP.name, timestamp, ego2global, key_frame, sample, filename, None)
            if key_frame is not None:  # nuScenes-lidarseg labels key frames only
                with timer("write"):
                    scene.add_lidarseg(token, lidarseg_labels(scan, world.categories))
            sweeps[j] = _Sweep(scan.points, scan.instance, ego2global, filename)
        return sweeps[j]

    occ3d_infos: dict[str, dict] = {}
    annotations: dict[int, list[tuple[int, dict]]] = defaultdict(list)
    for k in range(config.frames):
        first_needed = max(0, (k - config.mask_window) * SWEEPS_PER_KEY_FRAME)
        last_needed = min(num_sweeps - 1, (k + config.mask_window) * SWEEPS_PER_KEY_FRAME)
        for j in [j for j in sweeps if j < first_needed]:
            del sweeps[j]
        window = [sweep(j) for j in range(first_needed, last_needed + 1)]
        key_sweep = sweep(k * SWEEPS_PER_KEY_FRAME)
        key_instances, ego2global = key_sweep.instance, key_sweep.ego2global
        key_timestamp = scene.first_timestamp + k * KEY_FRAME_INTERVAL_US
        t_key = k * KEY_FRAME_INTERVAL_US / 1e6
        sample_token = scene.token("sample", k)

        camera_infos, views = {}, []
        for camera in cameras:
            timestamp = key_timestamp + offsets[camera.name]
            t = t_key + offsets[camera.name] / 1e6
            camera_ego2global = world.ego_pose(t)
            camera_primitives = world.primitives(t)
            with timer("cameras"):
                render = render_camera(
                    camera,
                    camera_ego2global,
                    camera_primitives,
                    world.ground,
                    world.sun_direction,
                    world.sky_zenith,
                    world.sky_horizon,
                    _child_seed(world_seed, 2, k, CAMERAS.index(camera.name)),
                )
            filename = f"samples/{camera.name}/{scene.log_name}__{camera.name}__{timestamp}.jpg"
            with timer("write"):
                write_jpeg(scene.root / filename, render.image, config.jpeg_quality)
            scene.add_sample_data(camera.name, timestamp, camera_ego2global, k, k, filename, (width, height))
            views.append(_View(camera, camera_ego2global, camera_primitives, render.instance))
            camera_infos[camera.name] = {
                "img_path": filename,
                "intrinsics": [list(row) for row in camera.intrinsics],
                "extrinsic": {"translation": list(camera.translation), "rotation": list(camera.rotation)},
                "ego_pose": scene.pose_record(camera_ego2global),
            }

        # The objects annotated in this frame: those in range that a LiDAR point or a camera pixel sees.
        ego_xy = ego2global[:2, 3]
        annotated: set[int] = set()
        lidar_counts = np.bincount(key_instances[key_instances >= 0]) if (key_instances >= 0).any() else np.zeros(0)
        for box in world.boxes(t_key):
            if np.hypot(*(box.center[:2] - ego_xy)) > ANNOTATION_RANGE:
                continue
            num_lidar = int(lidar_counts[box.instance]) if box.instance < lidar_counts.shape[0] else 0
            pixels = [int((view.instance == box.instance).sum()) for view in views]
            if num_lidar == 0 and sum(pixels) == 0:
                continue
            annotated.add(box.instance)
            with timer("boxes"):
                visibility = _box_visibility(box, views)
            annotations[box.instance].append(
                (
                    k,
                    {
                        "token": scene.token("sample_annotation", box.instance, k),
                        "sample_token": sample_token,
                        "instance_token": scene.token("instance", box.instance),
                        "visibility_token": visibility,
                        "attribute_tokens": [scene.shared_token("attribute", box.attribute)] if box.attribute else [],
                        "translation": [float(v) for v in box.center + scene.offset],
                        "size": [float(v) for v in box.size],
                        "rotation": [float(v) for v in yaw_quaternion(box.yaw)],
                        "prev": "",
                        "next": "",
                        "num_lidar_pts": num_lidar,
                        "num_radar_pts": 0,
                        "category": box.category,
                    },
                )
            )

        primitives = world.primitives(t_key)
        with timer("labels"):
            velocity = world.primitive_velocities(t_key)
            semantics, flow, instances = occupancy_flow_labels(primitives, velocity, world.ground, ego2global,
                                                               OCC3D_GRID, instances=True)  # fmt: skip
            # An object's id is the world's (+ 1), the same in every frame; its token is the instance table's where
            # this sample annotates it, and empty where it does not (unseen: no annotation, maybe no instance record).
            instance_tokens = {int(i): scene.token("instance", int(i) - 1) if int(i) - 1 in annotated else ""
                               for i in np.unique(instances[instances > 0])}  # fmt: skip
        with timer("mask_lidar"):
            global2ego = np.linalg.inv(ego2global)
            rays = []
            for past in window:
                lidar2key = global2ego @ past.ego2global @ lidar2ego
                xyz = past.points[:, :3].astype(np.float64)
                rays.append((lidar2key[:3, 3], xyz @ lidar2key[:3, :3].T + lidar2key[:3, 3]))
            mask_lidar = lidar_visibility(semantics, OCC3D_GRID, rays)
        with timer("mask_camera"):
            mask_camera = camera_visibility(
                semantics,
                OCC3D_GRID,
                [(c.cam2ego, c.K, c.width, c.height) for c in cameras],
            )
        gt_path = f"gts/{scene.name}/{sample_token}/labels.npz"
        with timer("write"):
            write_occ3d_labels(scene.root / gt_path, semantics, mask_lidar, mask_camera, flow, instances,
                               instance_tokens)  # fmt: skip
            if config.openocc:  # the same voxels in OpenOcc's classes
                openocc = occ3d_to_openocc(semantics)
                write_openocc_labels(scene.root / f"openocc_v2/{scene.name}/{sample_token}/labels.npz", openocc, flow)
            if config.surroundocc:
                lidar_file = Path(key_sweep.filename).name
                sparse = surroundocc_labels(primitives, world.ground, ego2global @ lidar2ego, SURROUNDOCC_GRID)
                write_surroundocc_labels(scene.root / "surroundocc" / "samples" / f"{lidar_file}.npy", sparse)

        scene.rows["sample"].append(
            {
                "token": sample_token,
                "timestamp": key_timestamp,
                "prev": scene.token("sample", k - 1) if k > 0 else "",
                "next": scene.token("sample", k + 1) if k + 1 < config.frames else "",
                "scene_token": scene.token("scene"),
            }
        )
        occ3d_infos[sample_token] = {
            "timestamp": key_timestamp,
            "ego_pose": scene.pose_record(ego2global),
            "gt_path": gt_path,
            "prev": scene.rows["sample"][-1]["prev"],
            "next": scene.rows["sample"][-1]["next"],
            "camera_sensor": camera_infos,
        }
        if progress is not None:
            progress(1)

    _write_annotations(scene, annotations)
    scene.link_sample_data()
    scene.rows["scene"].append(
        {
            "token": scene.token("scene"),
            "log_token": scene.token("log"),
            "nbr_samples": config.frames,
            "first_sample_token": scene.token("sample", 0),
            "last_sample_token": scene.token("sample", config.frames - 1),
            "name": scene.name,
            "description": f"synthetic drive, {world.location}",
        }
    )
    return {
        "scene": scene.name,
        "tables": dict(scene.rows),
        "occ3d_infos": occ3d_infos,
        "timings": dict(timer.seconds),
    }


def _write_annotations(scene: _SceneWriter, annotations: dict[int, list[tuple[int, dict]]]) -> None:
    ordered = []
    for instance in sorted(annotations):
        records = [record for _, record in annotations[instance]]
        _link(records)
        category = records[0].pop("category")
        for record in records[1:]:
            record.pop("category")
        scene.rows["instance"].append(
            {
                "token": scene.token("instance", instance),
                "category_token": scene.shared_token("category", category),
                "nbr_annotations": len(records),
                "first_annotation_token": records[0]["token"],
                "last_annotation_token": records[-1]["token"],
            }
        )
        ordered.extend((k, instance, record) for (k, _), record in zip(annotations[instance], records, strict=True))
    # Rows in key-frame order, then by object, like nuScenes' tables.
    scene.rows["sample_annotation"] = [record for _, _, record in sorted(ordered, key=lambda item: item[:2])]
