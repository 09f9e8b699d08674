"""Time and peak memory of ``build_index`` on tables of nuScenes trainval size, and the size and speed of its file.

The tables are generated straight as JSON into a temporary folder: 850 scenes of 40-41 key frames (34,149 samples),
six cameras at 12 Hz, LIDAR_TOP at 20 Hz and five radars at 13 Hz with one ego pose per sample_data record (about
2.6 M rows each, as in v1.0-trainval), and about 1.17 M annotations of 64 k instances linked by prev/next, plus an
empty ``gts/<scene>/<sample>/labels.npz`` per sample. No images or point files: the index builder reads none.

The measurement runs in a fresh interpreter, so its peak resident memory (``ru_maxrss``) counts loading the tables
and building the index only, then saving and loading the index file (``save_index`` / ``load_index``). Loading checks
every column and builds records when they are used: ``read_all_records_s`` is the time to build all of them after.

    python benchmarks/index_scale.py [--out benchmarks/results/index_scale.json] [--keep DIR]
"""

from __future__ import annotations

import argparse
import hashlib
import json
import math
import os
import resource
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from occkit.nuscenes import CAMERA_ORDER

VERSION = "v1.0-trainval"
SCENES = 850
SAMPLES = 34_149
ANNOTATIONS = 1_166_187
KEY_INTERVAL_US = 500_000
CAMERAS = CAMERA_ORDER
CAMERA_YAWS_DEG = (0.0, -55.0, 55.0, 180.0, 110.0, -110.0)
RADARS = ("RADAR_FRONT", "RADAR_FRONT_LEFT", "RADAR_FRONT_RIGHT", "RADAR_BACK_LEFT", "RADAR_BACK_RIGHT")
CATEGORIES = (
    "vehicle.car",
    "vehicle.truck",
    "vehicle.bus.rigid",
    "vehicle.trailer",
    "vehicle.construction",
    "vehicle.motorcycle",
    "vehicle.bicycle",
    "human.pedestrian.adult",
    "human.pedestrian.child",
    "movable_object.barrier",
    "movable_object.trafficcone",
    "movable_object.pushable_pullable",
    "static_object.bicycle_rack",
    "animal",
)


def token(*parts: object) -> str:
    return hashlib.md5("/".join(map(str, parts)).encode()).hexdigest()


def quaternions(yaw: np.ndarray, pitch: np.ndarray, roll: np.ndarray) -> np.ndarray:
    """``(N, 4)`` (w, x, y, z) of z-y-x (yaw, pitch, roll) rotations."""
    cy, sy, cp, sp, cr, sr = (f(a / 2) for a in (yaw, pitch, roll) for f in (np.cos, np.sin))
    return np.stack(
        (
            cr * cp * cy + sr * sp * sy,
            sr * cp * cy - cr * sp * sy,
            cr * sp * cy + sr * cp * sy,
            cr * cp * sy - sr * sp * cy,
        ),
        axis=-1,
    )


class TableWriter:
    """Appends records to ``<version>/<table>.json`` files as JSON lists, one record per line."""

    def __init__(self, folder: Path) -> None:
        folder.mkdir(parents=True, exist_ok=True)
        self.folder = folder
        self.files: dict[str, object] = {}
        self.counts: dict[str, int] = {}

    def add(self, table: str, records: list[dict]) -> None:
        if table not in self.files:
            self.files[table] = open(self.folder / f"{table}.json", "w")  # noqa: SIM115 (closed in close())
            self.files[table].write("[\n")
            self.counts[table] = 0
        if not records:
            return
        separator = ",\n" if self.counts[table] else ""
        self.files[table].write(separator + ",\n".join(map(json.dumps, records)))
        self.counts[table] += len(records)

    def close(self) -> dict[str, int]:
        for stream in self.files.values():
            stream.write("\n]\n")
            stream.close()
        return self.counts


def static_tables(writer: TableWriter) -> None:
    writer.add("category", [{"token": token("category", n), "name": n, "description": ""} for n in CATEGORIES])
    attributes = ("vehicle.moving", "vehicle.parked", "pedestrian.moving", "cycle.with_rider")
    writer.add("attribute", [{"token": token("attribute", n), "name": n, "description": ""} for n in attributes])
    writer.add("visibility", [{"token": str(i), "level": f"v{i}", "description": ""} for i in range(1, 5)])
    sensors = [(c, "camera") for c in CAMERAS] + [("LIDAR_TOP", "lidar")] + [(r, "radar") for r in RADARS]
    writer.add("sensor", [{"token": token("sensor", c), "channel": c, "modality": m} for c, m in sensors])


