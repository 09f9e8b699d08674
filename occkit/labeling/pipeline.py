"""``occkit label``: occupancy ground truth for every key frame of a nuScenes-layout dataset, from its sensor data.

Per scene (scenes run in parallel processes): plan the sweeps and boxes (:mod:`.sources`), aggregate the points
(:mod:`.aggregate`), then per key frame place them, vote the voxels' classes, densify if asked (:mod:`.voxels`),
cast the visibility masks (:mod:`occkit.geometry.visibility`) and write the label space's files:

* ``occ3d``: ``OUT/<scene>/<sample token>/labels.npz`` with ``semantics``, ``mask_lidar`` and ``mask_camera``,
  in the ego frame of the key frame's LiDAR timestamp (train on them with ``--set data.label_root=OUT``);
* ``surroundocc``: ``OUT/samples/<LiDAR file name>.npy`` sparse rows in the key frame's LiDAR frame.

``mask_lidar`` casts every return of the sweeps within ``mask_window`` key-frame intervals of the key frame from
its sensor, as the synthetic world's exact mask does; ``mask_camera`` casts rays from each camera of the key frame
through the generated labels, as Occ3D defines it. ``OUT/labeling.json`` records the settings and a per-scene
summary. The label files are a pure function of the dataset and the settings: byte for byte the same on every run
and for any number of workers.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from collections.abc import Callable
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, field
from pathlib import Path

import numpy as np

from occkit.data.labels import label_file
from occkit.geometry.visibility import camera_visibility, lidar_visibility
from occkit.label_files import write_occ3d_labels, write_surroundocc_labels
from occkit.label_space import LabelSpace, label_space
from occkit.labeling.aggregate import AggregateConfig, aggregate_scene
from occkit.labeling.sources import ScenePlan, lidarseg_to_occ3d, plan_scenes
from occkit.labeling.voxels import DENSIFY_METHODS, DensifyConfig, densify_poisson, key_frame_points, vote
from occkit.outputs import OutputLock, check_output_folder, publish_folder, staging_folder

__all__ = ["LabelConfig", "SUMMARY_FILE", "check_label_output", "label_scene", "label_dataset"]

#: The summary ``occkit label`` writes beside the labels; it also marks a folder as its output (an older occkit's
#: too, which wrote no manifest).
SUMMARY_FILE = "labeling.json"
#: The command named in the output folder's lock and manifest.
COMMAND = "occkit label"


@dataclass(frozen=True)
class LabelConfig:
    """Everything that decides the labels ``occkit label`` writes."""

    label_space: str = "occ3d"
    """The output's label space: ``occ3d`` or ``surroundocc``."""
    sweeps: int | None = None
    """Non-key sweeps used between consecutive key frames (evenly spread); None for all, 0 for key frames only."""
    densify: str = "none"
    """``none``, or ``poisson``: SurroundOcc's surface reconstruction (needs open3d)."""
    mask_window: int = 1
    """``mask_lidar`` casts the sweeps of this many key-frame intervals on each side of the key frame."""
    aggregate: AggregateConfig = field(default_factory=AggregateConfig)
    """How points are split into static and object points and labelled."""
    poisson: DensifyConfig = field(default_factory=DensifyConfig)
    """Settings of ``densify="poisson"``."""

    def __post_init__(self) -> None:
        if label_space(self.label_space).name not in ("occ3d", "surroundocc"):
            raise ValueError(f"occkit label writes occ3d or surroundocc labels, not {self.label_space}: OpenOcc v2's "
                             "flow needs tracked objects, which point clouds alone do not give")  # fmt: skip
        if self.densify not in DENSIFY_METHODS:
            raise ValueError(f"densify must be one of {', '.join(DENSIFY_METHODS)}, got {self.densify!r}")
        if self.mask_window < 0:
            raise ValueError(f"mask_window must be >= 0, got {self.mask_window}")
        if self.sweeps is not None and self.sweeps < 0:
            raise ValueError(f"sweeps must be >= 0 or None (all), got {self.sweeps}")


#: Metres of points kept around the grid for the surface reconstruction, so that it does not close at the edge.
_DENSIFY_MARGIN = 2.0


def _frame2global(space: LabelSpace, ego2global: np.ndarray, lidar2ego: np.ndarray) -> np.ndarray:
    return ego2global @ lidar2ego if space.frame == "lidar" else ego2global


