"""Sensor failures and corruptions of a sample's inputs, applied at evaluation time (``occkit robustness``).

A corruption is a name and a level: :data:`CORRUPTIONS` lists each with its parameters per level. Levels are
severities 1, 2, 3 (mild to harsh) for most; for ``missing_camera`` they are the six cameras, one each. The dataset
applies one corruption when its config names it (``DatasetConfig.corruption`` and ``corruption_severity``):

- cameras: failed cameras have their image zeroed (the mean colour after normalisation) and are masked out of the
  view transform (``Sample.camera_mask``), exactly as ``DatasetConfig.drop_cameras``;
- images: the raw image, as read from disk and before resizing, goes through the corruption families of
  RoboBEV / nuScenes-C (Xie et al. 2023) and ImageNet-C (Hendrycks and Dietterich 2019), made with albumentations;
- LiDAR: beams, points, sweeps, field of view, the whole sensor, or a delay between the LiDAR and the cameras;
- geometry: each camera's extrinsics rotated and shifted by a fixed amount in a random direction;
- temporal: earlier frames lost from a streamed model's memory (applied by the evaluation loop, not the dataset).

Every random draw comes from a generator seeded by ``(seed, sample token, corruption, level, stream)``, so a
corrupted sample is the same in every run, process and worker, and reproducible from its name and level alone.
"""

from __future__ import annotations

import math
import os
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import Tensor

from occkit.data.transforms import drop_lidar_beams, drop_points
from occkit.errors import require_module
from occkit.nuscenes import CAMERAS

__all__ = ["CORRUPTIONS", "Corruption", "SampleCorruption", "corruption_names"]


@dataclass(frozen=True)
class Corruption:
    """One corruption and its levels."""

    name: str
    family: str
    """``cameras``, ``images``, ``lidar``, ``geometry`` or ``temporal``."""
    summary: str
    levels: tuple[dict[str, Any], ...]
    """Parameters of level 1, 2, ...: the keys of the family's effect (see :class:`SampleCorruption`)."""
    labels: tuple[str, ...]
    """What each level is, for tables and plots (``"8 beams"``, ``"CAM_FRONT"``)."""
    needs: tuple[str, ...]
    """What a model must take for the corruption to apply: ``cameras``, ``lidar`` (both: fusion models only) or
    ``temporal`` (a streamed memory)."""
    ordered: bool = True
    """The levels are severities of one effect (a severity curve), not variants (one camera each)."""

    @property
    def severities(self) -> range:
        return range(1, len(self.levels) + 1)


def _image(name: str, summary: str, key: str, values: Sequence, label: str) -> Corruption:
    return Corruption(name, "images", summary, tuple({key: v} for v in values),
                      tuple(label.format(v) for v in values), ("cameras",))  # fmt: skip


