"""Score a folder of predictions against a ground-truth tree: mIoU, IoU and, for Occ3D, RayIoU.

Ground truth is the label space's layout (:mod:`occkit.label_space`): Occ3D's ``gts/<scene>/<token>/labels.npz``, or
SurroundOcc's ``samples/<LiDAR file>.npy`` (named after the LiDAR file, so the nuScenes tables are needed to pair
them with sample tokens). Predictions are one ``<token>.npz`` per frame holding ``semantics`` (Occ3D challenge
submissions, ``occkit predict``) or ``pred`` (SparseOcc), uint8 class ids on the label space's grid (a file with
both is scored on ``semantics``, and a note says so). Files are untrusted: each array's shape and dtype are checked
from its header before its data is read (:mod:`occkit.archives`), so memory is bounded by the grid. Frames are read
in a thread pool; each worker reduces its frame to a confusion matrix and, for RayIoU, to
ray counts, so memory stays flat however many frames there are. The totals agree with the official ``Metric_mIoU``
and SparseOcc's ``main_rayiou`` because both metrics are sums of per-frame counts.

:func:`write_report` turns the result into ``metrics.json``, ``metrics.md`` and ``per_class_iou.png``.
"""

from __future__ import annotations

import io
import json
import math
from collections.abc import Callable, Mapping
from concurrent.futures import ThreadPoolExecutor, as_completed
from pathlib import Path
from typing import Any, NamedTuple

import numpy as np

from occkit.archives import NpyHeader, NpzArchive
from occkit.data.labels import check_flow, label_file, read_labels
from occkit.data.names import path_under, safe_name
from occkit.label_space import OCC3D_SPACE, LabelSpace, label_space
from occkit.metrics.confusion import OccupancyMetric
from occkit.metrics.rayiou import AVE_THRESHOLD, FLOW_CLASSES, RAYIOU_THRESHOLDS, RayCounts, cast_frame
from occkit.metrics.raypq import RayPQCounts

__all__ = [
    "write_prediction",
    "PRED_KEYS",
    "find_gt_labels",
    "read_prediction",
    "read_prediction_flow",
    "read_ray_origins",
    "evaluate_predictions",
    "evaluate_prediction_folder",
    "markdown_table",
    "write_report",
    "plot_per_class_iou",
]

#: Keys a prediction file may store its grid under, in the order they are looked up.
PRED_KEYS: tuple[str, ...] = ("semantics", "pred")

_MASKS = {"camera": "camera", "lidar": "lidar", "none": None, None: None}
# How many missing tokens an error message lists before it only gives the count.
_LIST_AT_MOST = 10


def _token_list(tokens: list[str]) -> str:
    shown = ", ".join(tokens[:_LIST_AT_MOST])
    return shown + (f", ... ({len(tokens) - _LIST_AT_MOST} more)" if len(tokens) > _LIST_AT_MOST else "")