def calibrations(scene: int) -> dict[str, dict]:
    records = {}
    for channel, yaw in zip(CAMERAS, CAMERA_YAWS_DEG, strict=True):
        # Camera axes (x right, y down, z forward) in the ego frame, turned by the camera's yaw.
        a = math.radians(yaw)
        rotation = np.array([[-math.sin(a), 0, math.cos(a)], [math.cos(a), 0, math.sin(a)], [0, -1, 0]])
        w = math.sqrt(max(0.0, 1 + np.trace(rotation))) / 2
        q = [w, (rotation[2, 1] - rotation[1, 2]) / (4 * w), (rotation[0, 2] - rotation[2, 0]) / (4 * w)]
        q.append((rotation[1, 0] - rotation[0, 1]) / (4 * w))
        intrinsic = [[1266.4, 0.0, 816.3], [0.0, 1266.4, 491.5], [0.0, 0.0, 1.0]]
        records[channel] = {"rotation": q, "translation": [1.5 * math.cos(a), 0.5 * math.sin(a), 1.5]}
        records[channel]["camera_intrinsic"] = intrinsic
    records["LIDAR_TOP"] = {"translation": [0.94, 0.0, 1.84], "rotation": [0.7071, 0.0, 0.0, -0.7071]}
    for i, channel in enumerate(RADARS):
        records[channel] = {"translation": [3.4 - i, 0.0, 0.6], "rotation": [1.0, 0.0, 0.0, 0.0]}
    result = {}
    for channel, record in records.items():
        result[channel] = {
            "token": token("calibrated_sensor", scene, channel),
            "sensor_token": token("sensor", channel),
            "translation": record["translation"],
            "rotation": [float(v) for v in record["rotation"]],
            "camera_intrinsic": record.get("camera_intrinsic", []),
        }
    return result


def sensor_stream(
    scene: int, channel: str, times_us: np.ndarray, key_times_us: np.ndarray, sample_tokens: list[str], log: str
) -> tuple[list[dict], np.ndarray]:
    """sample_data rows of one channel: the reading nearest each key time is the key frame; others belong to the
    next sample, as in nuScenes."""
    key_rows = np.abs(times_us[None, :] - key_times_us[:, None]).argmin(axis=1)
    owner = np.searchsorted(key_rows, np.arange(len(times_us))).clip(max=len(key_rows) - 1)
    is_key = np.zeros(len(times_us), dtype=bool)
    is_key[key_rows] = True
    tokens = [token("sample_data", scene, channel, j) for j in range(len(times_us))]
    camera = channel.startswith("CAM")
    extension = "jpg" if camera else "pcd.bin" if channel == "LIDAR_TOP" else "pcd"
    rows = []
    for j, timestamp in enumerate(times_us.tolist()):
        folder = "samples" if is_key[j] else "sweeps"
        rows.append(
            {
                "token": tokens[j],
                "sample_token": sample_tokens[owner[j]],
                "ego_pose_token": tokens[j],
                "calibrated_sensor_token": token("calibrated_sensor", scene, channel),
                "timestamp": timestamp,
                "fileformat": "jpg" if camera else "pcd",
                "is_key_frame": bool(is_key[j]),
                "height": 900 if camera else 0,
                "width": 1600 if camera else 0,
                "filename": f"{folder}/{channel}/{log}__{channel}__{timestamp}.{extension}",
                "prev": tokens[j - 1] if j > 0 else "",
                "next": tokens[j + 1] if j + 1 < len(times_us) else "",
            }
        )
    return rows, times_us


def ego_poses(rng: np.random.Generator, rows: list[dict]) -> list[dict]:
    """One pose per sample_data row: a drive along an arc at constant speed, with gentle pitch and roll."""
    t = np.array([row["timestamp"] for row in rows], dtype=np.float64)
    t = (t - t.min()) / 1e6
    speed, turn, heading = rng.uniform(2, 12), rng.uniform(-0.05, 0.05), rng.uniform(-math.pi, math.pi)
    yaw = heading + turn * t
    x = 600 + speed / turn * (np.sin(yaw) - math.sin(heading))
    y = 1200 - speed / turn * (np.cos(yaw) - math.cos(heading))
    q = quaternions(yaw, 0.02 * np.sin(0.3 * t), 0.01 * np.cos(0.2 * t))
    translation = np.stack((x, y, np.zeros_like(x)), axis=-1)
    return [
        {"token": row["token"], "timestamp": row["timestamp"], "rotation": r, "translation": p}
        for row, r, p in zip(rows, q.tolist(), translation.tolist(), strict=True)
    ]


