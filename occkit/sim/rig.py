"""The nuScenes sensor rig: six cameras and LIDAR_TOP on the ego vehicle.

Poses follow the nuScenes calibration (Renault Zoe, ego origin at the rear axle on the ground): cameras at their
mounting points, yawed 0, +-55, +-110 and 180 degrees, intrinsics of the 1600x900 images (focal 1266 px for the
front and side cameras, 809 px for the wide back camera) scaled to the rendered size. LIDAR_TOP is an HDL-32E:
32 beams from -30.67 to +10.67 degrees, 20 Hz, mounted 1.84 m high and yawed -90 degrees (x right, y forward).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
import torch

from occkit.geometry.se3 import matrix_to_quaternion, quaternion_to_matrix
from occkit.nuscenes import CAMERAS

__all__ = ["CameraSpec", "LidarSpec", "camera_rig", "LIDAR_TOP", "yaw_quaternion", "pose_matrix"]


# name: (translation in ego (m), yaw (deg), focal length at 1600x900 (px))
_CAMERA_MOUNTS = {
    "CAM_FRONT": ((1.70, 0.016, 1.51), 0.0, 1266.4),
    "CAM_FRONT_RIGHT": ((1.55, -0.493, 1.50), -55.0, 1260.8),
    "CAM_FRONT_LEFT": ((1.52, 0.495, 1.51), 55.0, 1272.6),
    "CAM_BACK": ((0.03, 0.003, 1.58), 180.0, 809.2),
    "CAM_BACK_LEFT": ((1.04, 0.485, 1.59), 110.0, 1256.7),
    "CAM_BACK_RIGHT": ((1.01, -0.481, 1.56), -110.0, 1259.5),
}
_NUSCENES_SIZE = (1600, 900)


def yaw_quaternion(yaw: float) -> np.ndarray:
    """``(4,)`` unit quaternion (w, x, y, z) of a rotation by ``yaw`` radians about +z."""
    return np.array([math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)])


def _quaternion_to_matrix(q) -> np.ndarray:
    return quaternion_to_matrix(torch.as_tensor(q, dtype=torch.float64)).numpy()


def _matrix_to_quaternion(rotation: np.ndarray) -> np.ndarray:
    return matrix_to_quaternion(torch.as_tensor(rotation, dtype=torch.float64)).numpy()


def pose_matrix(translation, rotation_wxyz) -> np.ndarray:
    """``(4, 4)`` float64 homogeneous matrix from a translation and a (w, x, y, z) quaternion (nuScenes records)."""
    matrix = np.eye(4)
    matrix[:3, :3] = _quaternion_to_matrix(rotation_wxyz)
    matrix[:3, 3] = translation
    return matrix


@dataclass(frozen=True)
class CameraSpec:
    """One camera: name, cam2ego pose and pinhole intrinsics for an image of ``width x height`` pixels."""

    name: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    intrinsics: tuple[tuple[float, float, float], ...]
    width: int
    height: int

    @property
    def cam2ego(self) -> np.ndarray:
        """``(4, 4)`` float64 camera (x right, y down, z forward) to ego."""
        return pose_matrix(self.translation, self.rotation)

    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the field's name for the intrinsic matrix
        """``(3, 3)`` float64 intrinsic matrix."""
        return np.array(self.intrinsics)


def camera_rig(width: int = 800, height: int = 450) -> tuple[CameraSpec, ...]:
    """The six nuScenes cameras (in :data:`CAMERAS` order) for images of ``width x height`` pixels.

    The intrinsics are those of nuScenes' 1600x900 images scaled by ``width / 1600`` (and ``height / 900``),
    so a 16:9 size keeps the nuScenes fields of view.
    """
    if width < 8 or height < 8:
        raise ValueError(f"image size must be at least 8x8 pixels, got {width}x{height}")
    # Camera axes (x right, y down, z forward) expressed in ego axes (x forward, y left, z up), for yaw 0.
    camera_to_ego_axes = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    scale_u, scale_v = width / _NUSCENES_SIZE[0], height / _NUSCENES_SIZE[1]
    cameras = []
    for name in CAMERAS:
        translation, yaw_deg, focal = _CAMERA_MOUNTS[name]
        yaw = math.radians(yaw_deg)
        rotation = _quaternion_to_matrix(yaw_quaternion(yaw)) @ camera_to_ego_axes
        intrinsics = (
            (round(focal * scale_u, 6), 0.0, width / 2),
            (0.0, round(focal * scale_v, 6), height / 2),
            (0.0, 0.0, 1.0),
        )
        quaternion = tuple(float(v) for v in _matrix_to_quaternion(rotation))
        cameras.append(CameraSpec(name, translation, quaternion, intrinsics, width, height))  # type: ignore[arg-type]
    return tuple(cameras)


@dataclass(frozen=True)
class LidarSpec:
    """A spinning LiDAR: pose in ego, beam elevations, azimuth steps per revolution, range and rate."""

    name: str
    translation: tuple[float, float, float]
    rotation: tuple[float, float, float, float]
    elevations_deg: tuple[float, ...]
    azimuth_steps: int
    max_range: float
    rate_hz: float

    @property
    def lidar2ego(self) -> np.ndarray:
        """``(4, 4)`` float64 LiDAR frame (x right, y forward, z up) to ego."""
        return pose_matrix(self.translation, self.rotation)

    def ray_directions(self) -> tuple[np.ndarray, np.ndarray]:
        """Unit directions ``(R, 3)`` float64 in the LiDAR frame and ring index ``(R,)`` uint8 of every beam firing.

        Rings are numbered from the lowest beam (0) to the highest (31); firings are ordered by azimuth, then ring.
        """
        elevation = np.radians(np.asarray(self.elevations_deg))
        azimuth = np.arange(self.azimuth_steps) * (2 * np.pi / self.azimuth_steps)
        az, el = np.meshgrid(azimuth, elevation, indexing="ij")
        directions = np.stack((np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)), axis=-1)
        rings = np.broadcast_to(np.arange(len(elevation), dtype=np.uint8), az.shape)
        return directions.reshape(-1, 3), rings.reshape(-1).copy()


#: nuScenes LIDAR_TOP (Velodyne HDL-32E): 32 beams, 1084 firings per revolution (about 34.7k rays, 30k returns).
LIDAR_TOP = LidarSpec(
    name="LIDAR_TOP",
    translation=(0.943713, 0.0, 1.84023),
    rotation=tuple(float(v) for v in yaw_quaternion(-math.pi / 2)),  # type: ignore[arg-type]
    elevations_deg=tuple(float(v) for v in np.linspace(-30.67, 10.67, 32)),
    azimuth_steps=1084,
    max_range=70.0,
    rate_hz=20.0,
)
