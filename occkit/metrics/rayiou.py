"""RayIoU of the SparseOcc protocol on Occ3D-nuScenes grids, value for value, and the occupancy flow scores of the
CVPR 2024 occupancy-and-flow challenge on the same rays: mAVE and OccScore. Both read Occ3D's and OpenOcc v2's
labels (the same grid; the free id, the classes averaged and the moving classes' ids come from the label space, as
the reference's ``occ_class_names`` argument gives them).

Rays leave the LiDAR positions of a frame's scene (``origins``, ego metres) in 39 pitches x 360 azimuths and stop at
the first occupied voxel; a ray scores for a class when prediction and ground truth stop on that class at depths
closer than a threshold (1, 2 and 4 m). With flow, each ray also reads the velocity of the voxel it stops in; the
absolute velocity error (AVE) of a moving class is the mean L2 norm of the velocity difference over its true-positive
rays at 2 m, mAVE the mean over the moving classes that have one, and OccScore = 0.9 RayIoU + 0.1 max(1 - mAVE, 0)
(``projects/mmdet3d_plugin/datasets/ray_metrics.py`` of OccNet's challenge branch, the implementation its README
names; its dtypes and sums are kept, see ``tests/golden/occupancy_flow``).

The ray caster reproduces the reference's float arithmetic exactly: voxel coordinates rounded to float32 as its
inputs are, Amanatides-Woo stepping in double precision from ``int(origin)`` with its tie order, and the exit
distance of the stopping voxel. The generic traversal in :mod:`occkit.geometry.raycast` resolves ties differently
and is not used here.

Numpy arrays in and out; a numba kernel walks the rays.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numba
import numpy as np
import torch
from numba import njit, prange

from occkit.label_space import OCC3D_SPACE, LabelSpace

__all__ = ["RAYIOU_THRESHOLDS", "FLOW_CLASSES", "AVE_THRESHOLD", "ray_directions", "cast_rays_exact", "FrameRays",
           "cast_frame", "RayCounts", "rayiou", "rayiou_from_counts", "occ_score"]

#: Depth thresholds in metres of RayIoU@1, @2 and @4.
RAYIOU_THRESHOLDS: tuple[int, ...] = (1, 2, 4)

#: The moving classes whose velocity error mAVE averages (the challenge's eight), by name.
FLOW_CLASSES: tuple[str, ...] = ("car", "truck", "trailer", "bus", "construction_vehicle", "bicycle", "motorcycle",
                                 "pedestrian")  # fmt: skip

#: Depth threshold (m) of the true-positive rays whose velocity errors AVE averages.
AVE_THRESHOLD = 2

# RayIoU is defined on Occ3D's ego-frame grid with a free class (SparseOcc's protocol).
_GRID_SHAPE = OCC3D_SPACE.grid.shape
_LOWER = OCC3D_SPACE.grid.lower
# The reference divides by a float32 voxel size promoted to double; 0.4 in double flips some labels.
_VOXEL = float(np.float32(OCC3D_SPACE.grid.voxel_size[0]))
# Loop bound of the reference kernel (MAX_STEP): a ray that takes more steps stops where it is.
_MAX_STEP = 1000


@functools.cache
def _protocol(space: LabelSpace) -> tuple[int, int, tuple[int, ...]]:
    """``(free id, classes averaged, ids of FLOW_CLASSES)`` of a label space RayIoU is defined for; ValueError for
    another (SparseOcc's rays need Occ3D's ego-frame grid and a free class that ends last)."""
    if not space.rayiou or space.grid.shape != _GRID_SHAPE or space.free_index != space.num_classes - 1:
        raise ValueError(f"RayIoU is not defined for {space.name} labels (only on Occ3D's grid with a free class)")
    return space.free_index, space.num_classes - 1, tuple(space.taxonomy.index(name) for name in FLOW_CLASSES)


@functools.lru_cache(maxsize=1)
def _directions() -> np.ndarray:
    pitches = [-(math.pi / 2 - math.atan(k)) for k in range(1, 11)]
    # The step is re-derived from the last two pitches each time, as the reference does, so rounding accumulates alike.
    while pitches[-1] < 0.21:
        pitches.append(pitches[-1] + (pitches[-1] - pitches[-2]))
    rays = []
    # Scalar numpy calls per ray, as in the reference: vectorised trigonometry may round differently in the last bit.
    for pitch in pitches:
        for azimuth in np.arange(0, 360, 1):
            azimuth = np.deg2rad(azimuth)
            rays.append((np.cos(pitch) * np.cos(azimuth), np.cos(pitch) * np.sin(azimuth), np.sin(pitch)))
    out = np.array(rays, dtype=np.float32)
    out.flags.writeable = False
    return out


def ray_directions() -> np.ndarray:
    """Unit ray directions of the SparseOcc protocol.

    Returns:
        ``(14040, 3)`` float32: 39 pitches (-pi/2 + atan(k) for k = 1..10, then the last step repeated while the
        pitch is below 0.21 rad) x 360 azimuths (0..359 degrees), pitch-major.
    """
    return _directions().copy()


@njit(cache=True)
def _cast_one(labels, free, xo, yo, zo, xe, ye, ze):
    """Walk one ray through ``labels``; returns ``(distance in voxels, label, x, y, z)`` of the voxel it stops in.

    ``(xo, yo, zo)`` and ``(xe, ye, ze)`` are the float32 origin and end point in voxel coordinates, widened to
    double. Stops at the exit of the first occupied voxel (label other than ``free``), else at the exit of the last
    voxel inside the grid; a ray that never enters the grid gives ``(-1, labels[0, 0, 0])`` at voxel ``(0, 0, 0)``
    like the reference.
    """
    sx, sy, sz = labels.shape
    vx = int(xo)
    vy = int(yo)
    vz = int(zo)
    rx = xe - xo
    ry = ye - yo
    rz = ze - zo
    norm = math.sqrt(rx * rx + ry * ry + rz * rz)
    dx = rx / norm
    dy = ry / norm
    dz = rz / norm
    step_x = 1 if dx >= 0 else -1
    step_y = 1 if dy >= 0 else -1
    step_z = 1 if dz >= 0 else -1
    big = np.finfo(np.float64).max
    t_max_x = ((vx + (0 if step_x < 0 else 1)) - xo) / dx if dx != 0 else big
    t_max_y = ((vy + (0 if step_y < 0 else 1)) - yo) / dy if dy != 0 else big
    t_max_z = ((vz + (0 if step_z < 0 else 1)) - zo) / dz if dz != 0 else big
    t_delta_x = step_x / dx if dx != 0 else big
    t_delta_y = step_y / dy if dy != 0 else big
    t_delta_z = step_z / dz if dz != 0 else big

    was_inside = False
    last_d = -1.0
    last_label = labels[0, 0, 0]
    last_x = 0
    last_y = 0
    last_z = 0
    for _ in range(_MAX_STEP + 1):
        inside = 0 <= vx < sx and 0 <= vy < sy and 0 <= vz < sz
        if not inside and was_inside:
            break
        cx = vx
        cy = vy
        cz = vz
        # Tie order of the reference: X only when strictly smallest, then Y when strictly below Z, else Z.
        if t_max_x < t_max_y:
            if t_max_x < t_max_z:
                d = t_max_x
                vx += step_x
                t_max_x += t_delta_x
            else:
                d = t_max_z
                vz += step_z
                t_max_z += t_delta_z
        else:
            if t_max_y < t_max_z:
                d = t_max_y
                vy += step_y
                t_max_y += t_delta_y
            else:
                d = t_max_z
                vz += step_z
                t_max_z += t_delta_z
        if inside:
            was_inside = True
            label = labels[cx, cy, cz]
            if label != free:
                return d, label, cx, cy, cz
            last_d = d
            last_label = label
            last_x = cx
            last_y = cy
            last_z = cz
    return last_d, last_label, last_x, last_y, last_z


@njit(cache=True, parallel=True)
def _cast_kernel(labels, free, origins_vox, ends_vox, out_label, out_dist, out_voxel):
    """Cast every ray of every origin.

    Args:
        labels: ``(X, Y, Z)`` uint8 grid; ``free``: its free id.
        origins_vox: ``(T, 3)`` float32 origins in voxel coordinates.
        ends_vox: ``(T, R, 3)`` float32 ray end points (origin + unit direction) in voxel coordinates.
        out_label: ``(T * R,)`` uint8, receives the labels.
        out_dist: ``(T * R,)`` float32, receives the distances in voxels.
        out_voxel: ``(T * R, 3)`` int16, receives the index of the voxel each ray stops in.
    """
    n_origins = ends_vox.shape[0]
    n_rays = ends_vox.shape[1]
    for i in prange(n_origins * n_rays):
        t = i // n_rays
        r = i - t * n_rays
        d, label, x, y, z = _cast_one(
            labels,
            free,
            np.float64(origins_vox[t, 0]),
            np.float64(origins_vox[t, 1]),
            np.float64(origins_vox[t, 2]),
            np.float64(ends_vox[t, r, 0]),
            np.float64(ends_vox[t, r, 1]),
            np.float64(ends_vox[t, r, 2]),
        )
        out_label[i] = label
        out_dist[i] = np.float32(d)
        out_voxel[i, 0] = x
        out_voxel[i, 1] = y
        out_voxel[i, 2] = z


def _check_labels(labels: np.ndarray, name: str) -> np.ndarray:
    labels = np.asarray(labels)
    if labels.dtype != np.uint8:
        raise ValueError(f"{name} must be uint8, got {labels.dtype}")
    if labels.shape != _GRID_SHAPE:
        raise ValueError(f"{name} must have shape {_GRID_SHAPE}, got {labels.shape}")
    return np.ascontiguousarray(labels)


def _check_origins(origins: np.ndarray) -> np.ndarray:
    origins = np.asarray(origins)
    if origins.dtype.kind not in "iuf":
        raise ValueError(f"origins must be real numbers, got {origins.dtype}")
    if origins.ndim != 2 or origins.shape[1] != 3 or origins.shape[0] == 0:
        raise ValueError(f"origins must have shape (T, 3) with T >= 1, got {origins.shape}")
    origins = origins.astype(np.float64)
    if not np.isfinite(origins).all():
        raise ValueError("origins must be finite")
    return origins


def _to_voxels(points: np.ndarray) -> np.ndarray:
    # Float64 arithmetic rounded once to float32, the precision in which the reference hands points to its caster.
    return ((points - np.asarray(_LOWER)) / _VOXEL).astype(np.float32)


def cast_rays_exact(
    labels: np.ndarray, origins: np.ndarray, voxels: bool = False, space: LabelSpace = OCC3D_SPACE
) -> tuple[np.ndarray, np.ndarray] | tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cast the protocol's rays from each origin through one grid, bit for bit as SparseOcc's caster.

    Args:
        labels: ``(200, 200, 16)`` uint8 labels in (x, y, z) order; the space's free id (Occ3D 17, OpenOcc 16) is
            free, every other value occupied.
        origins: ``(T, 3)`` ray origins in ego metres (converted to float64).
        voxels: also return the voxel each ray stops in (the reference's ``coord_index``, where flow is read).
        space: the labels' label space (Occ3D or OpenOcc v2).

    Returns:
        ``(label, distance)``: ``(T * 14040,)`` uint8 label of the voxel each ray stops in and ``(T * 14040,)``
        float32 distance in metres to that voxel's exit, origin-major then pitch then azimuth; with ``voxels``, also
        ``(T * 14040, 3)`` int64 index of that voxel (``(0, 0, 0)`` for a ray that never enters the grid).

    Raises:
        ValueError: on a grid of another shape or dtype, origins not ``(T, 3)`` finite numbers, or a label space
            without RayIoU.
    """
    free = _protocol(space)[0]
    labels = _check_labels(labels, "labels")
    origins = _check_origins(origins)
    dirs = _directions().astype(np.float64)
    # End points are origin + direction summed in float64 before the shift and scale, as in the reference.
    ends = _to_voxels(dirs[None, :, :] + origins[:, None, :])
    n = ends.shape[0] * ends.shape[1]
    out_label = np.empty(n, dtype=np.uint8)
    out_dist = np.empty(n, dtype=np.float32)
    out_voxel = np.empty((n, 3), dtype=np.int16)
    # The kernel runs on the caller's torch thread count. numba's OpenMP layer shares torch's libgomp, and its first
    # launch after torch has run a parallel region sets the process's count to numba's own (numba issue 9387): the
    # caller's count is put back, and numba's own, even when the kernel raises.
    threads, numba_threads = torch.get_num_threads(), numba.get_num_threads()
    numba.set_num_threads(min(threads, numba.config.NUMBA_NUM_THREADS))
    try:
        _cast_kernel(labels, free, _to_voxels(origins), ends, out_label, out_dist, out_voxel)
    finally:
        numba.set_num_threads(numba_threads)
        torch.set_num_threads(threads)
    if voxels:
        return out_label, out_dist * np.float32(_VOXEL), out_voxel.astype(np.int64)
    return out_label, out_dist * np.float32(_VOXEL)