def annotations(rng: np.random.Generator, scene: int, sample_tokens: list[str], target: int) -> tuple[list, list]:
    """Instances seen over consecutive samples (about 18 each), moving at constant velocity."""
    records, instances = [], []
    count = 0
    while count < target:
        n = len(sample_tokens)
        length = int(min(n, rng.integers(1, 37), target - count))
        start = int(rng.integers(0, n - length + 1))
        instance = token("instance", scene, len(instances))
        category = CATEGORIES[int(rng.integers(0, len(CATEGORIES)))]
        tokens = [token("sample_annotation", instance, k) for k in range(length)]
        position = rng.uniform((500, 1100, 0.5), (700, 1300, 1.5))
        velocity = np.append(rng.uniform(-8, 8, 2), 0.0)
        size = rng.uniform((0.5, 0.5, 1.0), (3.0, 12.0, 4.0)).tolist()
        yaw = math.atan2(velocity[1], velocity[0])
        rotation = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
        for k in range(length):
            records.append(
                {
                    "token": tokens[k],
                    "sample_token": sample_tokens[start + k],
                    "instance_token": instance,
                    "visibility_token": str(int(rng.integers(1, 5))),
                    "attribute_tokens": [token("attribute", "vehicle.moving")],
                    "translation": (position + velocity * 0.5 * k).tolist(),
                    "size": size,
                    "rotation": rotation,
                    "prev": tokens[k - 1] if k > 0 else "",
                    "next": tokens[k + 1] if k + 1 < length else "",
                    "num_lidar_pts": int(rng.integers(0, 500)),
                    "num_radar_pts": 0,
                }
            )
        instances.append(
            {
                "token": instance,
                "category_token": token("category", category),
                "nbr_annotations": length,
                "first_annotation_token": tokens[0],
                "last_annotation_token": tokens[-1],
            }
        )
        count += length
    return records, instances


def write_scene(writer: TableWriter, root: Path, scene: int, samples: int, annotation_target: int) -> None:
    rng = np.random.default_rng([2024, scene])
    name = f"scene-{scene + 1:04d}"
    log = f"n015-2018-07-24-11-22-45+0800-{scene:04d}"
    t0 = 1_532_000_000_000_000 + scene * 60_000_000
    sample_tokens = [token("sample", scene, k) for k in range(samples)]
    # nuScenes' first key frames have few earlier sweeps: 0..9 here.
    first_key = t0 + int(rng.integers(0, 10)) * 50_000
    key_times = first_key + np.arange(samples) * KEY_INTERVAL_US + rng.integers(-2000, 2000, samples)
    end = int(key_times[-1]) + 60_000
    rows = []
    calibration = calibrations(scene)
    lidar_times = np.arange(t0, end, 50_000)
    lidar_times[np.abs(lidar_times[None] - key_times[:, None]).argmin(axis=1)] = key_times
    for channel in CAMERAS + ("LIDAR_TOP",) + RADARS:
        if channel == "LIDAR_TOP":
            times = lidar_times
        else:
            period = 83_333 if channel.startswith("CAM") else 76_923
            times = np.arange(t0 + int(rng.integers(0, period)), end, period)
        channel_rows, _ = sensor_stream(scene, channel, times, key_times, sample_tokens, log)
        rows.extend(channel_rows)
    writer.add("calibrated_sensor", list(calibration.values()))
    writer.add("sample_data", rows)
    writer.add("ego_pose", ego_poses(rng, rows))
    records, instances = annotations(rng, scene, sample_tokens, annotation_target)
    writer.add("sample_annotation", records)
    writer.add("instance", instances)
    writer.add(
        "sample",
        [
            {
                "token": sample_tokens[k],
                "timestamp": int(key_times[k]),
                "prev": sample_tokens[k - 1] if k > 0 else "",
                "next": sample_tokens[k + 1] if k + 1 < samples else "",
                "scene_token": token("scene", scene),
            }
            for k in range(samples)
        ],
    )
    writer.add(
        "scene",
        [
            {
                "token": token("scene", scene),
                "log_token": token("log", scene),
                "nbr_samples": samples,
                "first_sample_token": sample_tokens[0],
                "last_sample_token": sample_tokens[-1],
                "name": name,
                "description": "synthetic timing scene",
            }
        ],
    )
    writer.add("log", [{"token": token("log", scene), "logfile": log, "vehicle": "n015", "location": "singapore"}])
    for sample in sample_tokens:
        folder = root / "gts" / name / sample
        folder.mkdir(parents=True)
        (folder / "labels.npz").touch()