#: Name -> corruption. The image families follow RoboBEV / nuScenes-C's eight (brightness, low light, fog, snow,
#: motion blur, colour quantisation, camera crash, frame lost) plus ImageNet-C's Gaussian noise and JPEG; their three
#: levels span ImageNet-C's severities 1, 3 and 5 where it defines them, RoboBEV's formula otherwise (low light:
#: gamma 2 and a ceiling of 0.6 / 0.4 / 0.2 of full scale, then shot noise; colour: 4 / 3 / 2 bits).
CORRUPTIONS: dict[str, Corruption] = {
    corruption.name: corruption
    for corruption in (
        Corruption("missing_camera", "cameras", "one camera fails (its image is black and masked out)",
                   tuple({"cameras": (name,)} for name in CAMERAS), CAMERAS, ("cameras",), ordered=False),
        Corruption("missing_cameras", "cameras", "2 or 3 cameras fail, drawn at random per frame",
                   ({"count": 2}, {"count": 3}), ("2 cameras", "3 cameras"), ("cameras",)),
        Corruption("no_cameras", "cameras", "every camera fails: the LiDAR alone", ({"count": len(CAMERAS)},),
                   ("6 cameras",), ("cameras", "lidar")),
        _image("brightness", "overexposure: every channel + a fraction of full scale", "brightness",
               (0.1, 0.3, 0.5), "+{}"),
        Corruption("low_light", "images", "night: gamma 2, the range compressed to a ceiling, shot noise",
                   ({"ceiling": 0.6, "shot": 0.05}, {"ceiling": 0.4, "shot": 0.1}, {"ceiling": 0.2, "shot": 0.2}),
                   ("ceiling 0.6", "ceiling 0.4", "ceiling 0.2"), ("cameras",)),
        _image("fog", "fog: haze and blurred discs over the image", "fog", (0.3, 0.6, 0.9), "density {}"),
        Corruption("snow", "images", "snow: the brightest areas turned to snow cover",
                   tuple({"snow": v, "method": "bleach"} for v in (0.1, 0.3, 0.5)),
                   ("cover 0.1", "cover 0.3", "cover 0.5"), ("cameras",)),
        _image("motion_blur", "motion blur along a random direction", "kernel", (7, 15, 23), "{} px"),
        _image("gaussian_noise", "sensor noise, standard deviation as a fraction of full scale", "std",
               (0.08, 0.18, 0.38), "std {}"),
        _image("jpeg", "JPEG compression", "quality", (25, 15, 7), "quality {}"),
        _image("color_quant", "colour quantisation", "bits", (4, 3, 2), "{} bits"),
        Corruption("lidar_beams", "lidar", "a sparser LiDAR: every k-th of the 32 beams kept",
                   ({"keep_every": 2}, {"keep_every": 4}, {"keep_every": 8}), ("16 beams", "8 beams", "4 beams"),
                   ("lidar",)),
        Corruption("point_dropout", "lidar", "a fraction of the points of every sweep lost at random",
                   ({"fraction": 0.25}, {"fraction": 0.5}, {"fraction": 0.75}), ("25%", "50%", "75%"), ("lidar",)),
        Corruption("fewer_sweeps", "lidar", "a share of the model's earlier sweeps accumulated (rounded down)",
                   ({"keep": 0.5}, {"keep": 0.25}, {"keep": 0.0}), ("1/2 of them", "1/4 of them", "key frame only"),
                   ("lidar",)),
        Corruption("lidar_fov", "lidar", "the LiDAR sees only a sector around the ego's heading",
                   ({"degrees": 180}, {"degrees": 120}, {"degrees": 60}), ("180°", "120°", "60°"), ("lidar",)),
        Corruption("no_lidar", "lidar", "the LiDAR fails: the cameras alone", ({},), ("no points",),
                   ("cameras", "lidar")),
        Corruption("camera_extrinsics", "geometry",
                   "every camera's calibration off by a rotation and a shift of fixed size, random direction",
                   ({"degrees": 0.5, "metres": 0.02}, {"degrees": 1.0, "metres": 0.05},
                    {"degrees": 2.0, "metres": 0.1}),
                   ("0.5° 2 cm", "1° 5 cm", "2° 10 cm"), ("cameras",)),
        Corruption("lidar_delay", "geometry",
                   "the LiDAR data is k sweeps (50 ms each) older than the cameras and the key-frame pose",
                   ({"sweeps": 1}, {"sweeps": 2}, {"sweeps": 4}), ("50 ms", "100 ms", "200 ms"), ("lidar",)),
        Corruption("history_dropped", "temporal", "each frame is lost from the memory of later frames at random",
                   ({"probability": 0.25}, {"probability": 0.5}, {"probability": 1.0}), ("25%", "50%", "100%"),
                   ("temporal",)),
    )
}  # fmt: skip


def corruption_names() -> list[str]:
    return list(CORRUPTIONS)


def _hash(text: str) -> int:
    return zlib.crc32(text.encode())


def _image_transform(name: str, params: dict[str, Any], seed: int):
    """The albumentations pipeline of an image corruption level, seeded."""
    os.environ.setdefault("NO_ALBUMENTATIONS_UPDATE", "1")  # albumentations otherwise asks PyPI for a new version
    A = require_module("albumentations", "an image corruption", "pip install 'occkit[robustness]'")  # noqa: N806
    if name == "brightness":
        transforms = [A.RandomBrightnessContrast((params["brightness"],) * 2, (0.0, 0.0), p=1.0)]
    elif name == "low_light":
        transforms = [A.RandomGamma((200, 200), p=1.0), A.MultiplicativeNoise((params["ceiling"],) * 2, p=1.0),
                      A.ShotNoise((params["shot"],) * 2, p=1.0)]  # fmt: skip
    elif name == "fog":
        transforms = [A.RandomFog(fog_coef_range=(params["fog"],) * 2, alpha_coef=0.08, p=1.0)]
    elif name == "snow":
        transforms = [A.RandomSnow(snow_point_range=(params["snow"],) * 2, method=params["method"], p=1.0)]
    elif name == "motion_blur":
        transforms = [A.MotionBlur(blur_limit=(params["kernel"],) * 2, p=1.0)]
    elif name == "gaussian_noise":
        transforms = [A.GaussNoise(std_range=(params["std"],) * 2, p=1.0)]
    elif name == "jpeg":
        transforms = [A.ImageCompression(quality_range=(params["quality"],) * 2, p=1.0)]
    elif name == "color_quant":
        transforms = [A.Posterize(num_bits=params["bits"], p=1.0)]
    else:
        raise KeyError(name)
    return A.Compose(transforms, seed=seed)