def rayiou(
    gts: Sequence[np.ndarray] | np.ndarray,
    preds: Sequence[np.ndarray] | np.ndarray,
    origins: Sequence[np.ndarray] | np.ndarray,
    gt_flows: Sequence[np.ndarray] | np.ndarray | None = None,
    pred_flows: Sequence[np.ndarray] | np.ndarray | None = None,
    space: LabelSpace = OCC3D_SPACE,
) -> dict:
    """RayIoU over a set of frames, as SparseOcc's ``main_rayiou``; with flows, also mAVE and OccScore as the CVPR
    2024 challenge's ``ray_metrics.main``.

    Counts are summed over all rays of all frames whose ground-truth ray stops on something other than free space;
    a ray counts as a true positive at threshold ``t`` when both rays stop on the same label at depths differing by
    less than ``t`` metres. IoU per class is ``TP / (GT + PRED - TP)`` (NaN for a class absent from both). Each
    moving class's velocity errors are summed per frame over its true positives at :data:`AVE_THRESHOLD`, in float32
    as the reference sums them.

    Args:
        gts: ``(N, 200, 200, 16)`` uint8 ground-truth grids (an array or a sequence of ``(200, 200, 16)`` grids).
        preds: predicted grids, same layout.
        origins: ``N`` arrays of ``(T_i, 3)`` ray origins in each frame's ego metres (or one ``(N, T, 3)`` array).
        gt_flows, pred_flows: ``N`` ``(200, 200, 16, 2)`` float occupancy flows (m/s), both or neither.
        space: the label space of the grids (Occ3D: 17 classes averaged, 17 = free; OpenOcc v2: 16, 16 = free).

    Returns:
        ``rayiou`` (nanmean over the 3 thresholds x the ``K - 1`` classes but free), ``rayiou@1``, ``rayiou@2``,
        ``rayiou@4`` (nanmean over the classes), ``per_class`` ``{threshold: list of K - 1 floats}`` and ``counts``
        ``{"gt": list of K, "pred": list of K, "tp": {threshold: list of K}}`` with the last index free; thresholds
        are the ints of :data:`RAYIOU_THRESHOLDS`. With flows, also ``mave``, ``occ_score``, ``ave_per_class``
        (``K - 1`` floats, NaN for classes that do not move or have no true positive) and in ``counts`` ``ave_sum``
        (``K`` floats) and ``ave_count`` (``K`` ints).

    Raises:
        ValueError: on mismatched frame counts or a grid, flow or origin array of the wrong shape or dtype.
    """
    if not (len(gts) == len(preds) == len(origins)):
        raise ValueError(f"gts, preds and origins differ in length: {len(gts)}, {len(preds)}, {len(origins)}")
    with_flow = gt_flows is not None or pred_flows is not None
    if with_flow and (gt_flows is None or pred_flows is None or not len(gt_flows) == len(pred_flows) == len(gts)):
        raise ValueError("gt_flows and pred_flows must both be given, one per frame")
    counts = RayCounts(space)
    for i, (gt, pred, org) in enumerate(zip(gts, preds, origins, strict=True)):
        flows = (gt_flows[i], pred_flows[i]) if with_flow else ()
        counts.add_frame(cast_frame(gt, pred, org, space), *flows)
    return counts.compute(flow=with_flow)