def generate(root: Path) -> dict[str, int]:
    """Write tables of trainval size under ``root``; returns the row count of each table."""
    writer = TableWriter(root / VERSION)
    static_tables(writer)
    samples = np.full(SCENES, SAMPLES // SCENES)
    samples[: SAMPLES - samples.sum()] += 1
    per_sample = ANNOTATIONS / SAMPLES
    written = 0
    for scene in range(SCENES):
        target = round(per_sample * samples[: scene + 1].sum()) - written
        write_scene(writer, root, scene, int(samples[scene]), target)
        written += target
    # nuscenes-devkit checks that the map file exists (it opens it lazily): an empty stand-in.
    map_file = f"maps/{token('map')}.png"
    (root / "maps").mkdir()
    (root / map_file).touch()
    logs = [token("log", s) for s in range(SCENES)]
    writer.add("map", [{"token": token("map"), "log_tokens": logs, "category": "semantic_prior", "filename": map_file}])
    return writer.close()


def count_rows(path: Path) -> int:
    """Records in a table written by :class:`TableWriter` (one per line between the brackets)."""
    with open(path) as stream:
        return sum(1 for line in stream) - 2


def measure(root: Path, index_file: Path) -> dict:
    """Build, save and load the index of ``root``; run in a fresh interpreter so ``ru_maxrss`` counts only this."""
    from occkit.data.index import INDEX_FORMAT, index_tables, load_index, save_index
    from occkit.data.tables import load_tables

    def peak_gib() -> float:
        return round(resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 2**20, 2)  # ru_maxrss is KiB on Linux

    # build_index(root, version) is these two steps; timed apart to show where the time goes.
    start = time.perf_counter()
    tables = load_tables(root, VERSION)
    load_s = time.perf_counter() - start
    tables_peak = peak_gib()
    start = time.perf_counter()
    records = index_tables(tables, max_sweeps=10)
    index_s = time.perf_counter() - start
    del tables
    build_peak = peak_gib()
    start = time.perf_counter()
    save_index(records, index_file, {"version": VERSION, "root": str(root), "max_sweeps": 10})
    save_s = time.perf_counter() - start
    frames = len(records)
    boxes = sum(len(r.box_instances) for r in records)
    sweeps = sum(len(r.sweeps) for r in records)
    del records
    start = time.perf_counter()
    loaded, _ = load_index(index_file)
    load_index_s = time.perf_counter() - start
    assert len(loaded) == frames
    start = time.perf_counter()
    assert sum(len(record.box_instances) for record in loaded) == boxes
    read_all_s = time.perf_counter() - start
    return {
        "frames": frames,
        "boxes": boxes,
        "sweeps": sweeps,
        "build_index_s": round(load_s + index_s, 1),
        "load_tables_s": round(load_s, 1),
        "index_tables_s": round(index_s, 1),
        "peak_rss_after_load_tables_gib": tables_peak,
        "peak_rss_after_build_index_gib": build_peak,
        "index_format": INDEX_FORMAT,
        "save_index_s": round(save_s, 1),
        "index_file_mib": round(index_file.stat().st_size / 2**20, 1),
        "load_index_s": round(load_index_s, 1),
        "read_all_records_s": round(read_all_s, 1),
        "peak_rss_gib": peak_gib(),
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=Path("benchmarks/results/index_scale.json"))
    parser.add_argument("--keep", type=Path, help="generate into DIR (reused if it exists) and keep it")
    parser.add_argument("--measure", type=Path, help=argparse.SUPPRESS)  # the child process
    args = parser.parse_args()
    if args.measure is not None:
        print(json.dumps(measure(args.measure, args.measure / "index.npz")))
        return

    folder = args.keep or Path(tempfile.mkdtemp(prefix="occkit-index-scale-"))
    try:
        generate_s = None
        if not (folder / VERSION / "sample_data.json").is_file():
            start = time.perf_counter()
            generate(folder)
            generate_s = round(time.perf_counter() - start, 1)
        tables = {
            path.stem: {"rows": count_rows(path), "mib": round(path.stat().st_size / 2**20)}
            for path in sorted((folder / VERSION).glob("*.json"))
        }
        child = subprocess.run(
            [sys.executable, __file__, "--measure", str(folder)], check=True, capture_output=True, text=True
        )
        result = json.loads(child.stdout.strip().splitlines()[-1])
    finally:
        if args.keep is None:
            shutil.rmtree(folder, ignore_errors=True)
    report = {
        "tables": tables,
        "generate_s": generate_s,
        **result,
        "cpu_count": os.cpu_count(),
        "python": sys.version.split()[0],
    }
    print(json.dumps(report, indent=2))
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