def find_gt_labels(gt_root: str | Path, space: LabelSpace | str = OCC3D_SPACE,
                   frames: Mapping[str, tuple[str, str]] | None = None) -> dict[str, Path]:  # fmt: skip
    """Map each token to its ground-truth file, sorted by token.

    Args:
        gt_root: Occ3D's ``gts/`` folder, or the folder holding SurroundOcc's ``samples/``.
        space: the label space of the files.
        frames: token -> (scene, LiDAR file) of the dataset's key frames, from its tables; required for SurroundOcc
            (its files are named after the LiDAR file), and for Occ3D it limits the tree to those frames.

    Raises:
        FileNotFoundError: ``gt_root`` is not a folder.
        ValueError: the tree holds no ground truth, a frame's file is missing, or one token appears in two scenes.
    """
    space = label_space(space)
    gt_root = Path(gt_root)
    if not gt_root.is_dir():
        raise FileNotFoundError(f"ground-truth folder not found: {gt_root}")
    if frames is not None:
        paths = {token: label_file(space, gt_root, scene, token, lidar) for token, (scene, lidar) in frames.items()}
        missing = [token for token, path in paths.items() if not path.is_file()]
        if missing:
            raise ValueError(f"{gt_root}: no {space.name} ground truth for {len(missing)} of {len(paths)} frames: "
                             f"{_token_list(missing)} (e.g. {paths[missing[0]]})")  # fmt: skip
        return dict(sorted(paths.items()))
    if space.layout != "token_tree":
        raise ValueError(f"{space.name} ground truth is named after each frame's LiDAR file: give the dataset's "
                         "tables (--nuscenes ROOT --version V) to pair it with sample tokens")  # fmt: skip
    found: dict[str, Path] = {}
    for path in sorted(gt_root.glob("*/*/labels.npz")):
        token = path.parent.name
        if token in found:
            raise ValueError(f"token {token} has labels in two scenes: {found[token]} and {path}")
        found[token] = path
    if not found:
        raise ValueError(f"{gt_root} holds no <scene>/<token>/labels.npz (is it the {space.title} "
                         f"{space.label_folder}/ folder?)")  # fmt: skip
    return dict(sorted(found.items()))


def write_prediction(folder: Path, token: str, semantics: np.ndarray, flow: np.ndarray | None = None,
                     instances: np.ndarray | None = None) -> Path:  # fmt: skip
    """``folder/<token>.npz``, one Occ3D-format prediction file (``semantics``: uint8 ``(200, 200, 16)``; with
    ``flow``, also ``flow``: float32 ``(200, 200, 16, 2)`` m/s, the key of the challenge's ground truth; with
    ``instances``, the panoptic instance ids, int32 ``(200, 200, 16)``, 0 for stuff, which RayPQ scores), written
    atomically. The token must be a safe name (:func:`~occkit.data.names.safe_name`), so the file stays in
    ``folder`` whatever the tables say."""
    path = path_under(folder, safe_name(token, f"sample token (writing into {folder})") + ".npz", str(folder))
    arrays = {"semantics": semantics.astype(np.uint8)}
    if flow is not None:
        arrays["flow"] = flow.astype(np.float32)
    if instances is not None:
        arrays["instances"] = instances.astype(np.int32)
    buffer = io.BytesIO()
    np.savez_compressed(buffer, **arrays)
    from occkit.outputs import write_atomic  # a failed write (a full disk) removes its temporary file

    return write_atomic(path, buffer.getvalue())


def read_prediction(path: str | Path, space: LabelSpace | str = OCC3D_SPACE) -> np.ndarray:
    """Read one prediction file: ``semantics`` or ``pred``, integer class ids of ``space`` on its grid (Occ3D:
    ``(200, 200, 16)``, ids 0..17), as uint8.

    Raises:
        ValueError: unreadable file, no known key, wrong shape, non-integer dtype or ids outside the space's classes;
            the message names the file.
    """
    return _read_prediction(Path(path), label_space(space), extras=False).grid


def read_prediction_instances(path: str | Path, space: LabelSpace | str = OCC3D_SPACE) -> np.ndarray | None:
    """The panoptic ``instances`` of a prediction file as integer ``(X, Y, Z)`` (0: stuff), or None when it has none.

    Raises:
        ValueError: unreadable file, or instances of the wrong shape or dtype.
    """
    return _read_prediction(Path(path), label_space(space), extras=True).instances


def read_prediction_flow(path: str | Path, space: LabelSpace | str = OCC3D_SPACE) -> np.ndarray | None:
    """The ``flow`` of a prediction file as float32 ``(X, Y, Z, 2)`` m/s, or None when it has none.

    Raises:
        ValueError: unreadable file, or a flow of the wrong shape or dtype, not finite, or faster than
            :data:`~occkit.data.labels.MAX_FLOW_SPEED`.
    """
    return _read_prediction(Path(path), label_space(space), extras=True).flow


