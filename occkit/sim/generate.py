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

import os
import shutil
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

from occkit.nuscenes import LIDARSEG_TABLE, TABLE_NAMES
from occkit.outputs import OutputLock, check_output_folder, publish_folder, staging_folder
from occkit.sim.config import SimConfig, scene_name
from occkit.sim.scene import simulate_scene

__all__ = [
    "SimConfig",
    "simulate_dataset",
    "check_output",
    "estimate_resources",
    "DATASET_MARKER",
]

#: The file that marks a folder as written by ``occkit sim`` (also by an older occkit, which wrote no manifest).
DATASET_MARKER = "sim_config.yaml"
#: The command named in the output folder's lock and manifest.
COMMAND = "occkit sim"


def check_output(out: Path, overwrite: bool) -> None:
    """Refuse an ``out`` that :func:`simulate_dataset` may not write (before any work): a file, the current folder,
    a folder with content without ``overwrite``, or with ``overwrite`` anything but a dataset it wrote holding
    nothing else (:func:`occkit.outputs.check_replaceable`: every file, nested ones too, listed in its manifest)."""
    here = Path.cwd().resolve()
    if out.resolve() == here or out.resolve() in here.parents:
        raise ValueError(f"--out {out} is the current folder or holds it: occkit sim writes a dataset beside it and "
                         "renames it into place; give a folder of its own, e.g. data/synth")
    check_output_folder(out, overwrite, COMMAND, DATASET_MARKER)


def _prepare_output(out: Path, overwrite: bool) -> Path:
    """Check ``out`` and make an empty staging folder beside it; the caller holds the folder's lock, so a staging
    folder already there was left by a run that died."""
    check_output(out, overwrite)
    staging = staging_folder(out)
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


def simulate_dataset(
    config: SimConfig,
    out: str | Path,
    workers: int = 1,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
) -> dict:
    """Simulate ``config.scenes`` scenes and write them under ``out``; returns a summary dict.

    ``progress`` is called with the number of key frames finished since the last call. The run holds the lock of
    ``out`` (:class:`occkit.outputs.OutputLock`): a second run into the same folder is refused before any work.
    """
    out = Path(out)
    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    with OutputLock(out, COMMAND):
        return _simulate_locked(config, out, workers, overwrite, progress)


def _simulate_locked(config: SimConfig, out: Path, workers: int, overwrite: bool,
                     progress: Callable[[int], None] | None) -> dict:  # fmt: skip
    from occkit.sim.writer import static_tables, write_json

    staging = _prepare_output(out, overwrite)
    try:
        tables: dict[str, list[dict]] = {name: [] for name in (*TABLE_NAMES, LIDARSEG_TABLE)}
        tables.update(static_tables(config.version))
        results = _run_scenes(simulate_scene, config, staging, workers, progress)
        for result in results:  # scene order, whatever the completion order
            for name, rows in result["tables"].items():
                tables[name].extend(rows)
        for name in (*TABLE_NAMES, LIDARSEG_TABLE):
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
        _write_config(staging / DATASET_MARKER, config)
        publish_folder(staging, out, COMMAND, DATASET_MARKER)
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
