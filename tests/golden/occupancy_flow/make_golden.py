"""Golden reference data for mAVE and OccScore of the CVPR 2024 Occupancy and Flow challenge.

Independent numpy/scipy transcription of the challenge's ray metric (OpenDriveLab/OccNet, branch ``challenge``,
commit 2bb8fe6, ``projects/mmdet3d_plugin/datasets/ray_metrics.py`` with the CUDA ray caster
``tools/ray_iou/lib/dvr/dvr.cu``). It reads four frames of ``../occ3d_metrics`` (GT, prediction, LiDAR
origins), builds synthetic flow fields, casts the RayIoU query rays, and writes next to itself:

- ``inputs.npz``: the semantics, origins and flow fields evaluated (see README.md for the keys);
- ``reference.json``: RayIoU, per-class AVE, mAVE and OccScore, with every count behind them.

Before anything is written, the ray caster is checked bit for bit against the official per-ray labels and
distances in ``../occ3d_metrics/rayiou_rays_per_frame.npz``, and the ray counting against the official
``rayiou_sparseocc.json``. Usage: ``python make_golden.py`` (no arguments; fixed seed; byte-identical reruns).
"""

from __future__ import annotations

import io
import json
import math
import sys
import time
import warnings
import zipfile
from pathlib import Path

import numpy as np
from scipy import ndimage

HERE = Path(__file__).resolve().parent
OCC3D = HERE.parent / "occ3d_metrics"

# Occ3D-nuScenes label order; the challenge itself uses the 17-class OpenOcc list, and the reference code looks
# classes up by name, so running it with this list is a change of class list only.
CLASS_NAMES = [
    "others", "barrier", "bicycle", "bus", "car", "construction_vehicle", "motorcycle", "pedestrian",
    "traffic_cone", "trailer", "truck", "driveable_surface", "other_flat", "sidewalk", "terrain", "manmade",
    "vegetation", "free",
]  # fmt: skip
FLOW_CLASS_NAMES = ["car", "truck", "trailer", "bus", "construction_vehicle", "bicycle", "motorcycle", "pedestrian"]
FREE = len(CLASS_NAMES) - 1
FLOW_IDS = np.array([CLASS_NAMES.index(n) for n in FLOW_CLASS_NAMES])
THRESHOLDS = [1, 2, 4]
AVE_THRESHOLD_INDEX = 1  # the reference reports AVE at the 2 m threshold

FRAMES = [0, 5, 10, 15]  # indices into the 20 occ3d_metrics frames
SEED = 20240617
GRID = (200, 200, 16)
PC_MIN = np.array([-40.0, -40.0, -1.0])
VOXEL = np.float32(0.4)  # the reference divides and multiplies by float32 tensors holding 0.4
MAX_STEP = 1000  # dvr.cu loop bound
DBL_MAX = np.finfo(np.float64).max
# Velocities are uniform in [-SPEED, SPEED] m/s per axis. 2 m/s keeps the main scenario's mAVE below 1, so its
# OccScore exercises the 1 - mAVE term, while the all-zero prediction's mAVE lands above 1 (the clamp at 0).
SPEED = 2.0
FLOW_NOISE_SIGMA = 0.5


# ---------------------------------------------------------------------------------------------------------------
# Rays and ray casting
# ---------------------------------------------------------------------------------------------------------------


def lidar_ray_directions() -> np.ndarray:
    """Unit query directions as ``generate_lidar_rays`` builds them: float32 [14040, 3], pitch-major.

    Trig is evaluated one scalar at a time because the reference does so; numpy's vectorised float64 cos/sin
    may take SIMD code paths that differ from the scalar ones in the last bit.
    """
    pitches = [-(math.pi / 2 - math.atan(k)) for k in range(1, 11)]
    while pitches[-1] < 0.21:  # extend with the last spacing up to the nuScenes LiDAR's upper field of view
        pitches.append(pitches[-1] + (pitches[-1] - pitches[-2]))
    dirs = []
    for pitch in pitches:
        for azimuth_deg in np.arange(0, 360, 1):
            azimuth = np.deg2rad(azimuth_deg)
            cos_pitch = np.cos(pitch)
            dirs.append((cos_pitch * np.cos(azimuth), cos_pitch * np.sin(azimuth), np.sin(pitch)))
    return np.array(dirs, dtype=np.float32)