class _Prediction(NamedTuple):
    """One prediction file's grid, its flow and instances (None: not asked for, or absent), and which grid keys it
    holds."""

    grid: np.ndarray
    flow: np.ndarray | None
    keys: tuple[str, ...]
    """The :data:`PRED_KEYS` the file holds; the grid is the first one's."""
    instances: np.ndarray | None = None
    """Panoptic instance ids (key ``instances``, integer, the grid's shape; 0: no instance)."""


def _read_prediction(path: Path, space: LabelSpace, extras: bool) -> _Prediction:
    """The grid (and with ``extras`` the flow and the instances, where the file holds them) of a prediction file, each
    array's shape and dtype checked from its header before its data is read: a file declaring a larger array than the
    grid costs no memory."""
    try:
        with NpzArchive(path, "prediction") as archive:
            keys = tuple(key for key in PRED_KEYS if key in archive)
            if not keys:
                raise ValueError(f"{path}: has none of the keys {', '.join(PRED_KEYS)} "
                                 f"(keys: {', '.join(archive.keys) or 'none'})")  # fmt: skip
            grid = archive.read(keys[0], _grid_check(path, keys[0], space))
            pred_flow = archive.read("flow", _flow_check(path, space)) if extras and "flow" in archive else None
            instances = archive.read("instances", _instance_check(path, space)) \
                if extras and "instances" in archive else None  # fmt: skip
    except FileNotFoundError:
        raise ValueError(f"{path}: prediction file not found") from None
    except OSError as error:
        raise ValueError(f"{path}: cannot read prediction ({error})") from error
    last = space.num_classes - 1
    bad = (grid < 0) | (grid > last)
    if bad.any():
        raise ValueError(f"{path}: {keys[0]} holds class ids {np.unique(grid[bad])[:16].tolist()} outside 0..{last} "
                         f"({space.name})")  # fmt: skip
    if pred_flow is not None:
        pred_flow = check_flow(pred_flow, str(path))
    return _Prediction(grid.astype(np.uint8, copy=False), pred_flow, keys, instances)


def _instance_check(path: Path, space: LabelSpace) -> Callable[[NpyHeader], None]:
    def check(header: NpyHeader) -> None:
        if header.shape != space.grid.shape or header.dtype.kind not in "iu":
            raise ValueError(f"{path}: instances must be an integer {space.grid.shape} array, got {header.dtype} "
                             f"{header.shape}")  # fmt: skip

    return check


def _grid_check(path: Path, key: str, space: LabelSpace) -> Callable[[NpyHeader], None]:
    def check(header: NpyHeader) -> None:
        if header.shape != space.grid.shape:
            raise ValueError(f"{path}: {key} has shape {header.shape} but {space.name} predictions have "
                             f"{space.grid.shape}")  # fmt: skip
        if header.dtype.kind not in "iu":
            raise ValueError(f"{path}: {key} has dtype {header.dtype} but expected uint8 class ids")

    return check


def _flow_check(path: Path, space: LabelSpace) -> Callable[[NpyHeader], None]:
    shape = (*space.grid.shape, 2)

    def check(header: NpyHeader) -> None:
        if header.shape != shape or header.dtype.kind != "f":
            raise ValueError(f"{path}: flow must be a float {shape} array (m/s), got {header.dtype} {header.shape}")

    return check