class SampleCorruption:
    """One corruption at one level, as the dataset applies it to each sample.

    Args:
        name: a key of :data:`CORRUPTIONS`.
        severity: its level, 1 to the number of levels.
        seed: the seed of every draw (with the sample token, the name and the level).
    """

    def __init__(self, name: str, severity: int, seed: int = 0) -> None:
        if name not in CORRUPTIONS:
            raise ValueError(f"unknown corruption {name!r}; the corruptions are {', '.join(CORRUPTIONS)}")
        corruption = CORRUPTIONS[name]
        if isinstance(severity, bool) or not isinstance(severity, int) or severity not in corruption.severities:
            raise ValueError(f"corruption {name} has levels 1 to {len(corruption.levels)}, got {severity!r}")
        self.corruption = corruption
        self.name = name
        self.severity = severity
        self.seed = seed
        self.params = corruption.levels[severity - 1]

    def __repr__(self) -> str:
        return f"SampleCorruption({self.name!r}, {self.severity}, seed={self.seed})"

    @property
    def family(self) -> str:
        return self.corruption.family

    def rng(self, token: str, *stream: str) -> np.random.Generator:
        """The generator of one draw: the same for the same sample, corruption, level and stream, anywhere."""
        key = [self.seed, _hash(token), _hash(self.name), self.severity, *(_hash(s) for s in stream)]
        return np.random.default_rng(key)

    # ------------------------------------------------------------------------------------------------- cameras
    def failed_cameras(self, token: str, cameras: Sequence[str]) -> set[str]:
        """The cameras of ``cameras`` that fail in this sample."""
        if "cameras" in self.params:
            return set(self.params["cameras"]) & set(cameras)
        if "count" in self.params:
            count = min(self.params["count"], len(cameras))
            return {cameras[i] for i in self.rng(token, "cameras").choice(len(cameras), count, replace=False)}
        return set()

    def image(self, pixels: np.ndarray, token: str, camera: str) -> np.ndarray:
        """``(H, W, 3)`` uint8 -> the corrupted image (a new array; the input itself for other families)."""
        if self.family != "images":
            return pixels
        seed = int(self.rng(token, camera, "image").integers(2**31))
        return _image_transform(self.name, self.params, seed)(image=pixels)["image"]

    def cam2ego(self, cam2ego: np.ndarray, token: str, camera: str) -> np.ndarray:
        """``(4, 4)`` camera -> ego as the model is told it: for ``camera_extrinsics``, the true one moved in the
        camera frame by a rotation of ``degrees`` about a random axis and a shift of ``metres`` in a random direction.
        """
        if self.name != "camera_extrinsics":
            return cam2ego
        rng = self.rng(token, camera, "extrinsics")
        axis, shift = rng.normal(size=3), rng.normal(size=3)
        delta = np.eye(4)
        rotation = np.radians(self.params["degrees"]) * axis / np.linalg.norm(axis)
        from scipy.spatial.transform import Rotation  # here: scipy.spatial costs every command 0.3 s to import

        delta[:3, :3] = Rotation.from_rotvec(rotation).as_matrix()
        delta[:3, 3] = self.params["metres"] * shift / np.linalg.norm(shift)
        return np.asarray(cam2ego, dtype=np.float64) @ delta

    # --------------------------------------------------------------------------------------------------- LiDAR
    @property
    def lidar_missing(self) -> bool:
        return self.name == "no_lidar"

    @property
    def lidar_delay(self) -> int:
        """Sweeps by which the LiDAR lags (``lidar_delay``); 0 otherwise."""
        return self.params["sweeps"] if self.name == "lidar_delay" else 0

    def sweeps(self, sweeps: int) -> int:
        """The earlier sweeps loaded when the model takes ``sweeps`` (``fewer_sweeps``: 9 -> 4, 2, 0)."""
        return math.floor(sweeps * self.params["keep"]) if self.name == "fewer_sweeps" else sweeps

    def points(self, points: Tensor, token: str, sweep: int, lidar2ego: np.ndarray) -> Tensor:
        """Raw ``(P, 5)`` rows of one sweep (``x, y, z, intensity, ring`` in its LiDAR frame; ``sweep`` 0 is the key
        frame) -> the rows the corrupted sensor returns."""
        if self.name == "lidar_beams":
            return drop_lidar_beams(points, keep_every=self.params["keep_every"])
        if self.name == "point_dropout":
            return drop_points(points, self.params["fraction"], self.rng(token, str(sweep), "points"))
        if self.name == "lidar_fov":
            # The sector is centred on the ego's heading (ego x), whatever the LiDAR's mounting yaw.
            rotation = torch.tensor(np.asarray(lidar2ego, dtype=np.float64)[:2, :3], dtype=points.dtype)
            ego_xy = points[:, :3] @ rotation.T
            azimuth = torch.rad2deg(torch.atan2(ego_xy[:, 1], ego_xy[:, 0]))
            return points[azimuth.abs() <= self.params["degrees"] / 2]
        return points

    # ------------------------------------------------------------------------------------------------ temporal
    def forget(self, token: str) -> bool:
        """``history_dropped``: whether this frame is lost to the memory of the frames after it."""
        if self.name != "history_dropped":
            return False
        return bool(self.rng(token, "history").random() < self.params["probability"])
