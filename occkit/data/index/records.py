"""The records of an index: one :class:`FrameRecord` per key frame, with its :class:`SweepRecord` and
:class:`CameraRecord` sub-records, each field declared with its kind (:mod:`occkit.data.index.kinds`).

Frames and matrices follow docs/conventions.md: ``a2b`` maps points of frame ``a`` to frame ``b``; how the builder
computes each quantity: :mod:`occkit.data.index.builder`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import ClassVar

import numpy as np

from occkit.data.index.kinds import (
    _Channels,
    _Counts,
    _declare,
    _Flags,
    _Integer,
    _Matrix,
    _Name,
    _Number,
    _Path,
    _Record,
    _Records,
    _Texts,
)

#: Columns of a box row: centre (m), size (m, length along the heading), yaw (rad), velocity (m/s).
BOX_COLUMNS = ("x", "y", "z", "l", "w", "h", "yaw", "vx", "vy")


@dataclass(frozen=True, eq=False)
class SweepRecord(_Record):
    """One LiDAR sweep before a key frame."""

    NOUN: ClassVar[str] = "sweep"

    path: str = _declare(_Path())
    """Point file, relative to the dataset root."""
    timestamp: int = _declare(_Integer())
    """Microseconds."""
    sweep2lidar: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64: points of this sweep's LiDAR frame -> the key frame's LiDAR frame (through both ego
    poses and the global frame)."""
    time_lag: float = _declare(_Number())
    """Seconds from this sweep to the key frame, ``(key timestamp - timestamp) / 1e6``; >= 0."""


@dataclass(frozen=True, eq=False)
class CameraRecord(_Record):
    """The key-frame image of one camera."""

    NOUN: ClassVar[str] = "camera"

    path: str = _declare(_Path())
    """Image file, relative to the dataset root."""
    timestamp: int = _declare(_Integer())
    """Microseconds; the camera fires a little after the LiDAR key-frame timestamp."""
    width: int = _declare(_Integer())
    """Image width (pixels)."""
    height: int = _declare(_Integer())
    """Image height (pixels)."""
    intrinsics: np.ndarray = _declare(_Matrix(3, 3, repeats=True))
    """``(3, 3)`` float64 pinhole matrix."""
    cam2ego: np.ndarray = _declare(_Matrix(4, 4, repeats=True))
    """``(4, 4)`` float64 calibration: camera -> ego."""
    ego2global: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64 ego pose at the camera's own timestamp."""
    cam2keyego: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64 camera -> ego at the key frame: ``inv(key ego2global) @ ego2global @ cam2ego``."""


@dataclass(frozen=True, eq=False)
class FrameRecord(_Record):
    """One key frame (nuScenes sample): paths, poses, sensor geometry and boxes.

    Box fields are parallel: row / item ``i`` of each describes the sample's ``i``-th annotation.
    Box rows are ``(x, y, z, l, w, h, yaw, vx, vy)`` (:data:`BOX_COLUMNS`): the box centre (m), its length along
    the heading, width and height (m; nuScenes stores ``size`` as w, l, h), the heading angle about +z (rad, 0 along
    +x), and the velocity (m/s) in the same frame.
    """

    NOUN: ClassVar[str] = "record"

    token: str = _declare(_Name())
    """Sample token (a safe name: :mod:`occkit.data.names`)."""
    scene: str = _declare(_Name(empty=True))
    """Scene name, e.g. ``scene-0061`` (a safe name; ``""`` for frames of info files without one)."""
    scene_token: str = _declare(_Name(empty=True))
    """Scene token (a safe name or ``""``)."""
    timestamp: int = _declare(_Integer())
    """Sample timestamp, microseconds (the LIDAR_TOP key-frame timestamp)."""
    prev: str = _declare(_Name(empty=True))
    """Previous sample token, ``""`` at the start of the scene."""
    next: str = _declare(_Name(empty=True))
    """Next sample token, ``""`` at the end of the scene."""
    index_in_scene: int = _declare(_Integer())
    """Position of the sample in its scene, from 0."""
    ego2global: np.ndarray = _declare(_Matrix(4, 4))
    """``(4, 4)`` float64 ego pose at the LiDAR key-frame timestamp."""
    lidar_path: str = _declare(_Path())
    """Key-frame LiDAR point file, relative to the dataset root."""
    lidar2ego: np.ndarray = _declare(_Matrix(4, 4, repeats=True))
    """``(4, 4)`` float64 LIDAR_TOP calibration."""
    sweeps: tuple[SweepRecord, ...] = _declare(_Records(SweepRecord))
    """Earlier sweeps, newest first, within the scene; at most the ``max_sweeps`` the index was built with."""
    cameras: dict[str, CameraRecord] = _declare(_Channels(CameraRecord))
    """Channel -> key-frame image, in :data:`CAMERA_ORDER`. Treat as read-only."""
    boxes_ego: np.ndarray = _declare(_Matrix(None, 9))
    """``(N, 9)`` float64 boxes in the key frame's ego frame."""
    boxes_lidar: np.ndarray = _declare(_Matrix(None, 9))
    """``(N, 9)`` float64 boxes in the key frame's LiDAR frame."""
    velocity_valid: np.ndarray = _declare(_Flags())
    """``(N,)`` bool: False where nuscenes-devkit's velocity is NaN (no neighbour annotation within reach); the
    velocity columns hold 0 there."""
    box_categories: tuple[str, ...] = _declare(_Texts())
    """nuScenes category names, e.g. ``vehicle.car``."""
    box_detection_names: tuple[str | None, ...] = _declare(_Texts(nullable=True))
    """Detection class (:data:`occkit.classes.DETECTION_CLASSES`) or None for categories that are not targets."""
    box_instances: tuple[str, ...] = _declare(_Texts())
    """Instance tokens (the same object across samples)."""
    box_num_lidar_pts: np.ndarray = _declare(_Counts())
    """``(N,)`` int64 LiDAR points inside each box."""
    box_valid: np.ndarray = _declare(_Flags())
    """``(N,)`` bool: mmdetection3d's ``valid_flag``, ``num_lidar_pts + num_radar_pts > 0``: the box holds at least
    one LiDAR or radar point. Training with ``use_valid_flag`` (DAOcc, FlashOcc) keeps only these boxes as targets
    (:attr:`occkit.data.dataset.DatasetConfig.valid_boxes_only`)."""
    box_visibility: tuple[str, ...] = _declare(_Texts())
    """nuScenes visibility tokens, ``"1"`` (0-40% visible) to ``"4"`` (80-100%)."""
    occ_path: str | None = _declare(_Path(optional=True))
    """``gts/<scene>/<token>/labels.npz`` (Occ3D labels) if that file exists under the root, else None."""

    @property
    def num_boxes(self) -> int:
        return len(self.box_instances)

    def __repr__(self) -> str:
        # The generated repr prints every matrix and box: thousands of numbers per frame.
        return (
            f"FrameRecord(token={self.token!r}, scene={self.scene!r}, index_in_scene={self.index_in_scene}, "
            f"sweeps={len(self.sweeps)}, cameras={list(self.cameras)}, boxes={self.num_boxes}, "
            f"occ_path={self.occ_path!r})"
        )
