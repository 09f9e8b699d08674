"""Simulate scenes of the synthetic world and write them as nuScenes + Occ3D-nuScenes.

One scene is a drive of ``frames`` key frames at 2 Hz. LIDAR_TOP spins at 20 Hz (nine sweeps between key frames,
each with its own ego pose); the six cameras fire at every key frame as the LiDAR sweeps past them, so each
camera image has its own timestamp and ego pose, as in nuScenes. Every key frame gets Occ3D labels in the ego frame
at the LiDAR timestamp, with ``mask_lidar`` accumulated over the sweeps around it and ``mask_camera`` from rays of
the key frame's cameras, and 3D boxes of the annotated objects.

Scenes are independent and seeded by ``(seed, scene index)``, so they are simulated in parallel processes and the
output does not depend on the number of workers. The dataset is written to a hidden folder beside the target and
renamed into place only when complete.
"""

from __future__ import annotations

import dataclasses
import math
import os
import shutil
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

from occkit.sim.rig import CAMERA_NAMES, camera_rig
from occkit.sim.world import WorldConfig

__all__ = [
    "SimConfig",
    "simulate_dataset",
    "check_output",
    "estimate_resources",
    "DATASET_MARKER",
    "KEY_FRAME_INTERVAL_US",
    "SWEEP_INTERVAL_US",
]

KEY_FRAME_INTERVAL_US = 500_000  # 2 Hz key frames
SWEEP_INTERVAL_US = 50_000  # 20 Hz LiDAR
SWEEPS_PER_KEY_FRAME = KEY_FRAME_INTERVAL_US // SWEEP_INTERVAL_US
FIRST_TIMESTAMP_US = 1_700_000_000_000_000  # microseconds, like nuScenes timestamps


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
    cameras: tuple[str, ...] = CAMERA_NAMES
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
        unknown = [c for c in self.cameras if c not in CAMERA_NAMES]
        if unknown or not self.cameras:
            raise ValueError(f"unknown cameras {unknown}; choose from {', '.join(CAMERA_NAMES)}")
        if not self.version or "/" in self.version or self.version.startswith("."):
            raise ValueError(f"version must be a plain folder name like v1.0-synth, got {self.version!r}")
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(f"val_fraction must be in [0, 1), got {self.val_fraction}")
        if self.mask_window < 0:
            raise ValueError(f"mask_window must be >= 0, got {self.mask_window}")
        if not 0.0 <= self.lidar_dropout < 1.0:
            raise ValueError(f"lidar_dropout must be in [0, 1), got {self.lidar_dropout}")

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
    rig = {camera.name: camera for camera in camera_rig(64, 36)}
    offsets = {}
    for name in cameras:
        optical_axis = rig[name].cam2ego[:3, 2]
        yaw = math.atan2(optical_axis[1], optical_axis[0])
        turn = ((math.pi - yaw) % (2 * math.pi)) / (2 * math.pi)
        offsets[name] = int(round(turn * SWEEP_INTERVAL_US))
    return offsets


#: What ``occkit sim`` writes at the top of a dataset besides its table folder (``<version>/``) and what readers
#: add (``.occkit/``, the index cache): ``--overwrite`` replaces a folder holding these and nothing else.
_DATASET_ENTRIES = frozenset({"annotations.json", "gts", "maps", "samples", "sweeps", "splits.json", "sim_config.yaml",
                              "surroundocc", ".occkit"})  # fmt: skip
#: The file that marks a folder as written by ``occkit sim``.
DATASET_MARKER = "sim_config.yaml"


def _check_replaceable(out: Path) -> None:
    """Refuse to replace ``out`` unless it is a dataset ``occkit sim`` wrote, holding nothing else."""
    import yaml

    marker = out / DATASET_MARKER
    try:
        version = (yaml.safe_load(marker.read_text()) or {}).get("version")
    except (OSError, yaml.YAMLError, AttributeError):
        raise FileExistsError(f"--overwrite refused: {out} is not a dataset written by occkit sim (no readable "
                              f"{DATASET_MARKER}); nothing was deleted") from None  # fmt: skip
    foreign = sorted(entry.name for entry in out.iterdir() if entry.name not in _DATASET_ENTRIES | {version})
    if foreign:
        shown = ", ".join(foreign[:5]) + (f" and {len(foreign) - 5} more" if len(foreign) > 5 else "")
        raise FileExistsError(f"--overwrite refused: {out} holds entries occkit sim did not write ({shown}); move "
                              "them away or choose another folder; nothing was deleted")


def check_output(out: Path, overwrite: bool) -> None:
    """Refuse an ``out`` that :func:`simulate_dataset` may not write (before any work): a file, the current folder,
    a folder with content without ``overwrite``, or with ``overwrite`` anything but a dataset it wrote."""
    if out.exists() and not out.is_dir():
        raise FileExistsError(f"{out} exists and is not a directory")
    here = Path.cwd().resolve()
    if out.resolve() == here or out.resolve() in here.parents:
        raise ValueError(f"--out {out} is the current folder or holds it: occkit sim writes a dataset beside it and "
                         "renames it into place; give a folder of its own, e.g. data/synth")
    if out.exists() and any(out.iterdir()):
        if not overwrite:
            raise FileExistsError(f"{out} exists and is not empty; pass --overwrite to replace it")
        _check_replaceable(out)