def label_scene(plan: ScenePlan, lookup: np.ndarray, config: LabelConfig, out: Path,
                progress: Callable[[int], None] | None = None) -> dict:  # fmt: skip
    """Label every key frame of ``plan`` into ``out``; returns the scene's summary.

    Args:
        plan: the scene.
        lookup: ``(256,)`` lidarseg index -> Occ3D id.
        config: the settings.
        out: the output folder.
        progress: called with 1 after each key frame.
    """
    start = time.perf_counter()
    space = label_space(config.label_space)
    grid, empty = space.grid, space.free_index
    cloud = aggregate_scene(plan, lookup, config.aggregate)
    aggregated = time.perf_counter()
    occupied, observed = [], []
    for k, key in enumerate(plan.key_frames):
        sweep = plan.sweeps[key.sweep]
        frame2global = _frame2global(space, sweep.ego2global, sweep.lidar2ego)
        margin = _DENSIFY_MARGIN if config.densify != "none" else 0.0
        points, labels = key_frame_points(cloud, sweep.boxes, frame2global, grid, config.aggregate, margin)
        # SurroundOcc's files have no "others": its class 0 is noise, so Occ3D's others are not written.
        keep = labels != space.ignore_index
        if space.name == "surroundocc":
            keep &= labels != 0
        points, labels = points[keep], labels[keep]
        semantics = vote(points, labels, grid, empty)
        if config.densify == "poisson" and len(points) > config.poisson.max_nn:
            sensor = np.linalg.inv(frame2global) @ (sweep.ego2global @ sweep.lidar2ego)[:, 3]
            semantics = densify_poisson(points, labels, sensor[:3], semantics, grid, empty, config.poisson)
        occupied.append(int((semantics != empty).sum()))
        token = key.sample_token
        path = label_file(space, out, plan.name, token, sweep.filename)
        if space.name == "surroundocc":
            index = np.argwhere(semantics != empty)
            write_surroundocc_labels(path, np.concatenate((index, semantics[tuple(index.T)][:, None]), axis=1))
        else:
            to_frame = np.linalg.inv(frame2global)
            to_frame[:3, 3] += to_frame[:3, :3] @ cloud.origin  # the rays are stored relative to the origin
            first = plan.key_frames[max(0, k - config.mask_window)].sweep
            last = plan.key_frames[min(len(plan.key_frames) - 1, k + config.mask_window)].sweep
            rays = [(to_frame[:3, :3] @ sensor_xyz + to_frame[:3, 3],
                     returns.astype(np.float64) @ to_frame[:3, :3].T + to_frame[:3, 3])
                    for sensor_xyz, returns in cloud.rays[first : last + 1]]  # fmt: skip
            mask_lidar = lidar_visibility(semantics, grid, rays, free=empty)
            mask_camera = camera_visibility(semantics, grid, key.cameras, free=empty)
            observed.append(int(mask_camera.sum()))
            write_occ3d_labels(path, semantics, mask_lidar, mask_camera)
        if progress is not None:
            progress(1)
    end = time.perf_counter()
    counts = cloud.counts
    return {
        "scene": plan.name,
        "key_frames": len(plan.key_frames),
        "sweeps": len(plan.sweeps),
        "points": {
            "returns": counts.get("returns", 0),
            "static": int(len(cloud.static_label)),
            "objects": int(sum(len(labels) for _, labels in cloud.objects.values())),
            "dropped": {name: counts.get(name, 0) for name in ("ego_body", "moving_outside_boxes", "ignored_class",
                                                               "sweep_unlabelled", "sweep_moving_neighbour")},
        },  # fmt: skip
        "instances": len(cloud.objects),
        "occupied_voxels_per_frame": round(float(np.mean(occupied)), 1) if occupied else 0.0,
        "seconds": {"aggregate": round(aggregated - start, 3), "key_frames": round(end - aggregated, 3),
                    "total": round(end - start, 3)},  # fmt: skip
    }


def check_label_output(out: Path, overwrite: bool) -> None:
    """Refuse an ``out`` that :func:`label_dataset` may not write: a file, or a non-empty folder unless
    ``overwrite`` and it holds a previous ``occkit label`` output and nothing else
    (:func:`occkit.outputs.check_replaceable`: every file, nested ones too, listed in its manifest)."""
    check_output_folder(out, overwrite, COMMAND, SUMMARY_FILE)


def _label_scene_reporting(plan: ScenePlan, lookup: np.ndarray, config: LabelConfig, out: Path, queue) -> dict:
    os.environ.setdefault("OMP_NUM_THREADS", "1")
    return label_scene(plan, lookup, config, out, queue.put)


