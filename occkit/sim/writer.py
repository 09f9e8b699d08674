"""Writing the nuScenes + Occ3D-nuScenes on-disk layout, byte for byte reproducibly.

Layout under the dataset root::

    <version>/{category,attribute,visibility,instance,sensor,calibrated_sensor,ego_pose,log,scene,sample,
               sample_data,sample_annotation,map}.json
    maps/<token>.png                      drivable-area mask per log (nuscenes-devkit opens it)
    samples/CAM_*/<log>__CAM_*__<timestamp>.jpg
    samples/LIDAR_TOP/<log>__LIDAR_TOP__<timestamp>.pcd.bin      float32 (N, 5): x, y, z, intensity, ring
    sweeps/LIDAR_TOP/<log>__LIDAR_TOP__<timestamp>.pcd.bin
    lidarseg/<version>/<token>_lidarseg.bin   uint8 per key-frame point: nuScenes-lidarseg category index
    <version>/lidarseg.json               the lidarseg table (token = the LiDAR sample_data token)
    gts/<scene>/<sample_token>/labels.npz semantics, mask_lidar, mask_camera: uint8 (200, 200, 16); flow
                                          float32 (200, 200, 16, 2); instances, instance_ids, instance_tokens
    openocc_v2/<scene>/<sample_token>/labels.npz   (--openocc) semantics in OpenOcc v2's ids, flow
    surroundocc/samples/<LiDAR file>.npy  (--surroundocc) sparse (N, 4) rows x, y, z, class
    annotations.json                      Occ3D-style scene infos with train/val splits

Reproducibility: tokens are hashes of names, tables are written in a fixed order, and the Occ3D label archives
are written by :func:`occkit.label_files.write_occ3d_labels` with fixed zip timestamps.
"""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np

from occkit.classes import NUSCENES_TO_OCC3D
from occkit.nuscenes import CAMERA_ORDER, LIDAR_CHANNEL

__all__ = [
    "ATTRIBUTES",
    "VISIBILITY_LEVELS",
    "make_token",
    "static_tables",
    "write_json",
    "write_jpeg",
    "write_png",
    "write_points",
    "write_lidarseg",
]


#: nuScenes attribute names.
ATTRIBUTES = (
    "vehicle.moving",
    "vehicle.stopped",
    "vehicle.parked",
    "cycle.with_rider",
    "cycle.without_rider",
    "pedestrian.sitting_lying_down",
    "pedestrian.standing",
    "pedestrian.moving",
)

#: nuScenes visibility bins: token -> (level, description).
VISIBILITY_LEVELS = {
    "1": ("v0-40", "visibility of whole object is between 0 and 40%"),
    "2": ("v40-60", "visibility of whole object is between 40 and 60%"),
    "3": ("v60-80", "visibility of whole object is between 60 and 80%"),
    "4": ("v80-100", "visibility of whole object is between 80 and 100%"),
}

#: (channel, modality) of the sensor table, in nuScenes' order.
_SENSORS = (*((channel, "camera") for channel in CAMERA_ORDER), (LIDAR_CHANNEL, "lidar"))


def make_token(*parts: object) -> str:
    """A 32-hex-digit token, a pure function of its parts (nuScenes tokens have the same form)."""
    return hashlib.md5("/".join(str(p) for p in parts).encode()).hexdigest()


def static_tables(namespace: str) -> dict[str, list[dict]]:
    """The tables that do not depend on the scenes: category, attribute, visibility, sensor."""
    # All 32 categories with their nuScenes-lidarseg index (the order of NUSCENES_TO_OCC3D).
    category = [
        {"token": make_token(namespace, "category", name), "name": name, "description": "", "index": index}
        for index, name in enumerate(NUSCENES_TO_OCC3D)
    ]
    attribute = [
        {"token": make_token(namespace, "attribute", name), "name": name, "description": ""} for name in ATTRIBUTES
    ]
    visibility = [
        {"token": token, "level": level, "description": description}
        for token, (level, description) in VISIBILITY_LEVELS.items()
    ]
    sensor = [
        {"token": make_token(namespace, "sensor", channel), "channel": channel, "modality": modality}
        for channel, modality in _SENSORS
    ]
    return {"category": category, "attribute": attribute, "visibility": visibility, "sensor": sensor}


def write_json(path: Path, payload: object) -> None:
    """JSON in the nuScenes style (one field per line), deterministic."""
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(payload, indent=0, ensure_ascii=False) + "\n")


def write_jpeg(path: Path, image: np.ndarray, quality: int = 92) -> None:
    """``(H, W, 3)`` uint8 RGB image as a baseline JPEG (libjpeg output is deterministic for fixed settings)."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image, mode="RGB").save(path, format="JPEG", quality=quality, subsampling=2, optimize=False)


def write_png(path: Path, image: np.ndarray) -> None:
    """``(H, W)`` or ``(H, W, 3)`` uint8 image as PNG."""
    from PIL import Image

    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(image).save(path, format="PNG")


def write_points(path: Path, points: np.ndarray) -> None:
    """``(N, 5)`` points as the nuScenes ``.pcd.bin`` format: raw little-endian float32, row-major."""
    if points.ndim != 2 or points.shape[1] != 5:
        raise ValueError(f"{path}: LiDAR points must have shape (N, 5), got {points.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(np.ascontiguousarray(points, dtype="<f4").tobytes())


def write_lidarseg(path: Path, labels: np.ndarray) -> None:
    """``(N,)`` nuScenes-lidarseg labels as the dataset ships them: one uint8 category index per point."""
    if labels.ndim != 1:
        raise ValueError(f"{path}: lidarseg labels must have shape (N,), got {labels.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_bytes(np.ascontiguousarray(labels, dtype=np.uint8).tobytes())
