"""What the synthetic world simulates and how often: :class:`SimConfig`, :class:`WorldConfig` and the sensor timing
shared by the world, the scene simulation (:mod:`occkit.sim.scene`) and the dataset writer
(:mod:`occkit.sim.generate`)."""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field

from occkit.config import check_ranges
from occkit.nuscenes import CAMERAS

__all__ = [
    "SimConfig",
    "WorldConfig",
    "KEY_FRAME_INTERVAL_US",
    "SWEEP_INTERVAL_US",
    "SWEEPS_PER_KEY_FRAME",
    "FIRST_TIMESTAMP_US",
    "scene_name",
    "camera_time_offsets_us",
]

#: Inclusive bounds of the world's settings. Speeds are physical (the ego's 40 m/s is 144 km/h; objects move at a
#: fraction of it, and flow above 100 m/s is refused everywhere); the others keep a scene finite: each object is placed
#: by a walk whose step shrinks with the density, and the ground raster grows with the margin over the resolution.
_WORLD_RANGES = {"duration": (0.05, 3600.0), "ego_speed": (0.0, 40.0), "ground_resolution": (0.02, 2.0),
                 "margin": (0.0, 500.0), "density": (0.0, 10.0)}  # fmt: skip


@dataclass(frozen=True)
class WorldConfig:
    """Settings of the procedural world."""

    duration: float = 20.0
    """Seconds the ego drives (the scene length)."""
    ego_speed: tuple[float, float] = (4.0, 10.0)
    """Range (m/s) of the ego's mean speed, drawn per scene."""
    ground_resolution: float = 0.1
    """Cell size (m) of the ground raster."""
    margin: float = 60.0
    """The world extends this far (m) beyond the ego path; the sensors see about 55 m."""
    density: float = 1.0
    """Scales the number of objects: traffic, pedestrians, furniture (less makes faster tests)."""

    def __post_init__(self) -> None:
        lo, hi = self.ego_speed
        if not 0.0 < lo <= hi:
            raise ValueError(f"ego_speed must be a range 0 < lo <= hi, got {self.ego_speed}")
        for name in ("duration", "ground_resolution", "density"):
            if not getattr(self, name) > 0:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        check_ranges("world", self, _WORLD_RANGES)


KEY_FRAME_INTERVAL_US = 500_000  # 2 Hz key frames
SWEEP_INTERVAL_US = 50_000  # 20 Hz LiDAR
SWEEPS_PER_KEY_FRAME = KEY_FRAME_INTERVAL_US // SWEEP_INTERVAL_US
FIRST_TIMESTAMP_US = 1_700_000_000_000_000  # microseconds, like nuScenes timestamps


#: Inclusive bounds of the dataset's settings (the machine's disk and memory are checked beside them).
_SIM_RANGES = {"scenes": (1, 1_000_000), "frames": (1, 10_000), "seed": (0, 2**63 - 1), "image_size": (16, 16384),
               "val_fraction": (0.0, 1.0), "mask_window": (0, 100), "lidar_dropout": (0.0, 1.0),
               "jpeg_quality": (1, 100)}  # fmt: skip


@dataclass(frozen=True)
class SimConfig:
    """What to simulate and how to write it."""

    scenes: int = 2
    """Number of scenes."""
    frames: int = 40
    """Key frames per scene (2 Hz; nuScenes scenes have about 40)."""
    seed: int = 0
    """Seed of the whole dataset; scene i is seeded by (seed, i)."""
    image_size: tuple[int, int] = (800, 450)
    """Rendered camera images, width x height (nuScenes: 1600 x 900; intrinsics are scaled to match)."""
    cameras: tuple[str, ...] = CAMERAS
    """Camera channels to render."""
    version: str = "v1.0-synth"
    """Name of the table folder, as nuScenes names its versions (v1.0-trainval, v1.0-mini, ...)."""
    val_fraction: float = 0.25
    """Share of scenes (the last ones) in the val split; at least one scene each when there are two or more."""
    mask_window: int = 1
    """mask_lidar accumulates the LiDAR sweeps of this many key-frame intervals on each side of the key frame."""
    lidar_dropout: float = 0.05
    """Fraction of LiDAR returns dropped (absorbing surfaces, sensor noise)."""
    surroundocc: bool = False
    """Also write SurroundOcc ground truth (LiDAR frame, 0.5 m, sparse (N, 4))."""
    openocc: bool = False
    """Also write OpenOcc v2 ground truth (``openocc_v2/``: Occ3D's grid in OpenOcc's 17 classes, with flow, no
    visibility masks)."""
    jpeg_quality: int = 92
    """JPEG quality of the camera images."""
    world: WorldConfig = field(default_factory=WorldConfig)
    """Procedural world settings (the scene duration is set from ``frames``)."""

    def __post_init__(self):
        if self.scenes < 1 or self.frames < 1:
            raise ValueError(f"scenes and frames must be >= 1, got scenes={self.scenes}, frames={self.frames}")
        width, height = self.image_size
        if width < 16 or height < 16:
            raise ValueError(f"image_size must be at least 16x16, got {width}x{height}")
        unknown = [c for c in self.cameras if c not in CAMERAS]
        if unknown or not self.cameras:
            raise ValueError(f"unknown cameras {unknown}; choose from {', '.join(CAMERAS)}")
        if not self.version or "/" in self.version or self.version.startswith("."):
            raise ValueError(f"version must be a plain folder name like v1.0-synth, got {self.version!r}")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.mask_window < 0:
            raise ValueError(f"mask_window must be >= 0, got {self.mask_window}")
        if not 0.0 <= self.lidar_dropout < 1.0:
            raise ValueError(f"lidar_dropout must be in [0, 1), got {self.lidar_dropout}")
        check_ranges("", self, _SIM_RANGES)

    @property
    def duration(self) -> float:
        """Seconds of simulated time per scene: the key frames plus the camera firing after the last one."""
        return (self.frames - 1) * KEY_FRAME_INTERVAL_US / 1e6 + SWEEP_INTERVAL_US / 1e6

    def world_config(self) -> WorldConfig:
        """The world settings with the scene duration that the key frames need."""
        return dataclasses.replace(self.world, duration=self.duration)

    def split(self) -> tuple[list[int], list[int]]:
        """Scene indices of the train and val splits."""
        num_val = math.ceil(self.scenes * self.val_fraction) if self.scenes > 1 else 0
        num_val = min(max(num_val, 1 if self.scenes > 1 and self.val_fraction > 0 else 0), self.scenes - 1)
        return list(range(self.scenes - num_val)), list(range(self.scenes - num_val, self.scenes))


def scene_name(index: int) -> str:
    return f"scene-{index + 1:04d}"


def camera_time_offsets_us(cameras: tuple[str, ...]) -> dict[str, int]:
    """Delay of each camera's exposure after the key-frame LiDAR timestamp (the sweep triggers it as it passes).

    LIDAR_TOP starts each revolution pointing backwards and turns clockwise seen from above, so it reaches the
    front camera a quarter turn in (nuScenes' cameras lag the LiDAR timestamp by 0..50 ms the same way).
    """
    from occkit.sim.rig import camera_rig  # torch: not needed to read or check a config

    rig = {camera.name: camera for camera in camera_rig(64, 36)}
    offsets = {}
    for name in cameras:
        optical_axis = rig[name].cam2ego[:3, 2]
        yaw = math.atan2(optical_axis[1], optical_axis[0])
        turn = ((math.pi - yaw) % (2 * math.pi)) / (2 * math.pi)
        offsets[name] = int(round(turn * SWEEP_INTERVAL_US))
    return offsets