def _prepare_output(out: Path, overwrite: bool) -> Path:
    check_output(out, overwrite)
    staging = out.parent / f".{out.name}.partial"
    if staging.exists():
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    return staging


def estimate_resources(config: SimConfig) -> dict[str, float]:
    """Bytes the dataset takes on disk and one simulating process's peak memory, generously estimated.

    Measured on 4-frame scenes at 400x225 to 1600x900: about 4.8 MB of LiDAR key frame and sweeps per key frame,
    under 0.15 byte per camera pixel of JPEG, and a process peak of about 1 GB plus 170 bytes per image pixel.
    """
    width, height = config.image_size
    pixels = width * height
    per_frame = 6e6 + 0.3 * pixels * len(config.cameras)
    return {"disk": config.scenes * config.frames * per_frame, "memory_per_worker": 1.2e9 + 250 * pixels}


def _publish(staging: Path, out: Path) -> None:
    """Move the finished dataset into place; an existing one is replaced only after the new one is complete."""
    if out.exists():
        retired = out.parent / f".{out.name}.old"
        if retired.exists():
            shutil.rmtree(retired)
        out.rename(retired)
        staging.rename(out)
        shutil.rmtree(retired)
    else:
        staging.rename(out)


def simulate_dataset(
    config: SimConfig,
    out: str | Path,
    workers: int = 1,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Simulate ``config.scenes`` scenes and write them under ``out``; returns a summary dict.

    ``progress`` is called with the number of key frames finished since the last call.
    """
    from occkit.data.tables import TABLE_NAMES
    from occkit.sim.scene import simulate_scene
    from occkit.sim.writer import static_tables, write_json

    out = Path(out)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    staging = _prepare_output(out, overwrite)
    try:
        tables: dict[str, list[dict]] = {name: [] for name in TABLE_NAMES}
        tables.update(static_tables(config.version))
        results = _run_scenes(simulate_scene, config, staging, workers, progress)
        for result in results:  # scene order, whatever the completion order
            for name, rows in result["tables"].items():
                tables[name].extend(rows)
        for name in TABLE_NAMES:
            write_json(staging / config.version / f"{name}.json", tables[name])
        train, val = config.split()
        scene_infos = {result["scene"]: result["occ3d_infos"] for result in results}
        write_json(
            staging / "annotations.json",
            {
                "train_split": [scene_name(i) for i in train],
                "val_split": [scene_name(i) for i in val],
                "scene_infos": scene_infos,
            },
        )
        write_json(
            staging / "splits.json", {"train": [scene_name(i) for i in train], "val": [scene_name(i) for i in val]}
        )
        _write_config(staging / "sim_config.yaml", config)
        _publish(staging, out)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return {
        "root": str(out),
        "version": config.version,
        "scenes": config.scenes,
        "samples": len(tables["sample"]),
        "sample_data": len(tables["sample_data"]),
        "annotations": len(tables["sample_annotation"]),
        "timings": _merge_timings([r["timings"] for r in results]),
    }


def _run_scenes(simulate_scene, config: SimConfig, staging: Path, workers: int, progress) -> list[dict]:
    if workers == 1 or config.scenes == 1:
        return [simulate_scene(config, index, staging, progress) for index in range(config.scenes)]
    import multiprocessing

    # spawn, not fork: forked children of a process that already used torch/numba threads can deadlock.
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager:
        queue = manager.Queue()
        with ProcessPoolExecutor(max_workers=min(workers, config.scenes), mp_context=context) as pool:
            futures = [pool.submit(_simulate_scene_reporting, config, i, staging, queue) for i in range(config.scenes)]
            finished = 0
            total = config.scenes * config.frames
            while finished < total:
                if all(f.done() for f in futures) and queue.empty():
                    break
                try:
                    step = queue.get(timeout=0.5)
                except Exception:  # queue.Empty from the manager proxy
                    continue
                finished += step
                if progress is not None:
                    progress(step)
            return [f.result() for f in futures]


def _simulate_scene_reporting(config: SimConfig, index: int, staging: Path, queue) -> dict:
    from occkit.sim.scene import simulate_scene

    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return simulate_scene(config, index, staging, queue.put)


def _merge_timings(per_scene: list[dict[str, float]]) -> dict[str, float]:
    merged: dict[str, float] = {}
    for timings in per_scene:
        for stage, seconds in timings.items():
            merged[stage] = merged.get(stage, 0.0) + seconds
    return {stage: round(seconds, 3) for stage, seconds in merged.items()}


def _write_config(path: Path, config: SimConfig) -> None:
    from occkit.config import dump_yaml

    path.write_text(dump_yaml(config))