@dataclass(frozen=True)
class FrameRays:
    """One frame's protocol rays cast through its ground truth and its prediction, the ``R`` rays kept that the
    protocol counts: those whose ground-truth ray stops on something other than free space.

    Attributes:
        gt_label, pred_label: ``(R,)`` uint8 label of the voxel each ray stops in.
        gt_voxel, pred_voxel: ``(R, 3)`` int64 index of that voxel (where flow and instance ids are read).
        depth_error: ``(R,)`` float32 absolute difference of the two stopping depths, metres.
    """

    gt_label: np.ndarray
    pred_label: np.ndarray
    gt_voxel: np.ndarray
    pred_voxel: np.ndarray
    depth_error: np.ndarray


def cast_frame(gt: np.ndarray, pred: np.ndarray, origins: np.ndarray, space: LabelSpace = OCC3D_SPACE) -> FrameRays:
    """Cast the protocol's rays from ``origins`` (``(T, 3)`` ego metres) through a frame's ``(200, 200, 16)`` uint8
    ground truth and prediction, once for every score read on them (RayIoU, mAVE, RayPQ)."""
    free = _protocol(space)[0]
    gt_label, gt_dist, gt_voxel = cast_rays_exact(_check_labels(gt, "gt"), origins, voxels=True, space=space)
    pred_label, pred_dist, pred_voxel = cast_rays_exact(_check_labels(pred, "pred"), origins, voxels=True,
                                                        space=space)  # fmt: skip
    valid = gt_label != free
    return FrameRays(gt_label[valid], pred_label[valid], gt_voxel[valid], pred_voxel[valid],
                     np.abs(pred_dist[valid] - gt_dist[valid]))  # fmt: skip