def label_dataset(
    root: str | Path,
    version: str,
    out: str | Path,
    config: LabelConfig = LabelConfig(),  # noqa: B008 - frozen
    workers: int = 1,
    scenes: list[str] | None = None,
    overwrite: bool = False,
    progress: Callable[[int], None] | None = None,
    on_scene: Callable[[dict], None] | None = None,
    on_start: Callable[[int], None] | None = None,
) -> dict:
    """Label every key frame of the dataset at ``root`` (tables in ``root/version``) into ``out``.

    The labels are written to a hidden folder beside ``out`` and moved into place when all scenes are done, so an
    interrupted run leaves no partial output. The run holds the lock of ``out``
    (:class:`occkit.outputs.OutputLock`): a second run into the same folder is refused before any work.

    Args:
        root, version: the dataset.
        out: the output folder (:func:`check_label_output`).
        config: the settings.
        workers: scenes labelled in parallel processes.
        scenes: scene names to label (default: all).
        overwrite: replace a previous output.
        progress: called with the number of key frames finished since the last call.
        on_scene: called with each scene's summary as it finishes.
        on_start: called with the number of key frames to label, once the scenes are planned.

    Returns:
        The summary written to ``out/labeling.json``: settings, per-scene summaries, totals.
    """
    from occkit.data.tables import load_tables

    if workers < 1:
        raise ValueError(f"workers must be >= 1, got {workers}")
    out = Path(out)
    with OutputLock(out, COMMAND):
        check_label_output(out, overwrite)
        return _label_locked(load_tables(root, version), root, version, out, config, workers, scenes, progress,
                             on_scene, on_start)  # fmt: skip


def _label_locked(tables, root, version, out: Path, config: LabelConfig, workers: int, scenes, progress, on_scene,
                  on_start) -> dict:  # fmt: skip
    """:func:`label_dataset` once the output folder is locked and checked."""
    plans = plan_scenes(tables, scenes, config.sweeps)
    lookup = lidarseg_to_occ3d(tables)
    if on_start is not None:
        on_start(sum(len(plan.key_frames) for plan in plans))
    staging = staging_folder(out)
    if staging.exists():  # left by a run that died: the lock says no other run is writing it
        shutil.rmtree(staging)
    staging.mkdir(parents=True)
    start = time.perf_counter()
    try:
        summaries = _run(plans, lookup, config, staging, workers, progress, on_scene)
        seconds = time.perf_counter() - start
        frames = sum(s["key_frames"] for s in summaries)
        summary = {
            "root": str(root),
            "version": version,
            "config": asdict(config),
            "scenes": summaries,
            "key_frames": frames,
            "seconds": round(seconds, 3),
            "seconds_per_key_frame": round(seconds * workers / max(frames, 1), 3),
            "workers": workers,
        }
        (staging / SUMMARY_FILE).write_text(json.dumps(summary, indent=1) + "\n")
        publish_folder(staging, out, COMMAND, SUMMARY_FILE)
    except BaseException:
        shutil.rmtree(staging, ignore_errors=True)
        raise
    return summary


def _run(plans, lookup, config, out, workers, progress, on_scene) -> list[dict]:
    if workers == 1 or len(plans) <= 1:
        summaries = []
        for plan in plans:
            summaries.append(label_scene(plan, lookup, config, out, progress))
            if on_scene is not None:
                on_scene(summaries[-1])
        return summaries
    import multiprocessing
    from concurrent.futures import FIRST_COMPLETED, wait

    # spawn, not fork: forked children of a process that already used numba or torch threads can deadlock.
    context = multiprocessing.get_context("spawn")
    with context.Manager() as manager:
        queue = manager.Queue()
        with ProcessPoolExecutor(max_workers=min(workers, len(plans)), mp_context=context) as pool:
            futures = {pool.submit(_label_scene_reporting, plan, lookup, config, out, queue): i
                       for i, plan in enumerate(plans)}  # fmt: skip
            results: dict[int, dict] = {}
            pending = set(futures)
            while pending:
                done, pending = wait(pending, timeout=0.5, return_when=FIRST_COMPLETED)
                while not queue.empty():
                    step = queue.get()
                    if progress is not None:
                        progress(step)
                for future in done:
                    results[futures[future]] = future.result()
                    if on_scene is not None:
                        on_scene(results[futures[future]])
            while not queue.empty():
                step = queue.get()
                if progress is not None:
                    progress(step)
            return [results[i] for i in range(len(plans))]