def read_ray_origins(path: str | Path, tokens: list[str]) -> dict[str, np.ndarray]:
    """Read RayIoU origins: an npz mapping token -> ``(T, 3)`` float ray origins in ego metres.

    Raises:
        FileNotFoundError: no such file.
        ValueError: unreadable file, origins missing for some of ``tokens`` (listed), or an array not ``(T, 3)``.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"ray origins file not found: {path}")

    def origins_of(token: str) -> Callable[[NpyHeader], None]:
        def check(header: NpyHeader) -> None:
            shape = header.shape
            if len(shape) != 2 or shape[1] != 3 or shape[0] == 0 or header.dtype.kind != "f":
                raise ValueError(f"{path}: origins of {token} must be a float (T, 3) array, got {header.dtype} {shape}")

        return check

    try:
        with NpzArchive(path, "ray origins") as archive:
            missing = [token for token in tokens if token not in archive]
            if missing:
                raise ValueError(f"{path}: no ray origins for {len(missing)} of {len(tokens)} frames: "
                                 f"{_token_list(missing)}")  # fmt: skip
            origins = {token: archive.read(token, origins_of(token)) for token in tokens}
    except OSError as error:
        raise ValueError(f"{path}: cannot read ray origins ({error})") from error
    return {token: array.astype(np.float64, copy=False) for token, array in origins.items()}


def _score_frame(
    space: LabelSpace, token: str, gt_path: Path, pred_path: Path | None, mask: str | None,
    origins: np.ndarray | None,
) -> tuple[np.ndarray, RayCounts | None, RayPQCounts | None, tuple[str, ...]]:
    """Confusion matrix of one frame; when ``origins`` is given its RayIoU counts (with the velocity errors when the
    prediction carries flow) and, when it carries instances, its RayPQ counts on the same rays; and the grid keys its
    prediction file holds (for the note on files with two)."""
    # A frame without a prediction (allowed by the caller) is scored as if everything were predicted free.
    if pred_path is None:
        prediction = _Prediction(np.full(space.grid.shape, space.free_index, np.uint8), None, ())
    else:  # flow and instances are only read where they are scored: on RayIoU's rays
        prediction = _read_prediction(pred_path, space, extras=origins is not None)
    pred, pred_flow = prediction.grid, prediction.flow
    scored_flow = pred_flow is not None and origins is not None
    labels = read_labels(space, gt_path, token, flow=scored_flow, instances=prediction.instances is not None)
    metric = OccupancyMetric.for_space(space, mask)
    metric.update(labels.semantics, pred, labels.mask_camera, labels.mask_lidar)
    if origins is None:
        return metric.confusion, None, None, prediction.keys
    try:
        rays = cast_frame(labels.semantics, pred, origins, space)
        counts = RayCounts(space)
        counts.add_frame(rays, *((labels.flow, pred_flow) if scored_flow else ()))
    except ValueError as error:
        raise ValueError(f"sample {token}: RayIoU failed ({error})") from error
    panoptic = None
    if prediction.instances is not None:  # panoptic: RayPQ on the same rays
        panoptic = RayPQCounts()
        panoptic.add_cast(rays, labels.instances, prediction.instances)
    return metric.confusion, counts, panoptic, prediction.keys


def _pair_predictions(gt_paths: Mapping[str, Path], pred_dir: Path, allow_missing: bool,
                      note: Callable[[str], None]) -> dict[str, Path | None]:  # fmt: skip
    """Prediction file of each GT token (None where missing and allowed); raises listing the missing tokens, and
    notes the files that match no ground-truth frame (a wrong --preds or --gt shows up there)."""
    if not pred_dir.is_dir():
        raise FileNotFoundError(f"prediction folder not found: {pred_dir}")
    available = {path.stem: path for path in pred_dir.glob("*.npz")}
    missing = [token for token in gt_paths if token not in available]
    if missing and not allow_missing:
        raise ValueError(
            f"{pred_dir}: no prediction for {len(missing)} of {len(gt_paths)} frames: {_token_list(missing)} "
            "(pass --allow-missing to score them as all free)"
        )
    extra = sorted(name for name in available if name not in gt_paths)
    if extra:
        shown = ", ".join(f"{name}.npz" for name in extra[:2]) + (", ..." if len(extra) > 2 else "")
        note(f"{len(extra)} of the {len(available)} files in {pred_dir} match no ground-truth frame and were not "
             f"scored ({shown})")  # fmt: skip
    return {token: available.get(token) for token in gt_paths}


def evaluate_predictions(
    gt_root: str | Path,
    pred_dir: str | Path,
    mask: str | None = "default",
    ray_origins: str | Path | Mapping[str, np.ndarray] | None = None,
    compute_rayiou: bool = False,
    allow_missing: bool = False,
    workers: int = 4,
    progress: Callable[[int], None] | None = None,
    space: LabelSpace | str = OCC3D_SPACE,
    frames: Mapping[str, tuple[str, str]] | None = None,
    note: Callable[[str], None] | None = None,
) -> dict:
    """Score every ground-truth frame against ``<token>.npz`` predictions with the label space's protocol.

    Args:
        gt_root: Occ3D's ``gts/`` folder (``<scene>/<token>/labels.npz``), or the folder holding SurroundOcc's
            ``samples/``.
        pred_dir: folder of ``<token>.npz`` files with key ``semantics`` or ``pred``.
        mask: visibility mask applied to mIoU/IoU: ``"camera"`` (Occ3D's official setting), ``"lidar"``,
            ``"none"``/None, or ``"default"``: the label space's (SurroundOcc has none).
        ray_origins: npz path or mapping token -> ``(T, 3)`` ray origins; required when ``compute_rayiou``.
        compute_rayiou: also compute SparseOcc's RayIoU (masks are not used by it); Occ3D only.
        allow_missing: score a frame without prediction as all free instead of raising.
        workers: threads reading and scoring frames.
        progress: called with 1 after each frame.
        space: the label space of ground truth and predictions.
        frames: token -> (scene, LiDAR file) of the key frames (see :func:`find_gt_labels`).
        note: called with each note on the run, once per kind (not per file): prediction files that match no
            ground-truth frame, and files holding both ``semantics`` and ``pred`` (``semantics`` is scored).

    Returns:
        ``miou``, ``iou``, ``per_class_iou`` {class: float or None}, ``label_space``, ``mask``, ``frames``,
        ``missing_predictions`` and with RayIoU ``rayiou``, ``rayiou@1``, ``rayiou@2``, ``rayiou@4``, and when the
        predictions carry ``flow`` also ``mave`` (m/s), ``occ_score`` (the CVPR 2024 challenge's, read against
        the ground truth's ``flow``), ``ave_per_class`` and ``ave_rays`` (the true-positive rays each moving class's
        AVE averages over), and when they carry ``instances`` (panoptic) ``raypq``, ``raypq@1``, ``raypq@2``,
        ``raypq@4`` against the ground truth's ``instances``; fractions in [0, 1], NaN as None.

    Raises:
        FileNotFoundError: a folder or the origins file does not exist.
        ValueError: bad arguments, missing predictions or origins, or a file with wrong content (named).
    """
    space = label_space(space)
    if mask not in (*_MASKS, "default"):
        raise ValueError(f"mask must be camera, lidar or none, got {mask!r}")
    mode = space.check_mask(space.default_mask if mask == "default" else _MASKS[mask])
    if workers < 1:
        raise ValueError(f"workers must be at least 1, got {workers}")
    if compute_rayiou and not space.rayiou:
        raise ValueError(f"RayIoU is not defined for {space.name} labels (only on Occ3D's grid): leave out --rayiou")
    if compute_rayiou and ray_origins is None:
        raise ValueError("RayIoU needs ray origins (--ray-origins FILE.npz mapping token -> (T, 3) origins)")
    gt_paths = find_gt_labels(gt_root, space, frames)
    tokens = list(gt_paths)
    note = note or (lambda text: None)
    pred_paths = _pair_predictions(gt_paths, Path(pred_dir), allow_missing, note)
    origins: Mapping[str, np.ndarray] | None = None
    if compute_rayiou:
        origins = read_ray_origins(ray_origins, tokens) if isinstance(ray_origins, (str, Path)) else ray_origins
        missing = [token for token in tokens if token not in origins]
        if missing:
            raise ValueError(f"no ray origins for {len(missing)} of {len(tokens)} frames: {_token_list(missing)}")

    total = OccupancyMetric.for_space(space, mode)
    rays = RayCounts(space) if compute_rayiou else None
    panoptic, panoptic_frames = RayPQCounts(), 0
    both_keys: list[str] = []  # tokens whose file holds semantics and pred
    with ThreadPoolExecutor(max_workers=workers) as pool:
        futures = {
            pool.submit(_score_frame, space, t, gt_paths[t], pred_paths[t], mode,
                        None if origins is None else origins[t]): t
            for t in tokens
        }  # fmt: skip
        try:
            for future in as_completed(futures):
                confusion, counts, frame_panoptic, keys = future.result()
                total.confusion += confusion
                if len(keys) > 1:
                    both_keys.append(futures[future])
                if counts is not None:
                    rays.merge(counts)
                if frame_panoptic is not None:
                    panoptic.merge(frame_panoptic)
                    panoptic_frames += 1
                if progress is not None:
                    progress(1)
        except BaseException:
            # Fail fast: frames not yet started are dropped instead of being read only to be thrown away.
            for future in futures:
                future.cancel()
            raise

    if both_keys:
        first = pred_paths[min(both_keys)]
        note(f"{len(both_keys)} prediction file(s) hold both {' and '.join(PRED_KEYS)}: {PRED_KEYS[0]} was scored "
             f"(e.g. {first.name})")  # fmt: skip
    scores = total.compute()
    result = {
        "miou": _finite_or_none(scores["miou"]),
        "iou": _finite_or_none(scores["iou"]),
        "per_class_iou": scores["per_class_iou"],
        "label_space": space.name,
        "mask": mode or "none",
        "frames": len(tokens),
        "missing_predictions": sum(path is None for path in pred_paths.values()),
    }
    if compute_rayiou:
        predicted = result["frames"] - result["missing_predictions"]
        if 0 < rays.flow_frames < predicted:
            raise ValueError(f"{pred_dir}: {rays.flow_frames} of {predicted} predictions carry flow: mAVE needs it in "
                             "all of them (or in none, for RayIoU alone)")  # fmt: skip
        if 0 < panoptic_frames < predicted:
            raise ValueError(f"{pred_dir}: {panoptic_frames} of {predicted} predictions carry instances: RayPQ needs "
                             "them in all (or in none)")  # fmt: skip
        if panoptic_frames:
            pq = panoptic.compute()
            result.update({key: _finite_or_none(pq[key]) for key in ("raypq", "raypq@1", "raypq@2", "raypq@4")})
        result.update({key: _finite_or_none(value) for key, value in rays.scores().items()})
        if rays.flow_frames:
            ids = [space.taxonomy.index(name) for name in FLOW_CLASSES]
            ave = rays.compute()["ave_per_class"]
            result["ave_per_class"] = {name: _finite_or_none(ave[c])
                                       for name, c in zip(FLOW_CLASSES, ids, strict=True)}  # fmt: skip
            result["ave_rays"] = {name: int(rays.ave_count[c]) for name, c in zip(FLOW_CLASSES, ids, strict=True)}
    return result


def evaluate_prediction_folder(
    gt_root: str | Path,
    pred_dir: str | Path,
    space: LabelSpace | str = OCC3D_SPACE,
    *,
    mask: str | None = "default",
    rayiou: bool = False,
    ray_origins: str | Path | Mapping[str, np.ndarray] | None = None,
    nuscenes: str | Path | None = None,
    version: str = "v1.0-trainval",
    allow_missing: bool = False,
    workers: int = 4,
    progress: Callable[[int, int], None] | None = None,
    note: Callable[[str], None] | None = None,
) -> dict:
    """:func:`evaluate_predictions` of a ground-truth tree, its frames and ray origins found from the dataset's
    nuScenes tables when they are given (``occkit eval-preds``).

    Args:
        nuscenes, version: the dataset's tables: they pair SurroundOcc's files (named after each LiDAR file) with
            sample tokens, give RayIoU's origins (the key-frame poses) when ``ray_origins`` is None, and choose the
            frames (an Occ3D tree may cover only some of them). Without them an Occ3D tree's every
            ``<scene>/<token>`` is scored.
        rayiou: also RayIoU (and mAVE / OccScore when the predictions carry flow); Occ3D only; needs
            ``ray_origins`` or ``nuscenes``.
        progress: called with (frames done, frames in all) after each frame.

    The other arguments are :func:`evaluate_predictions`'.
    """
    from occkit.data.index import build_index
    from occkit.metrics.origins import records_ray_origins

    space = label_space(space) if isinstance(space, str) else space
    gt_root = Path(gt_root)
    if rayiou and not space.rayiou:
        raise ValueError(f"RayIoU is not defined for {space.name} labels (only on Occ3D's grid)")
    if mask != "default":
        space.check_mask(_MASKS.get(mask, mask))
    records = None if nuscenes is None else build_index(nuscenes, version, max_sweeps=0)
    if records is None and space.layout != "token_tree":
        raise ValueError(f"{space.name} labels: their files are named after each frame's LiDAR file; give the "
                         "dataset's nuScenes tables (root and version) to pair them with sample tokens")  # fmt: skip
    if rayiou and ray_origins is None:
        if records is None:
            raise ValueError("RayIoU needs ray origins: a token -> origins file, or the dataset's nuScenes tables")
        ray_origins = records_ray_origins(records)
    frames = None if records is None else {r.token: (r.scene, r.lidar_path) for r in records}
    if frames is not None and space.layout == "token_tree":  # a tree may cover a subset of the tables' frames
        frames = {token: frame for token, frame in frames.items() if (gt_root / frame[0] / token).is_dir()}
    total, done = len(find_gt_labels(gt_root, space, frames)), 0

    def step(count: int) -> None:
        nonlocal done
        done += count
        if progress is not None:
            progress(done, total)

    return evaluate_predictions(gt_root, pred_dir, mask=mask, ray_origins=ray_origins, compute_rayiou=rayiou,
                                allow_missing=allow_missing, workers=workers, progress=step, space=space,
                                frames=frames, note=note)  # fmt: skip


def _finite_or_none(value: float) -> float | None:
    # JSON has no NaN; null is what per_class_iou already uses for "not defined".
    return None if math.isnan(value) else float(value)


def _undefined(value: float | None) -> bool:
    """True for a score with nothing to average: ``None`` in ``metrics.json`` (JSON has no NaN), NaN in memory."""
    return value is None or math.isnan(value)


def _percent(value: float | None) -> str:
    return "-" if _undefined(value) else f"{100 * value:.2f}"


def markdown_table(result: Mapping) -> str:
    """The result as papers print it: percent with two decimals, mIoU, IoU and the semantic classes (free left out)."""
    space = label_space(result.get("label_space", "occ3d"))
    free = space.taxonomy.classes[space.free_index]
    classes = [name for name in result["per_class_iou"] if name != free]
    header = ["mIoU", "IoU", *classes]
    values = [_percent(result["miou"]), _percent(result["iou"])]
    values += [_percent(result["per_class_iou"][name]) for name in classes]
    lines = [
        f"{space.title}, {result['frames']} frames, mask: {result['mask'] or 'none'}, "
        f"missing predictions: {result['missing_predictions']}",
        "",
        "| " + " | ".join(header) + " |",
        "|" + "|".join(" ---: " for _ in header) + "|",
        "| " + " | ".join(values) + " |",
    ]
    for key, name in (("rayiou", "RayIoU"), ("raypq", "RayPQ")):
        if key in result:
            lines += _ray_table(result, key, name)
    if "mave" in result:
        lines += _flow_lines(result)
    return "\n".join(lines) + "\n"


def _ray_table(result: Mapping, key: str, name: str) -> list[str]:
    """A blank line and the table of a ray metric: its mean and its value at each depth threshold, in percent."""
    keys = [key, *(f"{key}@{t}" for t in RAYIOU_THRESHOLDS)]
    return [
        "",
        "| " + " | ".join([name, *(f"{name}@{t}" for t in RAYIOU_THRESHOLDS)]) + " |",
        "|" + "|".join(" ---: " for _ in keys) + "|",
        "| " + " | ".join(_percent(result[k]) for k in keys) + " |",
    ]


def _nan_as_null(value: Any) -> Any:
    """``value`` with every float NaN, nested in dicts and lists too, replaced by None (JSON's null)."""
    if isinstance(value, float) and math.isnan(value):
        return None
    if isinstance(value, Mapping):
        return {key: _nan_as_null(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [_nan_as_null(item) for item in value]
    return value


def _flow_lines(result: Mapping) -> list[str]:
    """The mAVE and OccScore table; where they are undefined, "n/a" and why, instead of a bare ``nan``."""
    if not _undefined(result["mave"]):
        row = f"| {result['mave']:.3f} | {_percent(result['occ_score'])} |"
        return ["", "| mAVE (m/s) | OccScore |", "| ---: | ---: |", row]
    # The challenge's code gives NaN for both (a mean over no class, then max(nan, 0)); the value is kept as it is,
    # the report says what it means.
    return ["", "| mAVE (m/s) | OccScore |", "| ---: | ---: |", "| n/a | n/a |", "",
            f"mAVE n/a: no true positive of a moving class ({', '.join(FLOW_CLASSES)}) within {AVE_THRESHOLD} m, "
            "so no velocity error to average; OccScore n/a as it needs mAVE (both NaN, as in the challenge's code)"]


def plot_per_class_iou(result: Mapping, path: str | Path, title: str | None = None) -> Path:
    """Per-class IoU bars in the taxonomy's colours, with the mIoU as a line; ``result`` as :func:`evaluate_predictions`
    returns it. The default title gives the frame count and the mask."""
    from occkit.figure import new_figure, save_figure

    names = list(result["per_class_iou"])
    values = [100 * (result["per_class_iou"][name] or 0.0) for name in names]
    taxonomy = label_space(result.get("label_space", "occ3d")).taxonomy
    colors = [tuple(c / 255 for c in taxonomy.colors[taxonomy.classes.index(name)]) for name in names]
    figure = new_figure(7, 0.32 * len(names) + 1.2, dpi=120)
    axis = figure.add_subplot()
    # A dark outline keeps the white (free) and black (others) bars visible on a white background.
    axis.barh(names, values, color=colors, edgecolor="#222222", linewidth=0.8)
    for row, name in enumerate(names):
        if result["per_class_iou"][name] is None:
            axis.text(1, row, "n/a", va="center", fontsize=8)
    if result["miou"] is not None:
        axis.axvline(100 * result["miou"], color="#444444", linestyle="--", linewidth=1, label="mIoU")
        axis.legend(loc="lower right", fontsize=8)
    axis.invert_yaxis()
    axis.set_xlim(0, 100)
    axis.set_xlabel("IoU (%)")
    axis.set_title(title or f"Per-class IoU, {result['frames']} frames, mask: {result['mask'] or 'none'}")
    figure.tight_layout()
    return save_figure(figure, path)


def write_report(result: Mapping, out_dir: str | Path) -> dict[str, Path]:
    """Write ``metrics.json`` (full precision), ``metrics.md`` (percent table) and ``per_class_iou.png``."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    paths = {
        "json": out_dir / "metrics.json",
        "markdown": out_dir / "metrics.md",
        "plot": out_dir / "per_class_iou.png",
    }
    # JSON has no NaN (Python would write a bare NaN that strict readers refuse): an undefined score is null.
    paths["json"].write_text(json.dumps(_nan_as_null(dict(result)), indent=2, allow_nan=False) + "\n")
    paths["markdown"].write_text(markdown_table(result))
    plot_per_class_iou(result, paths["plot"])
    return paths