class RayCounts:
    """RayIoU's ray counts, and for flow the velocity errors of mAVE, summed over frames (the scores are ratios of
    sums, so frames can be counted apart, by threads or ranks, and added).

    Attributes:
        gt, pred: ``(K,)`` int64 counted rays per ground-truth / predicted class (the last = free).
        tp: ``(3, K)`` int64 true positives per threshold of :data:`RAYIOU_THRESHOLDS`.
        ave_sum, ave_count: ``(K,)`` float64 summed velocity errors (m/s) and int64 true-positive rays at
            :data:`AVE_THRESHOLD` per class, over the frames counted with flow.
        frames, flow_frames: frames counted, and of them those counted with flow.
    """

    #: The summed arrays (what merging and reducing add up).
    _SUMS = ("gt", "pred", "tp", "ave_sum", "ave_count")

    def __init__(self, space: LabelSpace = OCC3D_SPACE) -> None:
        self.space = space
        free, _, self._flow_ids = _protocol(space)
        self.gt = np.zeros(free + 1, dtype=np.int64)
        self.pred = np.zeros(free + 1, dtype=np.int64)
        self.tp = np.zeros((len(RAYIOU_THRESHOLDS), free + 1), dtype=np.int64)
        self.ave_sum = np.zeros(free + 1, dtype=np.float64)
        self.ave_count = np.zeros(free + 1, dtype=np.int64)
        self.frames = self.flow_frames = 0

    def add_frame(self, rays: FrameRays, gt_flow: np.ndarray | None = None, pred_flow: np.ndarray | None = None
                  ) -> None:  # fmt: skip
        """Count one frame's rays; with its ``(200, 200, 16, 2)`` ground-truth and predicted flows (m/s), both or
        neither, also its velocity errors."""
        if (gt_flow is None) != (pred_flow is None):
            raise ValueError("gt_flow and pred_flow must both be given or both be None")
        width = self.gt.shape[0]
        self.gt += np.bincount(rays.gt_label, minlength=256)[:width]
        self.pred += np.bincount(rays.pred_label, minlength=256)[:width]
        same = rays.gt_label == rays.pred_label
        for j, threshold in enumerate(RAYIOU_THRESHOLDS):
            self.tp[j] += np.bincount(rays.gt_label[same & (rays.depth_error < threshold)], minlength=256)[:width]
        self.frames += 1
        if gt_flow is None:
            return
        gt_velocity = _ray_flow(gt_flow, rays.gt_voxel, "gt_flows")
        pred_velocity = _ray_flow(pred_flow, rays.pred_voxel, "pred_flows")
        tp = same & (rays.depth_error < AVE_THRESHOLD)
        for c in self._flow_ids:
            selected = tp & (rays.gt_label == c)
            if selected.any():
                # float32 norms summed in float32 per frame and class, then added in float64, as the reference.
                errors = np.linalg.norm(gt_velocity[selected] - pred_velocity[selected], axis=1)
                self.ave_sum[c] += np.sum(errors)
                self.ave_count[c] += errors.shape[0]
        self.flow_frames += 1

    def merge(self, other: RayCounts) -> None:
        """Add the counts of other frames (same label space)."""
        if other.space != self.space:
            raise ValueError(f"cannot merge {other.space.name} ray counts into {self.space.name} ones")
        for name in self._SUMS:
            setattr(self, name, getattr(self, name) + getattr(other, name))
        self.frames += other.frames
        self.flow_frames += other.flow_frames

    def reduce(self, reduce: Callable[[np.ndarray], np.ndarray]) -> None:
        """Replace every count by ``reduce(count)``: a sum over distributed ranks, which every rank calls alike."""
        for name in self._SUMS:
            setattr(self, name, np.asarray(reduce(getattr(self, name))).astype(getattr(self, name).dtype))
        self.frames, self.flow_frames = (int(n) for n in reduce(np.array([self.frames, self.flow_frames])))

    def compute(self, flow: bool | None = None) -> dict:
        """:func:`rayiou`'s scores of the frames counted; with ``flow`` (default: when a frame was counted with
        flow) also mAVE and OccScore."""
        flow = self.flow_frames > 0 if flow is None else flow
        extra = (self.ave_sum, self.ave_count) if flow else ()
        return rayiou_from_counts(self.gt, self.pred, self.tp, *extra, space=self.space)

    def scores(self) -> dict[str, float]:
        """The headline scores: ``rayiou`` and ``rayiou@1/2/4`` and, when a frame was counted with flow, ``mave`` and
        ``occ_score`` (NaN where undefined)."""
        result = self.compute()
        flow = ("mave", "occ_score") if self.flow_frames else ()
        return {key: float(result[key]) for key in ("rayiou", *(f"rayiou@{t}" for t in RAYIOU_THRESHOLDS), *flow)}