def cast_rays(labels: np.ndarray, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cast every direction from every origin through ``labels`` the way ``dvr.render_forward`` does.

    Returns the stop voxel (``coord_index``) as int64 [T*N, 3] in (x, y, z) order and the returned distance in
    metres as float32 [T*N], origin-major. The stop voxel is the first occupied voxel (label != free) along the
    ray, else the last voxel inside the grid; the distance is that voxel's exit distance. A ray that never
    enters the grid would keep the kernel's initial values: voxel (0, 0, 0) and distance -1 (times 0.4).

    All rays advance together, one Amanatides-Woo step per loop iteration, so the step counter is shared and the
    kernel's ``step > MAX_STEP`` bound applies to all of them at once. Rays that are finished are dropped.
    """
    occupied = labels != FREE  # the reference sets sigma = 1 below free, 0 at free, and keeps labels above free
    n_origins, n_dirs = len(origins), len(dirs)
    # Voxel coordinates are computed in float64 (float64 origins meet float32 tensors) and cast to float32,
    # which is what the kernel receives; it widens them back to double.
    origin_vox = ((origins - PC_MIN) / np.float64(VOXEL)).astype(np.float32).astype(np.float64)
    ends = dirs.astype(np.float64)[None, :, :] + origins[:, None, :]
    end_vox = ((ends - PC_MIN) / np.float64(VOXEL)).astype(np.float32).astype(np.float64)

    o = np.repeat(origin_vox, n_dirs, axis=0).T  # [3, M]
    e = end_vox.reshape(-1, 3).T
    m = n_origins * n_dirs
    r = e - o
    length = np.sqrt(r[0] * r[0] + r[1] * r[1] + r[2] * r[2])  # same evaluation order as the kernel
    d = r / length
    step = np.where(d >= 0, 1, -1)
    voxel = np.trunc(o).astype(np.int64)  # C int() truncates toward zero
    boundary = (voxel + (step > 0)).astype(np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        t_max = np.where(d != 0, (boundary - o) / d, DBL_MAX)
        t_delta = np.where(d != 0, step / d, DBL_MAX)

    stop = np.zeros((m, 3), dtype=np.int64)
    dist = np.full(m, -1.0, dtype=np.float64)

    # Per-ray state of the rays still marching; `ids` maps them back to their output slot.
    ids = np.arange(m)
    last = np.zeros((3, m), dtype=np.int64)  # last voxel seen inside the grid
    last_d = np.full(m, -1.0)
    was_inside = np.zeros(m, dtype=bool)
    size = np.array(GRID)[:, None]
    n_steps = 0
    while ids.size:
        inside = np.all((voxel >= 0) & (voxel < size), axis=0)
        # A ray that has left the grid never comes back: it keeps the last in-grid voxel (all free).
        left = was_inside & ~inside
        # The kernel's tie order: X only if strictly smallest, else Y if strictly below Z, else Z.
        x_lt_y = t_max[0] < t_max[1]
        axis = np.where(x_lt_y & (t_max[0] < t_max[2]), 0, np.where(~x_lt_y & (t_max[1] < t_max[2]), 1, 2))
        cols = np.arange(ids.size)
        exit_d = t_max[axis, cols]
        clipped = np.minimum(np.maximum(voxel, 0), size - 1)
        hit = inside & occupied[clipped[0], clipped[1], clipped[2]]
        last = np.where(inside, voxel, last)
        last_d = np.where(inside, exit_d, last_d)
        was_inside |= inside
        voxel[axis, cols] += step[axis, cols]
        t_max[axis, cols] += t_delta[axis, cols]
        n_steps += 1

        done = left | hit
        if n_steps > MAX_STEP:
            done[:] = True
        finished = done & was_inside  # rays that never entered keep (0, 0, 0) and -1
        stop[ids[finished]] = last[:, finished].T
        dist[ids[finished]] = last_d[finished]
        keep = ~done
        ids, voxel, step, t_max, t_delta = ids[keep], voxel[:, keep], step[:, keep], t_max[:, keep], t_delta[:, keep]
        last, last_d, was_inside = last[:, keep], last_d[keep], was_inside[keep]

    # The kernel writes the double distance into a float32 tensor; the reference then multiplies that tensor by
    # the voxel size in float32.
    metres = dist.astype(np.float32) * VOXEL
    return stop, metres


def sample_rays(
    labels: np.ndarray, flow: np.ndarray, origins: np.ndarray, dirs: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Per-ray records as ``process_one_sample`` returns them, plus the stop voxels.

    The records are float32 [T*N, 4]: label (cast to float32), distance in metres, flow x, flow y, all looked up
    at the stop voxel.
    """
    stop, metres = cast_rays(labels, origins, dirs)
    x, y, z = stop.T
    label = labels[x, y, z]
    pcd = np.concatenate([label.astype(np.float32)[:, None], metres[:, None], flow[x, y, z]], axis=1)
    assert pcd.dtype == np.float32
    return pcd, stop


# ---------------------------------------------------------------------------------------------------------------
# Metric
# ---------------------------------------------------------------------------------------------------------------


def count_rays(
    pcd_pred_list: list[np.ndarray], pcd_gt_list: list[np.ndarray], tp_only: bool = True, flow_dtype=np.float32
) -> dict:
    """Accumulate the counts of ``calc_metrics`` over frames (rays already restricted to valid GT rays).

    ``tp_only=False`` instead follows the standalone ``tools/ray_iou/metric.py``, which adds the flow error of
    ALL valid rays for every flow class that has a true positive in the frame (kept only as a diagnostic).
    ``flow_dtype=np.float64`` computes the flow errors and their sums in float64 (diagnostic only).

    Dtypes follow the reference: records are float32, so the per-ray flow error is a float32 norm, its per
    (frame, threshold, class) sum is a float32 pairwise sum, and that float32 total is added to a float64
    accumulator.
    """
    n_t, n_c = len(THRESHOLDS), len(CLASS_NAMES)
    gt_cnt = np.zeros(n_c)
    pred_cnt = np.zeros(n_c)
    tp_cnt = np.zeros((n_t, n_c))
    ave = np.zeros((n_t, n_c))
    ave[:, [c not in FLOW_CLASS_NAMES for c in CLASS_NAMES]] = np.nan
    ave_count = np.zeros((n_t, n_c))
    for pred, gt in zip(pcd_pred_list, pcd_gt_list, strict=True):
        depth_ok_by_t = [np.abs(pred[:, 1] - gt[:, 1]) < t for t in THRESHOLDS]  # float32 difference
        for ci, name in enumerate(CLASS_NAMES):
            in_pred = pred[:, 0] == ci
            in_gt = gt[:, 0] == ci
            gt_cnt[ci] += in_gt.sum()
            pred_cnt[ci] += in_pred.sum()
            for ti, depth_ok in enumerate(depth_ok_by_t):
                tp = in_gt & in_pred & depth_ok
                n_tp = tp.sum()
                tp_cnt[ti, ci] += n_tp
                if name in FLOW_CLASS_NAMES and n_tp > 0:
                    rows = tp if tp_only else slice(None)
                    diff = gt[rows, 2:4].astype(flow_dtype) - pred[rows, 2:4].astype(flow_dtype)
                    err = np.linalg.norm(diff, axis=1)
                    ave[ti, ci] += np.sum(err)
                    ave_count[ti, ci] += err.shape[0]
    return {"gt_cnt": gt_cnt, "pred_cnt": pred_cnt, "tp_cnt": tp_cnt, "ave": ave, "ave_count": ave_count}


def summarise(counts: dict) -> dict:
    """RayIoU, AVE, mAVE and OccScore from the counts, with the reference's NaN handling (0/0 -> NaN)."""
    with np.errstate(divide="ignore", invalid="ignore"), warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # nanmean of an all-NaN vector
        iou = [(counts["tp_cnt"][ti] / (counts["gt_cnt"] + counts["pred_cnt"] - counts["tp_cnt"][ti]))[:-1]
               for ti in range(len(THRESHOLDS))]  # fmt: skip
        ave = counts["ave"][AVE_THRESHOLD_INDEX][:-1] / counts["ave_count"][AVE_THRESHOLD_INDEX][:-1]
        rayiou = np.nanmean(iou)
        mave = np.nanmean(ave)
        rayiou_at = {t: np.nanmean(iou[ti]) for ti, t in enumerate(THRESHOLDS)}
    # Python's max keeps its first argument when the comparison is False, so a NaN mAVE gives a NaN score.
    occ_score = rayiou * 0.9 + max(1 - mave, 0.0) * 0.1
    return {"iou": iou, "ave": ave, "rayiou": rayiou, "rayiou_at": rayiou_at, "mave": mave, "occ_score": occ_score}


def evaluate(
    pcd_pred_list: list[np.ndarray], pcd_gt_list: list[np.ndarray], tp_only: bool = True, flow_dtype=np.float32
) -> dict:
    """``main`` of the reference without printing: keep valid rays (GT label != free), count, summarise."""
    preds, gts = [], []
    for pred, gt in zip(pcd_pred_list, pcd_gt_list, strict=True):
        valid = gt[:, 0].astype(np.int32) != FREE
        preds.append(pred[valid])
        gts.append(gt[valid])
    counts = count_rays(preds, gts, tp_only=tp_only, flow_dtype=flow_dtype)
    out = summarise(counts)
    out["counts"] = counts
    out["n_valid_rays"] = [int(len(g)) for g in gts]
    return out


# ---------------------------------------------------------------------------------------------------------------
# Inputs
# ---------------------------------------------------------------------------------------------------------------

CONNECTIVITY = ndimage.generate_binary_structure(3, 3)  # 26-connectivity


def make_gt_flow(sem: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """One random velocity per 26-connected component of flow-class voxels (all 8 classes pooled); a quarter of
    the components (n // 4, chosen at random) exactly static; 0 on every other voxel."""
    flow = np.zeros((*GRID, 2), dtype=np.float32)
    comp, n = ndimage.label(np.isin(sem, FLOW_IDS), structure=CONNECTIVITY)
    vel = rng.uniform(-SPEED, SPEED, size=(n + 1, 2)).astype(np.float32)
    vel[0] = 0.0  # background
    vel[1 + rng.choice(n, size=n // 4, replace=False)] = 0.0
    flow[:] = vel[comp]
    return flow


def make_pred_flow(pred: np.ndarray, flow_gt: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Noisy GT flow on predicted flow-class voxels, a fifth of predicted components wrong, plus decoys.

    Predicted flow-class voxels get the GT flow at the same voxel plus Gaussian noise; then a fifth of the
    26-connected components of predicted flow-class voxels get one random velocity each instead. Decoys (flow
    uniform in [-8, 8] m/s on 1 % of predicted non-flow-class occupied voxels and on 0.5 % of predicted free
    voxels) cannot reach the TP-only metric; ``main`` asserts so.
    """
    flow = np.zeros((*GRID, 2), dtype=np.float32)
    is_flow = np.isin(pred, FLOW_IDS)
    noise = rng.normal(0.0, FLOW_NOISE_SIGMA, size=(int(is_flow.sum()), 2))
    flow[is_flow] = (flow_gt[is_flow] + noise).astype(np.float32)
    comp, n = ndimage.label(is_flow, structure=CONNECTIVITY)
    wrong = 1 + rng.choice(n, size=n // 5, replace=False)
    wrong_vel = rng.uniform(-SPEED, SPEED, size=(len(wrong), 2)).astype(np.float32)
    for c, v in zip(wrong, wrong_vel, strict=True):
        flow[comp == c] = v
    for decoy, share in ((~is_flow & (pred != FREE), 0.01), (pred == FREE, 0.005)):
        idx = np.flatnonzero(decoy)
        pick = np.sort(rng.choice(idx, size=int(len(idx) * share), replace=False))
        flow.reshape(-1, 2)[pick] = rng.uniform(-8.0, 8.0, size=(len(pick), 2)).astype(np.float32)
    return flow


def decoy_mask(pred: np.ndarray) -> np.ndarray:
    """Voxels whose predicted flow must not matter: predicted non-flow-class or free."""
    return ~np.isin(pred, FLOW_IDS)


# ---------------------------------------------------------------------------------------------------------------
# Output helpers
# ---------------------------------------------------------------------------------------------------------------


def to_json(x):
    """Python floats/ints/lists for JSON, NaN as null."""
    if isinstance(x, dict):
        return {str(k): to_json(v) for k, v in x.items()}
    if isinstance(x, (list, tuple, np.ndarray)):
        return [to_json(v) for v in x]
    if isinstance(x, (bool, np.bool_)):
        return bool(x)
    if isinstance(x, (int, np.integer)):
        return int(x)
    x = float(x)
    return None if math.isnan(x) else x


def scenario_json(res: dict, with_counts: bool = True) -> dict:
    """The reference.json block of one evaluation."""
    ave = res["ave"]
    out = {
        "per_class_iou": {str(t): res["iou"][ti] for ti, t in enumerate(THRESHOLDS)},
        "rayiou": res["rayiou"],
        **{f"rayiou@{t}": v for t, v in res["rayiou_at"].items()},
        "ave_per_class": ave,
        "ave_per_flow_class": {n: ave[CLASS_NAMES.index(n)] for n in FLOW_CLASS_NAMES},
        "mave": res["mave"],
        "occ_score": res["occ_score"],
        "n_valid_rays_per_frame": res["n_valid_rays"],
    }
    if with_counts:
        c = res["counts"]
        out["counts"] = {
            "gt_cnt": c["gt_cnt"],
            "pred_cnt": c["pred_cnt"],
            "tp_cnt": {str(t): c["tp_cnt"][ti] for ti, t in enumerate(THRESHOLDS)},
            "ave_sum": {str(t): c["ave"][ti] for ti, t in enumerate(THRESHOLDS)},
            "ave_count": {str(t): c["ave_count"][ti] for ti, t in enumerate(THRESHOLDS)},
        }
    return to_json(out)


def write_npz(path: Path, arrays: dict) -> None:
    """``np.savez_compressed``, then every member re-stored with a fixed timestamp so reruns are byte-identical."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    buf.seek(0)
    out = io.BytesIO()
    with zipfile.ZipFile(buf) as src, zipfile.ZipFile(out, "w", compression=zipfile.ZIP_DEFLATED) as dst:
        for name in src.namelist():
            info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            dst.writestr(info, src.read(name))
    path.write_bytes(out.getvalue())


def same(a: dict, b: dict) -> bool:
    """Bit equality of two evaluations' counts (NaN equal to NaN)."""
    return all(np.array_equal(a["counts"][k], b["counts"][k], equal_nan=True) for k in a["counts"])


# ---------------------------------------------------------------------------------------------------------------


def main() -> None:
    """Build the inputs, check the caster against the official rays, evaluate, write the two files."""
    t0 = time.perf_counter()
    frames = np.load(OCC3D / "all_frames.npz")
    lidar = np.load(OCC3D / "lidar_origins.npz")
    official = np.load(OCC3D / "rayiou_rays_per_frame.npz")
    official_summary = json.loads((OCC3D / "rayiou_sparseocc.json").read_text())

    # The counting transcription must reproduce the official RayIoU of all 20 frames from the official rays.
    n_all = len(lidar["n_origins"])
    recs = {
        kind: [
            np.stack([official[f"{kind}_label_{i:02d}"].astype(np.float32), official[f"{kind}_dist_{i:02d}"],
                      np.zeros_like(official[f"{kind}_dist_{i:02d}"]), np.zeros_like(official[f"{kind}_dist_{i:02d}"])],
                     axis=1)
            for i in range(n_all)
        ]
        for kind in ("pred", "gt")
    }  # fmt: skip
    res20 = evaluate(recs["pred"], recs["gt"])
    ref20 = official_summary
    assert res20["rayiou"] == ref20["main_rayiou_return"]["RayIoU"]
    for ti, t in enumerate(THRESHOLDS):
        assert res20["rayiou_at"][t] == ref20["main_rayiou_return"][f"RayIoU@{t}"]
        assert to_json(res20["iou"][ti]) == ref20["per_class_iou"][f"@{t}"]
        assert to_json(res20["counts"]["tp_cnt"][ti]) == ref20["counts"]["tp_cnt"][f"@{t}"]
    assert to_json(res20["counts"]["gt_cnt"]) == ref20["counts"]["gt_cnt"]
    assert to_json(res20["counts"]["pred_cnt"]) == ref20["counts"]["pred_cnt"]
    assert res20["n_valid_rays"] == ref20["n_valid_rays_per_frame"]

    rng = np.random.default_rng(SEED)
    sem = frames["semantics"][FRAMES]
    pred = frames["pred"][FRAMES]
    origins = lidar["origins"][FRAMES]
    n_origins = lidar["n_origins"][FRAMES]
    flow_gt = np.stack([make_gt_flow(s, rng) for s in sem])
    flow_pred = np.stack([make_pred_flow(p, f, rng) for p, f in zip(pred, flow_gt, strict=True)])

    # Edge case: frame slot 0 with every predicted flow-class voxel relabelled "others", so no flow class can
    # have a true positive and mAVE is the mean of an empty set.
    edge_slot = 0
    edge_pred = np.where(np.isin(pred[edge_slot], FLOW_IDS), np.uint8(0), pred[edge_slot]).astype(np.uint8)

    dirs = lidar_ray_directions()
    t_cast = time.perf_counter()
    gt_pcd, pred_pcd, pred_pcd_zero, pred_pcd_nodecoy = [], [], [], []
    for k, fi in enumerate(FRAMES):
        org = origins[k, : n_origins[k]]
        g, g_stop = sample_rays(sem[k], flow_gt[k], org, dirs)
        p, p_stop = sample_rays(pred[k], flow_pred[k], org, dirs)
        # Bit-for-bit agreement with the official caster, for labels (also as looked up at our stop voxel) and
        # distances.
        for kind, rec, stop, grid in (("gt", g, g_stop, sem[k]), ("pred", p, p_stop, pred[k])):
            ref_label = official[f"{kind}_label_{fi:02d}"]
            ref_dist = official[f"{kind}_dist_{fi:02d}"]
            assert np.array_equal(grid[stop[:, 0], stop[:, 1], stop[:, 2]], ref_label), (kind, fi)
            assert np.array_equal(rec[:, 0], ref_label.astype(np.float32)), (kind, fi)
            assert np.array_equal(rec[:, 1], ref_dist), (kind, fi)
        gt_pcd.append(g)
        pred_pcd.append(p)
        p0 = p.copy()
        p0[:, 2:4] = 0.0
        pred_pcd_zero.append(p0)
        # Same rays with the decoy flows removed, to show they cannot matter.
        clean = np.where(decoy_mask(pred[k])[..., None], np.float32(0.0), flow_pred[k])
        pn = p.copy()
        pn[:, 2:4] = clean[p_stop[:, 0], p_stop[:, 1], p_stop[:, 2]]
        pred_pcd_nodecoy.append(pn)
    edge_pcd, _ = sample_rays(edge_pred, flow_pred[edge_slot], origins[edge_slot, : n_origins[edge_slot]], dirs)
    t_cast = time.perf_counter() - t_cast

    main_res = evaluate(pred_pcd, gt_pcd)
    zero_res = evaluate(pred_pcd_zero, gt_pcd)
    assert same(main_res, evaluate(pred_pcd_nodecoy, gt_pcd)), "decoy flows changed the result"
    edge_res = evaluate([edge_pcd], [gt_pcd[edge_slot]])
    perfect_res = evaluate(gt_pcd, gt_pcd)
    assert math.isnan(edge_res["mave"]) and math.isnan(edge_res["occ_score"])
    assert perfect_res["mave"] == 0.0 and perfect_res["occ_score"] == 1.0

    # RayIoU from the official per-ray arrays of the four frames, counted the same way, must match exactly.
    off = evaluate([recs["pred"][fi] for fi in FRAMES], [recs["gt"][fi] for fi in FRAMES])
    assert all(np.array_equal(off["counts"][k], main_res["counts"][k]) for k in ("gt_cnt", "pred_cnt", "tp_cnt"))
    assert off["rayiou"] == main_res["rayiou"]

    # Diagnostics: the size of the float32 summation effect, and the standalone metric.py variant.
    res64 = evaluate(pred_pcd, gt_pcd, flow_dtype=np.float64)
    variant = evaluate(pred_pcd, gt_pcd, tp_only=False)

    ref = scenario_json(main_res)
    ref["zero_flow"] = scenario_json(zero_res)
    ref["edge_cases"] = {
        "no_flow_tp": {
            "description": "frame slot 0 (frame_index 0) with inputs.npz edge_pred as prediction (every predicted "
            "flow-class voxel relabelled 0 'others') and the slot's flows: no flow class has a true positive, "
            "every AVE is NaN, mAVE = nanmean(all NaN) = NaN, and the reference's max(1 - nan, 0.0) returns nan, "
            "so its OccScore is NaN (null here).",
            **scenario_json(edge_res),
        },
        "perfect": {
            "description": "prediction = GT semantics and predicted flow = GT flow on all four frames.",
            **scenario_json(perfect_res, with_counts=False),
        },
    }
    ref["diagnostics"] = to_json(
        {
            "mave_with_float64_flow_errors": res64["mave"],
            "occ_score_with_float64_flow_errors": res64["occ_score"],
            "abs_diff_mave_float64_vs_reference": abs(res64["mave"] - main_res["mave"]),
            "metric_py_all_valid_rays_variant": {
                "ave_per_class": variant["ave"],
                "mave": variant["mave"],
                "occ_score": variant["occ_score"],
            },
        }
    )
    ref["meta"] = {
        "reference": "OpenDriveLab/OccNet branch challenge commit 2bb8fe69f0c09e4d014ec29a043d6d1d31d50849, "
        "projects/mmdet3d_plugin/datasets/ray_metrics.py (main, calc_metrics, process_one_sample, "
        "generate_lidar_rays) and tools/ray_iou/lib/dvr/dvr.cu (render_forward_cuda_kernel)",
        "class_names": CLASS_NAMES,
        "flow_class_names": FLOW_CLASS_NAMES,
        "free_label": FREE,
        "thresholds_m": THRESHOLDS,
        "ave_threshold_m": THRESHOLDS[AVE_THRESHOLD_INDEX],
        "frame_index": FRAMES,
        "seed": SEED,
        "speed_m_s": SPEED,
        "flow_noise_sigma_m_s": FLOW_NOISE_SIGMA,
        "n_rays_per_origin": len(dirs),
    }

    write_npz(
        HERE / "inputs.npz",
        {
            "frame_index": np.array(FRAMES, dtype=np.int64),
            "semantics": sem,
            "pred": pred,
            "origins": origins,
            "n_origins": n_origins,
            "flow_gt": flow_gt,
            "flow_pred": flow_pred,
            "edge_slot": np.int64(edge_slot),
            "edge_pred": edge_pred,
        },
    )
    (HERE / "reference.json").write_text(json.dumps(ref, sort_keys=True, indent=1) + "\n")
    print(
        f"rayiou {main_res['rayiou']!r} mave {main_res['mave']!r} occ_score {main_res['occ_score']!r} "
        f"zero-flow mave {zero_res['mave']!r}; casting {t_cast:.1f} s, total {time.perf_counter() - t0:.1f} s",
        file=sys.stderr,
    )


if __name__ == "__main__":
    main()