def _ray_flow(flow: np.ndarray, voxel: np.ndarray, name: str) -> np.ndarray:
    """``(R, 2)`` float32 flow of the voxels ``(R, 3)`` the rays stop in."""
    flow = np.asarray(flow)
    if flow.shape != (*_GRID_SHAPE, 2) or flow.dtype.kind != "f":
        raise ValueError(f"{name} must be float {(*_GRID_SHAPE, 2)} arrays, got {flow.dtype} {flow.shape}")
    return flow[voxel[:, 0], voxel[:, 1], voxel[:, 2]].astype(np.float32)


def rayiou_from_counts(
    gt_cnt: np.ndarray,
    pred_cnt: np.ndarray,
    tp_cnt: np.ndarray,
    ave_sum: np.ndarray | None = None,
    ave_count: np.ndarray | None = None,
    space: LabelSpace = OCC3D_SPACE,
) -> dict:
    """RayIoU (and with velocity errors mAVE and OccScore) from ray counts summed over frames (the metrics are
    ratios of sums, so frames can be counted apart).

    Args:
        gt_cnt, pred_cnt: ``(K,)`` int64 valid rays per GT / predicted class of the ``K`` classes of ``space``
            (the last = free).
        tp_cnt: ``(3, K)`` int64 true positives per threshold of :data:`RAYIOU_THRESHOLDS`.
        ave_sum, ave_count: ``(K,)`` summed velocity errors (m/s) and their true-positive rays per class at
            :data:`AVE_THRESHOLD`; None: no flow.
        space: the label space counted (Occ3D or OpenOcc v2).

    Returns:
        The dict of :func:`rayiou`.
    """
    _, num_classes, flow_ids = _protocol(space)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = (tp_cnt / (gt_cnt + pred_cnt - tp_cnt).astype(np.float64))[:, :num_classes]
    keys = list(RAYIOU_THRESHOLDS)
    result: dict = {"rayiou": _nanmean(iou)}
    for j, key in enumerate(keys):
        result[f"rayiou@{key}"] = _nanmean(iou[j])
    result["per_class"] = {key: [float(v) for v in iou[j]] for j, key in enumerate(keys)}
    result["counts"] = {
        "gt": np.asarray(gt_cnt).tolist(),
        "pred": np.asarray(pred_cnt).tolist(),
        "tp": {key: np.asarray(tp_cnt[j]).tolist() for j, key in enumerate(keys)},
    }
    if ave_sum is not None:
        ave = np.full(num_classes, np.nan)
        for c in flow_ids:
            if ave_count[c]:
                ave[c] = ave_sum[c] / ave_count[c]
        result["mave"] = _nanmean(ave)
        result["occ_score"] = occ_score(result["rayiou"], result["mave"])
        result["ave_per_class"] = [float(v) for v in ave]
        result["counts"]["ave_sum"] = [float(v) for v in ave_sum]
        result["counts"]["ave_count"] = np.asarray(ave_count).tolist()
    return result


def occ_score(rayiou: float, mave: float) -> float:
    """The challenge's ``0.9 RayIoU + 0.1 max(1 - mAVE, 0)`` (RayIoU as a fraction); NaN when mAVE is (no true
    positive of a moving class), as the reference's ``max(nan, 0.0)`` gives."""
    if math.isnan(mave):
        return float("nan")
    return 0.9 * rayiou + 0.1 * max(1.0 - mave, 0.0)


def _nanmean(values: np.ndarray) -> float:
    # All-NaN input (no valid ray at all) gives NaN without numpy's RuntimeWarning.
    if np.isnan(values).all():
        return float("nan")
    return float(np.nanmean(values))
